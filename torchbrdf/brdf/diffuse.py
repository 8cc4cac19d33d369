"""Diffuse reflectance models. Cosines are ``(*, 1)``; colours ``(*, C)``; results ``(*, C)``.

Each returns the BRDF value (including ``1/π``, without the ``n·l`` cosine).
"""

from __future__ import annotations

import math
from typing import overload

import torch
from torch import Tensor

from torchbrdf._math import half_safe
from torchbrdf._types import Color, Scalar
from torchbrdf.brdf import formula

__all__ = ["diffuse_lambert", "diffuse_burley", "diffuse_subsurface", "diffuse_oren_nayar"]

INV_PI = 1.0 / math.pi
# The dtype-independent torch ops of the shared formulas (only the elementwise ones are used here).
_OPS = formula.TorchOps(torch.float32)


@overload
def diffuse_lambert(base_color: Tensor) -> Tensor: ...
@overload
def diffuse_lambert(base_color: float) -> float: ...
@half_safe
def diffuse_lambert(base_color: Color) -> Color:
    """Lambert: ``base_color / π``; ``(*, 3)`` (or a float) in, the same shape out."""
    return base_color * INV_PI


@half_safe
def burley_retro_factor(n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor, roughness: Scalar) -> Tensor:
    """Burley's diffuse Fresnel factor ``lerp(1, Fd90, FL) · lerp(1, Fd90, FV)``, ``(*, 1)``.

    ``Fd90 = 0.5 + 2 roughness (l·h)²``: rough surfaces brighten toward grazing
    (retro-reflection), smooth ones darken (Burley 2012 §5.3).
    """
    return formula.burley_retro_factor(_OPS, n_dot_l, n_dot_v, l_dot_h, roughness)


@half_safe
def subsurface_factor(n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor, roughness: Scalar) -> Tensor:
    """Burley's Hanrahan–Krueger-like subsurface factor ``1.25 (Fss (1/(NL+NV) - 0.5) + 0.5)``.

    ``NL + NV`` is floored at 1e-7 (both at 1e-7 is the hardest grazing case the library
    supports; the value there is ~1e7 but finite).
    """
    return formula.subsurface_factor(_OPS, n_dot_l, n_dot_v, l_dot_h, roughness)


@half_safe
def diffuse_burley(
    n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor, base_color: Color, roughness: Scalar
) -> Tensor:
    """Burley's retro-reflective diffuse: ``base_color / π · Fd`` (see :func:`burley_retro_factor`).

    Cosines ``(*, 1)``, ``base_color`` ``(*, 3)`` or a float, ``roughness`` ``(*, 1)`` or a float;
    returns ``(*, 3)`` (``(*, 1)`` for a float ``base_color``).
    """
    return base_color * INV_PI * burley_retro_factor(n_dot_l, n_dot_v, l_dot_h, roughness)


@half_safe
def diffuse_subsurface(
    n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor, base_color: Color, roughness: Scalar
) -> Tensor:
    """The principled model's subsurface approximation: ``base_color / π · ss``.

    Cosines ``(*, 1)``, ``base_color`` ``(*, 3)`` or a float, ``roughness`` ``(*, 1)`` or a float;
    returns ``(*, 3)`` (``(*, 1)`` for a float ``base_color``).
    """
    return base_color * INV_PI * subsurface_factor(n_dot_l, n_dot_v, l_dot_h, roughness)


@half_safe
def diffuse_oren_nayar(
    n_dot_l: Tensor, n_dot_v: Tensor, l_dot_v: Tensor, base_color: Color, sigma: Scalar
) -> Tensor:
    """Oren–Nayar in PBRT's form, ``R/π (A + B max(0, cos Δφ) sin α tan β)``.

    Written without trigonometry: ``max(0, cos Δφ) sin α tan β = max(0, l·v - NL NV) /
    max(NL, NV)`` (the tangential dot product over the larger cosine), which is exact and has
    finite gradients at normal incidence.

    Args:
        n_dot_l, n_dot_v, l_dot_v: ``(*, 1)`` cosines.
        base_color: ``(*, C)`` reflectance.
        sigma: standard deviation of the facet angle in radians, ``(*, 1)`` or float.
    """
    s2 = sigma * sigma
    a = 1.0 - s2 / (2.0 * (s2 + 0.33))
    b = 0.45 * s2 / (s2 + 0.09)
    tangential = torch.clamp(l_dot_v - n_dot_l * n_dot_v, min=0.0)
    term = tangential / torch.clamp(torch.maximum(n_dot_l, n_dot_v), min=1e-7)
    return base_color * INV_PI * (a + b * term)
