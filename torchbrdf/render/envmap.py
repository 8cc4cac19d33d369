"""Environment lighting: ``∫ f(l, v) L(l) max(n·l, 0) dω`` over a lat-long map.

The map follows the library's lat-long convention (z up; row ``i`` at ``θ = (i + 0.5) π / H``,
column ``j`` at ``φ = -π + (j + 0.5) 2π / W``) and is read as **piecewise constant over
texels**: ``L(l)`` is the texel containing ``l`` (:func:`latlong_lookup`). That defines the
integral exactly; :func:`integrate_environment_quadrature` evaluates it by brute force.

Two strategies, both differentiable:

**Monte Carlo** (:func:`integrate_environment_mc`, unbiased). Half of the samples come from
the BRDF — a per-pixel mixture of cosine sampling (diffuse, subsurface, sheen), GGX
visible-normal sampling (Heitz 2018; primary specular, anisotropic when the material is)
and GTR1 sampling (Burley 2012 appendix B; clearcoat), weighted by rough lobe albedos —
and half from the map (luminance × solid angle, :class:`~torchbrdf.render.sampling.LatLongSampler`);
they are combined with the power heuristic (Veach 1995). A constant map is not sampled (all
samples go to the BRDF), so a white furnace is exact for Lambert. Numbers are a stratified
Hammersley set rotated per pixel by a seeded offset. The sample directions, densities and
MIS weights are treated as constants by autograd ("detached sampling"): the gradient is then
an unbiased estimate of the gradient of the integral for every input (material, normal,
position, map). Error: zero mean, standard deviation falling as ``1/sqrt(samples)`` (about
1–3 % per pixel at 256 samples for a smooth map and a glossy principled material; see
``docs/shading.md``); highly peaked lobes (roughness < 0.1) under a high-frequency map are
the hardest case.

The ``sampling`` switch (:data:`ENV_SAMPLINGS`) picks the proposal; every choice is unbiased,
stratified and seeded the same way, only the variance differs:

* ``"mis"`` (default) — the BRDF + map mixture above;
* ``"brdf"`` — every sample from the BRDF mixture (weight ``1 / pdf``); noisy when a small
  bright source (a sun) sits inside a rough lobe;
* ``"map"`` — every sample from the map's luminance (over the whole sphere, so samples below
  the surface are wasted; a constant map is then sampled uniformly); noisy for glossy lobes;
* ``"uniform"`` — uniform over the hemisphere about ``n`` (``pdf = 1 / 2π``), no importance
  sampling at all: the baseline the others are measured against.

**Split sum** (:func:`integrate_environment_split_sum`, fast, biased). Karis 2013, with the
map's concentrated sources taken out first: texels brighter than :data:`PEAK_CONTRAST` × the
map's mean radiance (a sun, a lamp; at most :data:`PEAK_DIRECTIONS` cells of them) are summed
exactly as directional lights through the BRDF itself (:func:`extract_peaks`; a specular lobe
too sharp for those cells sums them over finer cells, and a mirror reads them texel by texel),
and only the smooth rest is prefiltered. The specular integral of the rest is split into a prefiltered map
(the map convolved with the GGX lobe under the ``n = v = r`` assumption, at
``len(PREFILTER_ROUGHNESS)`` levels), read along the lobe's centroid and blended between the
two levels whose kernels have the lobe's mean cosine (down to the hemisphere's mean, for lobes
broader than the cosine) — so the lobe's first moment is right,
and a map linear in ``l`` is exact — times a pre-integrated (n·v, roughness) table of the lobe
with Schlick Fresnel split into a scale on ``Cspec0`` and a bias. Diffuse, subsurface and
sheen use the cosine-convolved irradiance times their own tabulated directional albedo;
Burley's diffuse reads the irradiance along its lobe's centroid, tabulated beside its albedo
(the retro-reflection leans the lobe toward ``v`` at grazing view), blended toward a sharper
prefiltered level where its lobe is narrower than the cosine (its tabulated mean cosine, so
its first moment is right too); clearcoat uses a (n·v, clearcoat_gloss) table and the
prefiltered map at the matching width along the mirror direction bent toward ``n``. The table
is computed from :func:`torchbrdf.principled` itself at first use and cached. Every
prefiltered level and the irradiance map conserve the map's power exactly (area resampling
with solid-angle overlaps, then a symmetrically normalised convolution), for any map size.
Error: exact for a constant map (white furnace) and, up to the levels' discretisation, for a
map linear in ``l``; under a sky with a sun within about 0.1 % over a sphere for every lobe
(0.2–0.5 % L1); a bias of a few percent remains for large, moderately bright regions with
sharp edges (a window, a 20× patch: too wide to be a peak, too sharp for one symmetric
kernel), at grazing view, and for anisotropic materials (treated as isotropic with the same
mean width, except at the peaks) — see ``docs/shading.md``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from functools import lru_cache
from typing import cast

import torch
from torch import Tensor

from torchbrdf._math import compute_dtype, dot, lerp, luminance, safe_normalize, safe_sqrt
from torchbrdf._types import BRDF, Device, Scalar
from torchbrdf.brdf.frames import frame_from_normal, to_local, to_world
from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS, PrincipledBRDF
from torchbrdf.render.sampling import (
    ALPHA_MIN,
    LatLongSampler,
    hammersley,
    latlong_row_solid_angles,
    latlong_texel_index,
    pdf_cosine_hemisphere,
    pdf_ggx_reflection,
    pdf_gtr1,
    reflect,
    rotated_hammersley,
    sample_cosine_hemisphere,
    sample_ggx_vndf,
    sample_gtr1,
)

__all__ = [
    "latlong_lookup",
    "latlong_bilinear",
    "integrate_environment_mc",
    "integrate_environment_quadrature",
    "integrate_environment_split_sum",
    "prefilter_environment",
    "irradiance_environment",
    "extract_peaks",
    "UNIFORM",
    "split_sum_table",
    "SplitSumEnvironment",
    "PREFILTER_ROUGHNESS",
    "SPLIT_SUM_TABLE_CHANNELS",
    "ENV_SAMPLINGS",
]

#: Roughness of each prefiltered level (level 0 is the map itself).
PREFILTER_ROUGHNESS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: Largest prefiltered level height; the kernel costs O(height² · width).
PREFILTER_MAX_HEIGHT = 128
#: Height of the irradiance (cosine-convolved) map.
IRRADIANCE_HEIGHT = 64
#: The split sum takes texels brighter than this multiple of the map's mean radiance out of
#: the map and sums them exactly, as directional lights (:func:`extract_peaks`): its
#: prefiltered lobe is symmetric about one lookup direction, which misplaces a small bright
#: source's response at grazing view by a few percent; a smooth remainder it handles well.
PEAK_CONTRAST = 64.0
#: Most directional lights the peaks of one map become (texels × cells), the brightest first.
PEAK_DIRECTIONS = 64
#: Most cells of the finer subdivision that lobes too sharp for the cells above are summed over.
PEAK_FINE_DIRECTIONS = 512
#: Peak texels are split into cells no larger than a texel of a map this tall (1.4°), finer
#: than a glossy lobe (2.8° cells aliased a roughness-0.2 highlight); lobes narrower than
#: four of them (roughness ≲ 0.2) are summed over cells up to 8× finer (PEAK_FINE_DIRECTIONS).
PEAK_CELL_ROWS = 128
# Points × directions the peaks are evaluated on at once (memory).
_PEAK_ELEMENTS_PER_PASS = 1 << 20
#: (n·v, roughness) table: resolution per axis and quasi-random samples per cell.
SPLIT_SUM_RESOLUTION = 32
SPLIT_SUM_SAMPLES = 1024
SPLIT_SUM_TABLE_CHANNELS = (
    "specular_scale",
    "specular_bias",
    "diffuse",
    "subsurface",
    "sheen",
    "clearcoat",
    "diffuse_tilt",
    "diffuse_spread",
    "specular_scale_bend",
    "specular_scale_spread",
    "specular_bias_bend",
    "specular_bias_spread",
)
#: Lobe names understood by the MC mixture.
SAMPLING_LOBES = ("diffuse", "specular", "clearcoat")
#: Proposals of the Monte Carlo integrator (``sampling=`` / ``shade(env_sampling=)``):
#: BRDF + map with the power heuristic, BRDF only, map only, uniform hemisphere.
ENV_SAMPLINGS = ("mis", "brdf", "map", "uniform")
# Minimum share of the BRDF samples any lobe with non-zero weight receives (robustness
# against a poor albedo guess).
_MIN_LOBE_SHARE = 0.05


# --------------------------------------------------------------------------------------
# Map lookups
# --------------------------------------------------------------------------------------


def _as_bhwc(radiance: Tensor) -> Tensor:
    """``(3, H, W)`` or ``(B, 3, H, W)`` -> channel-last ``(B, H, W, 3)``."""
    if radiance.dim() == 3:
        radiance = radiance.unsqueeze(0)
    return radiance.permute(0, 2, 3, 1)


def latlong_lookup(radiance: Tensor, d: Tensor, batch_index: Tensor | None = None) -> Tensor:
    """Radiance of the texel containing each direction (piecewise-constant map).

    Differentiable with respect to ``radiance`` (not ``d``: the lookup is piecewise constant).

    Args:
        radiance: ``(B, 3, H, W)`` or ``(3, H, W)`` lat-long map.
        d: ``(*, 3)`` directions.
        batch_index: int64 ``(*)`` map index per direction when ``B > 1``.

    Returns:
        ``(*, 3)``.
    """
    return _lookup_cl(_as_bhwc(radiance), d, batch_index)


def _lookup_cl(img: Tensor, d: Tensor, batch_index) -> Tensor:
    b, h, w, _ = img.shape
    row, col = latlong_texel_index(d.detach(), h, w)
    flat = row * w + col
    if b > 1:
        if batch_index is None:
            raise ValueError(f"batch_index is required to look up a batch of {b} maps")
        flat = flat + batch_index.long() * (h * w)
    table = img.reshape(b * h * w, 3)
    return table[flat]


def _direction_angles(d: Tensor) -> tuple[Tensor, Tensor]:
    """``(θ, φ)`` of ``d`` ``(*, 3)`` with finite gradients at the poles, each ``(*)``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    rho2 = x * x + y * y
    pole = rho2 < 1e-20
    xs = torch.where(pole, torch.ones_like(x), x)
    ys = torch.where(pole, torch.zeros_like(y), y)
    phi = torch.atan2(ys, xs)
    theta = torch.atan2(safe_sqrt(rho2), z)
    return theta, phi


