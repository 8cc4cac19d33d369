"""Masking–shadowing (geometry) terms.

``smith_g1_*`` give the fraction of microfacets visible from one direction; ``smith_g2_*``
combine light and view either separably (``G1(l) G1(v)``) or height-correlated
(``1 / (1 + Λ(l) + Λ(v))``, Heitz 2014). Anisotropic Smith needs only the *projected* alpha
of the direction, ``α_w = sqrt((w·x αx)² + (w·y αy)²) / sin θ_w``; pass ``tangent_alpha2``
``= (w·x αx)² + (w·y αy)²`` to the ``*_aniso`` helpers and everything stays free of
divisions by ``sin θ``. The non-Smith terms are Hoffman 2013 eq. 29–31. All inputs ``(*, 1)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchbrdf._math import half_safe, safe_sqrt
from torchbrdf._types import Scalar

__all__ = [
    "smith_g1_ggx",
    "smith_g1_ggx_aniso",
    "smith_lambda_ggx",
    "smith_g1_beckmann",
    "smith_g1_beckmann_walter",
    "smith_lambda_beckmann",
    "smith_g2_separable",
    "smith_g2_height_correlated",
    "smith_g2_ggx_correlated",
    "g_cook_torrance",
    "g_kelemen",
    "g_implicit",
]


def _tangent_alpha2(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Isotropic ``α² sin²θ = α² (1 - cos²θ)``."""
    return alpha * alpha * torch.clamp(1.0 - n_dot_w * n_dot_w, min=0.0)


@half_safe
def smith_g1_ggx_aniso(n_dot_w: Tensor, tangent_alpha2: Tensor) -> Tensor:
    """Heitz's anisotropic Smith G1 for GGX: ``2 cosθ / (cosθ + sqrt(cos²θ + (w·x αx)² + (w·y αy)²))``.

    Args:
        n_dot_w: ``(*, 1)`` cosine of the direction; G1 is 0 for ``n_dot_w <= 0``.
        tangent_alpha2: ``(*, 1)`` ``(w·x αx)² + (w·y αy)²``.
    """
    c = torch.clamp(n_dot_w, min=0.0)
    return 2.0 * c / (c + safe_sqrt(c * c + tangent_alpha2))


