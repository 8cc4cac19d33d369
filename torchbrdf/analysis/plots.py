"""Matplotlib figures for the views of :mod:`torchbrdf.analysis`, several BRDFs side by side.

Every function takes ``entries``: a sequence of ``(label, brdf)`` pairs where ``brdf`` is a
parameter-free callable ``brdf(l, v, n, x=None, y=None) -> (*, 3)`` — make one with
:func:`torchbrdf.analysis.bind_brdf` (``bind_brdf(principled, base_color=..., roughness=0.3)``)
or pass a :class:`~torchbrdf.measured.MERLBRDF` directly. Each returns a
:class:`matplotlib.figure.Figure` (created without pyplot, so nothing is shown and no
display is needed); save it with ``fig.savefig(path)``.

Colours of curves are per BRDF; curves plot the luminance (Rec. 709 weights) of the RGB
value. Images (slices, spheres) are shown like BRDF Explorer's: linear values times an
exposure ``2^EV``, clipped, sRGB-encoded; slices show ``π f`` so a white Lambert surface is
white.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from torchbrdf._types import BRDF, Angles
from torchbrdf.analysis import measures as A
from torchbrdf.io import to_display

if TYPE_CHECKING:  # matplotlib is imported only when a figure is drawn
    from matplotlib.figure import Figure

__all__ = [
    "display_image",
    "luminance",
    "plot_image_slices",
    "plot_spheres",
    "plot_albedo_curves",
    "plot_retro_reflection",
    "plot_specular_peaks",
    "plot_polar_lobes",
]

Entries = Sequence[tuple[str, BRDF]]
_LUMA = (0.2126, 0.7152, 0.0722)
# Each compared BRDF gets a colour AND a line style, so curves that coincide stay visible.
_LINESTYLES = ("-", "--", (0, (1, 1.2)), "-.", (0, (5, 1, 1, 1, 1, 1)))


def _style(i: int) -> dict[str, Any]:
    """Colour and line style of the ``i``-th compared BRDF."""
    return {"color": f"C{i}", "linestyle": _LINESTYLES[i % len(_LINESTYLES)]}


def _panel_title(label: str, width: int = 26) -> str:
    """A panel title wrapped onto lines of at most ``width`` characters (never clipped)."""
    return textwrap.fill(label, width)


def _figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def luminance(rgb: Tensor) -> np.ndarray:
    """Rec. 709 luminance of ``(*, 3)`` values, as a numpy array ``(*)``."""
    w = torch.tensor(_LUMA, dtype=rgb.dtype, device=rgb.device)
    return (rgb * w).sum(-1).detach().cpu().numpy()


def display_image(img: Tensor, exposure: float = 0.0) -> np.ndarray:
    """Linear ``(3, H, W)`` image to an ``(H, W, 3)`` sRGB array in [0, 1] (exposure, clip, sRGB)."""
    return to_display(img.detach().to("cpu", torch.float32), exposure=exposure).permute(1, 2, 0).numpy()


def plot_image_slices(
    entries: Entries, resolution: int = 128, phi_d: float = math.pi / 2, exposure: float = 0.0
) -> Figure:
    """Burley's image slices (Figure 3) of each BRDF at ``φd``, θd drawn upward as in the notes.

    The left edge is the specular peak, the bottom edge retro-reflection (``l = v``), the top
    edge the Fresnel peak. Where ``l`` or ``v`` is below the surface (``φd < 90°``, large θh
    and θd) there is no value: those pixels are grey, and a note under the figure says so.
    """
    k = len(entries)
    below = _below_horizon(resolution, phi_d)
    fig = _figure(2.6 * k + 0.4, 3.1 if below.any() else 2.9)
    axes = fig.subplots(1, k, squeeze=False)[0]
    for ax, (label, f) in zip(axes, entries):
        img = A.image_slice(f, resolution, phi_d) * math.pi
        shown = display_image(img, exposure)
        shown[below] = _HORIZON_GREY
        ax.imshow(shown, origin="lower", extent=(0, 90, 0, 90))
        ax.set_title(_panel_title(label), fontsize=9)
        ax.set_xlabel("θh (deg)")
        ax.set_xticks([0, 30, 60, 90])
        ax.set_yticks([0, 30, 60, 90])
    axes[0].set_ylabel("θd (deg)")
    note = "\ngrey: l or v below the surface (no value; f is 0 there by definition)" if below.any() else ""
    fig.suptitle(f"Image slices, φd = {math.degrees(phi_d):.0f}° (π·f, EV {exposure:+g}){note}", fontsize=10)
    return fig


_HORIZON_GREY = (0.55, 0.55, 0.6)  # a bluish grey no BRDF value is shown as


def _below_horizon(resolution: int, phi_d: float) -> np.ndarray:
    """``(resolution, resolution)`` bool: the slice's (θd row, θh column) pixels where ``l`` or ``v`` is below the surface."""
    from torchbrdf.analysis.slices import half_diff_to_lv

    t = (torch.arange(resolution, dtype=torch.float64) + 0.5) * (math.pi / 2) / resolution
    td, th = torch.meshgrid(t, t, indexing="ij")
    l, v = half_diff_to_lv(th, td, phi_d)
    return ((l[..., 2] <= 0) | (v[..., 2] <= 0)).numpy()


