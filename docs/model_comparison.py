"""Regenerate ``docs/model_comparison.png``: principled vs Smits spheres across roughness, and
their albedo curves (issue 6, item 6).

    python docs/model_comparison.py
"""

import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

import torchbrdf  # noqa: E402
from torchbrdf.analysis import albedo_curve, render_sphere  # noqa: E402

ROUGHNESS = (0.1, 0.3, 0.5, 0.8)
BASE = torch.tensor([0.8, 0.35, 0.15], dtype=torch.float64)
MODELS = {
    "principled": (torchbrdf.principled, {}),
    "Smits (Wall-E/Up)": (torchbrdf.smits, {}),
}


def srgb(img):
    img = img.clamp(min=0)
    return torch.where(img <= 0.0031308, 12.92 * img, 1.055 * img.clamp(min=1e-8) ** (1 / 2.4) - 0.055).clamp(0, 1)


def main(out=os.path.join(os.path.dirname(__file__), "model_comparison.png")):
    fig, axes = plt.subplots(len(MODELS) + 1, len(ROUGHNESS), figsize=(3 * len(ROUGHNESS), 3 * (len(MODELS) + 1)))
    for row, (name, (brdf, extra)) in enumerate(MODELS.items()):
        for col, r in enumerate(ROUGHNESS):
            img = render_sphere(brdf, 96, base_color=BASE, roughness=r, **extra)
            axes[row, col].imshow(srgb(img[0] if img.dim() == 4 else img).permute(1, 2, 0).numpy())
            axes[row, col].set_title(f"{name}\nroughness {r}", fontsize=9)
            axes[row, col].axis("off")
    for col, r in enumerate(ROUGHNESS):
        ax = axes[-1, col]
        for name, (brdf, extra) in MODELS.items():
            th, est = albedo_curve(brdf, base_color=torch.ones(3, dtype=torch.float64), roughness=r, **extra)
            ax.plot(torch.rad2deg(th).numpy(), est.value[:, 0].numpy(), label=name)
        ax.set_xlabel("view angle θv (degrees)")
        ax.set_ylabel("albedo (white base)")
        ax.set_ylim(0, 1.3)
        ax.set_title(f"albedo, roughness {r}", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
