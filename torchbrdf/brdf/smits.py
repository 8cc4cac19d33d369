r"""Smits' Wall-E / Up reflection model: six lobes whose weights partition the energy.

Reference: B. Smits, *Reflection Model Design for Wall-E and Up*, SIGGRAPH 2012 course
"Practical Physically Based Shading in Film and Game Production". The notes give the
equations as Mathematica snippets; this module implements every lobe and weight in them.

Notation
--------
All vectors are unit, channel-last ``(*, 3)`` and point away from the surface: ``l`` toward
the light, ``v`` toward the viewer, ``n`` the shading normal. ``Mix(a, b, t) = a + (b - a) t``
and the generalised Schlick blend is

    FrnlBlend(N, G, c) = Mix(N, G, (1 - c)^5),

with ``N`` the value at normal incidence and ``G`` the value at grazing incidence.

Weights (computed once the view is fixed)
-----------------------------------------
With ``c`` = ``base_color``, ``m`` = metallic, ``r`` = roughness, ``sN``/``sG`` the two Fresnel
scale controls::

    nReflD = clamp(sN Mix(0.05, 1, m))         # diffuse side: a metal has no diffuse
    nReflS = clamp(sN Mix(0.05, c, m))         # highlight side: a metal reflects its colour
    gRefl  = clamp(sG * 1)
    fv     = FrnlBlend(1 - nReflD, 1 - gRefl, n.v)
    dN     = Mix((1 - clear)(1 - nReflD) fv, 1, r)
    dG     = Mix((1 - clear)(1 - gRefl)  fv, 1, r)
    diffN  = c dN (1 - back)        diffG  = c dG (1 - back)
    diffTN = c dN back              diffTG = c dG back
    reflRatio = max(1 - 2r, 0)^3
    specN  = (1 - reflRatio) nReflS (1 - r)       specG  = (1 - reflRatio) gRefl (1 - r)
    reflN  = reflRatio nReflS (1 - r)             reflG  = reflRatio gRefl (1 - r)
    specTN = c (1 - reflRatio)(1 - nReflS)(1 - r) clear
    specTG = c (1 - reflRatio)(1 - gRefl)(1 - r) clear
    reflTN = c reflRatio (1 - nReflS)(1 - r) clear
    reflTG = c reflRatio (1 - gRefl)(1 - r) clear

The specular and reflection pairs are multiplied by ``highlight_tint``, the transmitted
specular and refraction pairs by ``transmit_tint``, and each pair by its own lobe scale.
``clamp`` is to ``[0, 1]``.

Lobes
-----
* diffuse (``n.l > 0``): ``FrnlBlend(diffN, diffG, n.l) / pi``;
* transmitted diffuse (``n.l < 0``): ``FrnlBlend(diffTN, diffTG, -n.l) / pi``;
* specular / reflection (``n.l > 0``): ``FrnlBlend(N, G, n.v) * S(l, v, n, p)`` with the
  specular exponent ``powerS`` and the reflection exponent ``powerR``;
* transmitted specular / refraction (``n.l < 0``): the same lobes about ``-n`` seen from the
  back-side view ``v_t`` (below).

The distribution-based highlight lobe (Ashikhmin & Premoze, "Distribution-based BRDFs") is

    D(h)       = weight / pi * exp(-power sin^2(theta_h)),   weight = power / (1 - e^-power),
    S(l, v, n) = D(h) (n.h) / (4 (v.h) max(n.l, n.v)),       h = normalize(l + v),

``D`` integrates to exactly 1 against ``(n.h) d omega_h`` for every exponent. The exponent
puts the 10 % falloff of ``D`` at the cone angle:
``power = ln 10 / sin^2(cone)``, with the specular cone ``5 deg + 30 deg r`` and the
reflection cone ``10 deg r``, each multiplied by its cone scale.

Choices where the notes are open (each is tested in ``tests/brdf/test_smits.py``)
----------------------------------------------------------------------------
1. **Normalising denominator of the highlight lobe.** The notes only say it was "changed a
   bit" so that the lobe comes closer to integrating to 1 for every view. As we read
   Ashikhmin-Premoze, their denominator is ``4 (n.l + n.v - (n.l)(n.v))``; we use
   ``4 (v.h) max(n.l, n.v) / (n.h)``. With ``d omega_l = 4 (v.h) d omega_h`` the albedo of
   ``S`` for any view is ``int D(h) (n.h) n.l / max(n.l, n.v) d omega_h <= int D (n.h) = 1``,
   so the lobe never returns more than its weight, for every exponent and view, and it is
   reciprocal. At normal incidence both forms agree; toward grazing ours keeps far more of
   the lobe (measured albedo at 89 deg view: 0.54 vs 0.02 for a 5 deg cone, 0.50 vs 0.27
   for a 90 deg cone). What it loses is the part of the lobe whose mirror direction falls
   below the horizon and the ``n.l / max(n.l, n.v)`` factor.
2. **Fresnel cosine of the highlight lobes.** The notes pass normal/grazing weights to the
   highlight lobes without fixing the cosine. We evaluate ``FrnlBlend`` at ``n.v`` -- the
   cosine whose share the diffuse weights already removed (``fv`` above) -- so, for a
   fixed view, reflection + transmission + diffuse weights sum to at most 1 for every
   parameter value in range (the notes' partition argument, exactly). Consequence: the
   diffuse lobe is reciprocal for all parameters, the highlight lobes are reciprocal only
   when the normal and grazing reflectances are equal.
3. **Typos in the notes' transmission weights.** ``diffTN`` is printed as
   ``c dG (1 - back)``; we use ``c dN back`` (the printed form would transmit with
   ``back = 0`` and double-count the grazing weight). ``specTG``/``reflTG`` are printed
   with ``reflRatio (1 - nRefl)``; we use ``(1 - reflRatio)``/``reflRatio`` times
   ``(1 - gRefl)``, the "1 - sG" term the text describes, so that the transmitted weights
   are exactly ``clear c (1 - r)`` times the complement of the reflected ones.
4. ``powerS``: the notes' ``Log[0.1^{}]`` is read as ``ln 0.1`` (the 10 % falloff the text
   states, as in ``powerR``). The notes' check integral runs ``theta`` over ``[0, pi]``
   (which vanishes by symmetry); the hemisphere ``[0, pi/2]`` is meant.
5. The reflection cone "0 (or epsilon in practice)" is floored at ``MIN_CONE_DEG`` = 0.25
   deg (``power`` about 1.2e5, peak values below the float16 range); every cone is clamped
   to ``[MIN_CONE_DEG, 90 deg]`` after its scale.
6. **Diffuse normalisation**: the lobe is divided by ``pi`` (the notes normalise the
   hemispherical integral by ``pi``), so ``FrnlBlend(diffN, diffG, n.l) = 1`` is a white
   Lambertian surface.
7. **Refraction geometry.** The index of refraction is the one whose normal-incidence
   Fresnel reflectance is the (scaled) dielectric reflectance ``R = clamp(0.05 sN, 0,
   0.9)``: ``eta = (1 + sqrt R) / (1 - sqrt R)`` (1.58 by default; metallic is ignored
   here). The view ray is refracted into the surface (``t``; there is no total internal
   reflection from outside) and mirrored about the normal axis into the back-side view
   ``v_t = 2 (t.n) n - t``, so that the back-side lobes about ``-n`` peak at ``l = t``.
   Cone angles are not changed by refraction (as in the notes).
8. **Scales**: ``fresnel_normal_scale``/``fresnel_grazing_scale`` multiply ``nRefl`` and
   ``gRefl`` (then clamped to ``[0, 1]``); tints and lobe scales multiply both weights of
   the lobes they affect. Tints, colours and scales above 1 are allowed but can break the
   energy bound -- they are artistic controls, as in the notes.
9. ``metallic``, ``roughness``, ``clear`` and ``back`` are clamped to ``[0, 1]``.
10. The model is isotropic: ``x``/``y`` are accepted for the common BRDF signature and
    ignored.

Layering
--------
:func:`smits_composite` implements the notes' simple layering: per-layer lobe weights are
combined by A-over-B compositing of the layer weights (listed top first: coverage of layer
``i`` is ``a_i prod_{j<i} (1 - a_j)``), and the two normals (diffuse, highlights), the four
cone angles and the refraction index are blended with weights ``coverage x lobe energy``.
A lobe's energy is the luminance of its albedo share at the current view:
``(20 N + G) / 21`` for the diffuse lobes (the exact hemispherical integral of
``FrnlBlend(N, G, n.l)``) and ``FrnlBlend(N, G, n.v)`` for the unit-integral highlight
lobes. Where layer presences leave coverage below 1, the uncovered part reflects nothing.
The notes' more complex layering (transmitted light of upper layers re-scattered by the
lobes of lower layers, their 3x3 interaction table) is not implemented.

Zero is returned, with zero gradients, where ``n.v <= 0`` or ``n.l = 0``. Half-precision
inputs are evaluated in float32 and cast back.

Use
---
``smits(l, v, n, x, y, **material)`` has the library's common BRDF signature, so any
renderer that takes a BRDF callable takes it, e.g. ``shade(gbuf, lights, brdf=SmitsBRDF())``
with the Smits parameter names as material keys. Lobes whose weight is a Python 0 are skipped
(``clear = 0``/``back = 0`` skip the transmission lobes, ``roughness >= 0.5`` the reflection
lobe, a 0 lobe scale its lobe); ``SmitsBRDF(lobes=...)`` selects lobes explicitly. Note that
the transmission lobes are only seen by a renderer that weights light from below the surface
by ``|n.l|``; one that clamps ``n.l`` at 0 renders the reflection side only.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import (
    cast_back,
    compute_dtype,
    cross_norm2,
    dot,
    is_zero,
    lerp,
    luminance,
    safe_div,
    safe_normalize,
    safe_sqrt,
    schlick_weight,
)
from torchbrdf._types import Color, Scalar

__all__ = [
    "SMITS_LOBES",
    "SmitsBRDF",
    "SmitsLayeredBRDF",
    "SmitsLobes",
    "smits",
    "smits_composite",
    "smits_cone_power",
    "smits_distribution",
    "smits_evaluate",
    "smits_highlight_lobe",
    "smits_layered",
    "smits_lobes",
]

DIELECTRIC_REFLECTANCE = 0.05
"""Default normal-incidence reflectance of a dielectric (``nRefl`` at metallic 0)."""
GRAZING_REFLECTANCE = 1.0
"""Default grazing reflectance (``gRefl``)."""
SPECULAR_CONE_DEG = (5.0, 35.0)
"""Specular cone angle at roughness 0 and 1, degrees."""
REFLECTION_CONE_DEG = (0.0, 10.0)
"""Reflection cone angle at roughness 0 and 1, degrees (floored at ``MIN_CONE_DEG``)."""
MIN_CONE_DEG = 0.25
"""Floor on every cone angle: keeps ``power`` finite (about 1.2e5) at roughness 0."""
CONE_FALLOFF = 0.1
"""Value of the normalised distribution at the cone angle, relative to its peak."""
MAX_ETA_REFLECTANCE = 0.9
"""Cap on the reflectance the refraction index is derived from (``eta <= 37.97``)."""
_ENERGY_EPS = 1e-6
"""Added to every lobe energy in layering so that all-zero energies fall back to coverage."""

_LN_FALLOFF = math.log(1.0 / CONE_FALLOFF)
_MIN_CONE = math.radians(MIN_CONE_DEG)
_MAX_CONE = 0.5 * math.pi

SMITS_LOBES = (
    "diffuse",
    "specular",
    "reflection",
    "transmit_diffuse",
    "transmit_specular",
    "refraction",
)
"""The six lobes, in evaluation order; each has a normal (``_n``) and a grazing (``_g``) weight."""
_LOBES = SMITS_LOBES
_COLOURS = ("base_color", "highlight_tint", "transmit_tint")
_HIGHLIGHTS = ("specular", "reflection", "transmit_specular", "refraction")


@dataclass(frozen=True)
class SmitsLobes:
    """Lobe weights, cone angles and normals of one Smits material at a fixed view.

    Every weight is a ``(*, 3)`` colour (normal-incidence ``*_n`` and grazing ``*_g``);
    cones are ``(*, 1)`` angles in radians; normals ``(*, 3)`` unit; ``eta`` ``(*, 1)``.
    Produced by :func:`smits_lobes`, combined by :func:`smits_composite`, evaluated by
    :func:`smits_evaluate`. ``pruned`` names lobes known to be zero (skipped).
    """

    diffuse_n: Tensor
    diffuse_g: Tensor
    specular_n: Tensor
    specular_g: Tensor
    reflection_n: Tensor
    reflection_g: Tensor
    transmit_diffuse_n: Tensor
    transmit_diffuse_g: Tensor
    transmit_specular_n: Tensor
    transmit_specular_g: Tensor
    refraction_n: Tensor
    refraction_g: Tensor
    specular_cone: Tensor
    reflection_cone: Tensor
    transmit_specular_cone: Tensor
    refraction_cone: Tensor
    diffuse_normal: Tensor
    highlight_normal: Tensor
    eta: Tensor
    pruned: frozenset = frozenset()


# --------------------------------------------------------------------------- helpers


def _frnl_blend(normal, grazing, cos: Tensor) -> Tensor:
    """Generalised Schlick blend ``Mix(normal, grazing, (1 - cos)^5)``; cos clamped to [0, 1]."""
    return lerp(normal, grazing, schlick_weight(cos))


def _check_args(named: dict) -> None:
    """Shape/dtype/device checks (and NaN checks under validation), as ``principled`` does.

    Directions and colours must end in 3, other parameters in 1; Python numbers and 0-d
    tensors pass for parameters. All tensors share one dtype and one device.
    """
    for name, t in named.items():
        if t is None:
            continue
        if name in ("l", "v", "n", "x", "y", "normal"):
            _checks.check_tensor(name, t, last=3)
        else:
            _checks.check_tensor(name, t, last=3 if name in _COLOURS else 1, allow_scalar=True)
    named = {k: t for k, t in named.items() if t is not None}
    _checks.check_same_dtype_device(named)
    _checks.check_broadcast(named)
    if _checks.validation_enabled():
        _checks.check_finite(named)


def _selected(lobes) -> frozenset:
    """Lobes left out by a ``lobes=`` selection (validated against :data:`SMITS_LOBES`)."""
    if lobes is None:
        return frozenset()
    unknown = set(lobes) - set(SMITS_LOBES)
    if unknown:
        raise ValueError(f"lobes: unknown lobe(s) {sorted(unknown)}; expected a subset of {SMITS_LOBES}")
    return frozenset(SMITS_LOBES) - frozenset(lobes)


def _as(x, ref: Tensor) -> Tensor:
    """Python float / tensor -> tensor in ``ref``'s dtype and device."""
    return torch.as_tensor(x, dtype=ref.dtype, device=ref.device)


