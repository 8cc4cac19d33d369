"""``python -m torchbrdf [--out DIR]``: the showcase — principled spheres and a BRDF image slice."""

from __future__ import annotations

import argparse
import os

import torch

from torchbrdf.io import file_in_the_way


BACKGROUND = 0.18  # linear mid grey behind the spheres: dark sides and smooth metals stand out from it


def sphere_grid(resolution: int = 96) -> torch.Tensor:
    """A figure of principled spheres, roughness across × metallic down, under a point light.

    A dim fill light from the lower left keeps the shadow side readable; the background is a
    mid grey (:data:`BACKGROUND`), so each sphere's silhouette shows, a smooth metal's too (it
    reflects only the two lights).

    Returns:
        ``(3, rows * resolution, cols * resolution)`` linear radiance.
    """
    from torchbrdf import principled

    u = ((torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * 2 - 1) * 1.12  # a margin between spheres
    yy, xx = torch.meshgrid(-u, u, indexing="ij")
    r2 = xx * xx + yy * yy
    inside = r2 < 1
    n = torch.stack([xx, yy, torch.sqrt(torch.clamp(1 - r2, min=0))], -1)
    p = n  # unit sphere at the origin
    cam = torch.tensor([0.0, 0.0, 6.0])
    key, fill = torch.tensor([3.0, 3.0, 5.0]), torch.tensor([-4.0, -2.0, 3.0])
    v = torch.nn.functional.normalize(cam - p, dim=-1)
    rows = []
    for metallic in (0.0, 0.5, 1.0):
        cols = []
        for roughness in (0.05, 0.25, 0.5, 0.75, 1.0):
            radiance = torch.zeros_like(n)
            for light, power in ((key, 40.0), (fill, 4.0)):
                to_l = light - p
                dist2 = (to_l * to_l).sum(-1, keepdim=True)
                l = to_l / torch.sqrt(dist2)
                f = principled(l, v, n, base_color=torch.tensor([0.8, 0.3, 0.1]), metallic=metallic,
                               roughness=roughness)
                radiance = radiance + f * power * torch.clamp((n * l).sum(-1, keepdim=True), min=0) / dist2
            cols.append(torch.where(inside[..., None], radiance, torch.full_like(radiance, BACKGROUND)))
        rows.append(torch.cat(cols, dim=1))
    return torch.cat(rows, dim=0).permute(2, 0, 1)


def main(argv: list[str] | None = None) -> None:
    """Write ``spheres.png`` and ``slice.png`` into ``--out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchbrdf import principled
    from torchbrdf.analysis.plots import plot_image_slices

    parser = argparse.ArgumentParser(prog="python -m torchbrdf", description=__doc__.replace("``", ""))
    parser.add_argument("--out", default="out", help="output folder (default: out)")
    args = parser.parse_args(argv)
    if (blocked := file_in_the_way(args.out)) is not None:
        parser.error(f"--out {args.out}: {blocked} is a file, not a folder")
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as e:
        parser.error(f"--out {args.out}: cannot create the folder ({e.strerror or e})")

    res = 128
    img = sphere_grid(res)
    srgb = torch.where(img <= 0.0031308, 12.92 * img, 1.055 * torch.clamp(img, min=1e-8) ** (1 / 2.4) - 0.055)
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.imshow(torch.clamp(srgb, 0, 1).permute(1, 2, 0).numpy())
    ax.set_xticks([res // 2 + res * i for i in range(5)], ["0.05", "0.25", "0.5", "0.75", "1.0"])
    ax.set_yticks([res // 2 + res * i for i in range(3)], ["0", "0.5", "1"])
    ax.set_xlabel("roughness")
    ax.set_ylabel("metallic")
    ax.set_title("Disney principled BRDF: base colour (0.8, 0.3, 0.1), key + fill point lights")
    fig.savefig(os.path.join(args.out, "spheres.png"), dpi=100, bbox_inches="tight")
    plt.close(fig)

    def copper(l, v, n, x=None, y=None):
        return principled(l, v, n, x, y, base_color=torch.tensor([0.8, 0.3, 0.1], dtype=l.dtype), roughness=0.3)

    # The same drawing as the explore report (θd upward), so the two never disagree.
    fig = plot_image_slices([("principled, roughness 0.3", copper)], resolution=128, exposure=-1.0)
    fig.savefig(os.path.join(args.out, "slice.png"), dpi=100)
    print(f"wrote {args.out}/spheres.png and {args.out}/slice.png")


if __name__ == "__main__":
    main()
