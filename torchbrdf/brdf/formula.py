"""The BRDF formulas written once, over an ``ops`` namespace: the principled BRDF, the
shader's light terms, the recovery's residual and the SVBRDF-capture GGX.

Every function here takes ``ops`` as its first argument and uses only Python arithmetic
operators (``+ - * /``, comparisons, ``&`` on masks) and the methods of ``ops``. The same
source therefore runs

* on torch tensors with :class:`TorchOps` — this *is* the eager path of
  :func:`torchbrdf.principled` (and of ``burley_retro_factor``, ``subsurface_factor``,
  ``ndf_gtr1``) and of :func:`torchbrdf.svbrdf_ggx`, and
* on the tracer's graph nodes with ``torchbrdf.kernels.trace.TraceOps`` — from which the
  fused kernels (forward, reverse-mode backward, forward-mode JVP) are generated.

A change to a constant or a line here changes the eager path and every kernel alike.

The ``ops`` namespace (shapes for :class:`TorchOps`; vectors ``(*, 3)``, scalars ``(*, 1)``):

==========================  ========================================================
``sqrt, rsqrt, log, log1p``  elementwise (``sqrt`` of a Python number is ``math.sqrt``)
``exp2``                     ``2^x`` elementwise
``abs(x)``                   ``|x|``
``maximum(a, b)``            ``torch.maximum`` (a tie splits the gradient in halves, as ATen)
``clamp(x, lo, hi)``         ``torch.clamp``
``clamp_min(x, lo)``         ``torch.clamp(x, min=lo)``; ``max(x, lo)`` on numbers
``where(c, a, b)``           ``torch.where`` (``a``/``b`` may be numbers)
``dot(a, b)``                ``(*, 3), (*, 3) -> (*, 1)``
``cross_norm2(a, b)``        ``|a × b|²``, ``(*, 1)``
``channel(x, i)``            ``x[..., i:i+1]``
``as_tensor(x)``             a number (or runtime float) as a compute-dtype tensor
``as_color(x)``              a colour ``(*, 3)`` (a number becomes grey)
``to_hi(x), to_compute(x)``  to float64 and back for float32 compute (identity for float64):
                             the rounding choices of the half-vector terms are part of the formula
``mask(valid, f)``           ``f`` where ``valid``, exactly 0 elsewhere, ``(*, 3)``
==========================  ========================================================

Parameters reach the formula as tensors or Python numbers; the tracer passes numbers that
are not known until run time as runtime-float nodes, which fold in double like Python floats.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable
from typing import Any, Protocol, TypeAlias

import torch
from torch import Tensor

from torchbrdf._math import cross_norm2, dot

# A value inside a formula: a Tensor or Python number (TorchOps), or a graph node / 3-vector of
# nodes (kernels.trace.TraceOps). The formulas are written once for both, and the two kinds share
# only arithmetic, which the type system cannot express as one type; hence Any, named here.
Value: TypeAlias = Any


class Ops(Protocol):
    """The ``ops`` namespace a formula receives: :class:`TorchOps` or the tracer's ``TraceOps``."""

    def sqrt(self, x: Value, /) -> Value: ...
    def rsqrt(self, x: Value, /) -> Value: ...
    def log(self, x: Value, /) -> Value: ...
    def log1p(self, x: Value, /) -> Value: ...
    def exp2(self, x: Value, /) -> Value: ...
    def abs(self, x: Value, /) -> Value: ...
    def maximum(self, a: Value, b: Value, /) -> Value: ...
    def dot(self, a: Value, b: Value, /) -> Value: ...
    def cross_norm2(self, a: Value, b: Value, /) -> Value: ...
    def clamp(self, x: Value, lo: float, hi: float, /) -> Value: ...
    def clamp_min(self, x: Value, lo: float, /) -> Value: ...
    def where(self, c: Value, a: Value, b: Value, /) -> Value: ...
    def channel(self, x: Value, i: int, /) -> Value: ...
    def as_tensor(self, x: Value, /) -> Value: ...
    def as_color(self, x: Value, /) -> Value: ...
    def to_hi(self, x: Value, /) -> Value: ...
    def to_compute(self, x: Value, /) -> Value: ...
    def mask(self, valid: Value, f: Value | None, /) -> Value: ...


