"""A map's concentrated sources (a sun, a lamp), taken out as directional lights.

Texels brighter than :data:`PEAK_CONTRAST` × the map's mean radiance (at most
:data:`PEAK_DIRECTIONS` cells of them) are split into cells and summed exactly through the
BRDF by the split sum; only the smooth rest is prefiltered.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchbrdf._math import compute_dtype, luminance
from torchbrdf.render.env.latlong import texel_cells
from torchbrdf.render.sampling import latlong_row_solid_angles

__all__ = [
    "PEAK_CONTRAST",
    "PEAK_DIRECTIONS",
    "PEAK_FINE_DIRECTIONS",
    "PEAK_CELL_ROWS",
    "PEAK_ELEMENTS_PER_PASS",
    "peak_subdivisions",
    "extract_peaks",
    "select_peaks",
    "peak_cells",
]


#: The split sum takes texels brighter than this multiple of the map's mean radiance out of
#: the map and sums them exactly, as directional lights (:func:`extract_peaks`): its
#: prefiltered lobe is symmetric about one lookup direction, which misplaces a small bright
#: source's response at grazing view by a few percent; a smooth remainder it handles well.
PEAK_CONTRAST = 64.0
#: Most directional lights the peaks of one map become (texels × cells), the brightest first.
PEAK_DIRECTIONS = 64
#: Most cells of the finer subdivision that lobes too sharp for the cells above are summed over.
PEAK_FINE_DIRECTIONS = 512
#: Peak texels are split into cells no larger than a texel of a map this tall (1.4°), finer
#: than a glossy lobe (2.8° cells aliased a roughness-0.2 highlight); lobes narrower than
#: four of them (roughness ≲ 0.2) are summed over cells up to 8× finer (PEAK_FINE_DIRECTIONS).
PEAK_CELL_ROWS = 128
# Points × directions the peaks are evaluated on at once (memory).
PEAK_ELEMENTS_PER_PASS = 1 << 20


def peak_subdivisions(height: int) -> int:
    """Cells per axis of a peak texel of a ``height``-row map (see :func:`extract_peaks`)."""
    return min(4, max(1, math.ceil(PEAK_CELL_ROWS / height)))


def extract_peaks(
    radiance: Tensor, contrast: float = PEAK_CONTRAST, max_directions: int = PEAK_DIRECTIONS
) -> tuple[Tensor, Tensor, Tensor]:
    """Take a map's concentrated sources (a sun, a lamp) out of it, as directional lights.

    A texel is a peak when its luminance exceeds ``contrast`` × the map's mean radiance
    (``Σ L Ω / 4π``); the brightest (by power) are taken, as many as ``max_directions``
    allows. Each peak texel is split into ``s × s`` cells of equal solid angle, no larger than
    a texel of a :data:`PEAK_CELL_ROWS`-row map (``s = ceil(PEAK_CELL_ROWS / H)``, at most 4),
    and every cell becomes a directional light of irradiance ``L Ω_cell`` at its centre. The
    peaks and the returned rest add up to the map exactly (its power is split, not changed).
    Differentiable in ``radiance``; the choice of texels is not. Outputs have ``radiance``'s
    dtype and device (texels are chosen in float32 at least: a sun overflows float16's
    luminance × solid angle); one host sync per call.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)``.
        contrast: a texel brighter than this multiple of the mean radiance is a peak.
        max_directions: most cells per map (``0``: no peaks).

    Returns:
        ``(rest, directions, irradiance)``: the map without its peaks ``(B, 3, H, W)``, the
        cells' unit directions ``(B, M, 3)`` and their irradiance ``(B, M, 3)`` (``M`` is the
        largest count over the batch; unused entries have zero irradiance). ``M = 0`` when no
        texel qualifies.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    found = select_peaks(img, contrast, max_directions)
    if found is None:
        none = img.new_zeros(img.shape[0], 0, 3)
        return img, none, none
    rest, idx, valid = found
    return (rest, *peak_cells(img, idx, valid, peak_subdivisions(img.shape[-2])))


def select_peaks(img: Tensor, contrast: float, max_directions: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """The peak texels of ``(B, 3, H, W)`` (see :func:`extract_peaks`).

    Returns ``(rest, idx, valid)`` with ``idx`` the flat texel indices ``(B, M)`` and ``valid``
    which of them are peaks, or ``None`` when no texel is one.
    """
    b, _, h, w = img.shape
    s = peak_subdivisions(h)
    per_map = min(max_directions // (s * s), h * w)
    dt, dev = img.dtype, img.device
    if per_map <= 0:
        return None
    with torch.no_grad():
        sel = compute_dtype(dt)  # (a sun overflows float16's luminance × solid angle)
        omega = latlong_row_solid_angles(h, w, dtype=sel, device=dev)[:, None]
        lum = luminance(img.detach().to(sel).movedim(1, -1)).squeeze(-1)  # (B, H, W)
        power = lum * omega
        mean = power.sum((1, 2), keepdim=True) / (4.0 * math.pi)
        score = torch.where((lum > contrast * mean) & (lum > 0), power, torch.zeros_like(power))
        top = torch.topk(score.reshape(b, -1), per_map, dim=1)
        count = int((top.values > 0).sum(1).max())  # the one host sync, once per map
    if count == 0:
        return None
    idx, valid = top.indices[:, :count], top.values[:, :count] > 0  # (B, M)
    keep = torch.ones(b, h * w, dtype=torch.bool, device=dev).scatter(1, idx, ~valid)
    return img * keep.view(b, 1, h, w).to(dt), idx, valid


def peak_cells(img: Tensor, idx: Tensor, valid: Tensor, s: int) -> tuple[Tensor, Tensor]:
    """Cells of some texels of ``img`` ``(B, 3, H, W)``, ``s × s`` per texel.

    ``idx``: flat texel indices ``(B, M)``; ``valid``: which are real. Returns the cells'
    directions and irradiance, ``(B, M·s², 3)`` each.
    """
    b, _, h, w = img.shape
    cells, omega_c = texel_cells(h, w, (idx // w).reshape(-1), (idx % w).reshape(-1), s, img.dtype)
    texel_l = img.flatten(2).transpose(1, 2).gather(1, idx[..., None].expand(-1, -1, 3))
    texel_l = texel_l * valid[..., None].to(img.dtype)  # (B, M, 3)
    irradiance = texel_l.repeat_interleave(s * s, dim=1) * omega_c.view(b, -1, 1)
    return cells.view(b, -1, 3), irradiance