def latlong_bilinear(
    img: Tensor, d: Tensor, batch_index: Tensor | None = None, *, angles: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """Bilinear lookup in a channel-last lat-long image (wraps in φ, clamps in θ).

    Differentiable with respect to ``img`` and ``d``.

    Args:
        img: ``(B, H, W, C)`` channel-last map.
        d: ``(*, 3)`` unit directions.
        batch_index: int64 ``(*)`` when ``B > 1``.
        angles: ``d``'s ``(θ, φ)`` when already known (several maps read along the same
            directions).

    Returns:
        ``(*, C)``.
    """
    b, h, w, c = img.shape
    theta, phi = _direction_angles(d) if angles is None else angles
    fy = theta * (h / math.pi) - 0.5
    fx = (phi + math.pi) * (w / (2.0 * math.pi)) - 0.5
    y0 = torch.floor(fy.detach())
    x0 = torch.floor(fx.detach())
    ty = (fy - y0).unsqueeze(-1)
    tx = (fx - x0).unsqueeze(-1)
    y0 = y0.long()
    x0 = x0.long()
    r0 = torch.clamp(y0, 0, h - 1)
    r1 = torch.clamp(y0 + 1, 0, h - 1)
    c0 = torch.remainder(x0, w)
    c1 = torch.remainder(x0 + 1, w)
    base: Tensor | int = 0
    if b > 1:
        if batch_index is None:
            raise ValueError(f"batch_index is required to look up a batch of {b} maps")
        base = batch_index.long() * (h * w)
    table = img.reshape(b * h * w, c)
    v00 = table[base + r0 * w + c0]
    v01 = table[base + r0 * w + c1]
    v10 = table[base + r1 * w + c0]
    v11 = table[base + r1 * w + c1]
    top = v00 + (v01 - v00) * tx
    bot = v10 + (v11 - v10) * tx
    return top + (bot - top) * ty


# --------------------------------------------------------------------------------------
# Material helpers (floats, 0-d tensors and per-pixel (P, C) maps alike)
# --------------------------------------------------------------------------------------

_PRINCIPLED_DEFAULTS = PRINCIPLED_DEFAULTS


def _param(material: dict, name: str):
    return material.get(name, _PRINCIPLED_DEFAULTS.get(name, 0.0))


def _is_zero(p) -> bool:
    return isinstance(p, numbers.Real) and float(p) == 0.0


def _t(p, like: Tensor) -> Tensor:
    """A material value as a tensor broadcastable against ``like`` ``(P, ...)``."""
    if isinstance(p, Tensor):
        return p.to(like.dtype)
    return torch.as_tensor(float(p), dtype=like.dtype, device=like.device)


def _rgb(p, like: Tensor) -> Tensor:
    """A colour value (float, 0-d, ``(..., 1)`` or ``(..., 3)``) as a tensor with last axis 3."""
    t = _t(p, like)
    if t.dim() == 0:
        return t.expand(3)
    return t.expand(*t.shape[:-1], 3)


def _unsq(p, dims: int):
    """Insert ``dims`` sample axes before the channel axis of a ``(P, C)`` material value."""
    if isinstance(p, Tensor) and p.dim() >= 2:
        return p.reshape(p.shape[:-1] + (1,) * dims + p.shape[-1:])
    return p


# --------------------------------------------------------------------------------------
# BRDF sampling mixture
# --------------------------------------------------------------------------------------


class _BRDFMixture:
    """Per-pixel mixture of cosine, GGX-VNDF and GTR1 sampling (all detached).

    Built for ``P`` pixels; ``sample``/``pdf`` take ``(P, k, ·)`` sample arrays.
    """

    def __init__(self, lobes, material, n, v, x, y):
        with torch.no_grad():
            n = n.detach()
            self.n = n.unsqueeze(1)
            self.x = x.detach().unsqueeze(1)
            self.y = y.detach().unsqueeze(1)
            v_local = to_local(v.detach(), x.detach(), y.detach(), n)
            self.v_local = v_local.unsqueeze(1)
            ones = torch.ones_like(n[..., :1])
            mat = {k: (val.detach() if isinstance(val, Tensor) else val) for k, val in material.items()}
            base = _rgb(mat.get("base_color", 1.0), n)
            lum = torch.clamp(luminance(base * ones), min=0.0)
            metal = torch.clamp(_t(_param(mat, "metallic"), n) * ones, 0.0, 1.0)
            weights = {}
            if "diffuse" in lobes:
                w = torch.zeros_like(ones)
                if lobes["diffuse"]:
                    w = w + lum
                if lobes.get("sheen", False):
                    w = w + 0.25 * torch.clamp(_t(_param(mat, "sheen"), n) * ones, min=0.0)
                weights["diffuse"] = (1.0 - metal) * w
            if "specular" in lobes:
                f0 = lerp(0.08 * _t(_param(mat, "specular"), n) * ones, lum, metal)
                weights["specular"] = torch.clamp(f0, 0.0, 1.0) + 0.1
                r = torch.clamp(_t(_param(mat, "roughness"), n) * ones, min=0.0)
                r2 = r * r
                aniso = _t(_param(mat, "anisotropic"), n) * ones
                aspect = torch.sqrt(torch.clamp(1.0 - 0.9 * aniso, min=0.1))
                self.ax = torch.clamp(r2 / aspect, min=ALPHA_MIN).unsqueeze(1)
                self.ay = torch.clamp(r2 * aspect, min=ALPHA_MIN).unsqueeze(1)
            if "clearcoat" in lobes:
                weights["clearcoat"] = 0.25 * torch.clamp(_t(_param(mat, "clearcoat"), n) * ones, min=0.0)
                gloss = _t(_param(mat, "clearcoat_gloss"), n) * ones
                self.ac = torch.clamp(lerp(0.1, 0.001, gloss), min=ALPHA_MIN).unsqueeze(1)
            names = [k for k in SAMPLING_LOBES if k in weights]
            w = torch.cat([weights[k] for k in names], dim=-1)  # (P, K)
            total = w.sum(-1, keepdim=True)
            # A pixel whose every weight is zero (black, non-metal, no clearcoat) still needs a
            # proposal: fall back to cosine sampling (or the first lobe).
            fallback = torch.zeros_like(w)
            fallback[..., 0] = 1.0
            w = torch.where(total > 0, w / torch.where(total > 0, total, torch.ones_like(total)), fallback)
            w = torch.where(w > 0, torch.clamp(w, min=_MIN_LOBE_SHARE), w)
            w = w / w.sum(-1, keepdim=True)
            self.names = names
            self.weights = w.unsqueeze(1)  # (P, 1, K)

    def sample(self, u: Tensor) -> Tensor:
        """World directions ``(P, k, 3)`` from uniform numbers ``(P, k, 2)``."""
        with torch.no_grad():
            cdf = torch.cumsum(self.weights, dim=-1)
            u1 = u[..., 0:1]
            idx = torch.clamp((u1 >= cdf).sum(-1, keepdim=True), max=len(self.names) - 1)  # (P, k, 1)
            lo = torch.where(
                idx > 0,
                torch.gather(cdf.expand(*u.shape[:-1], -1), -1, torch.clamp(idx - 1, min=0)),
                torch.zeros_like(u1),
            )
            wsel = torch.gather(self.weights.expand(*u.shape[:-1], -1), -1, idx)
            u1r = torch.clamp((u1 - lo) / torch.clamp(wsel, min=1e-30), 0.0, 1.0 - 1e-7)
            ur = torch.cat((u1r, u[..., 1:2]), dim=-1)
            out = torch.zeros(u.shape[:-1] + (3,), dtype=u.dtype, device=u.device)
            for k, name in enumerate(self.names):
                if name == "diffuse":
                    w_local = sample_cosine_hemisphere(ur)
                elif name == "specular":
                    h = sample_ggx_vndf(self.v_local, self.ax, self.ay, ur)
                    w_local = reflect(self.v_local, h)
                else:
                    h = sample_gtr1(self.ac, ur)
                    w_local = reflect(self.v_local, h)
                out = torch.where(idx == k, w_local, out)
            return to_world(out, self.x, self.y, self.n)

    def pdf(self, l: Tensor) -> Tensor:
        """Mixture density ``(P, k, 1)`` of world directions ``(P, k, 3)``."""
        with torch.no_grad():
            l_local = to_local(l, self.x, self.y, self.n)
            total = torch.zeros_like(l_local[..., :1])
            for k, name in enumerate(self.names):
                wk = self.weights[..., k : k + 1]
                if name == "diffuse":
                    p = pdf_cosine_hemisphere(l_local)
                elif name == "specular":
                    p = pdf_ggx_reflection(self.v_local, l_local, self.ax, self.ay)
                else:
                    h = safe_normalize(self.v_local + l_local)
                    lh = dot(l_local, h)
                    ph = pdf_gtr1(h, self.ac)
                    p = torch.where(lh > 0, ph / (4.0 * torch.clamp(lh, min=1e-30)), torch.zeros_like(ph))
                total = total + wk * p
            return torch.where(l_local[..., 2:3] > 0, total, torch.zeros_like(total))


def _mis_power(n_t: int, p_t: Tensor, n_o: int, p_o) -> Tensor:
    """``w_t / (n_t p_t)`` of the power heuristic: ``n_t p_t / ((n_t p_t)² + (n_o p_o)²)``.

    Computed relative to the larger term so it cannot overflow; 0 where both densities are 0.
    """
    a = n_t * p_t
    b = n_o * p_o if isinstance(p_o, Tensor) else torch.zeros_like(a)
    m = torch.maximum(a, b)
    ok = (m > 0) & torch.isfinite(m)
    ms = torch.where(ok, m, torch.ones_like(m))
    ra, rb = a / ms, b / ms
    w = ra / (ms * (ra * ra + rb * rb))
    return torch.where(ok & (a > 0), w, torch.zeros_like(w))


# --------------------------------------------------------------------------------------
# Monte Carlo
# --------------------------------------------------------------------------------------


def sampling_lobes_for(brdf: BRDF, material: dict) -> dict:
    """Which sampling lobes suit ``brdf`` with ``material``: ``{lobe: active}``.

    A BRDF may declare ``brdf.sampling_lobes`` (e.g. Lambert: ``("diffuse",)``). The
    principled BRDF (function or module) gets cosine + GGX + GTR1 for the lobes it will
    evaluate; any other callable is assumed principled-like.
    """
    declared = getattr(brdf, "sampling_lobes", None)
    if declared is not None:
        return {name: True for name in declared}
    wanted = getattr(brdf, "lobes", None) or ("diffuse", "subsurface", "specular", "sheen", "clearcoat")
    metal_one = (
        isinstance(_param(material, "metallic"), numbers.Real) and float(_param(material, "metallic")) == 1.0
    )
    out = {}
    dif = ("diffuse" in wanted or "subsurface" in wanted) and not metal_one
    sheen = "sheen" in wanted and not metal_one and not _is_zero(_param(material, "sheen"))
    if dif or sheen:
        out["diffuse"] = dif
        out["sheen"] = sheen
    if "specular" in wanted:
        out["specular"] = True
    if "clearcoat" in wanted and not _is_zero(_param(material, "clearcoat")):
        out["clearcoat"] = True
    if not out:
        out["diffuse"] = True
    return out


def _env_is_constant(radiance: Tensor) -> bool:
    r = radiance.detach()
    flat = r.reshape(r.shape[0], 3, -1) if r.dim() == 4 else r.reshape(1, 3, -1)
    return bool((flat.amax(-1) == flat.amin(-1)).all())


def _sampling_frame(n: Tensor, x, y, material: dict):
    """Frame for the proposal: the BRDF's own frame when anisotropy is actually present."""
    aniso = _param(material, "anisotropic")
    use_given = x is not None and (
        (isinstance(aniso, Tensor) and bool((aniso.detach() != 0).any()))
        or (not isinstance(aniso, Tensor) and not _is_zero(aniso))
    )
    if use_given:
        xs = x.detach()
        ys = torch.linalg.cross(n.detach(), xs, dim=-1) if y is None else y.detach()
        return xs, ys
    return frame_from_normal(n.detach())


def check_env_sampling(sampling: object, who: str, name: str = "sampling") -> str:
    """Validate a Monte Carlo proposal name (:data:`ENV_SAMPLINGS`); ``ValueError`` naming ``name``."""
    if not isinstance(sampling, str) or sampling not in ENV_SAMPLINGS:
        raise ValueError(f"{who}: `{name}` must be one of {ENV_SAMPLINGS}, got {sampling!r}")
    return sampling


class _MCSetup:
    """Sample budget and random shifts for one environment light.

    ``sampling`` (:data:`ENV_SAMPLINGS`) splits ``samples`` between the techniques:
    ``"mis"`` half BRDF / half map (all BRDF for a constant map or a single sample),
    ``"brdf"`` all BRDF, ``"map"`` all map, ``"uniform"`` all uniform-hemisphere.
    """

    def __init__(self, radiance: Tensor, samples: int, shifts_b: Tensor, shifts_m: Tensor, sampling: str = "mis"):
        self.sampling = check_env_sampling(sampling, "_MCSetup")
        self.n_uniform = 0
        if sampling == "mis":
            constant = _env_is_constant(radiance)
            self.n_map = 0 if constant or samples < 2 else samples // 2
            self.n_brdf = samples - self.n_map
        elif sampling == "brdf":
            self.n_map, self.n_brdf = 0, samples
        elif sampling == "map":
            self.n_map, self.n_brdf = samples, 0
        else:
            self.n_map, self.n_brdf, self.n_uniform = 0, 0, samples
        self.sampler = None if self.n_map == 0 else LatLongSampler(radiance)
        self.shifts_b = shifts_b
        self.shifts_m = shifts_m

    def count(self, technique: str) -> int:
        """Samples per point drawn by ``technique`` (``"brdf"``, ``"map"`` or ``"uniform"``)."""
        return {"brdf": self.n_brdf, "map": self.n_map, "uniform": self.n_uniform}[technique]

    def techniques(self) -> list[tuple[str, int, Tensor]]:
        """``(technique, samples, per-point shifts)`` for every technique with samples, in order.

        BRDF and uniform samples use the first shift, map samples the second.
        """
        out = [("brdf", self.n_brdf, self.shifts_b), ("map", self.n_map, self.shifts_m)]
        out.append(("uniform", self.n_uniform, self.shifts_b))
        return [t for t in out if t[1] > 0]


def _sample_uniform_hemisphere(u: Tensor) -> Tensor:
    """Local directions uniform in solid angle over ``z > 0`` (density ``1 / 2π``), ``(*, 2) -> (*, 3)``.

    ``cos θ = 1 - u₀`` and ``φ = 2π u₁``: stratification in ``u`` carries over to ``(cos θ, φ)``.
    """
    z = 1.0 - u[..., 0]
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    phi = (2.0 * math.pi) * u[..., 1]
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), dim=-1)