@half_safe
def smith_g1_ggx(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Isotropic Smith G1 for GGX (Walter et al. 2007), ``(*, 1)``."""
    return smith_g1_ggx_aniso(n_dot_w, _tangent_alpha2(n_dot_w, alpha))


@half_safe
def smith_lambda_ggx(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Smith Λ for GGX, ``(sqrt(1 + α² tan²θ) - 1) / 2``; large but finite at grazing.

    ``n_dot_w`` ``(*, 1)``, ``alpha`` a float or ``(*, 1)``; returns ``(*, 1)``.
    """
    c = torch.clamp(n_dot_w, min=1e-7)  # Λ → ∞ at the horizon; G built from it → 0
    return 0.5 * (safe_sqrt(c * c + _tangent_alpha2(c, alpha)) / c - 1.0)


@half_safe
def smith_lambda_beckmann(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Exact Smith Λ for Beckmann: ``(erf(a) - 1)/2 + exp(-a²)/(2a√π)``, ``a = cot θ / α``.

    ``n_dot_w`` ``(*, 1)``, ``alpha`` a float or ``(*, 1)``; returns ``(*, 1)``.
    """
    c = torch.clamp(n_dot_w, min=1e-7)
    sin_t = safe_sqrt(1.0 - c * c)
    a = torch.clamp(c / (alpha * sin_t), max=1e6)  # beyond 1e6 Λ is 0 to all precision
    return 0.5 * (torch.exp(-a * a) / (a * math.sqrt(math.pi)) - torch.erfc(a))


@half_safe
def smith_g1_beckmann(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Exact Smith G1 for Beckmann, ``1 / (1 + Λ)``; 0 for ``n_dot_w <= 0``.

    ``n_dot_w`` ``(*, 1)``, ``alpha`` a float or ``(*, 1)``; returns ``(*, 1)``.
    """
    g = 1.0 / (1.0 + smith_lambda_beckmann(n_dot_w, alpha))
    return torch.where(n_dot_w > 0, g, torch.zeros_like(g))


@half_safe
def smith_g1_beckmann_walter(n_dot_w: Tensor, alpha: Scalar) -> Tensor:
    """Walter et al.'s rational approximation of the Beckmann Smith G1 (error < 0.35 %).

    ``n_dot_w`` ``(*, 1)``, ``alpha`` a float or ``(*, 1)``; returns ``(*, 1)``.
    """
    c = torch.clamp(n_dot_w, min=1e-7)
    a = c / (alpha * safe_sqrt(1.0 - c * c))
    g = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    g = torch.where(a < 1.6, g, torch.ones_like(g))
    return torch.where(n_dot_w > 0, g, torch.zeros_like(g))


@half_safe
def smith_g2_separable(g1_l: Tensor, g1_v: Tensor) -> Tensor:
    """Separable masking–shadowing ``G1(l) G1(v)``: ``(*, 1)`` each, returns ``(*, 1)``."""
    return g1_l * g1_v


@half_safe
def smith_g2_height_correlated(lambda_l: Tensor, lambda_v: Tensor) -> Tensor:
    """Height-correlated masking–shadowing ``1 / (1 + Λ(l) + Λ(v))`` (Heitz 2014).

    ``lambda_l``, ``lambda_v`` ``(*, 1)``; returns ``(*, 1)``.
    """
    return 1.0 / (1.0 + lambda_l + lambda_v)


@half_safe
def smith_g2_ggx_correlated(n_dot_l: Tensor, n_dot_v: Tensor, tan_a2_l: Tensor, tan_a2_v: Tensor) -> Tensor:
    """Height-correlated GGX G2 without Λ's division: ``2 NL NV / (NV s_l + NL s_v)``.

    ``s_w = sqrt(cos²θ_w + tangent_alpha2_w)``; stays finite and tends to 0 at the horizon.
    All arguments ``(*, 1)``; returns ``(*, 1)``.
    """
    nl = torch.clamp(n_dot_l, min=0.0)
    nv = torch.clamp(n_dot_v, min=0.0)
    s_l = safe_sqrt(nl * nl + tan_a2_l)
    s_v = safe_sqrt(nv * nv + tan_a2_v)
    return 2.0 * nl * nv / torch.clamp(nv * s_l + nl * s_v, min=1e-30)


@half_safe
def g_cook_torrance(n_dot_l: Tensor, n_dot_v: Tensor, n_dot_h: Tensor, v_dot_h: Tensor) -> Tensor:
    """Cook–Torrance (Blinn–Torrance–Sparrow) G, Hoffman eq. 30: ``min(1, 2 NH NV / VH, 2 NH NL / VH)``."""
    vh = torch.clamp(v_dot_h, min=1e-7)
    t = 2.0 * n_dot_h / vh
    g = torch.minimum(torch.minimum(t * n_dot_v, t * n_dot_l), torch.ones_like(t))
    return torch.clamp(g, min=0.0)


@half_safe
def g_kelemen(n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor) -> Tensor:
    """Kelemen's approximation, Hoffman eq. 31: ``G = NL NV / (l·h)²``.

    Cosines ``(*, 1)``; returns ``(*, 1)``.
    """
    lh = torch.clamp(l_dot_h, min=1e-4)  # l·h >= cos(90°/2) ≈ 0.707 whenever NL, NV > 0
    return torch.clamp(n_dot_l, min=0.0) * torch.clamp(n_dot_v, min=0.0) / (lh * lh)


@half_safe
def g_implicit(n_dot_l: Tensor, n_dot_v: Tensor) -> Tensor:
    """Implicit geometry term, Hoffman eq. 29: ``G = NL NV`` (visibility term 1).

    ``(*, 1)`` cosines in, ``(*, 1)`` out.
    """
    return torch.clamp(n_dot_l, min=0.0) * torch.clamp(n_dot_v, min=0.0)