#: The principled BRDF's scalar parameters and their defaults (Burley 2012), in the order the
#: kernels and the shader take them.
PRINCIPLED_DEFAULTS = {
    "metallic": 0.0,
    "subsurface": 0.0,
    "specular": 0.5,
    "roughness": 0.5,
    "specular_tint": 0.0,
    "anisotropic": 0.0,
    "sheen": 0.0,
    "sheen_tint": 0.5,
    "clearcoat": 0.0,
    "clearcoat_gloss": 1.0,
}
#: The scalar parameter names (``(*, 1)`` channels each).
SCALAR_PARAMS = tuple(PRINCIPLED_DEFAULTS)
#: The lobes, in evaluation order.
LOBES = ("diffuse", "subsurface", "specular", "sheen", "clearcoat")


def is_const(p: Any, value: float) -> bool:
    """True when ``p`` is a Python number equal to ``value`` (a tensor is never assumed constant)."""
    return isinstance(p, numbers.Real) and float(p) == value


def active_lobes(params: dict, lobes: Iterable[str] | None = None) -> tuple[str, ...]:
    """Lobes ``principled`` evaluates for these parameters.

    A lobe is skipped when its weight is a Python number equal to 0 (exactly the same result,
    since the skipped term would be multiplied by 0) or when ``lobes`` leaves it out.
    """
    p = {**PRINCIPLED_DEFAULTS, **params}
    wanted = LOBES if lobes is None else tuple(lobes)
    unknown = set(wanted) - set(LOBES)
    if unknown:
        raise ValueError(f"lobes: unknown lobe(s) {sorted(unknown)}; expected a subset of {LOBES}")
    metal = is_const(p["metallic"], 1.0)
    skip = {
        "diffuse": metal or is_const(p["subsurface"], 1.0),
        "subsurface": metal or is_const(p["subsurface"], 0.0),
        "specular": False,
        "sheen": metal or is_const(p["sheen"], 0.0),
        "clearcoat": is_const(p["clearcoat"], 0.0),
    }
    return tuple(lobe for lobe in LOBES if lobe in wanted and not skip[lobe])

INV_PI = 1.0 / math.pi
# Cosine floor for the masked-out lanes and for grazing inputs: 1e-7 is the smallest cosine
# the library promises finite values for (1/(NL+NV) stays below 1e7).
COS_EPS = 1e-7
# 1 - 0.9 * anisotropic floor: anisotropic = 1 already gives aspect sqrt(0.1).
ASPECT2_MIN = 0.1
# The principled model's alpha floor (Burley 2012 code).
ALPHA_MIN = 1e-3
SQRT_EPS = 1e-12
NORM_EPS = 1e-12
# |x| below which t / log(1 + t) switches to its Taylor series.
SERIES_EPS = 1e-4
# Floor under NDF denominators (α² cos² + sin²): only a zero half vector or normal reaches it.
DEN_EPS = 1e-18
# |l + v|² below which there is no half vector (l = -v); such lanes borrow h = n.
HALF_DEGENERATE = 1e-20
# Squared distance floor for point lights (a light exactly on the surface): keeps 1/d² finite.
DIST2_EPS = 1e-12


