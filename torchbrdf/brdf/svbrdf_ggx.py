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

The formula is written once, :func:`torchbrdf.brdf.formula.svbrdf_ggx`: on torch tensors it is
the eager path, traced it is the ``svbrdf_ggx`` family of fused kernels (C on CPU, Triton on
CUDA), which a call uses under the rules of :func:`torchbrdf.principled`
(:data:`~torchbrdf.brdf.principled.FAST_PATH_MIN_LANES`, ``set_fast_path``,
``fused_at_every_size``, the backend; docs/fast_path.md).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, compute_dtype
from torchbrdf._types import Color, Scalar
from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import ALPHA_MIN  # the principled model's floor (Burley 2012 code)
from torchbrdf.brdf.principled import fast_backend

__all__ = ["SVBRDFGGX", "svbrdf_ggx", "ALPHA_MIN", "ROUGHNESS_FLOOR_DESCHAINTRE"]

"""Default floor on ``alpha = roughness^2``: keeps the GGX peak ``1 / (pi alpha^2)`` below 3.2e5."""

ROUGHNESS_FLOOR_DESCHAINTRE = 1e-3
"""Floor on ``roughness`` (not ``alpha``) in Deschaintre et al.'s renderer: ``alpha >= 1e-6``."""


def check_floors(alpha_floor: float | None, roughness_floor: float | None) -> None:
    """Refuse both floors at once, or a floor outside (0, 1] (``ValueError`` naming it)."""
    if alpha_floor is not None and roughness_floor is not None:
        raise ValueError(
            f"alpha_floor={alpha_floor!r} and roughness_floor={roughness_floor!r}: give at most one floor"
        )
    for name, value in (("alpha_floor", alpha_floor), ("roughness_floor", roughness_floor)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0 < value <= 1):
            raise ValueError(f"{name}: expected a number in (0, 1], got {_checks.excerpt(value)}")

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
    check_floors(alpha_floor, roughness_floor)
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
    c: dict[str, Any] = {
        "l": l.to(cdt),
        "v": v.to(cdt),
        "n": n.to(cdt),
        "diffuse_albedo": torch.as_tensor(diffuse_albedo, dtype=cdt, device=l.device),
        "specular_albedo": torch.as_tensor(specular_albedo, dtype=cdt, device=l.device),
        "roughness": torch.as_tensor(roughness, dtype=cdt, device=l.device),
    }
    if roughness_floor is not None:
        c["roughness_floor"] = float(roughness_floor)
    else:
        c["alpha_floor"] = ALPHA_MIN if alpha_floor is None else float(alpha_floor)
    # The fused kernels under principled's rules (lanes, set_fast_path, backend, dtype), else eager.
    backend = fast_backend(c)
    if backend is not None:
        from torchbrdf.kernels import ops as _kernel_ops

        f = _kernel_ops.svbrdf_ggx_fast(c, backend=backend)
    else:
        f = formula.svbrdf_ggx(formula.TorchOps(cdt, l.device), c)
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
        check_floors(alpha_floor, roughness_floor)
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
