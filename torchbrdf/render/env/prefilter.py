"""Prefiltered environment maps: power-conserving resampling and lobe convolutions.

Every prefiltered level and the irradiance map conserve the map's power exactly (area
resampling with solid-angle overlaps, then a symmetrically normalised convolution), for any
map size. :func:`prefilter_environment` convolves with the GGX lobe under the ``n = v = r``
assumption at each of :data:`PREFILTER_ROUGHNESS`; :func:`irradiance_environment` with the
cosine.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import torch
from torch import Tensor

from torchbrdf.render.sampling import ALPHA_MIN, latlong_row_solid_angles

__all__ = [
    "PREFILTER_ROUGHNESS",
    "PREFILTER_MAX_HEIGHT",
    "IRRADIANCE_HEIGHT",
    "UNIFORM",
    "kernel_mean_cosine",
    "prefilter_environment",
    "irradiance_environment",
]


#: Roughness of each prefiltered level (level 0 is the map itself).
PREFILTER_ROUGHNESS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: Largest prefiltered level height; the kernel costs O(height² · width).
PREFILTER_MAX_HEIGHT = 128
#: Height of the irradiance (cosine-convolved) map.
IRRADIANCE_HEIGHT = 64


@lru_cache(maxsize=64)
def _overlap_weights(src: int, dst: int, rows: bool) -> Tensor:
    """Overlap of each destination interval with each source interval, float64 ``(dst, src)``.

    Rows (``rows=True``): the solid-angle measure of the overlap of the θ bands,
    ``cos θ_lo - cos θ_hi`` (the exact integral of ``sin θ``). Columns: the overlap length
    in units of the full turn. Every source interval is covered exactly once, so the columns
    of the matrix sum to the source intervals' measures: resampling with it conserves power.
    """
    s = torch.arange(src + 1, dtype=torch.float64) / src
    d = torch.arange(dst + 1, dtype=torch.float64) / dst
    lo = torch.maximum(d[:-1, None], s[None, :-1])
    hi = torch.minimum(d[1:, None], s[None, 1:])
    if rows:
        return torch.clamp(torch.cos(lo * math.pi) - torch.cos(hi * math.pi), min=0.0)
    return torch.clamp(hi - lo, min=0.0)


def _downsample(img: Tensor, h: int, w: int) -> Tensor:
    """Power-conserving area resampling of ``(B, 3, H, W)`` to ``(B, 3, h, w)``.

    Each output texel is the solid-angle-weighted mean of the (piecewise-constant) input over
    its own area, with fractional overlaps of the row bands and columns, so
    ``Σ L Ω`` (the map's power) is the same before and after for every size ratio. (Pooling
    with overlapping windows, e.g. ``adaptive_avg_pool2d`` at non-integer ratios, is not.)
    """
    H, W = img.shape[-2:]
    if (h, w) == (H, W):
        return img
    rw = _overlap_weights(H, h, True)
    cw = _overlap_weights(W, w, False)
    # Normalise by the weights' own sums (= the output texel's measure) so constants map exactly.
    rw = (rw / rw.sum(1, keepdim=True)).to(img.dtype).to(img.device)
    cw = (cw / cw.sum(1, keepdim=True)).to(img.dtype).to(img.device)
    return torch.einsum("ki,bcij,lj->bckl", rw, img, cw)


#: Kernel of the broadest level: uniform over the hemisphere about ``r`` (mean cosine 1/2),
#: for lobes broader than the cosine (a rough specular or diffuse lobe at grazing view).
UNIFORM = "uniform"


def _lobe_kernel(rl: Tensor, alpha: float | str | None) -> Tensor:
    """Unnormalised prefiltering kernel at ``rl = r·l`` (any shape): ``max(r·l, 0)`` for
    ``alpha=None`` (the cosine lobe), ``[r·l > 0]`` for :data:`UNIFORM`, else
    ``D_α(r·h) max(r·l, 0)`` with ``h = normalize(r + l)``."""
    k = torch.clamp(rl, min=0.0)
    if alpha is None:
        return k
    if alpha == UNIFORM:
        return (rl > 0).to(rl.dtype)
    assert isinstance(alpha, float)
    # With h = normalize(r + l): (r·h)² = (1 + r·l) / 2 and |r × h|² = (1 - r·l) / 2.
    a2 = alpha * alpha
    den = a2 * 0.5 * (1.0 + rl) + 0.5 * (1.0 - rl)
    return k * a2 / (math.pi * den * den)


@lru_cache(maxsize=32)
def kernel_mean_cosine(alpha: float | str | None) -> float:
    """``∫ k (r·l) dω / ∫ k dω`` of :func:`_lobe_kernel`: how concentrated the lobe is about
    ``r`` (2/3 for the cosine lobe, → 1 as ``α`` → 0). A lobe symmetric about ``r`` with this
    mean cosine ``κ`` has first moment ``κ r``. Midpoint rule over the polar angle."""
    t = (torch.arange(20000, dtype=torch.float64) + 0.5) * (0.5 * math.pi / 20000)
    c = torch.cos(t)
    k = _lobe_kernel(c, alpha) * torch.sin(t)
    return float((k * c).sum() / k.sum())


@lru_cache(maxsize=32)
def _kernel_fft(h: int, w: int, alpha: float | str | None, dtype: torch.dtype, device_str: str) -> Tensor:
    """Conjugated rFFT along φ of the normalised lat-long convolution kernel, ``(h, h, w//2+1)``.

    Row ``i`` (output) against row ``i'`` and column offset ``j`` (input); the convolution
    along φ is exact (circular, by FFT) and the normalisation conserves power.

    ``alpha=None`` gives the cosine kernel ``max(r·l, 0)``; otherwise the GGX kernel
    ``D_α(r·h) max(r·l, 0)`` with ``h = normalize(r + l)`` (Karis' ``n = v = r``).
    """
    dev = torch.device(device_str)
    theta = (torch.arange(h, dtype=torch.float64) + 0.5) * (math.pi / h)
    dphi = torch.arange(w, dtype=torch.float64) * (2.0 * math.pi / w)
    st, ct = torch.sin(theta), torch.cos(theta)
    r = torch.stack((st, torch.zeros_like(st), ct), dim=-1)[:, None, None, :]  # (h, 1, 1, 3)
    l = torch.stack(
        (st[:, None] * torch.cos(dphi)[None], st[:, None] * torch.sin(dphi)[None], ct[:, None].expand(h, w)),
        dim=-1,
    )[None]  # (1, h, w, 3)
    rl = (r * l).sum(-1)  # cos of the angle between r and l, (h, h, w)
    k = _lobe_kernel(rl, alpha)
    # Normalise symmetrically, k[i, i', j] = g Ω_i' c_i c_i' (g depends on r·l only, so it is
    # symmetric in i, i'), with c solving c_i Σ g Ω_i' c_i' = 1 (symmetric Sinkhorn). Then every
    # row sums to 1 (a constant map is unchanged) AND Σ_i Ω_i k[i, i', ·] = Ω_i' (each input
    # texel's power is passed on whole). Normalising rows alone does only the former.
    omega = latlong_row_solid_angles(h, w, dtype=torch.float64)
    a = k.sum(-1) * omega[None, :]  # (h, h): Σ_j g Ω_i'
    c = torch.rsqrt(a.sum(1))
    for _ in range(200):
        c_new = torch.sqrt(c / (a @ c))
        done = bool(((c_new - c).abs() <= 1e-15 * c).all())
        c = c_new
        if done:
            break
    k = k * (omega[None, :] * c[:, None] * c[None, :])[..., None]
    kf = torch.conj(torch.fft.rfft(k, dim=-1))
    cdt = torch.complex64 if dtype in (torch.float32, torch.float16, torch.bfloat16) else torch.complex128
    return kf.to(cdt).to(dev)


def _convolve(img: Tensor, alpha: float | str | None) -> Tensor:
    """Convolve ``(B, 3, h, w)`` with the lat-long kernel (see :func:`_kernel_fft`)."""
    h, w = img.shape[-2:]
    kf = _kernel_fft(h, w, alpha, img.dtype, str(img.device))
    lf = torch.fft.rfft(img, dim=-1)
    of = torch.einsum("iak,bcak->bcik", kf, lf.to(kf.dtype))
    return torch.fft.irfft(of, n=w, dim=-1).to(img.dtype)


def _level_size(height: int, width: int, alpha: float) -> tuple[int, int]:
    # Texels well below the lobe's angular width (~2α in l): ~6/α rows, within [32, max]
    # (below 32 rows a small bright source smeared over a 6° texel biases even the broad lobes).
    hk = min(height, max(32, min(PREFILTER_MAX_HEIGHT, math.ceil(6.0 / alpha))))
    wk = max(1, round(width * hk / height))
    return hk, wk


def prefilter_environment(radiance: Tensor, roughness_levels: Sequence[float] = PREFILTER_ROUGHNESS) -> list[Tensor]:
    """GGX-prefiltered copies of a lat-long map, one per roughness level (differentiable).

    Level ``k`` is ``∫ L(l) D(h) max(r·l, 0) dω / ∫ D(h) max(r·l, 0) dω`` with
    ``h = normalize(r + l)`` and ``α = max(roughness², 0.001)``, evaluated as an FFT
    convolution along φ on a map area-averaged to a resolution matched to the lobe width
    (32–128 rows). Both steps conserve the map's power ``Σ L Ω`` exactly, whatever the size
    ratio. Roughness 0 returns the map itself.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)``.
        roughness_levels: perceptual roughness of each level.

    Returns:
        List of ``(B, 3, H_k, W_k)`` maps.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    H, W = img.shape[-2:]
    out = []
    for r in roughness_levels:
        if r <= 0:
            out.append(img)
            continue
        alpha = max(r * r, ALPHA_MIN)
        hk, wk = _level_size(H, W, alpha)
        out.append(_convolve(_downsample(img, hk, wk), alpha))
    return out


def irradiance_environment(radiance: Tensor, height: int = IRRADIANCE_HEIGHT,
                           kernel: str | None = None) -> Tensor:
    """Normalised cosine convolution ``∫ L max(n·l, 0) dω / π`` of a map, ``(B, 3, h, 2h)``.

    Normalised so that a constant map maps to itself exactly and the power ``Σ L Ω`` is kept
    (the map is first area-resampled to ``min(H, height)`` rows, which keeps it too). With
    ``kernel=UNIFORM``: the mean radiance over each hemisphere, ``∫ L dω / 2π``.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    H, W = img.shape[-2:]
    hk = min(H, height)
    wk = max(1, round(W * hk / H))
    return _convolve(_downsample(img, hk, wk), kernel)
