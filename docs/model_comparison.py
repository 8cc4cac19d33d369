"""Regenerate ``docs/model_comparison.png``: principled vs Smits spheres across roughness, and
their albedo curves.

    python docs/model_comparison.py

Each sphere has a key light from the upper left and a dim fill from the lower right, and sits on
a neutral grey, so its unlit side and silhouette stay visible.
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
RESOLUTION = 192
KEY = (-0.5, 0.6, 0.65)  # toward the key light, camera space (camera on +z, y up)
FILL = (0.7, -0.5, 0.5)  # toward the fill light
FILL_STRENGTH = 0.12
BACKGROUND = 0.18  # linear neutral grey (sRGB ~0.46)
BASE = torch.tensor([0.8, 0.35, 0.15], dtype=torch.float64)
MODELS = {
    "principled": (torchbrdf.principled, {}),
    "Smits (Wall-E/Up)": (torchbrdf.smits, {}),
}


def srgb(img):
    img = img.clamp(min=0)
    return torch.where(img <= 0.0031308, 12.92 * img, 1.055 * img.clamp(min=1e-8) ** (1 / 2.4) - 0.055).clamp(0, 1)


def lit_sphere(brdf, **params) -> torch.Tensor:
    """``(3, H, W)`` linear radiance: key + fill light on the sphere, :data:`BACKGROUND` around it."""
    img, mask = render_sphere(brdf, RESOLUTION, KEY, return_mask=True, **params)
    img = img + FILL_STRENGTH * render_sphere(brdf, RESOLUTION, FILL, **params)
    img = img[0] if img.dim() == 4 else img
    return torch.where(mask, img, torch.full_like(img, BACKGROUND))


def main(out=os.path.join(os.path.dirname(__file__), "model_comparison.png")):
    fig, axes = plt.subplots(len(MODELS) + 1, len(ROUGHNESS), figsize=(3.2 * len(ROUGHNESS), 3.2 * (len(MODELS) + 1)))
    for row, (name, (brdf, extra)) in enumerate(MODELS.items()):
        for col, r in enumerate(ROUGHNESS):
            img = lit_sphere(brdf, base_color=BASE, roughness=r, **extra)
            axes[row, col].imshow(srgb(img).permute(1, 2, 0).numpy())
            axes[row, col].set_title(f"{name}\nroughness {r}", fontsize=9)
            axes[row, col].axis("off")
    curves = {}
    for col, r in enumerate(ROUGHNESS):
        for name, (brdf, extra) in MODELS.items():
            th, est = albedo_curve(brdf, base_color=torch.ones(3, dtype=torch.float64), roughness=r, **extra)
            curves[name, r] = (torch.rad2deg(th).numpy(), est.value[:, 0].numpy())
    top = 1.05 * max(float(y.max()) for _, y in curves.values())
    for col, r in enumerate(ROUGHNESS):
        ax = axes[-1, col]
        for name in MODELS:
            ax.plot(*curves[name, r], label=name)
        ax.axhline(1.0, color="0.5", lw=0.8, ls="--", label="1 (energy conserved)")
        ax.set_xlabel("view angle θv (degrees)")
        ax.set_ylabel("directional albedo (white base)")
        ax.set_ylim(0, top)
        ax.set_title(f"albedo, roughness {r}", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