class TorchOps:
    """The ``ops`` namespace on torch tensors of compute dtype ``dtype`` on ``device``."""

    def __init__(self, dtype: torch.dtype, device: torch.device | str | None = None) -> None:
        self.dtype = dtype
        self.device = device
        self.hi = torch.float64 if dtype == torch.float32 else dtype

    @staticmethod
    def sqrt(x: Tensor | float) -> Tensor | float:
        """Square root (``math.sqrt`` on Python numbers)."""
        return torch.sqrt(x) if isinstance(x, Tensor) else math.sqrt(x)

    rsqrt = staticmethod(torch.rsqrt)
    log = staticmethod(torch.log)
    log1p = staticmethod(torch.log1p)
    exp2 = staticmethod(torch.exp2)
    abs = staticmethod(torch.abs)
    maximum = staticmethod(torch.maximum)
    dot = staticmethod(dot)
    cross_norm2 = staticmethod(cross_norm2)

    @staticmethod
    def clamp(x: Tensor, lo: float, hi: float) -> Tensor:
        """``x`` clamped to ``[lo, hi]``."""
        return torch.clamp(x, lo, hi)

    @staticmethod
    def clamp_min(x: Tensor | float, lo: float) -> Tensor | float:
        """``max(x, lo)`` (``torch.clamp(x, min=lo)`` on tensors)."""
        return torch.clamp(x, min=lo) if isinstance(x, Tensor) else max(x, lo)

    @staticmethod
    def where(c: Tensor, a: Tensor | float, b: Tensor | float) -> Tensor:
        """``a`` where ``c``, else ``b``."""
        return torch.where(c, a, b)

    @staticmethod
    def channel(x: Tensor, i: int) -> Tensor:
        """Channel ``i`` of a colour, ``(*, 1)``."""
        return x[..., i:i + 1]

    def as_tensor(self, x: Tensor | float) -> Tensor:
        """A number as a compute-dtype value."""
        return x if isinstance(x, Tensor) else torch.as_tensor(x, dtype=self.dtype, device=self.device)

    def as_color(self, x: Tensor | float) -> Tensor:
        """A colour ``(*, 3)``; a number becomes grey."""
        if isinstance(x, Tensor) and x.dim() > 0:
            return x
        return self.as_tensor(x).expand(3)

    def to_hi(self, x: Tensor) -> Tensor:
        """To float64 when computing in float32."""
        return x.to(self.hi)

    def to_compute(self, x: Tensor) -> Tensor:
        """Back to the compute dtype."""
        return x.to(self.dtype)

    def mask(self, valid: Tensor, f: Tensor | None) -> Tensor:
        """``f`` where ``valid``, exactly 0 elsewhere, ``(*, 3)``."""
        if f is None:
            f = torch.zeros((), dtype=self.dtype, device=valid.device)
        f = torch.broadcast_to(f, torch.broadcast_shapes(f.shape, valid.shape[:-1] + (3,)))
        return torch.where(valid, f, torch.zeros_like(f))


# ---------------------------------------------------------------------------------------------
# Pieces (each also the eager implementation of the public function named in its docstring)
# ---------------------------------------------------------------------------------------------

def lerp(a: Value, b: Value, t: Value) -> Value:
    """``a + (b - a) t``."""
    return a + (b - a) * t


def pow5(m: Value) -> Value:
    """``m^5`` as repeated products (no ``pow``)."""
    m2 = m * m
    return m2 * m2 * m


def schlick_weight(ops: Ops, u: Value) -> Value:
    """``(1 - u)^5`` with ``u`` clamped to ``[0, 1]``."""
    return pow5(ops.clamp(1.0 - u, 0.0, 1.0))


def burley_retro_factor(ops: Ops, nl: Value, nv: Value, lh: Value, roughness: Value) -> Value:
    """Burley's diffuse Fresnel factor (``torchbrdf.brdf.diffuse.burley_retro_factor``)."""
    fd90 = 0.5 + 2.0 * roughness * lh * lh
    return lerp(1.0, fd90, schlick_weight(ops, nl)) * lerp(1.0, fd90, schlick_weight(ops, nv))


