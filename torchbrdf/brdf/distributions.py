"""Microfacet normal distribution functions (NDFs), each normalised so ``∫ D(m) (n·m) dω = 1``.

Every isotropic NDF takes ``n_dot_h`` and optionally ``sin2_h = |n × h|^2``. Passing the
cross-product form of ``1 - (n·h)^2`` avoids the catastrophic cancellation of the naive
``1 + (α² - 1)(n·h)²`` at narrow peaks (float32 error drops from ~100 % to ~1e-7 at
α = 0.001). Shapes broadcast; the usual case is ``(*, 1)``.

Alpha is the NDF width, not the perceptual roughness; :func:`roughness_to_alpha` is the
only path between them and holds the floor. References: Burley 2012 appendix B (GTR,
eq. 1, 4, 13), Hoffman 2013 eq. 16–22 (Phong, Beckmann, Trowbridge–Reitz, ABC).
"""

from __future__ import annotations

import math
from typing import overload

import torch
from torch import Tensor

from torchbrdf._math import half_safe
from torchbrdf._types import Scalar
from torchbrdf.brdf import formula  # GTR1 is written once there (the principled clearcoat)
from torchbrdf.brdf.formula import ALPHA_MIN  # the principled model's floor (Burley 2012 code)

__all__ = [
    "ALPHA_MIN",
    "roughness_to_alpha",
    "ndf_ggx",
    "ndf_ggx_aniso",
    "ndf_gtr",
    "ndf_gtr1",
    "ndf_beckmann",
    "ndf_beckmann_aniso",
    "ndf_blinn_phong",
    "ndf_abc",
]

# |x| below which the removable-singularity helpers switch to their Taylor series
# (error ~x^4/720, far below float64 rounding for 1e-4).
_SERIES_EPS = 1e-4
# Floor under NDF denominators (α² cos² + sin²): only a zero half vector reaches it.
_DEN_EPS = 1e-18


@overload
def roughness_to_alpha(roughness: Tensor, alpha_min: float = ALPHA_MIN) -> Tensor: ...
@overload
def roughness_to_alpha(roughness: float, alpha_min: float = ALPHA_MIN) -> float: ...
def roughness_to_alpha(roughness: Scalar, alpha_min: float = ALPHA_MIN) -> Scalar:
    """Perceptual roughness to NDF width: ``α = max(alpha_min, roughness²)``."""
    if isinstance(roughness, Tensor):
        return torch.clamp(roughness * roughness, min=alpha_min)
    return max(alpha_min, roughness * roughness)


def _sin2(n_dot_h: Tensor, sin2_h: Tensor | None) -> Tensor:
    return torch.clamp(1.0 - n_dot_h * n_dot_h, min=0.0) if sin2_h is None else sin2_h


def _log_a2(a2: Tensor) -> Tensor:
    """``ln α²`` accurate everywhere: ``log1p(α² - 1)`` near 1 (where ``α² - 1`` is exact,
    Sterbenz) and ``log(α²)`` elsewhere (where forming ``α² - 1`` would drop α²'s digits)."""
    near_one = (a2 > 0.5) & (a2 < 2.0)
    return torch.where(near_one, torch.log1p(a2 - 1.0), torch.log(a2))


def _x_over_log1p(t: Tensor, log1p_t: Tensor | None = None) -> Tensor:
    """``t / log(1 + t)``, exact through its removable singularity at ``t = 0``.

    ``log1p_t`` may carry an accurately computed ``log(1 + t)`` (see :func:`_log_a2`).
    """
    small = t.abs() < _SERIES_EPS
    ts = torch.where(small, torch.ones_like(t), t)  # sanitised: the unused branch stays finite
    log_t = torch.log1p(ts) if log1p_t is None else torch.where(small, torch.log1p(ts), log1p_t)
    exact = ts / log_t
    series = 1.0 + t * (0.5 + t * (-1.0 / 12.0 + t / 24.0))
    return torch.where(small, series, exact)


def _x_over_expm1(u: Tensor) -> Tensor:
    """``u / (exp(u) - 1)``, exact through ``u = 0``."""
    small = u.abs() < _SERIES_EPS
    us = torch.where(small, torch.ones_like(u), u)
    exact = us / torch.expm1(us)
    series = 1.0 + u * (-0.5 + u / 12.0)
    return torch.where(small, series, exact)


def _expm1_over_x(u: Tensor) -> Tensor:
    """``(exp(u) - 1) / u``, exact through ``u = 0``."""
    small = u.abs() < _SERIES_EPS
    us = torch.where(small, torch.ones_like(u), u)
    exact = torch.expm1(us) / us
    series = 1.0 + u * (0.5 + u / 6.0)
    return torch.where(small, series, exact)


