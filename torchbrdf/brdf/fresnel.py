"""Fresnel reflectance: Schlick's approximation, exact dielectric and conductor forms.

Cosines are ``(*, 1)`` tensors (or broadcastable); reflectances broadcast against them, so an
RGB ``f0`` of shape ``(*, 3)`` gives an RGB result. References: Hoffman 2013 (seed 003) for
Schlick and the F0 table; PBRT's notes (seed 004) for the exact forms.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf._math import half_safe, safe_sqrt, schlick_weight

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
def fresnel_schlick(cos_theta: Tensor, f0, f90=1.0) -> Tensor:
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
def fresnel_dielectric(cos_theta_i: Tensor, eta) -> Tensor:
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


@half_safe
def fresnel_conductor(cos_theta_i: Tensor, eta, k) -> Tensor:
    """Exact unpolarised Fresnel reflectance of a conductor with complex IOR ``eta + i k``.

    Real-arithmetic form (no complex dtypes, so half precision and autograd work alike).

    Args:
        cos_theta_i: incident cosine ``(*, 1)``, clamped to ``[0, 1]``.
        eta: real part of the relative IOR, ``(*, C)`` or float.
        k: extinction coefficient (imaginary part), ``(*, C)`` or float.

    Returns:
        ``(*, C)`` reflectance in ``[0, 1]``.
    """
    cos_i = torch.clamp(cos_theta_i, 0.0, 1.0)
    cos2 = cos_i * cos_i
    sin2 = 1.0 - cos2
    t0 = eta * eta - k * k - sin2
    a2b2 = safe_sqrt(t0 * t0 + 4.0 * eta * eta * k * k)
    a = safe_sqrt(0.5 * (a2b2 + t0))
    t1 = a2b2 + cos2
    t2 = 2.0 * a * cos_i
    r_s = (t1 - t2) / (t1 + t2)
    t3 = cos2 * a2b2 + sin2 * sin2
    t4 = t2 * sin2
    r_p = r_s * (t3 - t4) / (t3 + t4)
    return 0.5 * (r_s + r_p)


def f0_from_ior(ior):
    """Normal-incidence reflectance ``((ior - 1) / (ior + 1))^2`` of a dielectric in air."""
    r = (ior - 1.0) / (ior + 1.0)
    return r * r


def ior_from_f0(f0):
    """Inverse of :func:`f0_from_ior` for ``0 <= f0 < 1``: ``(1 + sqrt F0) / (1 - sqrt F0)``."""
    s = torch.sqrt(torch.as_tensor(f0))
    return (1.0 + s) / (1.0 - s)


def f0_from_specular(specular):
    """Principled ``specular`` to normal-incidence reflectance: ``F0 = 0.08 * specular``."""
    return SPECULAR_TO_F0 * specular


def specular_from_f0(f0):
    """Inverse of :func:`f0_from_specular`: ``specular = F0 / 0.08``."""
    return f0 / SPECULAR_TO_F0
