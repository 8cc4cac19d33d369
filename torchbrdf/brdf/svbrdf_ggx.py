r"""The GGX model of the learned SVBRDF-capture literature.

The published single- and multi-image SVBRDF recovery methods -- Deschaintre et al. 2018
("Single-Image SVBRDF Capture with a Rendering-Aware Deep Network", SIGGRAPH 2018) and
2019 ("Flexible SVBRDF Capture with a Multi-Image Deep Network", EGSR 2019), Gao et al.
2019 ("Deep Inverse Rendering for High-Resolution SVBRDF Estimation from an Arbitrary
Number of Images", SIGGRAPH 2019) and Guo et al. 2020 (MaterialGAN, SIGGRAPH Asia 2020) --
render and report errors with one simple microfacet model, implemented here so results can
be compared with numbers published on that convention.

Maps (per pixel): shading normal ``n``, diffuse albedo ``rho_d`` (RGB), specular albedo
``rho_s`` (RGB, the normal-incidence reflectance F0) and roughness ``r`` (scalar). With
``h = normalize(l + v)``::

    f(l, v)  = rho_d (1 - rho_s) / pi  +  D(h) G(l, v) F(v.h) / (4 (n.l)(n.v))
    alpha    = r^2
    D(h)     = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)              (GGX)
    G(l, v)  = G1(n.l) G1(n.v),  G1(c) = c / (c (1 - k) + k),  k = alpha / 2   (Smith-Schlick)
    F(v.h)   = rho_s + (1 - rho_s) 2^((-5.55473 v.h - 6.98316) v.h)  (Unreal's spherical
               Gaussian approximation of Schlick's Fresnel, Karis 2013)

Convention notes:

* The diffuse term is damped by the *constant* ``1 - rho_s`` (not by a view-dependent
  Fresnel), as in those papers; the model is therefore not energy conserving at grazing
  angles and is reciprocal.
* ``roughness`` is the perceptual input and is squared into ``alpha``. A floor keeps ``D``
  finite at roughness 0, and the two conventions in use differ:

  - default, ``alpha_floor=ALPHA_MIN`` (1e-3): ``alpha = max(r^2, 1e-3)``, as this library
    always did -- the GGX peak ``1 / (pi alpha^2)`` stays below 3.2e5. This floor is *not*
    below what an 8-bit roughness map can express: codes 1..8 give ``alpha = (c / 255)^2``
    = 1.5e-5 .. 9.8e-4, which all render like ``alpha = 1e-3`` here;
  - ``roughness_floor=ROUGHNESS_FLOOR_DESCHAINTRE`` (1e-3): ``alpha = max(r, 1e-3)^2``
    (``alpha >= 1e-6``), the floor of Deschaintre et al.'s renderer
    (``roughness = tf.maximum(roughness, 0.001)``). Every 8-bit code keeps its own lobe; at
    code 1 the peak is ~4e3 times the default's.

  ``k = alpha / 2`` uses the floored ``alpha`` in both.
* ``G / (4 (n.l)(n.v))`` is evaluated in the cancelled form
  ``1 / (4 (n.l (1 - k) + k)(n.v (1 - k) + k))`` -- finite as ``n.l`` or ``n.v`` tend to 0.
* ``(n.h)^2 (alpha^2 - 1) + 1`` is computed as ``|n x h|^2 + alpha^2 (n.h)^2``: the same
  value without cancellation under a narrow peak.

The value is exactly 0, with zero gradients, where ``n.l <= 0`` or ``n.v <= 0``. The model is
isotropic: ``x``/``y`` are accepted for the common BRDF signature and ignored. Half-precision
inputs are evaluated in float32 and cast back (saturating).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, compute_dtype, cross_norm2, dot, safe_normalize
from torchbrdf._types import Color, Scalar
from torchbrdf.brdf.formula import ALPHA_MIN  # the principled model's floor (Burley 2012 code)

__all__ = ["SVBRDFGGX", "svbrdf_ggx", "ALPHA_MIN", "ROUGHNESS_FLOOR_DESCHAINTRE"]

"""Default floor on ``alpha = roughness^2``: keeps the GGX peak ``1 / (pi alpha^2)`` below 3.2e5."""

ROUGHNESS_FLOOR_DESCHAINTRE = 1e-3
"""Floor on ``roughness`` (not ``alpha``) in Deschaintre et al.'s renderer: ``alpha >= 1e-6``."""