def _mc_pass(
    brdf,
    lobes,
    n,
    v,
    x,
    y,
    material,
    env_cl,
    bidx,
    setup: _MCSetup,
    technique: str,
    start: int,
    count: int,
    shift: Tensor,
) -> Tensor:
    """Contribution ``(P, 3)`` of samples ``start .. start + count`` of one technique.

    ``technique`` is ``"brdf"``, ``"map"`` or ``"uniform"``; each sample is weighted by the
    power heuristic over the techniques ``setup`` uses (``1 / (n pdf)`` when it is the only one).
    """
    xs, ys = _sampling_frame(n, x, y, material)
    # The BRDF mixture is needed whenever BRDF samples exist (to draw them, or for the MIS
    # weight of map samples); map-only and uniform sampling never build it.
    mix = _BRDFMixture(lobes, material, n, v, xs, ys) if setup.n_brdf > 0 else None
    with torch.no_grad():
        total = setup.count(technique)
        u = rotated_hammersley(shift.detach(), start, count, total)  # (P, k, 2)
        bk = None if bidx is None else bidx[:, None].expand(u.shape[:-1])
        if technique == "brdf":
            assert mix is not None  # built whenever BRDF samples exist (n_brdf > 0)
            l = mix.sample(u)
            p_b = mix.pdf(l)
            p_m = setup.sampler.pdf(l, bk) if setup.sampler is not None else 0.0
            w = _mis_power(setup.n_brdf, p_b, setup.n_map, p_m)
        elif technique == "map":
            assert setup.sampler is not None  # map samples exist only with a sampler
            l, p_m = setup.sampler.sample(u, bk)
            p_o = mix.pdf(l) if mix is not None else 0.0
            w = _mis_power(setup.n_map, p_m, setup.n_brdf, p_o)
        elif technique == "uniform":
            l_local = _sample_uniform_hemisphere(u)
            l = to_world(l_local, xs.detach().unsqueeze(1), ys.detach().unsqueeze(1), n.detach().unsqueeze(1))
            w = torch.full_like(l[..., :1], 2.0 * math.pi / total)
        else:
            raise ValueError(f"_mc_pass: unknown technique {technique!r}")
        l = l.to(n.dtype)
        w = w.to(n.dtype)
    n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
    x1 = None if x is None else x.unsqueeze(1)
    y1 = None if y is None else y.unsqueeze(1)
    mat = {k: _unsq(val, 1) for k, val in material.items()}
    f = brdf(l, v1, n1, x1, y1, **mat)
    L = _lookup_cl(env_cl, l, bk)
    cos = torch.clamp(dot(n1, l), min=0.0)
    return (f * L * (cos * w)).sum(dim=1)


def integrate_environment_mc(
    brdf: BRDF,
    n: Tensor,
    v: Tensor,
    radiance: Tensor,
    material: dict,
    *,
    x: Tensor | None = None,
    y: Tensor | None = None,
    batch_index: Tensor | None = None,
    samples: int = 64,
    seed: int = 0,
    samples_per_pass: int | None = None,
    sampling: str = "mis",
) -> Tensor:
    """Monte Carlo estimate of the environment integral at ``P`` shading points.

    Args:
        brdf: callable with the principled signature ``brdf(l, v, n, x, y, **material)``.
        n: ``(P, 3)`` unit normals.
        v: ``(P, 3)`` unit view directions.
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)`` lat-long map.
        material: name -> float, 0-d tensor or ``(P, C)`` tensor.
        x: optional ``(P, 3)`` tangents (passed to the BRDF and used for anisotropic sampling).
        y: optional ``(P, 3)`` bitangents.
        batch_index: int64 ``(P,)`` map index per point when ``B > 1``.
        samples: samples per point (with ``"mis"``: half BRDF, half map, unless the map is
            constant).
        seed: seed of the per-point random rotations.
        samples_per_pass: samples evaluated together (memory); default all.
        sampling: the proposal, one of :data:`ENV_SAMPLINGS`: ``"mis"`` (BRDF + map, power
            heuristic; default), ``"brdf"`` (BRDF mixture only), ``"map"`` (map luminance
            only) or ``"uniform"`` (uniform hemisphere, no importance sampling). All are
            unbiased; see the module docstring for when each is noisy.

    Returns:
        ``(P, 3)`` outgoing radiance.

    Raises:
        ValueError: ``sampling`` is not one of :data:`ENV_SAMPLINGS`.
    """
    check_env_sampling(sampling, "integrate_environment_mc")
    p = n.shape[0]
    g = torch.Generator(device=n.device).manual_seed(int(seed))
    shifts = torch.rand((p, 2, 2), generator=g, dtype=n.dtype, device=n.device)
    setup = _MCSetup(radiance, samples, shifts[:, 0], shifts[:, 1], sampling)
    env_cl = _as_bhwc(radiance.to(n.dtype))
    lobes = sampling_lobes_for(brdf, material)
    k = samples_per_pass or samples
    out = torch.zeros_like(n)
    for technique, total, shift in setup.techniques():
        for start in range(0, total, k):
            out = out + _mc_pass(
                brdf,
                lobes,
                n,
                v,
                x,
                y,
                material,
                env_cl,
                batch_index,
                setup,
                technique,
                start,
                min(k, total - start),
                shift,
            )
    return out