@half_safe
def ndf_ggx(n_dot_h: Tensor, alpha: Scalar, sin2_h: Tensor | None = None) -> Tensor:
    """GGX / Trowbridge–Reitz (GTR with γ = 2): ``α² / (π (α² cos²θh + sin²θh)²)``.

    Args:
        n_dot_h: ``(*, 1)`` cosine of the half vector with the normal.
        alpha: width ``(*, 1)`` or float, > 0.
        sin2_h: optional ``|n × h|²``, ``(*, 1)``; computed from ``n_dot_h`` if omitted.

    Returns:
        ``(*, 1)`` density; 0 for ``n_dot_h <= 0``.
    """
    a2 = alpha * alpha
    # Floor: the smallest legitimate value is α² >= 1e-6 (at the peak); 1e-18 only guards a
    # zero half vector, and its square still fits float32.
    d = torch.clamp(a2 * n_dot_h * n_dot_h + _sin2(n_dot_h, sin2_h), min=_DEN_EPS)
    return torch.where(n_dot_h > 0, a2 / (math.pi * d * d), torch.zeros_like(d))


@half_safe
def ndf_ggx_aniso(
    h_dot_x: Tensor, h_dot_y: Tensor, n_dot_h: Tensor, alpha_x: Scalar, alpha_y: Scalar
) -> Tensor:
    """Anisotropic GGX (Burley eq. 13): ``1 / (π αx αy ((h·x/αx)² + (h·y/αy)² + (h·n)²)²)``.

    All arguments ``(*, 1)`` (alphas may be floats). Has no cancellation at the peak.
    """
    tx = h_dot_x / alpha_x
    ty = h_dot_y / alpha_y
    d = tx * tx + ty * ty + n_dot_h * n_dot_h
    return torch.where(n_dot_h > 0, 1.0 / (math.pi * alpha_x * alpha_y * d * d), torch.zeros_like(d))


@half_safe
def gtr_normalization(alpha: Scalar, gamma: Scalar) -> Tensor:
    """GTR normalisation ``(γ-1)(α²-1) / (π (1 - (α²)^(1-γ)))`` (Burley eq. 1).

    Rewritten as ``(1/π) · t/log1p(t) · u/expm1(u)`` with ``t = α² - 1`` and
    ``u = (1 - γ) ln α²`` so both removable singularities — γ = 1 (eq. 4) and α = 1 (1/π) —
    are evaluated exactly, without nudging the parameters.
    """
    alpha = torch.as_tensor(alpha)
    gamma = torch.as_tensor(gamma, dtype=alpha.dtype, device=alpha.device)
    a2 = alpha * alpha
    log_a2 = _log_a2(a2)
    u = (1.0 - gamma) * log_a2
    return _x_over_log1p(a2 - 1.0, log_a2) * _x_over_expm1(u) / math.pi


@half_safe
def ndf_gtr(n_dot_h: Tensor, alpha: Scalar, gamma: Scalar, sin2_h: Tensor | None = None) -> Tensor:
    """Generalised Trowbridge–Reitz (Burley eq. 1) for any ``γ > 0``.

    ``D = c(α, γ) / (α² cos²θh + sin²θh)^γ`` with :func:`gtr_normalization`.

    Args:
        n_dot_h: ``(*, 1)``.
        alpha: ``(*, 1)`` or float, > 0.
        gamma: ``(*, 1)`` or float, > 0 (1 is the clearcoat lobe, 2 is GGX).
        sin2_h: optional ``|n × h|²`` ``(*, 1)``.

    Returns:
        ``(*, 1)`` density; 0 for ``n_dot_h <= 0``.
    """
    alpha_t = torch.as_tensor(alpha, dtype=n_dot_h.dtype, device=n_dot_h.device)
    a2 = alpha_t * alpha_t
    base = a2 * n_dot_h * n_dot_h + _sin2(n_dot_h, sin2_h)
    base = torch.clamp(base, min=torch.finfo(n_dot_h.dtype).tiny)
    d = gtr_normalization(alpha_t, gamma) * torch.exp(-gamma * torch.log(base))
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))


@half_safe
def ndf_gtr1(n_dot_h: Tensor, alpha: Scalar, sin2_h: Tensor | None = None) -> Tensor:
    """GTR with γ = 1 (Burley eq. 4, the clearcoat lobe): ``(α²-1) / (π ln α² (α² cos² + sin²))``.

    ``n_dot_h`` ``(*, 1)``, ``alpha`` a float or ``(*, 1)``, ``sin2_h`` optional ``|n × h|²``
    ``(*, 1)``; returns the ``(*, 1)`` density.
    """
    ops = formula.TorchOps(n_dot_h.dtype, n_dot_h.device)
    return formula.ndf_gtr1(ops, n_dot_h, alpha, _sin2(n_dot_h, sin2_h))


