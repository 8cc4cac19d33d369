"""``python -m torchbrdf [--out DIR]``: the showcase — principled spheres and a BRDF image slice."""

from __future__ import annotations

import argparse
import math
import os

import torch


def sphere_grid(resolution: int = 96) -> torch.Tensor:
    """A figure of principled spheres, roughness across × metallic down, under a point light.

    Returns:
        ``(3, rows * resolution, cols * resolution)`` linear radiance.
    """
    from torchbrdf.brdf import principled

    u = (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * 2 - 1
    yy, xx = torch.meshgrid(-u, u, indexing="ij")
    r2 = xx * xx + yy * yy
    inside = r2 < 1
    n = torch.stack([xx, yy, torch.sqrt(torch.clamp(1 - r2, min=0))], -1)
    p = n  # unit sphere at the origin
    cam = torch.tensor([0.0, 0.0, 6.0])
    light = torch.tensor([3.0, 3.0, 5.0])
    v = torch.nn.functional.normalize(cam - p, dim=-1)
    to_l = light - p
    dist2 = (to_l * to_l).sum(-1, keepdim=True)
    l = to_l / torch.sqrt(dist2)
    rows = []
    for metallic in (0.0, 0.5, 1.0):
        cols = []
        for roughness in (0.05, 0.25, 0.5, 0.75, 1.0):
            f = principled(l, v, n, base_color=torch.tensor([0.8, 0.3, 0.1]), metallic=metallic, roughness=roughness,
                           clearcoat=0.0)
            radiance = f * 40.0 * torch.clamp((n * l).sum(-1, keepdim=True), min=0) / dist2 + 0.02 * f * math.pi
            cols.append(torch.where(inside[..., None], radiance, torch.zeros_like(radiance)))
        rows.append(torch.cat(cols, dim=1))
    return torch.cat(rows, dim=0).permute(2, 0, 1)


def main(argv=None) -> None:
    """Write ``spheres.png`` and ``slice.png`` into ``--out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchbrdf.brdf import principled
    from torchbrdf.analysis.slices import image_slice

    parser = argparse.ArgumentParser(prog="python -m torchbrdf", description=__doc__)
    parser.add_argument("--out", default="out", help="output folder (default: out)")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)

    img = sphere_grid()
    srgb = torch.where(img <= 0.0031308, 12.92 * img, 1.055 * torch.clamp(img, min=1e-8) ** (1 / 2.4) - 0.055)
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.imshow(torch.clamp(srgb, 0, 1).permute(1, 2, 0).numpy())
    ax.set_xticks([48 + 96 * i for i in range(5)], ["0.05", "0.25", "0.5", "0.75", "1.0"])
    ax.set_yticks([48 + 96 * i for i in range(3)], ["0", "0.5", "1"])
    ax.set_xlabel("roughness")
    ax.set_ylabel("metallic")
    ax.set_title("Disney principled BRDF, point light")
    fig.savefig(os.path.join(args.out, "spheres.png"), dpi=100, bbox_inches="tight")
    plt.close(fig)

    sl = image_slice(principled, 128, base_color=torch.tensor([0.8, 0.3, 0.1], dtype=torch.float64), roughness=0.3)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.imshow((sl / (1 + sl)).clamp(0, 1).permute(1, 2, 0).numpy() ** (1 / 2.2), extent=(0, 90, 90, 0))
    ax.set_xlabel("θh (degrees)")
    ax.set_ylabel("θd (degrees)")
    ax.set_title("image slice at φd = 90° (roughness 0.3)")
    fig.savefig(os.path.join(args.out, "slice.png"), dpi=100, bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {args.out}/spheres.png and {args.out}/slice.png")


if __name__ == "__main__":
    main()
