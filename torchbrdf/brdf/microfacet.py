"""A general microfacet specular BRDF ``f = D · F · G / (4 (n·l)(n·v))`` composed from parts.

Every combination of :mod:`~torchbrdf.brdf.distributions`, :mod:`~torchbrdf.fresnel` and
:mod:`~torchbrdf.masking` is available by name, so a model choice (GGX vs GTR, Schlick vs
exact Fresnel, separable vs height-correlated Smith) is one argument — which is how the
benchmark measures what each choice costs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
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


@dataclass
class _Terms:
    """The shared quantities of one evaluation that the table entries below read."""

    l: Tensor
    v: Tensor
    n: Tensor
    x: Tensor | None
    y: Tensor | None
    h: Tensor
    nl: Tensor
    nv: Tensor
    nh: Tensor
    lh: Tensor
    sin2_h: Tensor
    tan_a2: Callable[[Tensor], Tensor]  # α² tan²θ of a direction (anisotropic α when aniso)
    aniso: bool
    distribution: str
    p: dict[str, Any]  # the model parameters: alpha, alpha_y, f0, f90, ior, eta, k, gamma, abc_a


def _half_in_frame(t: _Terms) -> tuple[Tensor, Tensor]:
    """``(h·x, h·y)``: the half vector's tangent-frame components (anisotropic NDFs)."""
    assert t.x is not None and t.y is not None  # built whenever aniso
    return dot(t.h, t.x), dot(t.h, t.y)


def _ndf_ggx(t: _Terms) -> Tensor:
    a, ay = t.p["alpha"], t.p["alpha_y"]
    return ndf_ggx_aniso(*_half_in_frame(t), t.nh, a, ay) if t.aniso else ndf_ggx(t.nh, a, t.sin2_h)


def _ndf_beckmann(t: _Terms) -> Tensor:
    a, ay = t.p["alpha"], t.p["alpha_y"]
    return ndf_beckmann_aniso(*_half_in_frame(t), t.nh, a, ay) if t.aniso else ndf_beckmann(t.nh, a, t.sin2_h)


def _ndf_abc(t: _Terms) -> Tensor:
    if t.p["abc_a"] is None:
        raise ValueError("abc_a: the ABC distribution needs its 'B' parameter abc_a")
    return ndf_abc(t.nh, t.p["abc_a"], t.p["gamma"])


#: Normal distribution D by name.
_NDFS: dict[str, Callable[[_Terms], Tensor]] = {
    "ggx": _ndf_ggx,
    "beckmann": _ndf_beckmann,
    "gtr": lambda t: ndf_gtr(t.nh, t.p["alpha"], t.p["gamma"], t.sin2_h),
    "blinn_phong": lambda t: ndf_blinn_phong(t.nh, alpha_to_phong_exponent(t.p["alpha"])),
    "abc": _ndf_abc,
}


def _fresnel_conductor(t: _Terms) -> Tensor:
    if t.p["eta"] is None or t.p["k"] is None:
        raise ValueError("eta, k: the conductor Fresnel needs both the real IOR eta and extinction k")
    return fresnel_conductor(t.lh, t.p["eta"], t.p["k"])


#: Fresnel term F by name.
_FRESNELS: dict[str, Callable[[_Terms], Tensor]] = {
    "schlick": lambda t: fresnel_schlick(t.lh, t.p["f0"], t.p["f90"]),
    "dielectric": lambda t: fresnel_dielectric(t.lh, t.p["ior"]),
    "conductor": _fresnel_conductor,
    "none": lambda t: torch.ones_like(t.lh),
}


def _beckmann_alpha_eff(t: _Terms, w: Tensor, nw: Tensor) -> Tensor:
    """The effective (projected) Beckmann width along ``w``."""
    return torch.sqrt(torch.clamp(t.tan_a2(w) / torch.clamp(1 - nw * nw, min=1e-12), min=1e-12))


def _smith_separable(t: _Terms) -> Tensor:
    if t.distribution == "beckmann":
        a_l, a_v = _beckmann_alpha_eff(t, t.l, t.nl), _beckmann_alpha_eff(t, t.v, t.nv)
        return smith_g1_beckmann(t.nl, a_l) * smith_g1_beckmann(t.nv, a_v)
    return smith_g1_ggx_aniso(t.nl, t.tan_a2(t.l)) * smith_g1_ggx_aniso(t.nv, t.tan_a2(t.v))


def _smith_correlated(t: _Terms) -> Tensor:
    if t.distribution == "beckmann":
        a_l, a_v = _beckmann_alpha_eff(t, t.l, t.nl), _beckmann_alpha_eff(t, t.v, t.nv)
        return 1.0 / (1.0 + smith_lambda_beckmann(t.nl, a_l) + smith_lambda_beckmann(t.nv, a_v))
    return smith_g2_ggx_correlated(t.nl, t.nv, t.tan_a2(t.l), t.tan_a2(t.v))


#: Masking-shadowing term G by name. Smith terms use Beckmann's exact Λ for ``beckmann`` and
#: GGX's Λ otherwise.
_MASKINGS: dict[str, Callable[[_Terms], Tensor]] = {
    "smith_separable": _smith_separable,
    "smith_correlated": _smith_correlated,
    "cook_torrance": lambda t: g_cook_torrance(t.nl, t.nv, t.nh, dot(t.v, t.h)),
    "kelemen": lambda t: g_kelemen(t.nl, t.nv, t.lh),
    "implicit": lambda t: g_implicit(t.nl, t.nv),
}

DISTRIBUTIONS = tuple(_NDFS)
FRESNELS = tuple(_FRESNELS)
MASKINGS = tuple(_MASKINGS)


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

    params = dict(
        alpha=alpha, alpha_y=alpha_y, f0=f0, f90=f90, ior=ior, eta=eta, k=k, gamma=gamma, abc_a=abc_a
    )
    terms = _Terms(l, v, n, x, y, h, nl, nv, nh, lh, cross_norm2(n, h), tan_a2, aniso, distribution, params)
    d = _NDFS[distribution](terms)
    f = _FRESNELS[fresnel](terms)
    g = _MASKINGS[masking](terms)

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
