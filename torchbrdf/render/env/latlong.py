"""Lat-long environment maps: texel lookups, bilinear reads and texel cells.

The map follows the library's lat-long convention (z up; row ``i`` at ``θ = (i + 0.5) π / H``,
column ``j`` at ``φ = -π + (j + 0.5) 2π / W``) and is read as **piecewise constant over
texels**: ``L(l)`` is the texel containing ``l`` (:func:`latlong_lookup`). That defines the
environment integral exactly. Maps are ``(3, H, W)`` or ``(B, 3, H, W)``; the integrators read
them channel-last, ``(B, H, W, 3)`` (:func:`as_bhwc`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchbrdf._math import dot, safe_sqrt
from torchbrdf._types import BRDF
from torchbrdf.render.sampling import latlong_row_solid_angles, latlong_texel_index

__all__ = ["as_bhwc", "latlong_lookup", "lookup_cl", "direction_angles", "latlong_bilinear", "texel_cells",
           "directions_sum"]


def as_bhwc(radiance: Tensor) -> Tensor:
    """``(3, H, W)`` or ``(B, 3, H, W)`` -> channel-last ``(B, H, W, 3)``."""
    if radiance.dim() == 3:
        radiance = radiance.unsqueeze(0)
    return radiance.permute(0, 2, 3, 1)


def latlong_lookup(radiance: Tensor, d: Tensor, batch_index: Tensor | None = None) -> Tensor:
    """Radiance of the texel containing each direction (piecewise-constant map).

    Differentiable with respect to ``radiance`` (not ``d``: the lookup is piecewise constant).

    Args:
        radiance: ``(B, 3, H, W)`` or ``(3, H, W)`` lat-long map.
        d: ``(*, 3)`` directions.
        batch_index: int64 ``(*)`` map index per direction when ``B > 1``.

    Returns:
        ``(*, 3)``.
    """
    return lookup_cl(as_bhwc(radiance), d, batch_index)


def lookup_cl(img: Tensor, d: Tensor, batch_index: Tensor | None) -> Tensor:
    b, h, w, _ = img.shape
    row, col = latlong_texel_index(d.detach(), h, w)
    flat = row * w + col
    if b > 1:
        if batch_index is None:
            raise ValueError(f"batch_index is required to look up a batch of {b} maps")
        flat = flat + batch_index.long() * (h * w)
    table = img.reshape(b * h * w, 3)
    return table[flat]


def direction_angles(d: Tensor) -> tuple[Tensor, Tensor]:
    """``(θ, φ)`` of ``d`` ``(*, 3)`` with finite gradients at the poles, each ``(*)``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    rho2 = x * x + y * y
    pole = rho2 < 1e-20
    xs = torch.where(pole, torch.ones_like(x), x)
    ys = torch.where(pole, torch.zeros_like(y), y)
    phi = torch.atan2(ys, xs)
    theta = torch.atan2(safe_sqrt(rho2), z)
    return theta, phi


def latlong_bilinear(
    img: Tensor, d: Tensor, batch_index: Tensor | None = None, *, angles: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """Bilinear lookup in a channel-last lat-long image (wraps in φ, clamps in θ).

    Differentiable with respect to ``img`` and ``d``.

    Args:
        img: ``(B, H, W, C)`` channel-last map.
        d: ``(*, 3)`` unit directions.
        batch_index: int64 ``(*)`` when ``B > 1``.
        angles: ``d``'s ``(θ, φ)`` when already known (several maps read along the same
            directions).

    Returns:
        ``(*, C)``.
    """
    b, h, w, c = img.shape
    theta, phi = direction_angles(d) if angles is None else angles
    fy = theta * (h / math.pi) - 0.5
    fx = (phi + math.pi) * (w / (2.0 * math.pi)) - 0.5
    y0 = torch.floor(fy.detach())
    x0 = torch.floor(fx.detach())
    ty = (fy - y0).unsqueeze(-1)
    tx = (fx - x0).unsqueeze(-1)
    y0 = y0.long()
    x0 = x0.long()
    r0 = torch.clamp(y0, 0, h - 1)
    r1 = torch.clamp(y0 + 1, 0, h - 1)
    c0 = torch.remainder(x0, w)
    c1 = torch.remainder(x0 + 1, w)
    base: Tensor | int = 0
    if b > 1:
        if batch_index is None:
            raise ValueError(f"batch_index is required to look up a batch of {b} maps")
        base = batch_index.long() * (h * w)
    table = img.reshape(b * h * w, c)
    v00 = table[base + r0 * w + c0]
    v01 = table[base + r0 * w + c1]
    v10 = table[base + r1 * w + c0]
    v11 = table[base + r1 * w + c1]
    top = v00 + (v01 - v00) * tx
    bot = v10 + (v11 - v10) * tx
    return top + (bot - top) * ty


def texel_cells(height: int, width: int, rows: Tensor, cols: Tensor, subdivisions: int,
                 dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Centres and solid angles of the cells of lat-long texels: ``((K·s², 3), (K·s²,))``.

    Texel ``(rows[k], cols[k])`` (int64 ``(K,)``) is split into ``s × s`` cells of equal solid
    angle (uniform in ``cos θ`` and ``φ``), ``s = subdivisions``; its cells are consecutive.
    """
    s, dev = subdivisions, rows.device
    t = (torch.arange(s, dtype=torch.float64, device=dev) + 0.5) / s
    r = rows.to(torch.float64)[:, None]
    c0, c1 = torch.cos(r * (math.pi / height)), torch.cos((r + 1.0) * (math.pi / height))
    cos_t = c0 + t[None] * (c1 - c0)  # (K, s)
    phi = -math.pi + (cols.to(torch.float64)[:, None] + t[None]) * (2.0 * math.pi / width)  # (K, s)
    sin_t = torch.sqrt(torch.clamp(1.0 - cos_t * cos_t, min=0.0))
    d = torch.stack(
        (
            sin_t[:, :, None] * torch.cos(phi)[:, None, :],
            sin_t[:, :, None] * torch.sin(phi)[:, None, :],
            cos_t[:, :, None].expand(-1, -1, s),
        ),
        dim=-1,
    ).reshape(-1, 3)
    omega = latlong_row_solid_angles(height, width, dtype=torch.float64, device=dev)[rows] / (s * s)
    return d.to(dtype), omega.repeat_interleave(s * s).to(dtype)


def directions_sum(
    brdf: BRDF,
    n1: Tensor,
    v1: Tensor,
    x1: Tensor | None,
    y1: Tensor | None,
    mat: dict,
    ll: Tensor,
    weight: Tensor,
) -> Tensor:
    """``Σ_k f(l_k, v) w_k max(n·l_k, 0)`` over a few directions per point, ``(P, 3)``.

    ``ll`` ``(P, K, 3)`` are the directions, ``weight`` ``(P or 1, K, 3)`` their radiance ×
    solid angle; ``n1``/``v1``/``x1``/``y1`` are ``(P, 1, 3)`` and ``mat`` the material with a
    direction axis.
    """
    f = brdf(ll, v1, n1, x1, y1, **mat)
    return (f * weight * torch.clamp(dot(n1, ll), min=0.0)).sum(1)