def _floored_alpha(r: Tensor, alpha_floor, roughness_floor) -> Tensor:
    """``alpha = r^2`` with the floor convention chosen (see the module docstring)."""
    if roughness_floor is not None:
        return torch.square(torch.clamp(r, min=roughness_floor))
    return torch.clamp(r * r, min=ALPHA_MIN if alpha_floor is None else alpha_floor)


def _check_floors(alpha_floor: float | None, roughness_floor: float | None) -> None:
    if alpha_floor is not None and roughness_floor is not None:
        raise ValueError(
            f"alpha_floor={alpha_floor!r} and roughness_floor={roughness_floor!r}: give at most one floor"
        )
    for name, value in (("alpha_floor", alpha_floor), ("roughness_floor", roughness_floor)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0 < value <= 1):
            raise ValueError(f"{name}: expected a number in (0, 1], got {_checks.excerpt(value)}")

_SG_A = -5.55473
_SG_B = -6.98316


def _fresnel_sg(f0: Tensor, v_dot_h: Tensor) -> Tensor:
    """Unreal's spherical-Gaussian Schlick Fresnel ``f0 + (1 - f0) 2^((a c + b) c)``."""
    return f0 + (1.0 - f0) * torch.exp2((_SG_A * v_dot_h + _SG_B) * v_dot_h)


def svbrdf_ggx(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    diffuse_albedo: Color,
    specular_albedo: Color,
    roughness: Scalar,
    alpha_floor: float | None = None,
    roughness_floor: float | None = None,
) -> Tensor:
    """Diffuse + GGX BRDF of the SVBRDF-capture literature (Deschaintre 2018/2019, Gao 2019, MaterialGAN).

    Args:
        l: unit light directions ``(*, 3)``.
        v: unit view directions ``(*, 3)``.
        n: unit shading normals ``(*, 3)``.
        x: tangents ``(*, 3)``; unused (isotropic), accepted for the common signature.
        y: bitangents ``(*, 3)``; unused.
        diffuse_albedo: ``(*, 3)`` linear RGB in [0, 1] (or a float for grey).
        specular_albedo: ``(*, 3)`` linear RGB normal-incidence reflectance F0 in [0, 1]
            (or a float).
        roughness: ``(*, 1)`` in [0, 1]; ``alpha = roughness^2``, floored as below.
        alpha_floor: floor on ``alpha`` (default :data:`ALPHA_MIN` = 1e-3, this library's
            convention): ``alpha = max(roughness^2, alpha_floor)``.
        roughness_floor: floor on ``roughness`` instead (Deschaintre et al.'s renderer uses
            :data:`ROUGHNESS_FLOOR_DESCHAINTRE` = 1e-3): ``alpha = max(roughness,
            roughness_floor)^2``. Give at most one of the two floors; each must be in (0, 1].

    Returns:
        ``f(l, v)`` without the ``n.l`` cosine, ``(*, 3)``, in the dtype of ``l``; exactly 0
        where ``n.l <= 0`` or ``n.v <= 0``.

    Note:
        Any device and float dtype; half types are evaluated in float32 and cast back.

    Reference:
        Deschaintre et al. 2018, Sec. 3 and supplemental renderer; Karis, "Real Shading in
        Unreal Engine 4", SIGGRAPH 2013 course notes (Fresnel approximation, k = alpha/2).

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> f = svbrdf_ggx(n, n, n, diffuse_albedo=torch.ones(3), specular_albedo=torch.zeros(3),
        ...                roughness=1.0)
        >>> torch.allclose(f, torch.full((3,), 1 / math.pi + 1 / (4 * math.pi) * 2 ** (-5.55473 - 6.98316)))
        True
    """
    _check_floors(alpha_floor, roughness_floor)
    named = {
        "l": l,
        "v": v,
        "n": n,
        "x": x,
        "y": y,
        "diffuse_albedo": diffuse_albedo,
        "specular_albedo": specular_albedo,
        "roughness": roughness,
    }
    for name, t in named.items():
        if t is not None:
            last = 1 if name == "roughness" else 3
            _checks.check_tensor(name, t, last=last, allow_scalar=name not in ("l", "v", "n", "x", "y"))
    named = {k: t for k, t in named.items() if t is not None}
    _checks.check_same_dtype_device(named)
    _checks.check_broadcast(named)
    if _checks.validation_enabled():
        _checks.check_finite(named)
    out_dtype = l.dtype
    cdt = compute_dtype(l.dtype)
    l, v, n = l.to(cdt), v.to(cdt), n.to(cdt)
    rho_d = torch.as_tensor(diffuse_albedo, dtype=cdt, device=l.device)
    rho_s = torch.as_tensor(specular_albedo, dtype=cdt, device=l.device)
    r = torch.as_tensor(roughness, dtype=cdt, device=l.device)

    n_dot_l = dot(n, l)
    n_dot_v = dot(n, v)
    valid = (n_dot_l > 0) & (n_dot_v > 0)
    # Clamped copies: every branch below stays finite, so masking leaves zero gradients.
    nl = torch.clamp(n_dot_l, 0.0, 1.0)
    nv = torch.clamp(n_dot_v, 0.0, 1.0)
    h = safe_normalize(l + v)
    nh = torch.clamp(dot(n, h), 0.0, 1.0)
    vh = torch.clamp(dot(v, h), 0.0, 1.0)

    alpha = _floored_alpha(r, alpha_floor, roughness_floor)
    a2 = alpha * alpha
    base = cross_norm2(n, h) + a2 * nh * nh  # = (n.h)^2 (a2 - 1) + 1
    # For unit h, base >= min(a2, 1); the floor only acts where h degenerates (l = -v).
    base = torch.maximum(base, torch.clamp(a2, max=1.0))
    d = a2 / (math.pi * base * base)
    k = 0.5 * alpha
    vis = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))  # G / (4 n.l n.v)
    spec = d * vis * _fresnel_sg(rho_s, vh)
    diffuse = rho_d * (1.0 - rho_s) / math.pi
    f = diffuse + spec
    f = torch.where(valid, f, torch.zeros((), dtype=cdt, device=l.device))
    f = torch.broadcast_to(f, (*f.shape[:-1], 3))
    return cast_back(f, out_dtype)