def integrate_environment_quadrature(
    brdf: BRDF,
    n: Tensor,
    v: Tensor,
    radiance: Tensor,
    material: dict,
    *,
    x: Tensor | None = None,
    y: Tensor | None = None,
    batch_index: Tensor | None = None,
    subdivisions: int = 8,
    directions_per_pass: int = 4096,
) -> Tensor:
    """Brute-force reference for the environment integral (midpoint rule per texel).

    Every texel is split into ``subdivisions²`` cells of equal solid angle (uniform in
    ``cos θ`` and ``φ``) and the integrand is evaluated at each cell centre. The error is
    O(subdivisions⁻²) for a smooth BRDF; intended for tests and validation.

    Args:
        brdf: callable with the principled signature.
        n: ``(P, 3)`` unit normals.
        v: ``(P, 3)`` unit view directions.
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)`` lat-long map.
        material: name -> float, 0-d tensor or ``(P, C)`` tensor.
        x: optional ``(P, 3)`` tangents.
        y: optional ``(P, 3)`` bitangents.
        batch_index: int64 ``(P,)`` map index per point when ``B > 1``.
        subdivisions: cells per texel along each axis.
        directions_per_pass: directions evaluated together (memory).

    Returns:
        ``(P, 3)``.
    """
    env = _as_bhwc(radiance.to(n.dtype))
    b, h, w, _ = env.shape
    dev = n.device
    rows = torch.arange(h, device=dev).repeat_interleave(w)
    cols = torch.arange(w, device=dev).repeat(h)
    d, omega = _texel_cells(h, w, rows, cols, subdivisions, n.dtype)
    n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
    x1 = None if x is None else x.unsqueeze(1)
    y1 = None if y is None else y.unsqueeze(1)
    mat = {k: _unsq(val, 1) for k, val in material.items()}
    out = torch.zeros_like(n)
    for start in range(0, d.shape[0], directions_per_pass):
        dd = d[start : start + directions_per_pass].unsqueeze(0)  # (1, k, 3)
        ll = dd.expand(n.shape[0], -1, -1)
        bk = None if batch_index is None else batch_index[:, None].expand(ll.shape[:-1])
        weight = _lookup_cl(env, ll, bk) * omega[start : start + directions_per_pass, None]
        out = out + _directions_sum(brdf, n1, v1, x1, y1, mat, ll, weight)
    return out