@half_safe
def ndf_beckmann(n_dot_h: Tensor, alpha: Scalar, sin2_h: Tensor | None = None) -> Tensor:
    """Beckmann (Hoffman eq. 17): ``exp(-tan²θh / α²) / (π α² cos⁴θh)``.

    Args:
        n_dot_h: ``(*, 1)``.
        alpha: ``(*, 1)`` or float, > 0 (RMS slope).
        sin2_h: optional ``|n × h|²``.

    Returns:
        ``(*, 1)`` density; 0 for ``n_dot_h <= 0``.
    """
    a2 = alpha * alpha
    c = torch.clamp(n_dot_h, min=1e-6)  # exp(-tan²/α²) underflows to 0 long before c = 1e-6
    c2 = c * c
    d = torch.exp(-_sin2(n_dot_h, sin2_h) / (a2 * c2)) / (math.pi * a2 * c2 * c2)
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))


@half_safe
def ndf_beckmann_aniso(
    h_dot_x: Tensor, h_dot_y: Tensor, n_dot_h: Tensor, alpha_x: Scalar, alpha_y: Scalar
) -> Tensor:
    """Anisotropic Beckmann: ``exp(-((h·x/αx)² + (h·y/αy)²) / (h·n)²) / (π αx αy (h·n)⁴)``.

    Cosines ``(*, 1)``, ``alpha_x``/``alpha_y`` floats or ``(*, 1)``; returns the ``(*, 1)``
    density, 0 for ``n_dot_h <= 0``.
    """
    c = torch.clamp(n_dot_h, min=1e-6)
    c2 = c * c
    tx = h_dot_x / alpha_x
    ty = h_dot_y / alpha_y
    d = torch.exp(-(tx * tx + ty * ty) / c2) / (math.pi * alpha_x * alpha_y * c2 * c2)
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))


@half_safe
def ndf_blinn_phong(n_dot_h: Tensor, exponent: Scalar) -> Tensor:
    """Normalised Blinn–Phong (Hoffman eq. 16): ``(p + 2) / (2π) (n·h)^p``.

    Args:
        n_dot_h: ``(*, 1)``.
        exponent: Phong exponent ``p >= 0``, ``(*, 1)`` or float.
    """
    c = torch.clamp(n_dot_h, min=torch.finfo(n_dot_h.dtype).tiny)
    d = (exponent + 2.0) / (2.0 * math.pi) * torch.exp(exponent * torch.log(c))
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))


@overload
def alpha_to_phong_exponent(alpha: Tensor) -> Tensor: ...
@overload
def alpha_to_phong_exponent(alpha: float) -> float: ...
def alpha_to_phong_exponent(alpha: Scalar) -> Scalar:
    """Walter et al.'s correspondence ``p = 2 / α² - 2`` between Beckmann α and Phong."""
    return 2.0 / (alpha * alpha) - 2.0


@half_safe
def abc_normalization(a: Scalar, gamma: Scalar) -> Tensor:
    """Normalisation ``k_abc`` of the ABC NDF (Hoffman eq. 20–22).

    Evaluated from the closed-form integral ``2π/a² [b E(1-γ) - E(2-γ)]`` with
    ``b = 1 + a`` and ``E(p) = (b^p - 1)/p = ln b · expm1(p ln b)/(p ln b)``, which passes
    through both removable singularities (γ = 1 gives eq. 21, γ = 2 gives eq. 22) exactly.
    Accurate for ``a >~ 1e-3`` (the fitted range is 1–1000).
    """
    a = torch.as_tensor(a)
    gamma = torch.as_tensor(gamma, dtype=a.dtype, device=a.device)
    log_b = torch.log1p(a)
    e1 = log_b * _expm1_over_x((1.0 - gamma) * log_b)
    e2 = log_b * _expm1_over_x((2.0 - gamma) * log_b)
    integral = 2.0 * math.pi / (a * a) * ((1.0 + a) * e1 - e2)
    return 1.0 / integral


@half_safe
def ndf_abc(n_dot_h: Tensor, a: Scalar, gamma: Scalar) -> Tensor:
    """ABC distribution (Hoffman eq. 19): ``k_abc / (1 + a (1 - n·h))^γ``.

    Args:
        n_dot_h: ``(*, 1)``.
        a: the "B" parameter, > 0, ``(*, 1)`` or float.
        gamma: the "C" parameter, > 0, ``(*, 1)`` or float.
    """
    a_t = torch.as_tensor(a, dtype=n_dot_h.dtype, device=n_dot_h.device)
    base = 1.0 + a_t * (1.0 - torch.clamp(n_dot_h, 0.0, 1.0))
    d = abc_normalization(a_t, gamma) * torch.exp(-gamma * torch.log(base))
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))
