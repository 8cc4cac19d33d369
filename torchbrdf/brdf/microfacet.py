"""A general microfacet specular BRDF ``f = D · F · G / (4 (n·l)(n·v))`` composed from parts.

Every combination of :mod:`~torchbrdf.brdf.distributions`, :mod:`~torchbrdf.fresnel` and
:mod:`~torchbrdf.masking` is available by name, so a model choice (GGX vs GTR, Schlick vs
exact Fresnel, separable vs height-correlated Smith) is one argument — which is how the
benchmark measures what each choice costs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, compute_dtype, cross_norm2, dot, safe_normalize
from torchbrdf._types import Color, Scalar
from torchbrdf.brdf.distributions import (
    alpha_to_phong_exponent,
    ndf_abc,
    ndf_beckmann,
    ndf_beckmann_aniso,
    ndf_blinn_phong,
    ndf_ggx,
    ndf_ggx_aniso,
    ndf_gtr,
)
from torchbrdf.brdf.frames import frame_from_normal
from torchbrdf.brdf.fresnel import fresnel_conductor, fresnel_dielectric, fresnel_schlick
from torchbrdf.brdf.masking import (
    g_cook_torrance,
    g_implicit,
    g_kelemen,
    smith_g1_beckmann,
    smith_g1_ggx_aniso,
    smith_g2_ggx_correlated,
    smith_lambda_beckmann,
)

__all__ = ["microfacet", "MicrofacetBRDF", "DISTRIBUTIONS", "FRESNELS", "MASKINGS"]

DISTRIBUTIONS = ("ggx", "beckmann", "gtr", "blinn_phong", "abc")
FRESNELS = ("schlick", "dielectric", "conductor", "none")
MASKINGS = ("smith_separable", "smith_correlated", "cook_torrance", "kelemen", "implicit")


def _choice(name: str, value: str, options: Sequence[str]) -> None:
    if value not in options:
        raise ValueError(f"{name}: unknown choice {value!r}; expected one of {options}")


def microfacet(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    alpha: Scalar,
    alpha_y: Scalar | None = None,
    distribution: str = "ggx",
    fresnel: str = "schlick",
    masking: str = "smith_correlated",
    f0: Color = 0.04,
    f90: Color = 1.0,
    ior: Scalar = 1.5,
    eta: Color | None = None,
    k: Color | None = None,
    gamma: Scalar = 2.0,
    abc_a: Scalar | None = None,
) -> Tensor:
    """Microfacet reflection ``D F G / (4 NL NV)``.

    Args:
        l, v, n: unit vectors ``(*, 3)`` (toward light, toward viewer, normal).
        x, y: optional tangent frame ``(*, 3)``; used when ``alpha_y`` is given (anisotropic
            GGX / Beckmann). Built from ``n`` when omitted.
        alpha: NDF width ``(*, 1)`` or float (along ``x`` when anisotropic).
        alpha_y: width along ``y`` for anisotropic GGX/Beckmann; ``None`` = isotropic.
        distribution: one of :data:`DISTRIBUTIONS`. ``gtr`` uses ``gamma``; ``blinn_phong``
            uses Walter's ``p = 2/α² - 2``; ``abc`` uses ``abc_a`` and ``gamma``.
        fresnel: one of :data:`FRESNELS`: ``schlick`` (``f0``, ``f90``), ``dielectric``
            (``ior``), ``conductor`` (``eta``, ``k``), ``none`` (F = 1).
        masking: one of :data:`MASKINGS`. Smith terms use GGX's Λ for ``ggx``/``gtr``/
            ``abc``/``blinn_phong`` (γ ≠ 2 and ABC have no closed-form Smith) and
            Beckmann's exact Λ for ``beckmann``.

    Returns:
        ``(*, C)`` BRDF values, ``C`` from the Fresnel parameters (1 for ``none``); 0 where
        ``n·l <= 0`` or ``n·v <= 0``.
    """
    _choice("distribution", distribution, DISTRIBUTIONS)
    _choice("fresnel", fresnel, FRESNELS)
    _choice("masking", masking, MASKINGS)
    named = {"l": l, "v": v, "n": n}
    for name, t in named.items():
        _checks.check_tensor(name, t, last=3)
    dtype, _ = _checks.check_same_dtype_device(named)
    if _checks.validation_enabled():
        _checks.check_finite(
            {"l": l, "v": v, "n": n, "x": x, "y": y, "alpha": alpha, "alpha_y": alpha_y, "f0": f0,
             "f90": f90, "ior": ior, "eta": eta, "k": k, "gamma": gamma, "abc_a": abc_a}
        )
    cd = compute_dtype(dtype)
    cast = lambda t: t.to(cd) if isinstance(t, Tensor) else t  # noqa: E731
    l, v, n, x, y = map(cast, (l, v, n, x, y))
    alpha, alpha_y, f0, f90, ior, eta, k, gamma, abc_a = map(cast, (alpha, alpha_y, f0, f90, ior, eta, k, gamma, abc_a))

    nl_raw, nv_raw = dot(n, l), dot(n, v)
    valid = (nl_raw > 0) & (nv_raw > 0)
    nl, nv = torch.clamp(nl_raw, min=1e-7), torch.clamp(nv_raw, min=1e-7)
    h = safe_normalize(l + v)
    nh, lh = dot(n, h), torch.clamp(dot(l, h), 0.0, 1.0)

    aniso = alpha_y is not None
    if aniso:
        if x is None:
            x, y = frame_from_normal(n)
        elif y is None:
            y = torch.linalg.cross(n, x, dim=-1)
        tan_a2 = lambda w: (dot(w, x) * alpha) ** 2 + (dot(w, y) * alpha_y) ** 2  # noqa: E731
    else:
        tan_a2 = lambda w: alpha * alpha * torch.clamp(1.0 - dot(n, w) ** 2, min=0.0)  # noqa: E731

    sin2_h = cross_norm2(n, h)
    if distribution == "ggx":
        d = ndf_ggx_aniso(dot(h, x), dot(h, y), nh, alpha, alpha_y) if aniso else ndf_ggx(nh, alpha, sin2_h)
    elif distribution == "beckmann":
        d = ndf_beckmann_aniso(dot(h, x), dot(h, y), nh, alpha, alpha_y) if aniso else ndf_beckmann(nh, alpha, sin2_h)
    elif distribution == "gtr":
        d = ndf_gtr(nh, alpha, gamma, sin2_h)
    elif distribution == "blinn_phong":
        d = ndf_blinn_phong(nh, alpha_to_phong_exponent(alpha))
    else:
        if abc_a is None:
            raise ValueError("abc_a: the ABC distribution needs its 'B' parameter abc_a")
        d = ndf_abc(nh, abc_a, gamma)

    if fresnel == "schlick":
        f = fresnel_schlick(lh, f0, f90)
    elif fresnel == "dielectric":
        f = fresnel_dielectric(lh, ior)
    elif fresnel == "conductor":
        if eta is None or k is None:
            raise ValueError("eta, k: the conductor Fresnel needs both the real IOR eta and extinction k")
        f = fresnel_conductor(lh, eta, k)
    else:
        f = torch.ones_like(lh)

    if masking in ("smith_separable", "smith_correlated"):
        if distribution == "beckmann":
            alpha_eff_l = torch.sqrt(torch.clamp(tan_a2(l) / torch.clamp(1 - nl * nl, min=1e-12), min=1e-12))
            alpha_eff_v = torch.sqrt(torch.clamp(tan_a2(v) / torch.clamp(1 - nv * nv, min=1e-12), min=1e-12))
            if masking == "smith_separable":
                g = smith_g1_beckmann(nl, alpha_eff_l) * smith_g1_beckmann(nv, alpha_eff_v)
            else:
                g = 1.0 / (1.0 + smith_lambda_beckmann(nl, alpha_eff_l) + smith_lambda_beckmann(nv, alpha_eff_v))
        elif masking == "smith_separable":
            g = smith_g1_ggx_aniso(nl, tan_a2(l)) * smith_g1_ggx_aniso(nv, tan_a2(v))
        else:
            g = smith_g2_ggx_correlated(nl, nv, tan_a2(l), tan_a2(v))
    elif masking == "cook_torrance":
        g = g_cook_torrance(nl, nv, nh, dot(v, h))
    elif masking == "kelemen":
        g = g_kelemen(nl, nv, lh)
    else:
        g = g_implicit(nl, nv)

    out = d * f * g / (4.0 * nl * nv)
    out = torch.where(valid, out, torch.zeros_like(out))
    return cast_back(out, dtype)


class MicrofacetBRDF(nn.Module):
    """Module form of :func:`microfacet` holding the model choices.

    Args:
        distribution, fresnel, masking: as in :func:`microfacet`.

    Shape:
        ``forward(l, v, n, x=None, y=None, **params)``: vectors ``(*, 3)`` → ``(*, C)``.
    """

    def __init__(
        self, distribution: str = "ggx", fresnel: str = "schlick", masking: str = "smith_correlated"
    ) -> None:
        super().__init__()
        _choice("distribution", distribution, DISTRIBUTIONS)
        _choice("fresnel", fresnel, FRESNELS)
        _choice("masking", masking, MASKINGS)
        self.distribution, self.fresnel, self.masking = distribution, fresnel, masking

    def forward(
        self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None, **params: Any
    ) -> Tensor:
        """Evaluate; see :func:`microfacet`."""
        return microfacet(
            l, v, n, x, y, distribution=self.distribution, fresnel=self.fresnel, masking=self.masking, **params
        )

    def extra_repr(self) -> str:
        return f"distribution={self.distribution!r}, fresnel={self.fresnel!r}, masking={self.masking!r}"