def subsurface_factor(ops: Ops, nl: Value, nv: Value, lh: Value, roughness: Value) -> Value:
    """Burley's subsurface factor (``torchbrdf.brdf.diffuse.subsurface_factor``)."""
    fss90 = roughness * lh * lh
    fss = lerp(1.0, fss90, schlick_weight(ops, nl)) * lerp(1.0, fss90, schlick_weight(ops, nv))
    inv = 1.0 / ops.clamp_min(nl + nv, 1e-7)
    return 1.25 * (fss * (inv - 0.5) + 0.5)


def ndf_gtr1(ops: Ops, nh: Value, alpha: Value, sin2_h: Value) -> Value:
    """GTR1, the clearcoat NDF ``(α²-1) / (π ln α² (α² cos² + sin²))`` (``ndf_gtr1``).

    ``ln α²`` is ``log1p(α² - 1)`` near 1 (where ``α² - 1`` is exact) and ``log(α²)``
    elsewhere; ``t / log(1 + t)`` switches to its series through ``t = 0`` (the unused
    branch is fed 1 so it stays finite).
    """
    alpha_t = ops.as_tensor(alpha)
    a2 = alpha_t * alpha_t
    base = a2 * nh * nh + sin2_h
    log_a2 = ops.where((a2 > 0.5) & (a2 < 2.0), ops.log1p(a2 - 1.0), ops.log(a2))
    t = a2 - 1.0
    small = ops.abs(t) < SERIES_EPS
    exact = ops.where(small, 1.0, t) / ops.where(small, 1.0, log_a2)
    series = 1.0 + t * (0.5 + t * (-1.0 / 12.0 + t / 24.0))
    d = ops.where(small, series, exact) / (math.pi * ops.clamp_min(base, DEN_EPS))
    return ops.where(nh > 0.0, d, 0.0)


def g_over_4nn(ops: Ops, n_dot_w: Value, tangent_alpha2: Value) -> Value:
    """``G1(w) / (2 n·w) = 1 / (n·w + sqrt((n·w)² + tangent_alpha2))`` (addendum form)."""
    return 1.0 / (n_dot_w + ops.sqrt(ops.clamp_min(n_dot_w * n_dot_w + tangent_alpha2, SQRT_EPS)))


def half_vector_terms(ops: Ops, l: Value, v: Value, n: Value, x: Value | None = None,
                      y: Value | None = None) -> dict[str, Value]:
    """Half-vector cosines ``nh``, ``lh``, ``one_minus_lh``, ``sin2_h = |n × h|²`` (+ ``hx``, ``hy``).

    For float32 inputs these few projections (and ``1 - l·h``, the Schlick base that cancels
    near the mirror direction) are computed in float64 and rounded once: at α = 0.001 the
    peak's shape depends on ``h·x / α``, so float32's ~1e-7 absolute rounding of a dot product
    would become a ~2e-4 relative error of the BRDF. Everything downstream is a sum of
    positive terms and keeps float32's relative precision.

    Returns a dict of ``(*, 1)`` values in the compute dtype.
    """
    lw, vw, nw = ops.to_hi(l), ops.to_hi(v), ops.to_hi(n)
    lv = lw + vw
    # l = -v has no half vector; such lanes are masked (n·l or n·v <= 0) but must stay finite.
    ssq = ops.dot(lv, lv)
    h = ops.where(ssq < HALF_DEGENERATE, nw, lv * ops.rsqrt(ops.clamp_min(ssq, NORM_EPS)))
    lh = ops.clamp(ops.dot(lw, h), 0.0, 1.0)
    terms = {"nh": ops.dot(nw, h), "lh": lh, "one_minus_lh": 1.0 - lh, "sin2_h": ops.cross_norm2(nw, h)}
    if x is not None:
        terms["hx"], terms["hy"] = ops.dot(h, ops.to_hi(x)), ops.dot(h, ops.to_hi(y))
    return {k: ops.to_compute(t) for k, t in terms.items()}