def smits_cone_power(cone: Tensor) -> Tensor:
    """Exponent that puts the 10 % falloff of the distribution at the cone angle.

    Args:
        cone: cone angle in radians, ``(*, 1)``, in ``(0, pi/2]``.

    Returns:
        ``ln(10) / sin^2(cone)``, ``(*, 1)``.
    """
    return _LN_FALLOFF / torch.sin(cone).square()


def smits_distribution(sin2_theta_h: Tensor, power: Tensor) -> Tensor:
    """Normalised Gaussian-of-sin distribution ``weight / pi * exp(-power sin^2 theta_h)``.

    ``weight = power / (1 - exp(-power))`` makes ``int D(h) (n.h) d omega_h = 1`` over the
    hemisphere for every exponent.

    Args:
        sin2_theta_h: ``sin^2`` of the half-vector angle to the normal, ``(*, 1)``.
        power: exponent, ``(*, 1)``, positive.

    Returns:
        ``D``, ``(*, 1)``.
    """
    weight = power / (-torch.expm1(-power))
    return weight / math.pi * torch.exp(-power * sin2_theta_h)


def smits_highlight_lobe(l: Tensor, v: Tensor, n: Tensor, power: Tensor) -> Tensor:
    """Unit-weight distribution-based highlight lobe ``D(h) (n.h) / (4 (v.h) max(n.l, n.v))``.

    Its albedo is at most 1 for every view and exponent (module docstring, choice 1).

    Args:
        l: light directions ``(*, 3)``.
        v: view directions ``(*, 3)``.
        n: the lobe's normal ``(*, 3)``; ``l`` and ``v`` are taken on its positive side
            (cosines are clamped at 0).
        power: exponent ``(*, 1)``.

    Returns:
        Lobe value ``(*, 1)`` (without the ``n.l`` cosine).
    """
    sin2_theta_h, geometry = _highlight_geometry(l, v, n)
    return smits_distribution(sin2_theta_h, power) * geometry


