"""Fresnel reflectance: Schlick's approximation, exact dielectric and conductor forms.

Cosines are ``(*, 1)`` tensors (or broadcastable); reflectances broadcast against them, so an
RGB ``f0`` of shape ``(*, 3)`` gives an RGB result. References: Hoffman 2013 (seed 003) for
Schlick and the F0 table; PBRT's notes (seed 004) for the exact forms.
"""

from __future__ import annotations

from typing import TypeVar

import torch
from torch import Tensor

from torchbrdf._math import half_safe, safe_sqrt, schlick_weight
from torchbrdf._types import Color, Scalar

# A float in gives a float out, a tensor gives a tensor (the conversions below are pure arithmetic).
_S = TypeVar("_S", float, Tensor)

__all__ = [
    "fresnel_schlick",
    "fresnel_dielectric",
    "fresnel_conductor",
    "f0_from_ior",
    "ior_from_f0",
    "f0_from_specular",
    "specular_from_f0",
]

# Principled "specular" maps linearly onto normal-incidence reflectance: 0.5 -> F0 = 0.04.
SPECULAR_TO_F0 = 0.08


@half_safe
def fresnel_schlick(cos_theta: Tensor, f0: Color, f90: Color = 1.0) -> Tensor:
    """Schlick's approximation ``F0 + (F90 - F0) (1 - cos)^5``.

    Args:
        cos_theta: cosine between the light (or view) and the microfacet normal, ``(*, 1)``;
            clamped to ``[0, 1]``.
        f0: reflectance at normal incidence, ``(*, C)`` or float.
        f90: reflectance at grazing incidence, ``(*, C)`` or float (1 for physical Fresnel).

    Returns:
        ``(*, C)`` reflectance, broadcast of the inputs.
    """
    return f0 + (f90 - f0) * schlick_weight(cos_theta)


@half_safe
def fresnel_dielectric(cos_theta_i: Tensor, eta: Scalar) -> Tensor:
    """Exact unpolarised Fresnel reflectance of a dielectric interface.

    Args:
        cos_theta_i: cosine of the incident direction with the interface normal, ``(*, 1)``;
            negative when arriving from inside, in which case ``eta`` is inverted.
        eta: relative index of refraction ``n_transmitted / n_incident``, ``(*, C)`` or float.

    Returns:
        ``(*, C)`` reflectance in ``[0, 1]``; exactly 1 under total internal reflection.
    """
    eta = torch.as_tensor(eta, dtype=cos_theta_i.dtype, device=cos_theta_i.device)
    inside = cos_theta_i < 0
    eta = torch.where(inside, 1.0 / eta, eta)
    cos_i = torch.clamp(cos_theta_i.abs(), max=1.0)
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1.0
    # Keep the sqrt argument positive in the TIR branch so its gradient stays finite.
    cos_t = safe_sqrt(1.0 - torch.clamp(sin2_t, max=1.0))
    r_par = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    f = 0.5 * (r_par * r_par + r_perp * r_perp)
    return torch.where(tir, torch.ones_like(f), f)