def specular_dg(ops: Ops, l: Value, v: Value, x: Value | None, y: Value | None, nl: Value, nv: Value,
                hg: dict[str, Value], roughness: Value, anisotropic: Value) -> Value:
    """``Ds · Gs`` of the primary GGX lobe (``Gs`` already holds ``1 / (4 NL NV)``), ``(*, 1)``.

    Isotropic (``x`` is None): ``(h·x)² + (h·y)²`` is ``|n × h|²`` and no frame is needed.
    """
    nh = hg["nh"]
    r2 = roughness * roughness
    if x is None:
        alpha = ops.clamp_min(r2, ALPHA_MIN)
        a2 = alpha * alpha
        den = ops.clamp_min(a2 * nh * nh + hg["sin2_h"], DEN_EPS)  # 0 only for a zero-length n (masked)
        ds = a2 / (math.pi * den * den)
        gs = g_over_4nn(ops, nl, a2 * (1.0 - nl * nl)) * g_over_4nn(ops, nv, a2 * (1.0 - nv * nv))
        return ops.where(nh > 0.0, ds * gs, 0.0)
    aspect = ops.sqrt(ops.clamp_min(1.0 - 0.9 * anisotropic, ASPECT2_MIN))
    ax = ops.clamp_min(r2 / aspect, ALPHA_MIN)
    ay = ops.clamp_min(r2 * aspect, ALPHA_MIN)
    hx, hy = hg["hx"] / ax, hg["hy"] / ay
    den = ops.clamp_min(hx * hx + hy * hy + nh * nh, DEN_EPS)
    ds = 1.0 / (math.pi * ax * ay * den * den)
    lx, ly, vx, vy = ops.dot(l, x) * ax, ops.dot(l, y) * ay, ops.dot(v, x) * ax, ops.dot(v, y) * ay
    gs = g_over_4nn(ops, nl, lx * lx + ly * ly) * g_over_4nn(ops, nv, vx * vx + vy * vy)
    return ops.where(nh > 0.0, ds * gs, 0.0)


