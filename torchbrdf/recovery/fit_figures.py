"""Figures of a measured-BRDF fit: measured vs fitted image slices and lit spheres.

Drawn with matplotlib's object API (no pyplot: nothing is shown, no display is needed) from
the layers below the recovery only: MERL's half/difference directions
(:func:`torchbrdf.brdf.measured.merl_directions`) for the slices and the screen-space shader
(:func:`torchbrdf.render.shading.shade`) for the spheres. Images are shown as linear values
times ``2^EV``, clipped and sRGB-encoded (:func:`torchbrdf.io.to_display`); slices show ``π f``
so a white Lambert surface is white.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, cast

import numpy as np
import torch
from torch import Tensor

from torchbrdf.brdf.measured import merl_directions
from torchbrdf.io import to_display
from torchbrdf.render.geometry import sphere_gbuffer
from torchbrdf.render.lights import DirectionalLight
from torchbrdf.render.shading import shade

if TYPE_CHECKING:  # matplotlib is imported only when a figure is drawn
    from matplotlib.figure import Figure

__all__ = ["slice_image", "sphere_image", "slice_comparison_figure", "spheres_figure"]

#: A parameter-free BRDF callable ``brdf(l, v, n, x=None, y=None) -> (*, 3)``.
BRDFCallable = Callable[..., Tensor]
#: Rec. 709 luminance weights of linear RGB.
REC709 = (0.2126, 0.7152, 0.0722)
#: Direction toward the spheres' light, camera space (upper left, in front).
SPHERE_LIGHT = (-1.0, 1.0, 1.2)


def _figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def _shown(img: Tensor, exposure: float) -> np.ndarray:
    return to_display(img.detach().to("cpu", torch.float32), exposure=exposure).permute(1, 2, 0).numpy()


def slice_image(brdf: BRDFCallable, resolution: int = 128, phi_d: float = math.pi / 2) -> Tensor:
    """``f`` over Burley's ``(θh, θd)`` image slice at fixed ``φd``, float64.

    Returns ``(3, resolution, resolution)``: row = θd (0 at row 0), column = θh (0 at the left),
    both sampling ``[0, π/2)`` at pixel centres.
    """
    t = (torch.arange(resolution, dtype=torch.float64) + 0.5) * (math.pi / 2) / resolution
    td, th = torch.meshgrid(t, t, indexing="ij")
    l, v = merl_directions(th, td, torch.full_like(th, phi_d))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(l)
    out = brdf(l, v, n)
    return out.expand(*out.shape[:-1], 3).permute(2, 0, 1)


def sphere_image(brdf: BRDFCallable, resolution: int = 128,
                 light_direction: Sequence[float] = SPHERE_LIGHT) -> tuple[Tensor, Tensor]:
    """A unit sphere lit by one directional light of irradiance π, through the shader.

    Returns ``(image (3, H, W) linear radiance, mask (H, W) bool)``, float64, ``H = W = resolution``.
    """
    g = sphere_gbuffer(resolution, resolution, dtype=torch.float64)
    ld = torch.nn.functional.normalize(torch.tensor(light_direction, dtype=torch.float64), dim=0)
    img = shade(g, DirectionalLight(ld, torch.full((3,), math.pi, dtype=torch.float64)),
                lambda l, v, n, x=None, y=None, **_: brdf(l, v, n))[0]
    mask = cast(Tensor, g.mask)  # sphere_gbuffer always sets the coverage mask
    return img, mask[0, 0].bool()


def slice_comparison_figure(reference: BRDFCallable, model: BRDFCallable,
                            labels: Sequence[str] = ("measured", "fitted"), resolution: int = 128,
                            exposure: float = 0.0) -> Figure:
    """Slices (φd = 90°) of a reference and a model BRDF and their log2 luminance ratio.

    Blue where the model is too dark; the colour bar spans ±1 stop.
    """
    a = slice_image(reference, resolution) * math.pi
    b = slice_image(model, resolution) * math.pi
    lum = torch.tensor(REC709, dtype=a.dtype)[:, None, None]
    la, lb = (a * lum).sum(0), (b * lum).sum(0)
    valid = (la > 0) | (lb > 0)
    ratio = torch.where(valid, torch.log2((lb + 1e-4) / (la + 1e-4)), torch.full_like(la, float("nan")))
    fig = _figure(9.0, 3.1)
    axes = fig.subplots(1, 3)
    for ax, img, name in ((axes[0], a, labels[0]), (axes[1], b, labels[1])):
        ax.imshow(_shown(img, exposure), origin="lower", extent=(0, 90, 0, 90))
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("θh (deg)")
    axes[0].set_ylabel("θd (deg)")
    im = axes[2].imshow(ratio.numpy(), origin="lower", extent=(0, 90, 0, 90), cmap="RdBu_r", vmin=-1, vmax=1)
    axes[2].set_title(f"log2({labels[1]} / {labels[0]})", fontsize=9)
    axes[2].set_xlabel("θh (deg)")
    fig.colorbar(im, ax=axes[2], shrink=0.85, label="stops")
    fig.suptitle("Image slices, φd = 90° (π·f)", fontsize=10)
    return fig


def spheres_figure(entries: Sequence[tuple[str, BRDFCallable]], resolution: int = 128,
                   exposure: float = 0.0) -> Figure:
    """Lit spheres (:func:`sphere_image`) of ``(label, brdf)`` pairs side by side, on grey."""
    fig = _figure(2.4 * len(entries) + 0.2, 2.7)
    axes = fig.subplots(1, len(entries), squeeze=False)[0]
    for ax, (label, f) in zip(axes, entries):
        img, mask = sphere_image(f, resolution)
        shown = _shown(img, exposure)
        shown[~mask.numpy()] = 0.25  # grey backdrop so the shadowed silhouette reads
        ax.imshow(shown)
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"Lit spheres (directional light, EV {exposure:+g})", fontsize=10)
    return fig