def _coincidence_note(curves: Sequence[tuple[str, np.ndarray, np.ndarray]], unit: str = "°",
                      tolerance: float = 0.03) -> str:
    """A line for each pair of curves that agree within ``tolerance`` (relative) over at least half their range.

    ``curves``: ``(label, x, y)`` on the same ``x``. Such curves are drawn on top of each other,
    so the figure says where they coincide instead of leaving a legend entry without a visible line.
    """
    notes = []
    for i in range(len(curves)):
        for j in range(i + 1, len(curves)):
            (a, x, ya), (b, _, yb) = curves[i], curves[j]
            if len(ya) != len(yb) or len(ya) < 2:
                continue
            scale = np.maximum(np.maximum(np.abs(ya), np.abs(yb)), 1e-12)
            agree = np.concatenate(([False], np.abs(ya - yb) / scale <= tolerance, [False]))
            edges = np.flatnonzero(np.diff(agree.astype(np.int8)))  # run starts and ends, paired
            if len(edges) == 0:
                continue
            runs = edges.reshape(-1, 2)
            lo, hi = max(runs, key=lambda r: r[1] - r[0])
            if x[hi - 1] - x[lo] < 0.5 * (x[-1] - x[0]):
                continue
            where = "everywhere" if lo == 0 and hi == len(x) else f"from {x[lo]:.0f}{unit} to {x[hi - 1]:.0f}{unit}"
            notes.append(f"'{a}' and '{b}' coincide within {tolerance:.0%} {where}")
    return "\n".join(notes)


def plot_spheres(
    entries: Entries,
    resolution: int = 160,
    exposure: float = 0.0,
    light_direction: Sequence[float] | Tensor = A.DEFAULT_SPHERE_LIGHT,
) -> Figure:
    """Lit spheres (one directional light of irradiance π, upper left) through the shader."""
    k = len(entries)
    fig = _figure(2.4 * k + 0.2, 2.7)
    axes = fig.subplots(1, k, squeeze=False)[0]
    for ax, (label, f) in zip(axes, entries):
        img, mask = A.render_sphere(f, resolution, light_direction, return_mask=True)
        shown = display_image(img, exposure)
        shown[~mask.cpu().numpy()] = 0.25  # grey backdrop so the shadowed silhouette reads
        ax.imshow(shown)
        ax.set_title(_panel_title(label), fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"Lit spheres (directional light, EV {exposure:+g})", fontsize=10)
    return fig


def plot_albedo_curves(
    entries: Entries,
    theta_v: Angles | None = None,
    method: str = "quadrature",
    samples: int | tuple[int, int] | None = None,
) -> Figure:
    """Albedo (directional–hemispherical reflectance) against the view angle (Figures 11, 12).

    Thick lines: luminance; thin lines of the same colour: the R, G, B channels; shaded band:
    ± error estimate.
    """
    fig = _figure(6.0, 3.6)
    ax = fig.subplots()
    for i, (label, f) in enumerate(entries):
        th, est = A.albedo_curve(f, theta_v, method, samples)
        deg = np.degrees(th.numpy())
        y, e = luminance(est.value), luminance(est.error)
        (line,) = ax.plot(deg, y, label=f"{label} (luminance)", lw=1.8, **_style(i))
        ax.fill_between(deg, y - e, y + e, color=line.get_color(), alpha=0.25, lw=0)
        for c in range(3):
            ax.plot(deg, est.value[:, c].numpy(), lw=0.6, alpha=0.7, **_style(i),
                    label=f"{label} (R, G, B)" if c == 0 else None)
    ax.set_xlabel("θv (deg)")
    ax.set_ylabel("albedo ρ(θv)")
    ax.set_xlim(0, 90)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2 if len(entries) > 2 else 1)
    ax.set_title(f"Directional albedo ({method})", fontsize=10)
    return fig


