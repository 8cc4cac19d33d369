"""The pictures a recovery writes for a person: map panels, the fit check and the loss curve.

Every figure labels its axes and gives its values a colour bar or a stated scale; the
maps' raw PNGs (one pixel per map pixel) are written by :mod:`~torchbrdf.recovery.outputs`.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import ModuleType

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.capture.format import Capture
from torchbrdf.io import atomic_path
from torchbrdf.recovery.progress import stage_seconds

__all__ = ["metallic_preview", "maps_figure", "comparison_figure", "loss_figure", "pyplot"]


def metallic_preview(metallic: Tensor) -> Tensor:
    """RGB preview ``(3, H, W)`` of ``metallic (1, H, W)``: binary pixels black (0) and white (1),
    fractional ones (0 < m < 1, the soft-metal stage's) coloured from red (m → 0) through
    orange to yellow (m → 1), so they stand out from both classes."""
    m = metallic.clamp(0, 1)
    frac = (m > 0) & (m < 1)
    tint = torch.cat((torch.ones_like(m), 0.15 + 0.85 * m, 0.1 * torch.ones_like(m)), 0)
    return torch.where(frac, tint, m.expand(3, -1, -1))



def pyplot() -> ModuleType:
    """matplotlib's pyplot on the file-only Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def comparison_figure(path: Path, cap: Capture, pred: Tensor, max_rows: int = 6) -> None:
    """Captured / re-rendered / 10×|difference| for up to ``max_rows`` lights, labelled.

    The panels are composed into one mosaic shown in a single axes at one figure pixel per
    image pixel: 18 separate axes cost most of a second to lay out and draw.
    """
    from torchbrdf.io import to_display

    captured = cap.images.detach().float().cpu()
    pred = pred.detach().float().cpu()
    n, _, h, w = captured.shape
    if max(h, w) > 256:  # panels of at most 256 px: a figure, not a second copy of the images
        h, w = max(1, round(h * 256 / max(h, w))), max(1, round(w * 256 / max(h, w)))
        captured = F.interpolate(captured, size=(h, w), mode="area")
        pred = F.interpolate(pred, size=(h, w), mode="area")
    elif max(h, w) < 200:  # and at least 200 px (pixel-replicated), room for the labels
        k = math.ceil(200 / max(h, w))
        captured = captured.repeat_interleave(k, -1).repeat_interleave(k, -2)
        pred = pred.repeat_interleave(k, -1).repeat_interleave(k, -2)
        h, w = h * k, w * k
    pick = sorted({round(k * (n - 1) / max(1, min(n, max_rows) - 1)) for k in range(min(n, max_rows))})
    scale = float(torch.quantile(captured.flatten()[:: max(1, captured.numel() // 200000)].clamp(min=0), 0.9))
    exposure = -math.log2(max(scale, 1e-6)) - 1.0
    gap = max(2, w // 64)  # white gutter between panels
    mosaic = torch.ones(3, len(pick) * (h + gap) - gap, 3 * (w + gap) - gap)
    for r, k in enumerate(pick):
        a = to_display(captured[k], exposure=exposure, tonemap="aces")
        b = to_display(pred[k], exposure=exposure, tonemap="aces")
        d = ((pred[k] - captured[k]).abs() * 10 * 2**exposure).clamp(0, 1)
        for c, img in enumerate((a, b, d)):
            y, x = r * (h + gap), c * (w + gap)
            mosaic[:, y:y + h, x:x + w] = img
    plt = pyplot()
    dpi = 100
    margin_l, margin_t, margin_b = 1.1, 0.55, 0.1  # inches: row labels, column titles + title
    iw, ih = mosaic.shape[2] / dpi, mosaic.shape[1] / dpi
    fig = plt.figure(figsize=(iw + margin_l + 0.1, ih + margin_t + margin_b), dpi=dpi)
    ax = fig.add_axes((margin_l / fig.get_figwidth(), margin_b / fig.get_figheight(),
                       iw / fig.get_figwidth(), ih / fig.get_figheight()))
    ax.imshow(mosaic.permute(1, 2, 0).numpy(), interpolation="nearest")
    cols = ("captured", "re-rendered from the maps", "|difference| × 10")
    ax.xaxis.tick_top()
    ax.set_xticks([c * (w + gap) + w / 2 for c in range(3)], cols, fontsize=9)
    ax.set_yticks([r * (h + gap) + h / 2 for r in range(len(pick))],
                  [f"light {k}\n{cap.files[k]}" for k in pick], fontsize=8)
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    fig.suptitle(f"Fit check, {len(pick)} of {n} lights (exposure {exposure:+.1f} EV, ACES tone map; "
                 "difference at the same exposure)", fontsize=8, y=1 - 0.08 / fig.get_figheight(), va="top")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", pil_kwargs={"compress_level": 3})
    plt.close(fig)


_LOSS_LABEL = "fit loss: mean squared log residual\n(per pixel, training light and channel)"


def loss_figure(path: Path, history: list) -> None:
    """Plot the fit loss per iteration.

    Both hypotheses and each pixel's better one in the dual stages, the chosen class
    afterwards; stage boundaries marked.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.6))
    it = [h["iteration"] for h in history]
    fit = [h.get("fit", {}) for h in history]

    def series(key):
        return [f.get(key, float("nan")) for f in fit]

    best = [f.get("best", f.get("chosen", float("nan"))) for f in fit]
    if any("dielectric" in f for f in fit):
        ax.semilogy(it, series("dielectric"), "--", color="tab:blue",
                    label="dielectric hypothesis (dual stages)")
        ax.semilogy(it, series("metal"), ":", color="tab:orange", label="metal hypothesis (dual stages)")
    ax.semilogy(it, best, "-o", ms=2.5, color="black",
                label="each pixel's better hypothesis (dual) / its chosen class (after)")
    finite = [v for v in series("dielectric") + series("metal") + best if math.isfinite(v) and v > 0]
    k = 0  # the first iteration of each stage run
    for run in stage_seconds(history):
        if k:
            ax.axvline(it[k] - 0.5, color="grey", lw=0.6)
        # Above the plotting area, where no curve runs.
        ax.text(it[k] - 0.5, 1.01, f"{run['stage']} {run['size']}²", fontsize=7, rotation=60,
                va="bottom", ha="left", transform=ax.get_xaxis_transform(), color="dimgrey", clip_on=False)
        k += run["iterations"]
    if it:
        ax.set_xlim(min(it) - 0.6, max(it) + 0.6)
    if finite:
        ax.set_ylim(min(finite) / 1.5, max(finite) * 3)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("LM iteration (all stages)")
    ax.set_ylabel(_LOSS_LABEL, fontsize=8)
    ax.set_title("SVBRDF recovery: fit loss per iteration (stage and level size marked above)", fontsize=9,
                 pad=44)
    ax.grid(True, which="major", alpha=0.3)
    # Below the axes, where it hides no curve.
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


#: Panels of :func:`maps_figure`: map name, title, colour-bar label.
_MAP_PANELS = (
    ("roughness", "roughness", "roughness (0 smooth, 1 rough)"),
    ("specular", "specular", "specular (dielectric reflectance / 0.08)"),
    ("metallic", "metallic", "metallic (0 dielectric, 1 metal)"),
    ("confidence", "confidence", "confidence (1 measured, 0 from the priors)"),
)


def maps_figure(path: Path, maps: dict, confidence: Tensor | None = None) -> None:
    """All recovered maps in one labelled figure: scalar maps with colour bars, axes in sample units.

    ``maps``: ``(C, H, W)`` maps by name (see :data:`~torchbrdf.capture.synthetic.MAP_NAMES`);
    ``confidence``: ``(1, H, W)`` in [0, 1] or None. Base colour is shown in sRGB, the normal
    as its tangent-space xyz mapped from [-1, 1] to RGB. The axes give the sample's world
    x/y coordinates ([-1, 1], the scale of every panel).
    """
    from torchbrdf.io import to_display

    plt = pyplot()
    scalars = [panel for panel in _MAP_PANELS
               if panel[0] in maps or (panel[0] == "confidence" and confidence is not None)]
    n = 2 + len(scalars)
    cols = 3
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    extent = (-1.0, 1.0, -1.0, 1.0)  # row 0 is the +y edge (docs/capture_format.md)
    panels: list[tuple[str, Tensor, str | None]] = [
        ("base colour (sRGB display)", to_display(maps["base_color"], srgb=True), None),
        ("normal (xyz → RGB, [-1, 1] → [0, 1])", (maps["normal"] * 0.5 + 0.5).clamp(0, 1), None)]
    for key, title, bar_label in scalars:
        img = confidence if key == "confidence" and confidence is not None else maps[key]
        panels.append((title, img, bar_label))
    for index, (ax, (title, img, scale)) in enumerate(zip(axes.flat, panels)):
        if scale is None:
            ax.imshow(img.permute(1, 2, 0).numpy(), extent=extent, interpolation="nearest")
        else:
            im = ax.imshow(img[0].numpy(), extent=extent, vmin=0.0, vmax=1.0, cmap="viridis",
                           interpolation="nearest")
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).set_label(scale, fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("sample x (world units)", fontsize=7)
        if index % cols == 0:  # one y label per row: the colour bars' labels need the room
            ax.set_ylabel("sample y (world units)", fontsize=7)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