def _sqrt0(x: Tensor) -> Tensor:
    """``sqrt(x)`` for ``x >= 0``, exact (no floor), with gradient 0 instead of inf at ``x = 0``."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


@half_safe
def fresnel_conductor(cos_theta_i: Tensor, eta: Color, k: Color) -> Tensor:
    """Exact unpolarised Fresnel reflectance of a conductor with complex IOR ``eta + i k``.

    Real-arithmetic form (no complex dtypes, so half precision and autograd work alike),
    agreeing with complex arithmetic (pbrt-v4's ``FrComplex``) to ~1e-10 relative in float64
    for ``eta`` in [0.05, 5], ``k`` in [0, 10] and every angle -- including a nearly lossless
    ``eta < 1`` beyond the critical angle, where the textbook form loses ``a`` to cancellation.

    With ``a + i b = sqrt((eta + i k)^2 - sin^2)`` (``a, b >= 0``) and ``c = cos``, ``s2 = sin^2``::

        r_s = ((a - c)^2 + b^2) / ((a + c)^2 + b^2)
        r_p = r_s ((a c - s2)^2 + b^2 c^2) / ((a c + s2)^2 + b^2 c^2)

    Every numerator and denominator is a sum of squares (no cancellation). ``a^2`` and ``b^2``
    come from ``t0 = eta^2 - k^2 - s2`` and ``|.| = sqrt(t0^2 + 4 eta^2 k^2)``: the larger of the
    two is ``(|.| + |t0|) / 2`` and the smaller ``eta^2 k^2`` divided by it (their product),
    instead of ``(|.| - |t0|) / 2``, which cancels. Square roots are exact, with zero gradient at
    0 (``k = 0`` under total internal reflection), so gradients stay finite everywhere.

    Args:
        cos_theta_i: incident cosine ``(*, 1)``, clamped to ``[0, 1]``.
        eta: real part of the relative IOR, ``(*, C)`` or float, > 0.
        k: extinction coefficient (imaginary part), ``(*, C)`` or float, >= 0.

    Returns:
        ``(*, C)`` reflectance in ``[0, 1]``; 1 at grazing incidence (``cos = 0``).
    """
    c = torch.clamp(cos_theta_i, 0.0, 1.0)
    c2 = c * c
    # (1 - c)(1 + c): 1 - c is exact for c >= 1/2, so sin^2 keeps its relative accuracy where it
    # is small -- needed at the critical angle of a small eta, where t0 below is ~0.
    s2 = (1.0 - c) * (1.0 + c)
    ek2 = (eta * k) ** 2  # (Im of (eta + i k)^2 / 2)^2 = a^2 b^2
    t0 = eta * eta - k * k - s2  # a^2 - b^2
    norm = _sqrt0(t0 * t0 + 4.0 * ek2)  # a^2 + b^2
    big = 0.5 * (norm + t0.abs())
    small = ek2 / torch.where(big > 0, big, torch.ones_like(big))  # big = 0 only where ek2 = 0
    a2 = torch.where(t0 >= 0, big, small)
    b2 = torch.where(t0 >= 0, small, big)
    a = _sqrt0(a2)
    b2c2 = b2 * c2
    num_s, den_s = (a - c) ** 2 + b2, (a + c) ** 2 + b2
    ac = a * c
    num_p, den_p = (ac - s2) ** 2 + b2c2, (ac + s2) ** 2 + b2c2
    # den_s = 0 only at grazing incidence on an index-matched lossless interface (the limit
    # there is 1, as for every other interface at grazing); den_p = 0 only for eta = k = 0.
    one = torch.ones_like(den_s)
    r_s = torch.where(den_s > 0, num_s / torch.where(den_s > 0, den_s, one), one)
    ratio_p = torch.where(den_p > 0, num_p / torch.where(den_p > 0, den_p, one), one)
    return 0.5 * r_s * (1.0 + ratio_p)


def f0_from_ior(ior: _S) -> _S:
    """Normal-incidence reflectance ``((ior - 1) / (ior + 1))^2`` of a dielectric in air."""
    r = (ior - 1.0) / (ior + 1.0)
    return r * r


def ior_from_f0(f0: Scalar) -> Tensor:
    """Inverse of :func:`f0_from_ior` for ``0 <= f0 < 1``: ``(1 + sqrt F0) / (1 - sqrt F0)``.

    Returns a tensor of ``f0``'s shape (0-d for a float).
    """
    s = torch.sqrt(torch.as_tensor(f0))
    return (1.0 + s) / (1.0 - s)


def f0_from_specular(specular: _S) -> _S:
    """Principled ``specular`` to normal-incidence reflectance: ``F0 = 0.08 * specular``."""
    return SPECULAR_TO_F0 * specular


def specular_from_f0(f0: _S) -> _S:
    """Inverse of :func:`f0_from_specular`: ``specular = F0 / 0.08``."""
    return f0 / SPECULAR_TO_F0
