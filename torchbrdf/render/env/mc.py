"""Monte Carlo environment integration, and the brute-force quadrature it is checked against.

:func:`integrate_environment_mc` is unbiased. Half of the samples come from the BRDF — a
per-pixel mixture of cosine sampling (diffuse, subsurface, sheen), GGX visible-normal sampling
(Heitz 2018; primary specular, anisotropic when the material is) and GTR1 sampling (Burley
2012 appendix B; clearcoat), weighted by rough lobe albedos — and half from the map (luminance
× solid angle, :class:`~torchbrdf.render.sampling.LatLongSampler`); they are combined with the
power heuristic (Veach 1995). The ``sampling`` switch (:data:`ENV_SAMPLINGS`) picks another
proposal; every choice is unbiased, stratified and seeded the same way. Sample directions,
densities and MIS weights are constants to autograd ("detached sampling"), so the gradient is
an unbiased estimate too. :class:`MCSetup` and :func:`mc_pass` are the pieces the shader runs
pass by pass. :func:`integrate_environment_quadrature` sums every texel (the exact integral of
the piecewise-constant map). The full error behaviour is in :mod:`torchbrdf.render.envmap`.
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from torchbrdf._math import dot, is_zero, lerp, luminance, safe_normalize
from torchbrdf._types import BRDF
from torchbrdf.brdf.frames import frame_from_normal, to_local, to_world
from torchbrdf.render.env.latlong import as_bhwc, directions_sum, lookup_cl, texel_cells
from torchbrdf.render.env.params import as_rgb, as_tensor_like, param_value, with_sample_axes
from torchbrdf.render.sampling import (
    ALPHA_MIN,
    LatLongSampler,
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
    "SAMPLING_LOBES",
    "ENV_SAMPLINGS",
    "sampling_lobes_for",
    "check_env_sampling",
    "MCSetup",
    "mc_pass",
    "integrate_environment_mc",
    "integrate_environment_quadrature",
]


#: Lobe names understood by the MC mixture.
SAMPLING_LOBES = ("diffuse", "specular", "clearcoat")
#: Proposals of the Monte Carlo integrator (``sampling=`` / ``shade(env_sampling=)``):
#: BRDF + map with the power heuristic, BRDF only, map only, uniform hemisphere.
ENV_SAMPLINGS = ("mis", "brdf", "map", "uniform")
# Minimum share of the BRDF samples any lobe with non-zero weight receives (robustness
# against a poor albedo guess).
_MIN_LOBE_SHARE = 0.05


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
            base = as_rgb(mat.get("base_color", 1.0), n)
            lum = torch.clamp(luminance(base * ones), min=0.0)
            metal = torch.clamp(as_tensor_like(param_value(mat, "metallic"), n) * ones, 0.0, 1.0)
            weights = {}
            if "diffuse" in lobes:
                w = torch.zeros_like(ones)
                if lobes["diffuse"]:
                    w = w + lum
                if lobes.get("sheen", False):
                    w = w + 0.25 * torch.clamp(as_tensor_like(param_value(mat, "sheen"), n) * ones, min=0.0)
                weights["diffuse"] = (1.0 - metal) * w
            if "specular" in lobes:
                f0 = lerp(0.08 * as_tensor_like(param_value(mat, "specular"), n) * ones, lum, metal)
                weights["specular"] = torch.clamp(f0, 0.0, 1.0) + 0.1
                r = torch.clamp(as_tensor_like(param_value(mat, "roughness"), n) * ones, min=0.0)
                r2 = r * r
                aniso = as_tensor_like(param_value(mat, "anisotropic"), n) * ones
                aspect = torch.sqrt(torch.clamp(1.0 - 0.9 * aniso, min=0.1))
                self.ax = torch.clamp(r2 / aspect, min=ALPHA_MIN).unsqueeze(1)
                self.ay = torch.clamp(r2 * aspect, min=ALPHA_MIN).unsqueeze(1)
            if "clearcoat" in lobes:
                weights["clearcoat"] = 0.25 * torch.clamp(as_tensor_like(param_value(mat, "clearcoat"), n) * ones, min=0.0)
                gloss = as_tensor_like(param_value(mat, "clearcoat_gloss"), n) * ones
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
        isinstance(param_value(material, "metallic"), numbers.Real) and float(param_value(material, "metallic")) == 1.0
    )
    out = {}
    dif = ("diffuse" in wanted or "subsurface" in wanted) and not metal_one
    sheen = "sheen" in wanted and not metal_one and not is_zero(param_value(material, "sheen"))
    if dif or sheen:
        out["diffuse"] = dif
        out["sheen"] = sheen
    if "specular" in wanted:
        out["specular"] = True
    if "clearcoat" in wanted and not is_zero(param_value(material, "clearcoat")):
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
    aniso = param_value(material, "anisotropic")
    use_given = x is not None and (
        (isinstance(aniso, Tensor) and bool((aniso.detach() != 0).any()))
        or (not isinstance(aniso, Tensor) and not is_zero(aniso))
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


class MCSetup:
    """Sample budget and random shifts for one environment light.

    ``sampling`` (:data:`ENV_SAMPLINGS`) splits ``samples`` between the techniques:
    ``"mis"`` half BRDF / half map (all BRDF for a constant map or a single sample),
    ``"brdf"`` all BRDF, ``"map"`` all map, ``"uniform"`` all uniform-hemisphere.
    """

    def __init__(self, radiance: Tensor, samples: int, shifts_b: Tensor, shifts_m: Tensor, sampling: str = "mis"):
        self.sampling = check_env_sampling(sampling, "MCSetup")
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


def mc_pass(
    brdf: BRDF,
    lobes: dict,
    n: Tensor,
    v: Tensor,
    x: Tensor | None,
    y: Tensor | None,
    material: dict,
    env_cl: Tensor,
    bidx: Tensor | None,
    setup: MCSetup,
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
            raise ValueError(f"mc_pass: unknown technique {technique!r}")
        l = l.to(n.dtype)
        w = w.to(n.dtype)
    n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
    x1 = None if x is None else x.unsqueeze(1)
    y1 = None if y is None else y.unsqueeze(1)
    mat = {k: with_sample_axes(val, 1) for k, val in material.items()}
    f = brdf(l, v1, n1, x1, y1, **mat)
    L = lookup_cl(env_cl, l, bk)
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
    setup = MCSetup(radiance, samples, shifts[:, 0], shifts[:, 1], sampling)
    env_cl = as_bhwc(radiance.to(n.dtype))
    lobes = sampling_lobes_for(brdf, material)
    k = samples_per_pass or samples
    out = torch.zeros_like(n)
    for technique, total, shift in setup.techniques():
        for start in range(0, total, k):
            out = out + mc_pass(
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
    env = as_bhwc(radiance.to(n.dtype))
    b, h, w, _ = env.shape
    dev = n.device
    rows = torch.arange(h, device=dev).repeat_interleave(w)
    cols = torch.arange(w, device=dev).repeat(h)
    d, omega = texel_cells(h, w, rows, cols, subdivisions, n.dtype)
    n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
    x1 = None if x is None else x.unsqueeze(1)
    y1 = None if y is None else y.unsqueeze(1)
    mat = {k: with_sample_axes(val, 1) for k, val in material.items()}
    out = torch.zeros_like(n)
    for start in range(0, d.shape[0], directions_per_pass):
        dd = d[start : start + directions_per_pass].unsqueeze(0)  # (1, k, 3)
        ll = dd.expand(n.shape[0], -1, -1)
        bk = None if batch_index is None else batch_index[:, None].expand(ll.shape[:-1])
        weight = lookup_cl(env, ll, bk) * omega[start : start + directions_per_pass, None]
        out = out + directions_sum(brdf, n1, v1, x1, y1, mat, ll, weight)
    return out
