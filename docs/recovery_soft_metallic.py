"""Figure for docs/recovery.md: continuous metallic, ground truth against the recovery.

``python docs/recovery_soft_metallic.py [OUT_PNG] [--size 128]``

Generates the tuning captures ``rusted_metal`` seed 1 and ``aa_inlay`` seed 1 (16 ring lights +
the flash, 1 % noise) in a temporary folder, recovers each with the default settings and
shows the true and the recovered metallic map in the colours of the recovery's
``metallic.png`` (:func:`torchbrdf.recovery.svbrdf.metallic_preview`: 0 black, 1 white,
fractional values red → orange → yellow), with a key for those colours.
"""

import argparse
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from torchbrdf.capture.synthetic import generate_capture, make_material
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery.svbrdf import metallic_preview

CASES = (("rusted_metal", 1), ("aa_inlay", 1))


def main(png: str, size: int) -> None:
    fig, axes = plt.subplots(1, 2 * len(CASES) + 1, figsize=(3.2 * (2 * len(CASES)) + 1.2, 3.6),
                             gridspec_kw={"width_ratios": [1] * (2 * len(CASES)) + [0.12]})
    with tempfile.TemporaryDirectory() as tmp:
        for i, (recipe, seed) in enumerate(CASES):
            cap = Path(tmp) / recipe
            generate_capture(cap, recipe=recipe, seed=seed, size=size)
            got = recover(cap, RecoveryConfig(), progress=False).maps["metallic"]
            true = make_material(recipe, seed, size)["metallic"]
            for j, (m, what) in enumerate(((true, "ground truth"), (got, "recovered"))):
                ax = axes[2 * i + j]
                ax.imshow(metallic_preview(m.float().cpu()).permute(1, 2, 0).numpy(), interpolation="nearest")
                frac = float(((m > 0) & (m < 1)).float().mean())
                ax.set_title(f"{recipe} {seed}: {what}\n{100 * frac:.1f} % fractional", fontsize=9)
                ax.set_xticks([])
                ax.set_yticks([])
    key = torch.linspace(0, 1, 101).reshape(1, -1, 1)  # (1, H=101, W=1): 0 at the bottom after flip
    axes[-1].imshow(metallic_preview(key).permute(1, 2, 0).numpy()[::-1], aspect="auto",
                    extent=(0, 1, 0, 1))
    axes[-1].set_xticks([])
    axes[-1].set_ylabel("metallic")
    axes[-1].yaxis.set_label_position("right")
    axes[-1].yaxis.tick_right()
    fig.suptitle(f"metallic maps, {size}² tuning captures (16 ring lights + flash, 1 % noise)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(png, dpi=110)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("png", nargs="?", default="docs/recovery_soft_metallic.png", help="output PNG")
    ap.add_argument("--size", type=int, default=128, help="capture size in pixels")
    a = ap.parse_args()
    main(a.png, a.size)