def _highlight_geometry(l: Tensor, v: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
    """Exponent-independent parts of the highlight lobe, shared by lobes on the same side.

    Returns:
        ``(sin^2 theta_h, (n.h) / (4 (v.h) max(n.l, n.v)))``, each ``(*, 1)``.
    """
    h = safe_normalize(l + v)  # l = -v: h = 0, and the lobe is 0 with finite gradients
    n_dot_l = torch.clamp(dot(n, l), min=0.0)
    n_dot_v = torch.clamp(dot(n, v), min=0.0)
    n_dot_h = torch.clamp(dot(n, h), min=0.0)
    v_dot_h = torch.clamp(dot(v, h), min=0.0)
    # |n x h|^2 instead of 1 - (n.h)^2: no cancellation under the narrow reflection peak.
    return cross_norm2(n, h), safe_div(n_dot_h, 4.0 * v_dot_h * torch.maximum(n_dot_l, n_dot_v))


def _transmit_view(v: Tensor, n: Tensor, eta: Tensor) -> Tensor:
    """Back-side view ``2 (t.n) n - t`` where ``t`` is ``-v`` refracted into the surface.

    Args:
        v: view directions ``(*, 3)`` (above the surface).
        n: normals ``(*, 3)``.
        eta: relative index of refraction ``(*, 1)``, >= 1.

    Returns:
        Unit directions ``(*, 3)`` below the surface, with ``-n.v_t = cos(theta_t)``.
    """
    cos_i = torch.clamp(dot(n, v), 0.0, 1.0)
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    cos_t = safe_sqrt(1.0 - sin2_t)  # eta >= 1: sin2_t <= 1, no total internal reflection
    return safe_normalize(v / eta - (cos_i / eta + cos_t) * n)


# --------------------------------------------------------------------------- lobes


def smits_lobes(  # noqa: D417 (the material parameters are documented once, in `smits`)
    v: Tensor,
    n: Tensor,
    *,
    base_color: Color,
    metallic: Scalar = 0.0,
    roughness: Scalar = 0.5,
    clear: Scalar = 0.0,
    back: Scalar = 0.0,
    fresnel_normal_scale: Scalar = 1.0,
    fresnel_grazing_scale: Scalar = 1.0,
    highlight_tint: Color = 1.0,
    transmit_tint: Color = 1.0,
    diffuse_scale: Scalar = 1.0,
    specular_scale: Scalar = 1.0,
    reflection_scale: Scalar = 1.0,
    transmit_diffuse_scale: Scalar = 1.0,
    transmit_specular_scale: Scalar = 1.0,
    refraction_scale: Scalar = 1.0,
    specular_cone_scale: Scalar = 1.0,
    reflection_cone_scale: Scalar = 1.0,
    transmit_specular_cone_scale: Scalar = 1.0,
    refraction_cone_scale: Scalar = 1.0,
) -> SmitsLobes:
    """The twelve lobe weights, four cone angles and refraction index at a fixed view.

    Args:
        v: view directions ``(*, 3)``.
        n: normals ``(*, 3)``.
        base_color .. refraction_cone_scale: as in :func:`smits`.

    Returns:
        :class:`SmitsLobes` in the compute dtype (float32 for half inputs), every field
        broadcast against ``v``'s batch shape.
    """
    params = dict(locals())
    _check_args(params)
    cdt = compute_dtype(v.dtype)
    v = v.to(cdt)
    n = n.to(cdt)
    c = _as(base_color, v)
    m = torch.clamp(_as(metallic, v), 0.0, 1.0)
    r = torch.clamp(_as(roughness, v), 0.0, 1.0)
    clr = torch.clamp(_as(clear, v), 0.0, 1.0)
    bk = torch.clamp(_as(back, v), 0.0, 1.0)
    s_n = _as(fresnel_normal_scale, v)
    s_g = _as(fresnel_grazing_scale, v)

    n_refl_d = torch.clamp(s_n * lerp(DIELECTRIC_REFLECTANCE, 1.0, m), 0.0, 1.0)
    n_refl_s = torch.clamp(s_n * lerp(DIELECTRIC_REFLECTANCE, c, m), 0.0, 1.0)
    g_refl = torch.clamp(s_g * GRAZING_REFLECTANCE, 0.0, 1.0)
    n_dot_v = torch.clamp(dot(n, v), 0.0, 1.0)

    # Diffuse: what the view-side Fresnel leaves, blended to constant diffuse by roughness.
    fv = _frnl_blend(1.0 - n_refl_d, 1.0 - g_refl, n_dot_v)
    d_n = lerp((1.0 - clr) * (1.0 - n_refl_d) * fv, 1.0, r)
    d_g = lerp((1.0 - clr) * (1.0 - g_refl) * fv, 1.0, r)
    diffuse_n = c * d_n * (1.0 - bk) * _as(diffuse_scale, v)
    diffuse_g = c * d_g * (1.0 - bk) * _as(diffuse_scale, v)
    transmit_diffuse_n = c * d_n * bk * _as(transmit_diffuse_scale, v)
    transmit_diffuse_g = c * d_g * bk * _as(transmit_diffuse_scale, v)

    # Highlights: roughness partitions between reflection and specular, then fades out.
    t = torch.clamp(1.0 - 2.0 * r, min=0.0)
    refl_ratio = t * t * t
    fade = 1.0 - r
    tint_h = _as(highlight_tint, v)
    tint_t = _as(transmit_tint, v)
    spec_w = (1.0 - refl_ratio) * fade
    refl_w = refl_ratio * fade
    specular_n = spec_w * n_refl_s * tint_h * _as(specular_scale, v)
    specular_g = spec_w * g_refl * tint_h * _as(specular_scale, v)
    reflection_n = refl_w * n_refl_s * tint_h * _as(reflection_scale, v)
    reflection_g = refl_w * g_refl * tint_h * _as(reflection_scale, v)
    t_spec = c * spec_w * clr * tint_t * _as(transmit_specular_scale, v)
    t_refl = c * refl_w * clr * tint_t * _as(refraction_scale, v)
    transmit_specular_n = t_spec * (1.0 - n_refl_s)
    transmit_specular_g = t_spec * (1.0 - g_refl)
    refraction_n = t_refl * (1.0 - n_refl_s)
    refraction_g = t_refl * (1.0 - g_refl)

    spec_cone = torch.deg2rad(lerp(SPECULAR_CONE_DEG[0], SPECULAR_CONE_DEG[1], r))
    refl_cone = torch.deg2rad(lerp(REFLECTION_CONE_DEG[0], REFLECTION_CONE_DEG[1], r))

    def cone(angle, scale):
        return torch.clamp(angle * _as(scale, v), _MIN_CONE, _MAX_CONE)

    r_eta = torch.clamp(s_n * DIELECTRIC_REFLECTANCE, 0.0, MAX_ETA_REFLECTANCE)
    sq = safe_sqrt(r_eta)
    eta = (1.0 + sq) / (1.0 - sq)

    values = dict(
        diffuse_n=diffuse_n,
        diffuse_g=diffuse_g,
        specular_n=specular_n,
        specular_g=specular_g,
        reflection_n=reflection_n,
        reflection_g=reflection_g,
        transmit_diffuse_n=transmit_diffuse_n,
        transmit_diffuse_g=transmit_diffuse_g,
        transmit_specular_n=transmit_specular_n,
        transmit_specular_g=transmit_specular_g,
        refraction_n=refraction_n,
        refraction_g=refraction_g,
        specular_cone=cone(spec_cone, specular_cone_scale),
        reflection_cone=cone(refl_cone, reflection_cone_scale),
        transmit_specular_cone=cone(spec_cone, transmit_specular_cone_scale),
        refraction_cone=cone(refl_cone, refraction_cone_scale),
        diffuse_normal=n,
        highlight_normal=n,
        eta=eta,
    )
    batch = torch.broadcast_shapes(*(x.shape[:-1] if x.dim() else () for x in values.values()))
    out = {}
    for k, x in values.items():
        ch = 3 if (k.endswith(("_n", "_g")) or k.endswith("normal")) else 1
        out[k] = torch.broadcast_to(x, (*batch, ch))
    return SmitsLobes(**out, pruned=_pruned_lobes(params))


def _pruned_lobes(params: dict) -> frozenset[str]:
    """Lobes whose weights are exactly 0 for Python-number parameters (no tensor is read);
    ``params`` are :func:`smits_lobes`' arguments by name."""
    pruned = {name for name in SMITS_LOBES if is_zero(params[name + "_scale"])}
    if is_zero(params["clear"]):
        pruned |= {"transmit_specular", "refraction"}
    if is_zero(params["back"]):
        pruned.add("transmit_diffuse")
    roughness = params["roughness"]
    if isinstance(roughness, numbers.Real) and float(roughness) >= 0.5:
        pruned |= {"reflection", "refraction"}
    if isinstance(roughness, numbers.Real) and float(roughness) >= 1.0:
        pruned |= {"specular", "transmit_specular"}
    return frozenset(pruned)


# --------------------------------------------------------------------------- evaluation


def smits_evaluate(l: Tensor, v: Tensor, n: Tensor, lobes: SmitsLobes) -> Tensor:
    """Evaluate a lobe set: reflection for ``n.l > 0``, transmission for ``n.l < 0``.

    Args:
        l: light directions ``(*, 3)``.
        v: view directions ``(*, 3)``.
        n: geometric/shading normal deciding above/below ``(*, 3)``; the lobes use their
            own ``diffuse_normal`` / ``highlight_normal``.
        lobes: from :func:`smits_lobes` or :func:`smits_composite`.

    Returns:
        ``f(l, v)``, ``(*, 3)``, in the compute dtype; exactly 0 where ``n.v <= 0`` or
        ``n.l = 0``.
    """
    cdt = lobes.eta.dtype
    l, v, n = l.to(cdt), v.to(cdt), n.to(cdt)
    n_dot_l = dot(n, l)
    n_dot_v = dot(n, v)
    above = (n_dot_l > 0) & (n_dot_v > 0)
    below = (n_dot_l < 0) & (n_dot_v > 0)
    pruned = lobes.pruned

    nd = lobes.diffuse_normal
    nh = lobes.highlight_normal
    cos_dl = dot(nd, l)
    cos_hv = dot(nh, v)
    zero = torch.zeros((), dtype=cdt, device=l.device)

    front = zero
    if "diffuse" not in pruned:
        front = _frnl_blend(lobes.diffuse_n, lobes.diffuse_g, torch.clamp(cos_dl, 0.0, 1.0)) / math.pi
    if not {"specular", "reflection"} <= pruned:
        sin2, geometry = _highlight_geometry(l, v, nh)
        for name in ("specular", "reflection"):
            if name in pruned:
                continue
            w = _frnl_blend(getattr(lobes, name + "_n"), getattr(lobes, name + "_g"), cos_hv)
            power = smits_cone_power(getattr(lobes, name + "_cone"))
            front = front + w * smits_distribution(sin2, power) * geometry

    rear = zero
    if "transmit_diffuse" not in pruned:
        rear = (
            rear
            + _frnl_blend(lobes.transmit_diffuse_n, lobes.transmit_diffuse_g, torch.clamp(-cos_dl, 0.0, 1.0))
            / math.pi
        )
    if not {"transmit_specular", "refraction"} <= pruned:
        v_t = _transmit_view(v, nh, lobes.eta)
        sin2, geometry = _highlight_geometry(l, v_t, -nh)
        for name in ("transmit_specular", "refraction"):
            if name in pruned:
                continue
            w = _frnl_blend(getattr(lobes, name + "_n"), getattr(lobes, name + "_g"), cos_hv)
            power = smits_cone_power(getattr(lobes, name + "_cone"))
            rear = rear + w * smits_distribution(sin2, power) * geometry

    out = torch.where(above, front, torch.where(below, rear, zero))
    batch = torch.broadcast_shapes(out.shape[:-1], lobes.eta.shape[:-1], n_dot_l.shape[:-1])
    return torch.broadcast_to(out, (*batch, 3))


def smits(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    base_color: Color,
    metallic: Scalar = 0.0,
    roughness: Scalar = 0.5,
    clear: Scalar = 0.0,
    back: Scalar = 0.0,
    fresnel_normal_scale: Scalar = 1.0,
    fresnel_grazing_scale: Scalar = 1.0,
    highlight_tint: Color = 1.0,
    transmit_tint: Color = 1.0,
    diffuse_scale: Scalar = 1.0,
    specular_scale: Scalar = 1.0,
    reflection_scale: Scalar = 1.0,
    transmit_diffuse_scale: Scalar = 1.0,
    transmit_specular_scale: Scalar = 1.0,
    refraction_scale: Scalar = 1.0,
    specular_cone_scale: Scalar = 1.0,
    reflection_cone_scale: Scalar = 1.0,
    transmit_specular_cone_scale: Scalar = 1.0,
    refraction_cone_scale: Scalar = 1.0,
    lobes: Iterable[str] | None = None,
) -> Tensor:
    """Smits' Wall-E/Up BRDF/BTDF ``f(l, v)`` (without the ``|n.l|`` cosine).

    Reflection (diffuse, specular, reflection lobes) where ``n.l > 0``, transmission
    (transmitted diffuse, transmitted specular, refraction) where ``n.l < 0``; zero where
    ``n.v <= 0``. Equations and choices: module docstring.

    Args:
        l: unit light directions ``(*, 3)``.
        v: unit view directions ``(*, 3)``.
        n: unit shading normals ``(*, 3)``.
        x: tangents ``(*, 3)``; unused (isotropic model), accepted for the common signature.
        y: bitangents ``(*, 3)``; unused.
        base_color: surface colour ``(*, 3)`` linear RGB in [0, 1] (or a float for grey).
        metallic: ``(*, 1)`` in [0, 1]; 1 removes diffuse and colours the highlights.
        roughness: ``(*, 1)`` in [0, 1]; 0 is a tight reflection, 1 fully diffuse.
        clear: ``(*, 1)`` in [0, 1]; share of the entering light passing straight through.
        back: ``(*, 1)`` in [0, 1]; share of the diffuse light leaving from the back side.
        fresnel_normal_scale: ``(*, 1)``, scales the normal-incidence reflectance
            (0.8 gives the 0.04 of index 1.5); also sets the refraction index.
        fresnel_grazing_scale: ``(*, 1)``, scales the grazing reflectance (1 by default).
        highlight_tint: ``(*, 3)`` colour on the specular and reflection lobes.
        transmit_tint: ``(*, 3)`` colour on the transmitted specular and refraction lobes.
        diffuse_scale: ``(*, 1)`` scale on the diffuse lobe. Lobe scales above 1 can break
            energy conservation; a Python 0 skips the lobe.
        specular_scale: ``(*, 1)`` scale on the specular lobe.
        reflection_scale: ``(*, 1)`` scale on the reflection lobe.
        transmit_diffuse_scale: ``(*, 1)`` scale on the transmitted diffuse lobe.
        transmit_specular_scale: ``(*, 1)`` scale on the transmitted specular lobe.
        refraction_scale: ``(*, 1)`` scale on the refraction lobe.
        specular_cone_scale: ``(*, 1)`` scale on the specular cone angle.
        reflection_cone_scale: ``(*, 1)`` scale on the reflection cone angle.
        transmit_specular_cone_scale: ``(*, 1)`` scale on the transmitted specular cone.
        refraction_cone_scale: ``(*, 1)`` scale on the refraction cone angle.
        lobes: optional subset of :data:`SMITS_LOBES` to evaluate (the others are skipped,
            as if their scale were 0). Lobes whose weight is a Python 0 (a zero scale,
            ``clear``/``back`` = 0, reflection at ``roughness >= 0.5``) are always skipped,
            which changes nothing but the cost.

    Returns:
        ``(*, 3)`` BRDF/BTDF values in the dtype of ``l``.

    Note:
        Any device and float dtype; half types are evaluated in float32 and cast back.
        Gradients are zero (never NaN) where the value is forced to 0. Gradients w.r.t.
        the parameters are discontinuous at the clamps of their ranges.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> f = smits(n, n, n, base_color=torch.ones(3), roughness=1.0)
        >>> torch.allclose(f * math.pi, torch.ones(3))
        True
    """
    lobe_set = smits_lobes(
        v,
        n,
        base_color=base_color,
        metallic=metallic,
        roughness=roughness,
        clear=clear,
        back=back,
        fresnel_normal_scale=fresnel_normal_scale,
        fresnel_grazing_scale=fresnel_grazing_scale,
        highlight_tint=highlight_tint,
        transmit_tint=transmit_tint,
        diffuse_scale=diffuse_scale,
        specular_scale=specular_scale,
        reflection_scale=reflection_scale,
        transmit_diffuse_scale=transmit_diffuse_scale,
        transmit_specular_scale=transmit_specular_scale,
        refraction_scale=refraction_scale,
        specular_cone_scale=specular_cone_scale,
        reflection_cone_scale=reflection_cone_scale,
        transmit_specular_cone_scale=transmit_specular_cone_scale,
        refraction_cone_scale=refraction_cone_scale,
    )
    _check_args({"l": l, "v": v, "x": x, "y": y})
    skip = _selected(lobes)
    if skip:
        lobe_set = replace(lobe_set, pruned=lobe_set.pruned | skip)
    return cast_back(smits_evaluate(l, v, n, lobe_set), l.dtype)


# --------------------------------------------------------------------------- layering


def _lobe_energy(lobes: SmitsLobes, name: str, cos_hv: Tensor) -> Tensor:
    """Luminance of a lobe's albedo share at the current view, ``(*, 1)``."""
    w_n = getattr(lobes, name + "_n")
    w_g = getattr(lobes, name + "_g")
    if name in ("diffuse", "transmit_diffuse"):
        # int_0^1 FrnlBlend(N, G, mu) 2 mu d mu = N + (G - N) 2 B(2, 6) = (20 N + G) / 21
        share = (20.0 * w_n + w_g) / 21.0
    else:
        share = _frnl_blend(w_n, w_g, cos_hv)
    return luminance(share)


def smits_composite(
    v: Tensor, lobe_sets: Sequence[SmitsLobes], layer_weights: Sequence[Scalar]
) -> SmitsLobes:
    """Combine layers into one lobe set: A-over-B weights, energy-weighted cones and normals.

    Args:
        v: view directions ``(*, 3)``.
        lobe_sets: per-layer :class:`SmitsLobes`, top layer first.
        layer_weights: per-layer presence/opacity ``(*, 1)`` tensors or floats in [0, 1].

    Returns:
        One :class:`SmitsLobes`. Its weights are ``sum_i coverage_i W_i`` with
        ``coverage_i = a_i prod_{j<i} (1 - a_j)``; the diffuse/highlight normals, each cone
        angle and ``eta`` are averages weighted by ``coverage_i * energy_i`` of the lobes
        they serve (luminance of the albedo share at this view).
    """
    if len(lobe_sets) != len(layer_weights) or not lobe_sets:
        raise ValueError("smits_composite: need one layer weight per lobe set (at least one)")
    ref = lobe_sets[0].eta
    v = v.to(ref.dtype)
    remaining = torch.ones((), dtype=ref.dtype, device=ref.device)
    coverage = []
    for a in layer_weights:
        a = torch.clamp(_as(a, ref), 0.0, 1.0)
        coverage.append(a * remaining)
        remaining = remaining * (1.0 - a)

    out = {}
    for name in _LOBES:
        for suffix in ("_n", "_g"):
            key = name + suffix
            out[key] = sum(c * getattr(s, key) for c, s in zip(coverage, lobe_sets))

    energies = []
    for s in lobe_sets:
        cos_hv = dot(s.highlight_normal, v)
        energies.append({name: _lobe_energy(s, name, cos_hv) + _ENERGY_EPS for name in _LOBES})

    def blend(attr, weights):
        num = sum(w * getattr(s, attr) for w, s in zip(weights, lobe_sets))
        return safe_div(num, sum(weights))

    for name in _HIGHLIGHTS:
        out[name + "_cone"] = blend(name + "_cone", [c * e[name] for c, e in zip(coverage, energies)])
    w_diff = [c * (e["diffuse"] + e["transmit_diffuse"]) for c, e in zip(coverage, energies)]
    w_high = [c * sum(e[k] for k in _HIGHLIGHTS) for c, e in zip(coverage, energies)]
    w_tran = [c * (e["transmit_specular"] + e["refraction"]) for c, e in zip(coverage, energies)]
    # (cast: `sum` of a non-empty sequence of tensors is a tensor, never its start value 0)
    out["diffuse_normal"] = safe_normalize(
        cast(Tensor, sum(w * s.diffuse_normal for w, s in zip(w_diff, lobe_sets)))
    )
    out["highlight_normal"] = safe_normalize(
        cast(Tensor, sum(w * s.highlight_normal for w, s in zip(w_high, lobe_sets)))
    )
    out["eta"] = blend("eta", w_tran)
    batch = torch.broadcast_shapes(*(x.shape[:-1] for x in out.values()))
    out = {k: torch.broadcast_to(x, (*batch, x.shape[-1])) for k, x in out.items()}
    pruned = frozenset.intersection(*(s.pruned for s in lobe_sets))
    return SmitsLobes(**out, pruned=pruned)


def smits_layered(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    layers: Sequence[Mapping[str, Any]],
    layer_weights: Sequence[Scalar],
    lobes: Iterable[str] | None = None,
) -> Tensor:
    """Layered Smits material: several parameter sets composited by :func:`smits_composite`.

    Args:
        l: light directions ``(*, 3)``.
        v: view directions ``(*, 3)``.
        n: shading normal ``(*, 3)``; decides reflection vs transmission and is the default
            normal of every layer.
        x: unused.
        y: unused.
        layers: top layer first; each a mapping of :func:`smits` keyword parameters, plus an
            optional ``"normal"`` ``(*, 3)`` for that layer (e.g. its own bump).
        layer_weights: presence/opacity of each layer, ``(*, 1)`` or floats in [0, 1].
        lobes: optional subset of :data:`SMITS_LOBES` to evaluate.

    Returns:
        ``f(l, v)``, ``(*, 3)`` in the dtype of ``l``.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> coat = dict(base_color=torch.ones(3), roughness=0.1)
        >>> rust = dict(base_color=torch.tensor([0.4, 0.2, 0.1]), roughness=0.9)
        >>> smits_layered(n, n, n, layers=[coat, rust], layer_weights=[0.3, 1.0]).shape
        torch.Size([3])
    """
    _check_args({"l": l, "v": v, "n": n, "x": x, "y": y})
    _check_args({"l": l, **{f"layer_weights[{i}]": a for i, a in enumerate(layer_weights)}})
    sets = []
    for params in layers:
        params = dict(params)
        n_i = params.pop("normal", n)
        sets.append(smits_lobes(v, n_i, **params))
    lobe_set = smits_composite(v, sets, layer_weights)
    skip = _selected(lobes)
    if skip:
        lobe_set = replace(lobe_set, pruned=lobe_set.pruned | skip)
    return cast_back(smits_evaluate(l, v, n, lobe_set), l.dtype)


# --------------------------------------------------------------------------- modules


class SmitsBRDF(nn.Module):
    """Module form of :func:`smits`; the material parameters are passed to ``forward``.

    Args:
        lobes: optional subset of :data:`SMITS_LOBES` to evaluate (default: all).

    Shape:
        - l, v, n (x, y unused): ``(*, 3)``; material keyword maps broadcast against them.
        - Output: ``(*, 3)``.

    Example:
        >>> brdf = SmitsBRDF(lobes=("diffuse", "specular"))
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> brdf(n, n, n, base_color=torch.ones(3), roughness=0.3).shape
        torch.Size([3])
    """

    def __init__(self, lobes: Iterable[str] | None = None) -> None:
        super().__init__()
        _selected(lobes)  # validates the names
        self.lobes = None if lobes is None else tuple(lobes)

    def forward(
        self,
        l: Tensor,
        v: Tensor,
        n: Tensor,
        x: Tensor | None = None,
        y: Tensor | None = None,
        **material: Any,
    ) -> Tensor:
        """Evaluate :func:`smits` with the given material parameters."""
        return smits(l, v, n, x, y, lobes=self.lobes, **material)

    def extra_repr(self) -> str:
        """Lobe selection, for ``print(module)``."""
        return f"lobes={self.lobes}"


class SmitsLayeredBRDF(nn.Module):
    """Module form of :func:`smits_layered`.

    Args:
        lobes: optional subset of :data:`SMITS_LOBES` to evaluate (default: all).

    Shape:
        - l, v, n: ``(*, 3)``; ``layers``: sequence of parameter mappings; ``layer_weights``:
          sequence of ``(*, 1)`` or floats.
        - Output: ``(*, 3)``.
    """

    def __init__(self, lobes: Iterable[str] | None = None) -> None:
        super().__init__()
        _selected(lobes)
        self.lobes = None if lobes is None else tuple(lobes)

    def forward(
        self,
        l: Tensor,
        v: Tensor,
        n: Tensor,
        x: Tensor | None = None,
        y: Tensor | None = None,
        *,
        layers: Sequence[Mapping[str, Any]],
        layer_weights: Sequence[Scalar],
    ) -> Tensor:
        """Evaluate :func:`smits_layered`."""
        return smits_layered(l, v, n, x, y, layers=layers, layer_weights=layer_weights, lobes=self.lobes)

    def extra_repr(self) -> str:
        """Lobe selection, for ``print(module)``."""
        return f"lobes={self.lobes}"