def principled(ops: Ops, c: dict, active: tuple, need_tint: bool, frame: bool) -> Value:
    """The Disney principled BRDF ``f(l, v)`` (without the ``n·l`` cosine).

    Args:
        ops: :class:`TorchOps` or the tracer's ops.
        c: ``l, v, n`` ``(*, 3)``; ``x, y`` ``(*, 3)`` (used when ``frame``; filled in by the
            caller); ``base_color`` ``(*, 3)`` or a number; the ten scalar parameters
            ``(*, 1)`` or numbers, all in the compute dtype.
        active: the lobes to evaluate (see ``principled.active_lobes``).
        need_tint: whether the tint colour is needed (``specular_tint`` or a tinted sheen).
        frame: whether the anisotropic form (with the tangent frame) is evaluated.

    Returns:
        ``(*, 3)``; exactly 0 where ``n·l <= 0`` or ``n·v <= 0``.
    """
    l, v, n = c["l"], c["v"], c["n"]
    x, y = (c["x"], c["y"]) if frame else (None, None)
    base = ops.as_color(c["base_color"])
    metallic, roughness = c["metallic"], c["roughness"]

    nl_raw, nv_raw = ops.dot(n, l), ops.dot(n, v)
    valid = (nl_raw > 0.0) & (nv_raw > 0.0)
    nl = ops.clamp_min(nl_raw, COS_EPS)
    nv = ops.clamp_min(nv_raw, COS_EPS)
    hg = half_vector_terms(ops, l, v, n, x, y)
    nh, lh = hg["nh"], hg["lh"]
    fh = pow5(hg["one_minus_lh"])

    if need_tint:
        lum = 0.3 * ops.channel(base, 0) + 0.6 * ops.channel(base, 1) + 0.1 * ops.channel(base, 2)
        positive = lum > 0.0
        ctint = ops.where(positive, base / ops.where(positive, lum, 1.0), 1.0)
    else:
        ctint = 1.0

    f = None

    def acc(term):
        return term if f is None else f + term

    dielectric = 1.0 - metallic

    # Diffuse and subsurface, blended by `subsurface` (weights kept separate so that a lobe
    # whose weight is exactly zero can be dropped without changing a bit of the result).
    if "diffuse" in active or "subsurface" in active:
        ss_w = c["subsurface"]
        mix = 0.0
        if "diffuse" in active:
            mix = burley_retro_factor(ops, nl, nv, lh, roughness) * (1.0 - ss_w)
        if "subsurface" in active:
            mix = mix + subsurface_factor(ops, nl, nv, lh, roughness) * ss_w
        f = acc((INV_PI * mix) * base * dielectric)

    if "sheen" in active:
        csheen = lerp(1.0, ctint, c["sheen_tint"])
        f = acc((fh * c["sheen"]) * csheen * dielectric)

    if "specular" in active:
        cspec0 = lerp(0.08 * c["specular"] * lerp(1.0, ctint, c["specular_tint"]), base, metallic)
        fs = lerp(cspec0, 1.0, fh)
        f = acc(fs * specular_dg(ops, l, v, x, y, nl, nv, hg, roughness, c["anisotropic"]))

    if "clearcoat" in active:
        alpha_c = ops.clamp_min(lerp(0.1, 0.001, c["clearcoat_gloss"]), ALPHA_MIN)
        dr = ndf_gtr1(ops, nh, alpha_c, hg["sin2_h"])
        fr = lerp(0.04, 1.0, fh)
        gr = g_over_4nn(ops, nl, 0.0625 * (1.0 - nl * nl)) * g_over_4nn(ops, nv, 0.0625 * (1.0 - nv * nv))
        f = acc((0.25 * c["clearcoat"]) * gr * fr * dr)

    return ops.mask(valid, f)


# ---------------------------------------------------------------------------------------------
# Shading: one light's contribution at a surface point (the shader's per-light term)
# ---------------------------------------------------------------------------------------------
# Written once over ``ops`` like the BRDF above: the eager shader
# (``torchbrdf.render.shading``) runs these on torch tensors with any BRDF callable, and the
# fused shading kernels (``torchbrdf.kernels.codegen_shade``) trace them with the principled
# BRDF, the per-pixel values outside and the light parameters inside the light loop.
# ``brdf`` is a callable ``brdf(l) -> f (*, 3)`` closing over ``v, n`` and the material.

def normalize(ops: Ops, a: Value) -> Value:
    """``a / |a|`` with ``|a|²`` floored at ``NORM_EPS`` (a zero vector stays 0, finite gradient)."""
    return a * ops.rsqrt(ops.clamp_min(ops.dot(a, a), NORM_EPS))


def view_direction(ops: Ops, camera: Value, pos: Value) -> Value:
    """``v = normalize(C - P)``: unit direction from the surface point toward the camera, ``(*, 3)``."""
    return normalize(ops, camera - pos)


def point_light(ops: Ops, pos: Value, n: Value, position: Value, intensity: Value,
                brdf: Callable[[Value], Value]) -> Value:
    """Point light: ``f(l, v) I max(n·l, 0) / |q - P|²`` with ``l = normalize(q - P)``, ``(*, 3)``.

    Args:
        pos, n: surface point and unit normal ``(*, 3)``; position ``q``, intensity ``I``
            ``(*, 3)`` (broadcast).
    """
    d = position - pos
    dist2 = ops.clamp_min(ops.dot(d, d), DIST2_EPS)
    l = d * ops.rsqrt(dist2)
    f = brdf(l)
    cos = ops.clamp_min(ops.dot(n, l), 0.0)
    return f * intensity * (cos / dist2)