def _log_curves(
    entries: Entries, fn: Callable[[BRDF], tuple[Tensor, Tensor]], xlabel: str, title: str
) -> Figure:
    fig = _figure(6.0, 3.6)
    ax = fig.subplots()
    curves = []
    for i, (label, f) in enumerate(entries):
        th, val = fn(f)
        y = np.maximum(luminance(val), 1e-6)
        curves.append((label, np.degrees(th.numpy()), y))
        ax.semilogy(curves[-1][1], y, label=label, lw=1.6, **_style(i))
    ax.set_xlabel(xlabel)
    ax.set_ylabel("f (luminance, 1/sr)")
    ax.grid(alpha=0.3, which="both")
    note = _coincidence_note(curves)
    ax.legend(fontsize=8, title=note or None, title_fontsize=7)
    ax.set_title(title, fontsize=10)
    return fig


def plot_retro_reflection(entries: Entries) -> Figure:
    """Retro-reflective response ``f(θh, θd = 0)`` on a log axis (Figure 6)."""
    return _log_curves(entries, A.retro_reflection_curve, "θh = θl = θv (deg)", "Retro-reflection (θd = 0)")


def plot_specular_peaks(entries: Entries, theta_d: float = math.radians(10.0)) -> Figure:
    """Specular peak ``f(θh)`` at fixed ``θd``, ``φd = 90°`` on a log axis (Figure 9)."""
    return _log_curves(
        entries,
        lambda f: A.specular_peak_curve(f, theta_d=theta_d),
        "θh (deg)",
        f"Specular peak (θd = {math.degrees(theta_d):.0f}°, φd = 90°)",
    )


def plot_polar_lobes(
    entries: Entries,
    thetas_i: Sequence[float] = (math.radians(30.0), math.radians(60.0)),
    cosine: bool = True,
) -> Figure:
    """Polar plots of ``f·cos θl`` in the plane of incidence, one column per incidence angle.

    The light arrives from the left at ``θi`` (grey ray); the mirror direction is at ``+θi``.
    Top row: linear radius (the shape of the peaks); bottom row: log radius over four decades
    below the largest value (diffuse and specular on one plot).
    """
    k = len(thetas_i)
    fig = _figure(3.3 * k, 6.2)
    axes = fig.subplots(2, k, subplot_kw={"projection": "polar"}, squeeze=False)
    notes_per_column = []
    for col, ti in enumerate(thetas_i):
        curves = []
        for i, (label, f) in enumerate(entries):
            theta_o, val = A.polar_lobe(f, ti, cosine=cosine)
            curves.append((label, theta_o.numpy(), luminance(val)))
        note = _coincidence_note([(a, np.degrees(x), y) for a, x, y in curves])
        notes_per_column += [f"θi = {math.degrees(ti):.0f}°: {line}" for line in note.splitlines()]
        top = max(float(c[2].max()) for c in curves)
        top = top if top > 0 else 1.0
        decades = 4.0
        for row, ax in enumerate(axes[:, col]):
            for i, (label, to, y) in enumerate(curves):
                r = y if row == 0 else np.clip(np.log10(np.maximum(y, 1e-30) / top) + decades, 0.0, None)
                ax.plot(to, r, label=label, lw=1.4, **_style(i))
            rmax = top if row == 0 else decades
            ax.plot([-ti, -ti], [0, rmax], color="0.5", lw=1.0)
            ax.set_theta_zero_location("N")
            ax.set_theta_direction(-1)
            ax.set_thetamin(-90)
            ax.set_thetamax(90)
            ax.set_rmax(rmax)
            ax.tick_params(labelsize=7)
            if row == 1:
                ticks = np.arange(0, decades + 1)
                ax.set_rticks(ticks)
                ax.set_yticklabels([f"{top * 10 ** (t - decades):.1g}" for t in ticks])
            ax.set_title(f"θi = {math.degrees(ti):.0f}°, {'linear' if row == 0 else 'log'} radius", fontsize=9)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(entries), 3), fontsize=7,
               title="\n".join(notes_per_column) or None, title_fontsize=7)
    what = "f · cos θl" if cosine else "f"
    fig.suptitle(f"Lobes in the plane of incidence ({what}, luminance)", fontsize=10)
    return fig