def _texel_cells(height: int, width: int, rows: Tensor, cols: Tensor, subdivisions: int,
                 dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Centres and solid angles of the cells of lat-long texels: ``((K·s², 3), (K·s²,))``.

    Texel ``(rows[k], cols[k])`` (int64 ``(K,)``) is split into ``s × s`` cells of equal solid
    angle (uniform in ``cos θ`` and ``φ``), ``s = subdivisions``; its cells are consecutive.
    """
    s, dev = subdivisions, rows.device
    t = (torch.arange(s, dtype=torch.float64, device=dev) + 0.5) / s
    r = rows.to(torch.float64)[:, None]
    c0, c1 = torch.cos(r * (math.pi / height)), torch.cos((r + 1.0) * (math.pi / height))
    cos_t = c0 + t[None] * (c1 - c0)  # (K, s)
    phi = -math.pi + (cols.to(torch.float64)[:, None] + t[None]) * (2.0 * math.pi / width)  # (K, s)
    sin_t = torch.sqrt(torch.clamp(1.0 - cos_t * cos_t, min=0.0))
    d = torch.stack(
        (
            sin_t[:, :, None] * torch.cos(phi)[:, None, :],
            sin_t[:, :, None] * torch.sin(phi)[:, None, :],
            cos_t[:, :, None].expand(-1, -1, s),
        ),
        dim=-1,
    ).reshape(-1, 3)
    omega = latlong_row_solid_angles(height, width, dtype=torch.float64, device=dev)[rows] / (s * s)
    return d.to(dtype), omega.repeat_interleave(s * s).to(dtype)


def _directions_sum(
    brdf: BRDF, n1: Tensor, v1: Tensor, x1, y1, mat: dict, ll: Tensor, weight: Tensor
) -> Tensor:
    """``Σ_k f(l_k, v) w_k max(n·l_k, 0)`` over a few directions per point, ``(P, 3)``.

    ``ll`` ``(P, K, 3)`` are the directions, ``weight`` ``(P or 1, K, 3)`` their radiance ×
    solid angle; ``n1``/``v1``/``x1``/``y1`` are ``(P, 1, 3)`` and ``mat`` the material with a
    direction axis.
    """
    f = brdf(ll, v1, n1, x1, y1, **mat)
    return (f * weight * torch.clamp(dot(n1, ll), min=0.0)).sum(1)


# --------------------------------------------------------------------------------------
# Split sum
# --------------------------------------------------------------------------------------


@lru_cache(maxsize=64)
def _overlap_weights(src: int, dst: int, rows: bool) -> Tensor:
    """Overlap of each destination interval with each source interval, float64 ``(dst, src)``.

    Rows (``rows=True``): the solid-angle measure of the overlap of the θ bands,
    ``cos θ_lo - cos θ_hi`` (the exact integral of ``sin θ``). Columns: the overlap length
    in units of the full turn. Every source interval is covered exactly once, so the columns
    of the matrix sum to the source intervals' measures: resampling with it conserves power.
    """
    s = torch.arange(src + 1, dtype=torch.float64) / src
    d = torch.arange(dst + 1, dtype=torch.float64) / dst
    lo = torch.maximum(d[:-1, None], s[None, :-1])
    hi = torch.minimum(d[1:, None], s[None, 1:])
    if rows:
        return torch.clamp(torch.cos(lo * math.pi) - torch.cos(hi * math.pi), min=0.0)
    return torch.clamp(hi - lo, min=0.0)


def _downsample(img: Tensor, h: int, w: int) -> Tensor:
    """Power-conserving area resampling of ``(B, 3, H, W)`` to ``(B, 3, h, w)``.

    Each output texel is the solid-angle-weighted mean of the (piecewise-constant) input over
    its own area, with fractional overlaps of the row bands and columns, so
    ``Σ L Ω`` (the map's power) is the same before and after for every size ratio. (Pooling
    with overlapping windows, e.g. ``adaptive_avg_pool2d`` at non-integer ratios, is not.)
    """
    H, W = img.shape[-2:]
    if (h, w) == (H, W):
        return img
    rw = _overlap_weights(H, h, True)
    cw = _overlap_weights(W, w, False)
    # Normalise by the weights' own sums (= the output texel's measure) so constants map exactly.
    rw = (rw / rw.sum(1, keepdim=True)).to(img.dtype).to(img.device)
    cw = (cw / cw.sum(1, keepdim=True)).to(img.dtype).to(img.device)
    return torch.einsum("ki,bcij,lj->bckl", rw, img, cw)


#: Kernel of the broadest level: uniform over the hemisphere about ``r`` (mean cosine 1/2),
#: for lobes broader than the cosine (a rough specular or diffuse lobe at grazing view).
UNIFORM = "uniform"


def _lobe_kernel(rl: Tensor, alpha: float | str | None) -> Tensor:
    """Unnormalised prefiltering kernel at ``rl = r·l`` (any shape): ``max(r·l, 0)`` for
    ``alpha=None`` (the cosine lobe), ``[r·l > 0]`` for :data:`UNIFORM`, else
    ``D_α(r·h) max(r·l, 0)`` with ``h = normalize(r + l)``."""
    k = torch.clamp(rl, min=0.0)
    if alpha is None:
        return k
    if alpha == UNIFORM:
        return (rl > 0).to(rl.dtype)
    assert isinstance(alpha, float)
    # With h = normalize(r + l): (r·h)² = (1 + r·l) / 2 and |r × h|² = (1 - r·l) / 2.
    a2 = alpha * alpha
    den = a2 * 0.5 * (1.0 + rl) + 0.5 * (1.0 - rl)
    return k * a2 / (math.pi * den * den)


@lru_cache(maxsize=32)
def _kernel_mean_cosine(alpha: float | str | None) -> float:
    """``∫ k (r·l) dω / ∫ k dω`` of :func:`_lobe_kernel`: how concentrated the lobe is about
    ``r`` (2/3 for the cosine lobe, → 1 as ``α`` → 0). A lobe symmetric about ``r`` with this
    mean cosine ``κ`` has first moment ``κ r``. Midpoint rule over the polar angle."""
    t = (torch.arange(20000, dtype=torch.float64) + 0.5) * (0.5 * math.pi / 20000)
    c = torch.cos(t)
    k = _lobe_kernel(c, alpha) * torch.sin(t)
    return float((k * c).sum() / k.sum())


@lru_cache(maxsize=32)
def _kernel_fft(h: int, w: int, alpha: float | str | None, dtype: torch.dtype, device_str: str) -> Tensor:
    """Conjugated rFFT along φ of the normalised lat-long convolution kernel, ``(h, h, w//2+1)``.

    Row ``i`` (output) against row ``i'`` and column offset ``j`` (input); the convolution
    along φ is exact (circular, by FFT) and the normalisation conserves power.

    ``alpha=None`` gives the cosine kernel ``max(r·l, 0)``; otherwise the GGX kernel
    ``D_α(r·h) max(r·l, 0)`` with ``h = normalize(r + l)`` (Karis' ``n = v = r``).
    """
    dev = torch.device(device_str)
    theta = (torch.arange(h, dtype=torch.float64) + 0.5) * (math.pi / h)
    dphi = torch.arange(w, dtype=torch.float64) * (2.0 * math.pi / w)
    st, ct = torch.sin(theta), torch.cos(theta)
    r = torch.stack((st, torch.zeros_like(st), ct), dim=-1)[:, None, None, :]  # (h, 1, 1, 3)
    l = torch.stack(
        (st[:, None] * torch.cos(dphi)[None], st[:, None] * torch.sin(dphi)[None], ct[:, None].expand(h, w)),
        dim=-1,
    )[None]  # (1, h, w, 3)
    rl = (r * l).sum(-1)  # cos of the angle between r and l, (h, h, w)
    k = _lobe_kernel(rl, alpha)
    # Normalise symmetrically, k[i, i', j] = g Ω_i' c_i c_i' (g depends on r·l only, so it is
    # symmetric in i, i'), with c solving c_i Σ g Ω_i' c_i' = 1 (symmetric Sinkhorn). Then every
    # row sums to 1 (a constant map is unchanged) AND Σ_i Ω_i k[i, i', ·] = Ω_i' (each input
    # texel's power is passed on whole). Normalising rows alone does only the former.
    omega = latlong_row_solid_angles(h, w, dtype=torch.float64)
    a = k.sum(-1) * omega[None, :]  # (h, h): Σ_j g Ω_i'
    c = torch.rsqrt(a.sum(1))
    for _ in range(200):
        c_new = torch.sqrt(c / (a @ c))
        done = bool(((c_new - c).abs() <= 1e-15 * c).all())
        c = c_new
        if done:
            break
    k = k * (omega[None, :] * c[:, None] * c[None, :])[..., None]
    kf = torch.conj(torch.fft.rfft(k, dim=-1))
    cdt = torch.complex64 if dtype in (torch.float32, torch.float16, torch.bfloat16) else torch.complex128
    return kf.to(cdt).to(dev)


def _convolve(img: Tensor, alpha: float | str | None) -> Tensor:
    """Convolve ``(B, 3, h, w)`` with the lat-long kernel (see :func:`_kernel_fft`)."""
    h, w = img.shape[-2:]
    kf = _kernel_fft(h, w, alpha, img.dtype, str(img.device))
    lf = torch.fft.rfft(img, dim=-1)
    of = torch.einsum("iak,bcak->bcik", kf, lf.to(kf.dtype))
    return torch.fft.irfft(of, n=w, dim=-1).to(img.dtype)


def _level_size(height: int, width: int, alpha: float) -> tuple[int, int]:
    # Texels well below the lobe's angular width (~2α in l): ~6/α rows, within [32, max]
    # (below 32 rows a small bright source smeared over a 6° texel biases even the broad lobes).
    hk = min(height, max(32, min(PREFILTER_MAX_HEIGHT, math.ceil(6.0 / alpha))))
    wk = max(1, round(width * hk / height))
    return hk, wk


def prefilter_environment(radiance: Tensor, roughness_levels: Sequence[float] = PREFILTER_ROUGHNESS) -> list[Tensor]:
    """GGX-prefiltered copies of a lat-long map, one per roughness level (differentiable).

    Level ``k`` is ``∫ L(l) D(h) max(r·l, 0) dω / ∫ D(h) max(r·l, 0) dω`` with
    ``h = normalize(r + l)`` and ``α = max(roughness², 0.001)``, evaluated as an FFT
    convolution along φ on a map area-averaged to a resolution matched to the lobe width
    (32–128 rows). Both steps conserve the map's power ``Σ L Ω`` exactly, whatever the size
    ratio. Roughness 0 returns the map itself.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)``.
        roughness_levels: perceptual roughness of each level.

    Returns:
        List of ``(B, 3, H_k, W_k)`` maps.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    H, W = img.shape[-2:]
    out = []
    for r in roughness_levels:
        if r <= 0:
            out.append(img)
            continue
        alpha = max(r * r, ALPHA_MIN)
        hk, wk = _level_size(H, W, alpha)
        out.append(_convolve(_downsample(img, hk, wk), alpha))
    return out


def irradiance_environment(radiance: Tensor, height: int = IRRADIANCE_HEIGHT,
                           kernel: str | None = None) -> Tensor:
    """Normalised cosine convolution ``∫ L max(n·l, 0) dω / π`` of a map, ``(B, 3, h, 2h)``.

    Normalised so that a constant map maps to itself exactly and the power ``Σ L Ω`` is kept
    (the map is first area-resampled to ``min(H, height)`` rows, which keeps it too). With
    ``kernel=UNIFORM``: the mean radiance over each hemisphere, ``∫ L dω / 2π``.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    H, W = img.shape[-2:]
    hk = min(H, height)
    wk = max(1, round(W * hk / H))
    return _convolve(_downsample(img, hk, wk), kernel)


def _peak_subdivisions(height: int) -> int:
    """Cells per axis of a peak texel of a ``height``-row map (see :func:`extract_peaks`)."""
    return min(4, max(1, math.ceil(PEAK_CELL_ROWS / height)))


def extract_peaks(
    radiance: Tensor, contrast: float = PEAK_CONTRAST, max_directions: int = PEAK_DIRECTIONS
) -> tuple[Tensor, Tensor, Tensor]:
    """Take a map's concentrated sources (a sun, a lamp) out of it, as directional lights.

    A texel is a peak when its luminance exceeds ``contrast`` × the map's mean radiance
    (``Σ L Ω / 4π``); the brightest (by power) are taken, as many as ``max_directions``
    allows. Each peak texel is split into ``s × s`` cells of equal solid angle, no larger than
    a texel of a :data:`PEAK_CELL_ROWS`-row map (``s = ceil(PEAK_CELL_ROWS / H)``, at most 4),
    and every cell becomes a directional light of irradiance ``L Ω_cell`` at its centre. The
    peaks and the returned rest add up to the map exactly (its power is split, not changed).
    Differentiable in ``radiance``; the choice of texels is not. Outputs have ``radiance``'s
    dtype and device (texels are chosen in float32 at least: a sun overflows float16's
    luminance × solid angle); one host sync per call.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)``.
        contrast: a texel brighter than this multiple of the mean radiance is a peak.
        max_directions: most cells per map (``0``: no peaks).

    Returns:
        ``(rest, directions, irradiance)``: the map without its peaks ``(B, 3, H, W)``, the
        cells' unit directions ``(B, M, 3)`` and their irradiance ``(B, M, 3)`` (``M`` is the
        largest count over the batch; unused entries have zero irradiance). ``M = 0`` when no
        texel qualifies.
    """
    img = radiance.unsqueeze(0) if radiance.dim() == 3 else radiance
    found = _select_peaks(img, contrast, max_directions)
    if found is None:
        none = img.new_zeros(img.shape[0], 0, 3)
        return img, none, none
    rest, idx, valid = found
    return (rest, *_peak_cells(img, idx, valid, _peak_subdivisions(img.shape[-2])))


def _select_peaks(img: Tensor, contrast: float, max_directions: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """The peak texels of ``(B, 3, H, W)`` (see :func:`extract_peaks`).

    Returns ``(rest, idx, valid)`` with ``idx`` the flat texel indices ``(B, M)`` and ``valid``
    which of them are peaks, or ``None`` when no texel is one.
    """
    b, _, h, w = img.shape
    s = _peak_subdivisions(h)
    per_map = min(max_directions // (s * s), h * w)
    dt, dev = img.dtype, img.device
    if per_map <= 0:
        return None
    with torch.no_grad():
        sel = compute_dtype(dt)  # (a sun overflows float16's luminance × solid angle)
        omega = latlong_row_solid_angles(h, w, dtype=sel, device=dev)[:, None]
        lum = luminance(img.detach().to(sel).movedim(1, -1)).squeeze(-1)  # (B, H, W)
        power = lum * omega
        mean = power.sum((1, 2), keepdim=True) / (4.0 * math.pi)
        score = torch.where((lum > contrast * mean) & (lum > 0), power, torch.zeros_like(power))
        top = torch.topk(score.reshape(b, -1), per_map, dim=1)
        count = int((top.values > 0).sum(1).max())  # the one host sync, once per map
    if count == 0:
        return None
    idx, valid = top.indices[:, :count], top.values[:, :count] > 0  # (B, M)
    keep = torch.ones(b, h * w, dtype=torch.bool, device=dev).scatter(1, idx, ~valid)
    return img * keep.view(b, 1, h, w).to(dt), idx, valid


def _peak_cells(img: Tensor, idx: Tensor, valid: Tensor, s: int) -> tuple[Tensor, Tensor]:
    """Cells of some texels of ``img`` ``(B, 3, H, W)``, ``s × s`` per texel.

    ``idx``: flat texel indices ``(B, M)``; ``valid``: which are real. Returns the cells'
    directions and irradiance, ``(B, M·s², 3)`` each.
    """
    b, _, h, w = img.shape
    cells, omega_c = _texel_cells(h, w, (idx // w).reshape(-1), (idx % w).reshape(-1), s, img.dtype)
    texel_l = img.flatten(2).transpose(1, 2).gather(1, idx[..., None].expand(-1, -1, 3))
    texel_l = texel_l * valid[..., None].to(img.dtype)  # (B, M, 3)
    irradiance = texel_l.repeat_interleave(s * s, dim=1) * omega_c.view(b, -1, 1)
    return cells.view(b, -1, 3), irradiance


_TABLE_CACHE: dict = {}


def _compute_split_sum_table(res: int, samples: int) -> Tensor:
    """The (n·v, roughness) table in float64 on the CPU, ``(12, res, res)``; see :func:`split_sum_table`."""
    from torchbrdf.brdf.principled import principled

    dt = torch.float64
    nodes = torch.linspace(0.0, 1.0, res, dtype=dt)
    # The Hammersley points moved to the centres of their strata: left in the corners (i / N)
    # they integrate with an O(1/N) error, 0.2-0.4 % of the albedos at 256 samples, which a
    # white furnace showed as the split sum's bias.
    u = hammersley(0, samples, samples, dtype=dt) + 0.5 / samples  # (S, 2)
    table = torch.zeros(len(SPLIT_SUM_TABLE_CHANNELS), res, res, dtype=dt)
    rows = 8  # n·v nodes per batched evaluation: (rows, res, samples) points per call
    for i0 in range(0, res, rows):
        # Grazing floor: n·v = 0 is degenerate; the ceiling keeps the mirror angle non-zero.
        nv = torch.clamp(nodes[i0 : i0 + rows], min=1e-4, max=1.0 - 1e-4)
        m = nv.shape[0]
        shape = (m, res, samples)
        v = torch.stack((torch.sqrt(1.0 - nv * nv), torch.zeros_like(nv), nv), dim=-1)[
            :, None, None, :
        ].expand(*shape, 3)
        n = torch.tensor([0.0, 0.0, 1.0], dtype=dt).expand(*shape, 3)
        col = nodes[None, :, None, None].expand(*shape, 1)  # roughness (or gloss) per column
        uu = u.expand(*shape, 2)

        def f(l, **kw):
            kw.setdefault("base_color", 0.0)
            kw.setdefault("specular", 0.0)
            return principled(l, v, n, **kw)[..., 0:1]

        def mean(x):
            return x.mean(dim=(2, 3))

        # Specular: GGX visible-normal sampling, weight cos / pdf.
        alpha = torch.clamp(col * col, min=ALPHA_MIN)
        l = reflect(v, sample_ggx_vndf(v, alpha, alpha, uu))
        pdf = pdf_ggx_reflection(v, l, alpha, alpha)
        ok = pdf > 0
        wgt = torch.where(
            ok,
            torch.clamp(l[..., 2:3], min=0.0) / torch.where(ok, pdf, torch.ones_like(pdf)),
            torch.zeros_like(pdf),
        )
        f_bias = f(l, roughness=col)
        f_full = f(l, roughness=col, base_color=1.0, metallic=1.0)
        table[0, i0 : i0 + m] = mean((f_full - f_bias) * wgt)
        table[1, i0 : i0 + m] = mean(f_bias * wgt)
        # Each part's centroid (its angle from n, on the mirror side, -x) and spread (mean
        # cosine about the centroid): where and how wide the prefiltered map is read. The
        # Fresnel part leans further toward the mirror at grazing view. The angle is stored as a
        # fraction of the mirror direction's, smooth in n·v where the angle itself,
        # ∝ sqrt(1 - n·v), is not (interpolated linearly it would lag near n·v = 1).
        for c, part in ((8, f_full - f_bias), (10, f_bias)):
            fs = part * wgt
            mx, mz = mean(fs * l[..., 0:1]), mean(fs * l[..., 2:3])
            table[c, i0 : i0 + m] = torch.atan2(-mx, mz) / torch.acos(nv)[:, None]
            table[c + 1, i0 : i0 + m] = torch.hypot(mx, mz) / mean(fs)
        # Diffuse-like lobes: cosine sampling, weight π.
        l = sample_cosine_hemisphere(uu)
        f0 = f(l, roughness=col)
        fd = math.pi * (f(l, roughness=col, base_color=1.0) - f0)  # Burley's diffuse × cos / pdf
        table[2, i0 : i0 + m] = mean(fd)
        # Its lobe's centroid (x toward v, z along n): Burley's retro-reflection leans toward v.
        table[6, i0 : i0 + m] = mean(fd * l[..., 0:1]) / mean(fd * l[..., 2:3])
        # ... and its spread: the length of its first moment over its albedo, |∫ Fd cos l| / ∫ Fd cos.
        moment = torch.hypot(mean(fd * l[..., 0:1]), mean(fd * l[..., 2:3]))
        table[7, i0 : i0 + m] = moment / table[2, i0 : i0 + m]
        table[3, i0 : i0 + m] = mean(math.pi * (f(l, roughness=col, base_color=1.0, subsurface=1.0) - f0))
        table[4, i0 : i0 + m] = mean(math.pi * (f(l, roughness=col, sheen=1.0, sheen_tint=0.0) - f0))
        # Clearcoat over (n·v, gloss): GTR1 sampling.
        ac = torch.clamp(lerp(0.1, 0.001, col), min=ALPHA_MIN)
        h = sample_gtr1(ac, uu)
        l = reflect(v, h)
        lh = dot(l, h)
        pdf = torch.where(lh > 0, pdf_gtr1(h, ac) / (4.0 * torch.clamp(lh, min=1e-30)), torch.zeros_like(lh))
        ok = pdf > 0
        wgt = torch.where(
            ok,
            torch.clamp(l[..., 2:3], min=0.0) / torch.where(ok, pdf, torch.ones_like(pdf)),
            torch.zeros_like(pdf),
        )
        fc = f(l, roughness=0.5, clearcoat=1.0, clearcoat_gloss=col) - f(l, roughness=0.5)
        table[5, i0 : i0 + m] = mean(fc * wgt)
    return table


def split_sum_table(
    *,
    dtype: torch.dtype = torch.float32,
    device: Device = None,
    resolution: int = SPLIT_SUM_RESOLUTION,
    samples: int = SPLIT_SUM_SAMPLES,
) -> Tensor:
    """Pre-integrated directional albedos of the principled lobes, computed once and cached.

    Channels (:data:`SPLIT_SUM_TABLE_CHANNELS`), each over a ``resolution²`` grid of
    ``n·v ∈ [0, 1]`` (axis 1) × roughness ``∈ [0, 1]`` (axis 2; clearcoat_gloss for the
    clearcoat channel), with ``∫ · max(n·l, 0) dω`` of:

    0. ``specular_scale``: ``Ds Gs (1 - FH)`` (multiplies ``Cspec0``);
    1. ``specular_bias``: ``Ds Gs FH``;
    2. ``diffuse``: Burley's diffuse ``Fd / π``;
    3. ``subsurface``: the subsurface term ``ss / π``;
    4. ``sheen``: ``FH``;
    5. ``clearcoat``: ``0.25 Gr Fr Dr``;
    6. ``diffuse_tilt``: not an albedo but the direction of Burley's diffuse lobe,
       ``∫ Fd (l·t) cos dω / ∫ Fd (l·n) cos dω`` with ``t`` the tangent toward ``v`` (0 for a
       Lambertian lobe; > 0 where the retro-reflection leans the lobe toward the viewer). The
       split sum reads the irradiance along ``normalize(n + tilt · t)``, the lobe's centroid.
    7. ``diffuse_spread``: the mean cosine of Burley's diffuse lobe about that centroid,
       ``|∫ Fd cos l dω| / ∫ Fd cos dω`` (2/3 for a Lambertian lobe; more where the lobe is
       narrower than the cosine, as at roughness 0). See :meth:`SplitSumEnvironment.diffuse`.
    8. ``specular_scale_bend``: the angle between ``n`` and the centroid of the lobe of
       channel 0, ``Ds Gs (1 - FH) cos``, as a fraction of the mirror direction's angle
       ``acos(n·v)``: the centroid is ``n cos a - t sin a`` with ``a = bend · acos(n·v)``.
       Below 1: a rough lobe leans toward the normal, and at grazing view it is lifted above
       the horizon.
    9. ``specular_scale_spread``: that lobe's mean cosine about its centroid (1 for a mirror).
    10. ``specular_bias_bend``, 11. ``specular_bias_spread``: the same for the lobe of channel
        1, ``Ds Gs FH cos`` (closer to the mirror at grazing view). See
        :meth:`SplitSumEnvironment.specular_lobe`.

    Computed with :func:`torchbrdf.principled` itself (so the table follows the model
    exactly) using ``samples`` Hammersley samples per cell, centred in their strata, with the
    matching importance sampler (VNDF, cosine, GTR1) in float64, then cast: the albedos are
    the model's to about 1e-3 (tested against a brute-force quadrature).

    Returns:
        ``(12, resolution, resolution)`` in ``dtype`` on ``device``.
    """
    device = torch.device("cpu") if device is None else torch.device(device)
    key64 = (resolution, samples)
    if key64 not in _TABLE_CACHE:
        _TABLE_CACHE[key64] = _compute_split_sum_table(resolution, samples)
    key = (resolution, samples, dtype, str(device))
    if key not in _TABLE_CACHE:
        _TABLE_CACHE[key] = _TABLE_CACHE[key64].to(device=device, dtype=dtype)
    return _TABLE_CACHE[key]


def _table_lookup(table: Tensor, nv: Tensor, r: Tensor) -> Tensor:
    """Bilinear lookup of ``(C, N, N)`` at ``nv``, ``r`` (each ``(P, 1)``, clamped) -> ``(P, C)``."""
    c, res, _ = table.shape
    fy = torch.clamp(nv, 0.0, 1.0) * (res - 1)
    fx = torch.clamp(r, 0.0, 1.0) * (res - 1)
    y0 = torch.clamp(torch.floor(fy.detach()), 0, res - 2)
    x0 = torch.clamp(torch.floor(fx.detach()), 0, res - 2)
    ty, tx = fy - y0, fx - x0
    y0, x0 = y0.long()[..., 0], x0.long()[..., 0]
    flat = table.permute(1, 2, 0).reshape(res * res, c)
    v00 = flat[y0 * res + x0]
    v01 = flat[y0 * res + x0 + 1]
    v10 = flat[(y0 + 1) * res + x0]
    v11 = flat[(y0 + 1) * res + x0 + 1]
    top = v00 + (v01 - v00) * tx
    bot = v10 + (v11 - v10) * tx
    return top + (bot - top) * ty


class SplitSumEnvironment:
    """A map prepared for the split-sum approximation: irradiance + prefiltered levels.

    The map's peaks (texels brighter than ``peak_contrast`` × its mean radiance, e.g. a sun)
    are taken out first and summed exactly as directional lights (:func:`extract_peaks`);
    the irradiance and the prefiltered levels hold the rest.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)`` lat-long map (gradients flow through).
        dtype: compute dtype (default the map's).
        peak_contrast: see :func:`extract_peaks`.
        peak_directions: most directional lights the peaks become; ``0`` prefilters the whole
            map (the plain split sum).
    """

    def __init__(
        self,
        radiance: Tensor,
        dtype: torch.dtype | None = None,
        *,
        peak_contrast: float = PEAK_CONTRAST,
        peak_directions: int = PEAK_DIRECTIONS,
    ) -> None:
        dtype = dtype or radiance.dtype
        img = radiance.to(dtype)
        img = img.unsqueeze(0) if img.dim() == 3 else img
        h = img.shape[-2]
        found = _select_peaks(img, peak_contrast, peak_directions)
        s_coarse = _peak_subdivisions(h)
        # The peaks' cells (radians: their rows' height), and the same texels in finer cells for
        # sharp lobes: up to 8× finer, at most PEAK_FINE_DIRECTIONS cells, and as a map (zero
        # elsewhere) for lobes sharper still.
        self.peak_cell = math.pi / (h * s_coarse)
        self.fine_cell = self.peak_cell
        self.peak_map: Tensor | None = None
        if found is None:
            rest = img
            self.peak_directions = self.peak_irradiance = img.new_zeros(img.shape[0], 0, 3)
            self.fine_directions = self.fine_irradiance = self.peak_directions
        else:
            rest, idx, valid = found
            self.peak_directions, self.peak_irradiance = _peak_cells(img, idx, valid, s_coarse)
            s_fine = max(s_coarse, min(8 * s_coarse, math.isqrt(PEAK_FINE_DIRECTIONS // idx.shape[1])))
            self.fine_directions, self.fine_irradiance = _peak_cells(img, idx, valid, s_fine)
            self.fine_cell = math.pi / (h * s_fine)
            self.peak_map = _as_bhwc(img - rest)
        self.irradiance = _as_bhwc(irradiance_environment(rest))
        self.levels = [_as_bhwc(m) for m in prefilter_environment(rest)]
        # Broader than every level: the hemisphere's mean (32 rows: its kernel is smooth).
        self.broad = _as_bhwc(irradiance_environment(rest, 32, UNIFORM))
        self.roughness = PREFILTER_ROUGHNESS
        self.batch = self.irradiance.shape[0]
        # The roughest level below 1: the lobe a diffuse lobe narrower than the cosine blends in.
        sharp = max(i for i, r in enumerate(self.roughness) if 0 < r < 1)
        self._sharp = self.levels[sharp]
        alpha_sharp = max(self.roughness[sharp] ** 2, ALPHA_MIN)
        # Mean cosine of each level's kernel (level 0, the map itself: 1), decreasing, then the
        # broad map's (1/2); and of the maps a diffuse lobe blends (that level, the cosine, broad).
        k_broad = _kernel_mean_cosine(UNIFORM)
        self._level_kappa = [
            1.0 if r <= 0 else _kernel_mean_cosine(max(r * r, ALPHA_MIN)) for r in self.roughness
        ] + [k_broad]
        self._diffuse_kappa = [_kernel_mean_cosine(alpha_sharp), _kernel_mean_cosine(None), k_broad]

    def specular(self, r_dir: Tensor, roughness: Scalar, batch_index: Tensor | None = None) -> Tensor:
        """Prefiltered radiance along ``r_dir`` ``(P, 3)`` at ``roughness`` (float or ``(P, 1)``)."""
        k = len(self.roughness) - 1
        if isinstance(roughness, Tensor):
            t = torch.clamp(roughness, 0.0, 1.0) * k
            acc: Tensor | float = 0.0
            for i, level in enumerate(self.levels):
                wi = torch.clamp(1.0 - (t - i).abs(), min=0.0)
                acc = acc + wi * latlong_bilinear(level, r_dir, batch_index)
            return cast(Tensor, acc)  # a tensor: there is always at least one level
        tf = min(max(float(roughness), 0.0), 1.0) * k
        i0 = min(int(math.floor(tf)), k - 1)
        a = tf - i0
        out = latlong_bilinear(self.levels[i0], r_dir, batch_index) * (1.0 - a)
        if a > 0:
            out = out + latlong_bilinear(self.levels[i0 + 1], r_dir, batch_index) * a
        return out

    def specular_lobe(self, direction: Tensor, spread: Tensor, batch_index: Tensor | None = None) -> Tensor:
        """Prefiltered radiance ``(P, 3)`` along ``direction`` ``(P, 3)``, at a lobe width.

        ``spread`` ``(P, 1)`` is the lobe's mean cosine about ``direction``.

        The two levels whose kernels' mean cosines bracket ``spread`` are blended linearly in
        the mean cosine (level 0, the map itself, counts as 1), so the blend has the lobe's
        mean cosine; read along the lobe's centroid, it has the lobe's first moment and is
        exact for a map linear in ``l``. Past the roughest level (the cosine lobe, 2/3) the blend
        continues toward the hemisphere's mean (:attr:`broad`, 1/2).
        """
        return _blend_by_mean_cosine(self.levels + [self.broad], self._level_kappa, spread, direction, batch_index)

    def sharpness(self, width: Tensor | float) -> tuple[Tensor | float, Tensor | float]:
        """How a lobe of angular width ``width`` (radians) sees the peaks: ``(w_fine, w_map)``.

        A cell is one direction, so a lobe not much wider than the cells falls between them.
        ``w_fine``: the share summed over the finer cells instead (1 for lobes narrower than
        4 cells, 0 for lobes wider than 6, linear between); ``w_map``: the share read from
        :attr:`peak_map` along the lobe instead (1 for lobes narrower than 2 fine cells, 0 for
        lobes wider than 4; exact as the lobe narrows to a mirror, where a texel is
        constant across it). ``w_map ≤ w_fine``.
        """
        if self.peak_map is None:
            return 0.0, 0.0

        def ramp(w):
            return torch.clamp(w, 0.0, 1.0) if isinstance(w, Tensor) else min(max(w, 0.0), 1.0)

        c, f = self.peak_cell, self.fine_cell
        return ramp((6.0 * c - width) / (2.0 * c)), ramp((4.0 * f - width) / (2.0 * f))

    def peaks(
        self,
        brdf: BRDF,
        n: Tensor,
        v: Tensor,
        material: dict,
        x: Tensor | None = None,
        y: Tensor | None = None,
        batch_index: Tensor | None = None,
        fine: bool = False,
    ) -> Tensor | float:
        """The peaks' exact contribution ``Σ f(l_k, v) E_k max(n·l_k, 0)``, ``(P, 3)``.

        ``0.0`` when the map has none. Arguments as in :func:`integrate_environment_split_sum`;
        ``fine``: over the finer cells.
        """
        if fine:
            dirs, irr = self.fine_directions, self.fine_irradiance
        else:
            dirs, irr = self.peak_directions, self.peak_irradiance
        count = dirs.shape[1]
        if count == 0:
            return 0.0
        n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
        x1 = None if x is None else x.unsqueeze(1)
        y1 = None if y is None else y.unsqueeze(1)
        mat = {k: _unsq(val, 1) for k, val in material.items()}
        per_pass = max(1, _PEAK_ELEMENTS_PER_PASS // max(n.shape[0], 1))
        out: Tensor | float = 0.0
        for start in range(0, count, per_pass):
            d, e = dirs[:, start : start + per_pass], irr[:, start : start + per_pass]
            if batch_index is not None and self.batch > 1:
                d, e = d[batch_index], e[batch_index]
            ll = d.expand(n.shape[0], -1, -1)
            out = out + _directions_sum(brdf, n1, v1, x1, y1, mat, ll, e)
        return out

    def diffuse(self, n: Tensor, batch_index: Tensor | None = None, spread: Tensor | None = None) -> Tensor:
        """Normalised irradiance ``∫ L max(n·l, 0) dω / π`` at normals ``(P, 3)`` -> ``(P, 3)``.

        With ``spread`` ``(P, 1)`` (a lobe's mean cosine about ``n``, 2/3 for the cosine lobe):
        for a lobe narrower than the cosine (``spread > 2/3``) the irradiance is blended with
        the roughest prefiltered level below 1 (mean cosine ``κ_s ≈ 0.73``), weight
        ``(spread - 2/3) / (κ_s - 2/3)`` clamped to [0, 1], so the blend has the lobe's mean
        cosine. A lobe centred on ``n`` with the right albedo and mean cosine has the right
        first moment: the split sum is then exact for a map linear in ``l`` (a sky gradient, or
        the far field of a small source), where the cosine lobe alone is off by the spread's
        difference. A lobe broader than the cosine (``spread < 2/3``) is blended toward the
        hemisphere's mean (:attr:`broad`, mean cosine 1/2) the same way.
        """
        if spread is None:
            return latlong_bilinear(self.irradiance, n, batch_index)
        maps = [self._sharp, self.irradiance, self.broad]
        return _blend_by_mean_cosine(maps, self._diffuse_kappa, spread, n, batch_index)


def _blend_by_mean_cosine(maps: list[Tensor], kappa: list[float], spread: Tensor, direction: Tensor,
                          batch_index: Tensor | None) -> Tensor:
    """Maps ``(B, h, w, 3)`` blended linearly in their kernels' mean cosines ``kappa``
    (decreasing) to a lobe's mean cosine ``spread`` ``(P, 1)``, read along ``direction``
    ``(P, 3)``: ``(P, 3)``. A spread outside ``kappa``'s range reads the nearest end's map."""
    s = torch.clamp(spread, min=kappa[-1], max=kappa[0])
    angles = _direction_angles(direction)
    acc = torch.zeros_like(direction)
    for i, m in enumerate(maps):
        # Hat function in κ: 1 at κ_i, 0 at the neighbouring maps' κ (flat past either end).
        up = (s - kappa[i + 1]) / (kappa[i] - kappa[i + 1]) if i + 1 < len(kappa) else None
        down = (kappa[i - 1] - s) / (kappa[i - 1] - kappa[i]) if i > 0 else None
        hat = down if up is None else up if down is None else torch.minimum(up, down)
        wi = torch.clamp(cast(Tensor, hat), 0.0, 1.0)
        if _may_be_nonzero(wi):  # (a material's roughness range reads two or three maps)
            acc = acc + wi * latlong_bilinear(m, direction, batch_index, angles=angles)
    return acc


def _dominant_direction(n: Tensor, r_dir: Tensor, alpha) -> Tensor:
    """Lookup direction of the prefiltered map: the mirror direction bent toward ``n``.

    A rough lobe's energy is centred between the mirror direction and the normal, the more
    so the rougher it is (the ``n = v = r`` prefilter ignores this). The blend factor
    ``s (sqrt(s) + α)`` with ``s = 1 - α`` is the fit of Lagarde & de Rousiers, "Moving
    Frostbite to PBR" (2014), §4.9.3; on a sphere under smooth and noisy maps it cuts the
    split sum's median error against quadrature by 2–7× for roughness ≥ 0.5.
    """
    s = 1.0 - alpha
    if isinstance(s, Tensor):
        s = torch.clamp(s, min=0.0)
        f = s * (torch.sqrt(s) + alpha)
    else:
        s = max(s, 0.0)
        f = s * (math.sqrt(s) + alpha)
    return safe_normalize(n + (r_dir - n) * f)


def brdf_kind(brdf: BRDF) -> str:
    """``"lambert"``, ``"principled"`` or ``"custom"`` — what the split sum knows how to handle."""
    if getattr(brdf, "sampling_lobes", None) == ("diffuse",):
        return "lambert"
    from torchbrdf.brdf.principled import principled

    if brdf is principled or isinstance(brdf, PrincipledBRDF):
        return "principled"
    return "custom"


def integrate_environment_split_sum(
    brdf: BRDF,
    n: Tensor,
    v: Tensor,
    env: SplitSumEnvironment,
    material: dict,
    *,
    x: Tensor | None = None,
    y: Tensor | None = None,
    batch_index: Tensor | None = None,
) -> Tensor:
    """Split-sum approximation of the environment integral at ``P`` points.

    Supports :func:`torchbrdf.principled` / :class:`~torchbrdf.PrincipledBRDF` (respecting
    its ``lobes``) and the Lambert BRDF; anisotropy is approximated by the isotropic lobe
    of the same mean width ``roughness²``. The map's peaks (:func:`extract_peaks`) are added
    exactly, with ``brdf`` itself (anisotropy included).

    Args:
        brdf: the BRDF (its kind selects the formula; see :func:`brdf_kind`).
        n: ``(P, 3)`` unit normals.
        v: ``(P, 3)`` unit view directions.
        env: a :class:`SplitSumEnvironment`.
        material: name -> float, 0-d tensor or ``(P, C)`` tensor.
        x: optional ``(P, 3)`` tangents (for the peaks of an anisotropic material).
        y: optional ``(P, 3)`` bitangents.
        batch_index: int64 ``(P,)`` when the map is batched.

    Returns:
        ``(P, 3)``.
    """
    kind = brdf_kind(brdf)
    base = _rgb(material.get("base_color", 1.0), n)
    if kind not in ("principled", "lambert"):
        raise ValueError(
            f"env_strategy='split_sum' supports the principled and Lambert BRDFs, not {brdf!r}; "
            "use env_strategy='mc'"
        )
    peaks = env.peaks(brdf, n, v, material, x, y, batch_index)
    if kind == "lambert":
        return env.diffuse(n, batch_index) * base + peaks
    from torchbrdf.brdf.principled import active_lobes

    lobes = active_lobes(material, getattr(brdf, "lobes", None))
    p = {k: material.get(k, d) for k, d in _PRINCIPLED_DEFAULTS.items()}
    metal, rough = p["metallic"], p["roughness"]
    nv = torch.clamp(dot(n, v), 0.0, 1.0)
    r_t = _t(rough, n) * torch.ones_like(nv)
    table = split_sum_table(dtype=n.dtype, device=n.device)
    tab = _table_lookup(table, nv, r_t)
    lum = luminance(base)
    positive = lum > 0
    ctint = torch.where(
        positive, base / torch.where(positive, lum, torch.ones_like(lum)), torch.ones_like(base)
    )
    out = torch.zeros_like(n) + peaks
    dielectric = 1.0 - metal
    if "diffuse" in lobes:
        # Irradiance along the centroid of Burley's lobe, which leans toward v at grazing view
        # (irradiance along n alone misses the retro-reflection there).
        t_dir = safe_normalize(v - nv * n)
        d_dir = safe_normalize(n + tab[:, 6:7] * t_dir)
        w_d = dielectric * (1.0 - p["subsurface"]) * tab[:, 2:3]
        # ... and blended toward a sharper level where the lobe is narrower than the cosine.
        out = out + env.diffuse(d_dir, batch_index, spread=tab[:, 7:8]) * base * w_d
    if "subsurface" in lobes:
        out = out + env.diffuse(n, batch_index) * base * (dielectric * p["subsurface"] * tab[:, 3:4])
    if "sheen" in lobes:
        csheen = lerp(1.0, ctint, p["sheen_tint"])
        out = out + env.diffuse(n, batch_index) * csheen * (dielectric * p["sheen"] * tab[:, 4:5])
    r_dir = reflect(v, n)
    if "specular" in lobes:
        cspec0 = lerp(0.08 * p["specular"] * lerp(1.0, ctint, p["specular_tint"]), base, metal)
        # Each part of the lobe (scale on Cspec0, Fresnel bias) read along its centroid, at its
        # width: its first moment is then right (exact for a map linear in l). The centroid is
        # at a = bend·θ from n toward the mirror side (θ = acos(n·v), kept below 1 - 1e-6 in
        # n·v: acos' is infinite at 1); v - (n·v) n has length sin θ.
        theta = torch.acos(torch.clamp(nv, max=1.0 - 1e-6))
        off_n = (v - nv * n) / torch.sin(theta)
        # A lobe too sharp for the peaks' cells sees them through finer cells, and sharper
        # still through the peak map (SplitSumEnvironment.sharpness).
        w_fine, w_map = env.sharpness(torch.sqrt(2.0 * torch.clamp(1.0 - tab[:, 9:10], min=0.0)))
        for c, weight in ((8, cspec0 * tab[:, 0:1]), (10, tab[:, 1:2])):
            angle = tab[:, c : c + 1] * theta
            look = safe_normalize(n * torch.cos(angle) - off_n * torch.sin(angle))
            out = out + env.specular_lobe(look, tab[:, c + 1 : c + 2], batch_index) * weight
            if _may_be_nonzero(w_map):  # (texel-constant: a mirror sees one texel)
                out = out + w_map * _lookup_cl(cast(Tensor, env.peak_map), look, batch_index) * weight
        if _may_be_nonzero(w_fine):
            out = out + _sharp_peaks(env, w_fine, w_map, n, v, material, x, y, batch_index)
    if "clearcoat" in lobes:
        gloss = p["clearcoat_gloss"]
        g_t = _t(gloss, n) * torch.ones_like(nv)
        e_cc = _table_lookup(table[5:6], nv, g_t)
        ac = lerp(0.1, 0.001, gloss)
        ac = torch.clamp(ac, min=ALPHA_MIN) if isinstance(ac, Tensor) else max(ac, ALPHA_MIN)
        r_cc = torch.sqrt(ac) if isinstance(ac, Tensor) else math.sqrt(ac)
        look = _dominant_direction(n, r_dir, ac)
        # (No swap for the peaks here: GTR1's tails hold most of its energy, and the cells
        # resolve them; at gloss 1 the cells are −4 % off over a sphere, the peak map −17 %.)
        out = out + env.specular(look, r_cc, batch_index) * (p["clearcoat"] * e_cc)
    return out


#: The principled specular lobe on its own (the peaks it cannot resolve are swapped).
_SPECULAR_ONLY = PrincipledBRDF(lobes=("specular",))


def _sharp_peaks(env: SplitSumEnvironment, w_fine: Tensor | float, w_map: Tensor | float, n: Tensor,
                 v: Tensor, material: dict, x: Tensor | None, y: Tensor | None,
                 batch_index: Tensor | None) -> Tensor:
    """The specular lobe's response to the peaks moved between cells, ``(P, 3)``.

    From the cells to the fine cells (share ``w_fine``) and from those to the peak map (share
    ``w_map``, added by the caller): ``(w_fine - w_map) F - w_fine C`` with ``F`` / ``C`` the
    sums over the fine / coarse cells. On the CPU only at the points where ``w_fine``
    ``(P, 1)`` is non-zero (roughness ≲ 0.2); elsewhere at every point (no host sync).
    """

    def shift(n, v, mat, x, y, bi, wf, wm):
        fine = env.peaks(_SPECULAR_ONLY, n, v, mat, x, y, bi, fine=True)
        coarse = env.peaks(_SPECULAR_ONLY, n, v, mat, x, y, bi)
        return (wf - wm) * fine - wf * coarse + torch.zeros_like(n)

    if (not isinstance(w_fine, Tensor) or w_fine.device.type != "cpu" or n.shape[0] < 2
            or torch.compiler.is_compiling()):
        return shift(n, v, material, x, y, batch_index, w_fine, w_map)
    idx = w_fine[:, 0].nonzero()[:, 0]
    count = n.shape[0]

    def sub(t):
        return t[idx] if isinstance(t, Tensor) and t.dim() >= 1 and t.shape[0] == count else t

    part = shift(n[idx], v[idx], {k: sub(t) for k, t in material.items()}, sub(x), sub(y), sub(batch_index),
                 w_fine[idx], sub(w_map))
    return torch.zeros_like(n).index_add(0, idx, part)


def _may_be_nonzero(w: Tensor | float) -> bool:
    """Whether a weight may be non-zero anywhere.

    True without looking on an accelerator (a host sync) and under ``torch.compile`` (a graph
    break).
    """
    if isinstance(w, Tensor):
        return w.device.type != "cpu" or torch.compiler.is_compiling() or bool((w != 0).any())
    return w != 0