def directional_light(ops: Ops, n: Value, direction: Value, irradiance: Value,
                      brdf: Callable[[Value], Value]) -> Value:
    """Directional light: ``f(d, v) E max(n·d, 0)`` with ``d`` normalised, ``(*, 3)``."""
    l = normalize(ops, direction)
    f = brdf(l)
    cos = ops.clamp_min(ops.dot(n, l), 0.0)
    return f * irradiance * cos


# ---------------------------------------------------------------------------------------------
# Capture fitting: one pixel under one point light, as a log residual (the SVBRDF recovery)
# ---------------------------------------------------------------------------------------------

#: The BRDFs the light-loop kernels (shading, the recovery's residual) take by name.
LOOP_BRDFS = ("principled", "svbrdf_ggx")


def capture_log_residual(ops: Ops, c: dict, active: tuple, need_tint: bool, frame: bool,
                         family: str = "principled") -> Value:
    """``log(max(L + ε, ε/2)) − log_obs`` with ``L`` the capture's radiance, ``(*, 3)``.

    ``L = f(l, v) I max(n·l, 0) / |q − P|²`` (:func:`point_light` with the principled BRDF,
    ``v`` = :func:`view_direction`) is what docs/capture_format.md defines a capture pixel to
    be. ``c`` holds the principled material (as :func:`principled` takes it), ``pos`` (the
    surface point ``P``), ``n``, ``camera``, ``light_pos`` ``q``, ``light_int`` ``I``,
    ``log_obs`` (``log(observed + ε)``) and ``eps`` ``ε``. The recovery's fit minimises the
    square of this; the fused kernels evaluate it, its JVPs and its backward in one pass per
    lane, with the geometry inside. ``family="svbrdf_ggx"``: the recovery's GGX model, the
    same principled unknowns rendered by :func:`svbrdf_ggx` through :func:`ggx_albedos`.
    """
    if family not in LOOP_BRDFS:
        raise ValueError(f"family: expected one of {LOOP_BRDFS}, got {family!r}")
    v = view_direction(ops, c["camera"], c["pos"])
    if family == "svbrdf_ggx":
        ggx = {**c, **ggx_albedos(c)}

        def brdf(l: Value) -> Value:
            return svbrdf_ggx(ops, {**ggx, "l": l, "v": v})
    else:
        def brdf(l: Value) -> Value:
            return principled(ops, {**c, "l": l, "v": v}, active, need_tint, frame)

    rad = point_light(ops, c["pos"], c["n"], c["light_pos"], c["light_int"], brdf)
    eps = c["eps"]
    return ops.log(ops.clamp_min(rad + eps, 0.5 * eps)) - c["log_obs"]


# ---------------------------------------------------------------------------------------------
# The GGX model of the SVBRDF-capture literature (torchbrdf.brdf.svbrdf_ggx)
# ---------------------------------------------------------------------------------------------

# Unreal's spherical-Gaussian fit of Schlick's (1 - c)^5: 2^((SG_A c + SG_B) c) (Karis 2013).
SG_A = -5.55473
SG_B = -6.98316
# The GGX denominator's floor as a fraction of its least value for unit vectors, min(alpha^2, 1).
GGX_DEN_FLOOR = 0.5


def fresnel_sg(ops: Ops, f0: Value, v_dot_h: Value) -> Value:
    """Unreal's spherical-Gaussian Schlick Fresnel ``f0 + (1 - f0) 2^((a c + b) c)``, ``(*, 3)``."""
    return f0 + (1.0 - f0) * ops.exp2((SG_A * v_dot_h + SG_B) * v_dot_h)