class SVBRDFGGX(nn.Module):
    """Module form of :func:`svbrdf_ggx`; the maps are passed to ``forward``.

    Args:
        alpha_floor: floor on ``alpha`` (default :data:`ALPHA_MIN`); see :func:`svbrdf_ggx`.
        roughness_floor: floor on ``roughness`` instead (e.g.
            :data:`ROUGHNESS_FLOOR_DESCHAINTRE`); at most one of the two.

    Shape:
        - l, v, n (x, y unused): ``(*, 3)``; ``diffuse_albedo``/``specular_albedo`` ``(*, 3)``,
          ``roughness`` ``(*, 1)``.
        - Output: ``(*, 3)``.
    """

    def __init__(self, alpha_floor: float | None = None, roughness_floor: float | None = None) -> None:
        super().__init__()
        _check_floors(alpha_floor, roughness_floor)
        self.alpha_floor = alpha_floor
        self.roughness_floor = roughness_floor

    def forward(self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None, *,
                diffuse_albedo: Color, specular_albedo: Color, roughness: Scalar,
                alpha_floor: float | None = None, roughness_floor: float | None = None) -> Tensor:
        """Evaluate :func:`svbrdf_ggx` with the given maps and this module's floor.

        A floor given here replaces the module's. The parameters are spelled out so that callers
        (``shade``) can check a material's keys against them.
        """
        floors: dict[str, Any] = {"alpha_floor": self.alpha_floor, "roughness_floor": self.roughness_floor}
        floors.update({k: f for k, f in (("alpha_floor", alpha_floor), ("roughness_floor", roughness_floor))
                       if f is not None})
        return svbrdf_ggx(l, v, n, x, y, diffuse_albedo=diffuse_albedo, specular_albedo=specular_albedo,
                          roughness=roughness, **floors)

    def extra_repr(self) -> str:
        if self.roughness_floor is not None:
            return f"roughness_floor={self.roughness_floor}"
        return f"alpha_floor={ALPHA_MIN if self.alpha_floor is None else self.alpha_floor}"