def ggx_albedos(c: dict) -> dict:
    """The recovery's GGX model's albedos from principled maps ``base_color``, ``metallic``, ``specular``.

    ``diffuse_albedo = base (1 − m)``, ``specular_albedo = 0.08 s (1 − m) + base m``: the
    principled model's F0 and its dielectric diffuse weight, so the fit keeps one set of unknowns.
    ``base_color (*, 3)``, ``metallic`` and ``specular`` ``(*, 1)`` (tensors, numbers or traced
    values, broadcast); returns both albedos ``(*, 3)``.
    """
    base, m = c["base_color"], c["metallic"]
    return {"diffuse_albedo": base * (1 - m), "specular_albedo": base * m + 0.08 * c["specular"] * (1 - m)}


def svbrdf_ggx(ops: Ops, c: dict, active: tuple = (), need_tint: bool = False, frame: bool = False) -> Value:
    """The SVBRDF-capture GGX ``f(l, v)`` (without the ``n·l`` cosine); see :mod:`torchbrdf.brdf.svbrdf_ggx`.

    Args:
        ops: :class:`TorchOps` or the tracer's ops.
        c: ``l, v, n`` ``(*, 3)``; ``diffuse_albedo``, ``specular_albedo`` ``(*, 3)`` and
            ``roughness`` ``(*, 1)`` in the compute dtype; one floor, ``alpha_floor``
            (``alpha = max(r², floor)``) or ``roughness_floor`` (``alpha = max(r, floor)²``),
            a number.
        active, need_tint, frame: unused (the kernel families' common signature).

    Returns:
        ``(*, 3)``; exactly 0 where ``n·l <= 0`` or ``n·v <= 0``.
    """
    l, v, n = c["l"], c["v"], c["n"]
    rho_d, rho_s, r = ops.as_color(c["diffuse_albedo"]), ops.as_color(c["specular_albedo"]), c["roughness"]
    n_dot_l, n_dot_v = ops.dot(n, l), ops.dot(n, v)
    valid = (n_dot_l > 0.0) & (n_dot_v > 0.0)
    # Clamped copies: every branch below stays finite, so masking leaves zero gradients.
    nl = ops.clamp(n_dot_l, 0.0, 1.0)
    nv = ops.clamp(n_dot_v, 0.0, 1.0)
    h = normalize(ops, l + v)
    nh = ops.clamp(ops.dot(n, h), 0.0, 1.0)
    vh = ops.clamp(ops.dot(v, h), 0.0, 1.0)

    if c.get("roughness_floor") is not None:
        r_floored = ops.clamp_min(r, c["roughness_floor"])
        alpha = r_floored * r_floored
    else:
        alpha = ops.clamp_min(r * r, c.get("alpha_floor", ALPHA_MIN))
    a2 = alpha * alpha
    base = ops.cross_norm2(n, h) + a2 * nh * nh  # = (n.h)^2 (a2 - 1) + 1, without cancellation
    # For unit h, base >= min(a2, 1) (equal at roughness 1 and at h = n); the floor, half that so
    # it never ties there, only acts where h degenerates (l = -v): d stays below 4 / (pi a2).
    base = ops.maximum(base, GGX_DEN_FLOOR * ops.clamp(a2, 0.0, 1.0))
    d = a2 / (math.pi * base * base)
    k = 0.5 * alpha
    vis = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))  # G / (4 n.l n.v), cancelled
    spec = d * vis * fresnel_sg(ops, rho_s, vh)
    diffuse = rho_d * (1.0 - rho_s) / math.pi
    return ops.mask(valid, diffuse + spec)


def capture_log_residual_ggx(ops: Ops, c: dict, active: tuple, need_tint: bool, frame: bool) -> Value:
    """:func:`capture_log_residual` of the recovery's GGX model (``family="svbrdf_ggx"``)."""
    return capture_log_residual(ops, c, active, need_tint, frame, "svbrdf_ggx")


#: The formulas a fused kernel family can be built from (``_KernelSpec.family``).
FAMILIES: dict[str, Callable[..., Value]] = {"principled": principled, "capture": capture_log_residual,
                                             "capture_ggx": capture_log_residual_ggx, "svbrdf_ggx": svbrdf_ggx}
