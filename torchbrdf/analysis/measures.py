"""Looking at BRDFs: albedo, furnace tests, reciprocity, slices, curves, lobes and spheres.

The views follow Burley's BRDF Explorer (Burley 2012, §3): image slices over (θh, θd)
(Figure 3), retro-reflection and specular-peak curves (Figures 6 and 9), albedo against
the view angle (Figures 11 and 12), polar plots of a lobe in the plane of incidence and
lit spheres. Every function takes any BRDF callable of the library,

    ``brdf(l, v, n, x=None, y=None, **params) -> (*, 3)``  (or ``(*, 1)`` for grey models),

plus its material parameters as keyword arguments, e.g.
``directional_albedo(torchbrdf.principled, 0.3, base_color=1.0, roughness=0.4)``. A grey
``(*, 1)`` result is repeated to three channels. :func:`bind_brdf` turns a callable and its
parameters into the parameter-free form the functions use internally.

All analysis runs in float64 by default (``dtype=`` changes it) in the local frame
``x = +X``, ``y = +Y``, ``n = +Z``. The view direction at angle ``θv`` lies in the x-z plane,
``v = (sin θv, 0, cos θv)``.

Directional albedo (directional–hemispherical reflectance)
    ``ρ(v) = ∫ f(l, v) (n·l) dω_l``. Two estimators, each returning an :class:`Estimate`
    (value and error):

    * ``"quadrature"`` (deterministic): the integral is written over the half vector,
      ``dω_l = 4 (v·h) dω_h`` with ``l = reflect(v, h)``, because every specular lobe is
      centred at ``h = n`` whatever the view. θh is split into geometrically graded panels
      (each half the width of the next, down to a quarter of the lobe width α) carrying
      Gauss–Legendre nodes; φh uses the periodic midpoint rule. The error estimate is the
      difference from the same rule with half the nodes per panel and half the φ nodes,
      which bounds the error of the finer rule when the rule converges.
    * ``"mc"``: Monte Carlo with independent uniform numbers and importance sampling from
      the cosine density, GGX visible normals (Heitz 2018), the GTR1 clearcoat lobe
      (Burley 2012, appendix B) or an equal mixture (balance-heuristic density); the error
      is the standard error ``σ / √N``.

Lobe width hint
    Both estimators need to know how narrow the peak is. ``alpha_hint`` may be given; by
    default it is taken from the parameters: ``alpha`` (microfacet models), else
    ``roughness²`` (principled), lowered to the clearcoat α when a clearcoat is present;
    for a BRDF with neither (measured data), 0.01 for quadrature and cosine-only sampling
    for Monte Carlo.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple, cast, overload

import numpy as np
import torch
from torch import Tensor

from torchbrdf._checks import sample_counts
from torchbrdf._types import BRDF, Angles, Device
from torchbrdf.analysis import slices as _slices
from torchbrdf.brdf.distributions import ndf_beckmann, ndf_ggx
from torchbrdf.brdf.masking import smith_g1_beckmann, smith_g1_ggx

__all__ = [
    "Estimate",
    "FurnaceResult",
    "ReciprocityResult",
    "bind_brdf",
    "view_direction",
    "lobe_alpha_hint",
    "clearcoat_alpha",
    "directional_albedo",
    "albedo_curve",
    "white_furnace",
    "weak_white_furnace",
    "reciprocity_error",
    "image_slice",
    "retro_reflection_curve",
    "specular_peak_curve",
    "polar_lobe",
    "render_sphere",
]

DEFAULT_DTYPE = torch.float64
# Points evaluated per BRDF call: bounds the memory of the principled BRDF's intermediates
# (~100 float64 (*, 3) temporaries, i.e. ~0.3 GB at 2^17 points).
CHUNK = 1 << 17
# Lobe width assumed for quadrature when nothing is known about the BRDF: resolves peaks
# down to α ≈ 0.005 (the principled model floors α at 0.001).
DEFAULT_QUADRATURE_ALPHA = 0.01
# Smallest α used to place quadrature panels / sampling lobes.
ALPHA_FLOOR = 1e-3


class Estimate(NamedTuple):
    """A numerical estimate and its error estimate: two tensors of one shape (``(T, 3)`` for a curve)."""

    value: Tensor
    error: Tensor


class FurnaceResult(NamedTuple):
    """Outcome of :func:`white_furnace`.

    Attributes:
        theta_v: ``(T,)`` view angles (radians).
        albedo: ``(T, 3)`` directional albedo.
        error: ``(T, 3)`` its error estimate.
        max_albedo: largest albedo over angles and channels.
        passed: ``max(albedo - 3 error) <= 1 + tol``: no energy is created.
    """

    theta_v: Tensor
    albedo: Tensor
    error: Tensor
    max_albedo: float
    passed: bool


class ReciprocityResult(NamedTuple):
    """Outcome of :func:`reciprocity_error`: largest ``|f(l,v) - f(v,l)|``, absolute and relative."""

    max_abs: float
    max_rel: float


# --------------------------------------------------------------------------------------
# BRDF adapters and frames
# --------------------------------------------------------------------------------------


def bind_brdf(brdf: BRDF, **params: Any) -> BRDF:
    """Bind material parameters to a BRDF callable and make its result RGB.

    Args:
        brdf: ``brdf(l, v, n, x=None, y=None, **params) -> (*, 3)`` or ``(*, 1)``.
        **params: material parameters (floats, strings for model choices, or tensors that
            broadcast against ``(*, 3)`` / ``(*, 1)``).

    Returns:
        ``f(l, v, n, x=None, y=None) -> (*, 3)``. Tensor parameters are cast to the
        directions' dtype and device on each call.

    Example:
        >>> from torchbrdf import principled
        >>> f = bind_brdf(principled, base_color=0.5, roughness=0.3)
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> f(n, n, n).shape
        torch.Size([3])
    """

    def bound(l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None) -> Tensor:
        p = {k: (t.to(l.device, l.dtype) if isinstance(t, Tensor) else t) for k, t in params.items()}
        out = brdf(l, v, n, x, y, **p)
        if out.shape[-1] == 1:
            out = out.expand(*out.shape[:-1], 3)
        return out

    bound.params = dict(params)  # type: ignore[attr-defined]
    bound.brdf = brdf  # type: ignore[attr-defined]
    return bound


def _frame(like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(n, x, y)`` = (+Z, +X, +Y) expanded to ``like``'s shape ``(*, 3)``."""
    e = torch.eye(3, dtype=like.dtype, device=like.device)
    return e[2].expand_as(like), e[0].expand_as(like), e[1].expand_as(like)


def _eval(f: Callable[..., Tensor], l: Tensor, v: Tensor) -> Tensor:
    """Evaluate a bound BRDF in the local frame over ``(*, 3)`` directions, chunked."""
    l, v = torch.broadcast_tensors(l, v)
    shape = l.shape[:-1]
    lf, vf = l.reshape(-1, 3), v.reshape(-1, 3)
    outs = []
    for s in range(0, lf.shape[0], CHUNK):
        lc, vc = lf[s : s + CHUNK], vf[s : s + CHUNK]
        n, x, y = _frame(lc)
        outs.append(f(lc, vc, n, x, y))
    out = torch.cat(outs, 0) if outs else lf.new_zeros(0, 3)
    return out.reshape(*shape, 3)


def view_direction(theta_v: Angles, dtype: torch.dtype = DEFAULT_DTYPE, device: Device = None) -> Tensor:
    """View vectors in the x-z plane: ``(sin θv, 0, cos θv)``.

    Args:
        theta_v: float or ``(T,)`` angles from the normal, radians.

    Returns:
        ``(T, 3)`` (or ``(3,)`` for a float).
    """
    t = torch.as_tensor(theta_v, dtype=dtype, device=device)
    return torch.stack((torch.sin(t), torch.zeros_like(t), torch.cos(t)), dim=-1)


def lobe_alpha_hint(params: dict[str, Any]) -> float | None:
    """Narrowest lobe width α suggested by a BRDF's parameters (see the module docstring).

    Returns:
        ``alpha`` (its minimum if a tensor), else ``max(roughness², 0.001)`` (default
        roughness 0.5 for the principled model when ``base_color`` is given), lowered to the
        clearcoat α when ``clearcoat`` is non-zero; ``None`` when nothing hints at a width.
    """

    def smallest(p) -> float:
        return float(torch.as_tensor(p).min()) if isinstance(p, Tensor) else float(p)

    alpha = None
    if "alpha" in params:
        alpha = smallest(params["alpha"])
        if params.get("alpha_y") is not None:
            alpha = min(alpha, smallest(params["alpha_y"]))
    elif "roughness" in params or "base_color" in params:
        r = smallest(params.get("roughness", 0.5))
        alpha = r * r
        aniso = params.get("anisotropic", 0.0)
        if (isinstance(aniso, Tensor) and bool((aniso != 0).any())) or (not isinstance(aniso, Tensor) and aniso != 0):
            alpha *= math.sqrt(0.1)  # the narrow axis of the most anisotropic lobe
    ac = clearcoat_alpha(params)
    if ac is not None:
        alpha = ac if alpha is None else min(alpha, ac)
    return None if alpha is None else max(alpha, ALPHA_FLOOR)


def _theta_tensor(theta, dtype, device) -> tuple[Tensor, bool]:
    t = torch.as_tensor(theta, dtype=dtype, device=device)
    return t.reshape(-1), t.dim() == 0


# --------------------------------------------------------------------------------------
# Half-vector quadrature
# --------------------------------------------------------------------------------------


def _graded_theta_nodes(alpha: float, per_panel: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Gauss–Legendre nodes and weights on ``[0, π/2]`` in panels graded toward 0.

    Panel edges are ``π/2 · 2^-k`` for ``k = 0..K`` with the smallest edge at most α/4, plus 0.
    """
    k_max = max(1, math.ceil(math.log2((math.pi / 2) / (max(alpha, ALPHA_FLOOR) / 4))))
    edges = [0.0] + [(math.pi / 2) * 2.0 ** (-k) for k in range(k_max, -1, -1)]
    x, w = np.polynomial.legendre.leggauss(per_panel)
    nodes, weights = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        nodes.append(0.5 * (b - a) * x + 0.5 * (b + a))
        weights.append(0.5 * (b - a) * w)
    t = torch.tensor(np.concatenate(nodes), dtype=dtype, device=device)
    wt = torch.tensor(np.concatenate(weights), dtype=dtype, device=device)
    return t, wt


def _half_vector_grid(alpha: float, n_theta: int, n_phi: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Half vectors ``(N, 3)`` over the upper hemisphere and solid-angle weights ``(N, 1)``."""
    th, wth = _graded_theta_nodes(alpha, n_theta, dtype, device)
    ph = (torch.arange(n_phi, dtype=dtype, device=device) + 0.5) * (2 * math.pi / n_phi)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    st = torch.sin(T)
    h = torch.stack((st * torch.cos(P), st * torch.sin(P), torch.cos(T)), dim=-1).reshape(-1, 3)
    w = (wth[:, None] * st * (2 * math.pi / n_phi)).reshape(-1, 1)
    return h, w


def _albedo_rule(f, v: Tensor, alpha: float, n_theta: int, n_phi: int) -> Tensor:
    """One quadrature rule for ``(T, 3)`` albedos at views ``v`` ``(T, 3)``."""
    h, w = _half_vector_grid(alpha, n_theta, n_phi, v.dtype, v.device)
    out = []
    for vi in v:
        vh = (h * vi).sum(-1, keepdim=True)
        l = 2.0 * vh * h - vi
        lz = l[:, 2:3]
        ok = (vh > 0) & (lz > 0)
        fv = _eval(f, l, vi.expand_as(l))
        integrand = torch.where(ok, fv * lz * 4.0 * vh * w, torch.zeros_like(fv))
        out.append(integrand.sum(0))
    return torch.stack(out, 0)


# --------------------------------------------------------------------------------------
# Samplers (from torchbrdf.sampling when present, else small local versions)
# --------------------------------------------------------------------------------------


def _sample_cosine(u: Tensor) -> tuple[Tensor, Tensor]:
    """Cosine-weighted directions ``(*, 3)`` and their solid-angle density ``(*, 1)``."""
    try:
        from torchbrdf.render.sampling import pdf_cosine_hemisphere, sample_cosine_hemisphere
    except ImportError:  # fallback: Malley's method on a uniformly sampled disk
        r, phi = torch.sqrt(u[..., 0]), 2 * math.pi * u[..., 1]
        z = torch.sqrt(torch.clamp(1 - r * r, min=0.0))
        d = torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), -1)
        return d, d[..., 2:3] / math.pi
    d = sample_cosine_hemisphere(u)
    return d, pdf_cosine_hemisphere(d)


def _ggx_reflection_sampler():
    """``(sample(v, alpha, u) -> l, pdf(v, l, alpha) -> (*, 1))`` for GGX reflection.

    Uses the visible-normal sampler of :mod:`torchbrdf.sampling`; without that module, falls
    back to sampling ``D(h) (n·h)`` (Walter 2007), which is unbiased but noisier at grazing.
    """
    try:
        from torchbrdf.render.sampling import pdf_ggx_reflection, reflect, sample_ggx_vndf

        def sample(v, a, u):
            return reflect(v, sample_ggx_vndf(v, a, a, u))

        def pdf(v, l, a):
            return pdf_ggx_reflection(v, l, a, a)

        return sample, pdf
    except ImportError:

        def sample(v, a, u):
            tan2 = a * a * u[..., 0] / torch.clamp(1 - u[..., 0], min=1e-12)
            c = 1 / torch.sqrt(1 + tan2)
            s = torch.sqrt(torch.clamp(1 - c * c, min=0.0))
            phi = 2 * math.pi * u[..., 1]
            h = torch.stack((s * torch.cos(phi), s * torch.sin(phi), c), -1)
            return 2 * (v * h).sum(-1, keepdim=True) * h - v

        def pdf(v, l, a):
            h = torch.nn.functional.normalize(v + l, dim=-1)
            nh = h[..., 2:3]
            d = ndf_ggx(nh, a)
            vh = torch.clamp((v * h).sum(-1, keepdim=True), min=1e-12)
            return d * nh / (4 * vh)

        return sample, pdf


def _gtr1_reflection_sampler():
    """``(sample, pdf)`` for GTR1 (clearcoat) half vectors, Burley 2012 appendix B; needs :mod:`torchbrdf.sampling`."""
    from torchbrdf.render.sampling import pdf_gtr1, pdf_half_to_reflection, reflect, sample_gtr1

    def sample(v, a, u):
        return reflect(v, sample_gtr1(a, u))

    def pdf(v, l, a):
        h = torch.nn.functional.normalize(v + l, dim=-1)
        return pdf_half_to_reflection(pdf_gtr1(h, a), (l * h).sum(-1, keepdim=True))

    return sample, pdf


def _strategies(names, alpha: float | None, alpha_clearcoat: float | None):
    """``[(sample(v, u) -> l, pdf(v, l) -> (*, 1))]`` for the named densities."""
    out: list[tuple[Callable[..., Tensor], Callable[..., Tensor]]] = []
    for name in names:
        if name == "cosine":
            out.append((lambda v, u: _sample_cosine(u)[0], lambda v, l: torch.clamp(l[..., 2:3], min=0.0) / math.pi))
        elif name == "ggx":
            if alpha is None:
                raise ValueError("sampler 'ggx' needs a lobe width: pass alpha_hint")
            smp, pdf = _ggx_reflection_sampler()
            out.append((lambda v, u, s=smp: s(v, alpha, u), lambda v, l, p=pdf: p(v, l, alpha)))
        elif name == "gtr1":
            if alpha_clearcoat is None:
                raise ValueError("sampler 'gtr1' needs the clearcoat width: pass clearcoat/clearcoat_gloss")
            smp, pdf = _gtr1_reflection_sampler()
            out.append((lambda v, u, s=smp: s(v, alpha_clearcoat, u), lambda v, l, p=pdf: p(v, l, alpha_clearcoat)))
        else:
            raise ValueError(f"sampler: unknown density {name!r}; expected 'cosine', 'ggx', 'gtr1', 'mix' or 'auto'")
    return out


def _albedo_mc(f, v: Tensor, samples: int, strategies, seed: int) -> Estimate:
    """One-sample-per-strategy-block MC: equal blocks from each density, balance-heuristic pdf."""
    gen = torch.Generator(device=v.device).manual_seed(seed)
    k = len(strategies)
    bounds = [round(i * samples / k) for i in range(k + 1)]
    vals, errs = [], []
    for vi in v:
        u = torch.rand((samples, 2), generator=gen, dtype=v.dtype, device=v.device)
        vv = vi.expand(samples, 3)
        l = torch.cat([smp(vv[a:b], u[a:b]) for (smp, _), a, b in zip(strategies, bounds[:-1], bounds[1:])], 0)
        pdf = sum(p(vv, l) for _, p in strategies) / k
        lz = l[:, 2:3]
        ok = (lz > 0) & (pdf > 0)
        fv = _eval(f, torch.where(ok, l, vv), vv)
        est = torch.where(ok, fv * lz / torch.where(ok, pdf, torch.ones_like(pdf)), torch.zeros_like(fv))
        vals.append(est.mean(0))
        errs.append(est.std(0) / math.sqrt(samples))
    return Estimate(torch.stack(vals), torch.stack(errs))


def clearcoat_alpha(params: dict[str, Any]) -> float | None:
    """The principled clearcoat's GTR1 width ``lerp(0.1, 0.001, clearcoat_gloss)``, or ``None`` without a clearcoat."""
    cc = params.get("clearcoat", 0.0)
    if not ((isinstance(cc, Tensor) and bool((cc != 0).any())) or (not isinstance(cc, Tensor) and cc != 0)):
        return None
    g = params.get("clearcoat_gloss", 1.0)
    g = float(torch.as_tensor(g).max()) if isinstance(g, Tensor) else float(g)
    return max(0.1 + (0.001 - 0.1) * min(max(g, 0.0), 1.0), ALPHA_FLOOR)


# --------------------------------------------------------------------------------------
# Albedo and furnace tests
# --------------------------------------------------------------------------------------


def directional_albedo(
    brdf: BRDF,
    theta_v: Angles,
    method: str = "quadrature",
    samples: int | tuple[int, int] | None = None,
    *,
    sampler: str | Sequence[str] = "auto",
    alpha_hint: float | None = None,
    seed: int = 0,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> Estimate:
    """Directional–hemispherical reflectance ``ρ(v) = ∫ f(l, v) (n·l) dω_l`` with an error estimate.

    Args:
        brdf: BRDF callable ``brdf(l, v, n, x, y, **params) -> (*, 3)`` (or ``(*, 1)``).
        theta_v: view angle(s) from the normal in radians, float or ``(T,)``.
        method: ``"quadrature"`` (deterministic, half-vector Gauss–Legendre; see the module
            docstring) or ``"mc"`` (importance-sampled Monte Carlo).
        samples: quadrature: ``(nodes per θ panel, φ nodes)`` or an int for the first
            (default ``(16, 96)``, at least ``(2, 8)``: the error estimate halves them); MC:
            samples per view (default 4096, at least 2; of a pair, the first).
        sampler: MC density: ``"cosine"``, ``"ggx"`` (visible normals of the primary lobe's
            width), ``"gtr1"`` (the principled clearcoat lobe, Burley 2012 appendix B), a
            tuple of these (equal shares, balance-heuristic density), ``"mix"`` (cosine +
            GGX, + GTR1 when a clearcoat is present) or ``"auto"`` (``"mix"`` when a lobe
            width is known, else ``"cosine"``).
        alpha_hint: lobe width placing the quadrature panels / the GGX sampler; default from
            the parameters (:func:`lobe_alpha_hint`), including those bound by
            :func:`bind_brdf`.
        seed: MC seed (the estimate is deterministic given the seed).
        dtype: evaluation dtype (float64 by default).
        **params: material parameters for ``brdf``.

    Returns:
        :class:`Estimate` of ``(T, 3)`` tensors (``(3,)`` for a float ``theta_v``): the
        albedo and its error estimate (quadrature: difference from the half-resolution
        rule; MC: standard error ``σ / √N``).

    Example:
        >>> from torchbrdf.brdf.lambert import lambert
        >>> a, err = directional_albedo(lambert, 0.5, base_color=0.7)
        >>> round(float(a[0]), 3), bool(abs(a[0] - 0.7) <= err[0])
        (0.7, True)
    """
    f = bind_brdf(brdf, **params)
    theta, scalar = _theta_tensor(theta_v, dtype, device)
    v = view_direction(theta, dtype, device)
    if alpha_hint is None:  # a callable made by bind_brdf carries its parameters
        alpha_hint = lobe_alpha_hint({**getattr(brdf, "params", {}), **params})
    hint = alpha_hint
    if method == "quadrature":
        # the error estimate halves both counts: a rule it cannot halve would claim no error
        n_theta, n_phi = sample_counts("samples", samples, (16, 96), least=(2, 8))
        a = hint if hint is not None else DEFAULT_QUADRATURE_ALPHA
        fine = _albedo_rule(f, v, a, n_theta, n_phi)
        coarse = _albedo_rule(f, v, a, max(n_theta // 2, 1), max(n_phi // 2, 4))
        est = Estimate(fine, (fine - coarse).abs())
    elif method == "mc":
        n = sample_counts("samples", samples, (4096, 1), least=(2, 1))[0]  # 2: a spread; a pair: its first
        all_params = {**getattr(brdf, "params", {}), **params}
        a_cc = clearcoat_alpha(all_params)
        ggx_alpha = hint
        if "roughness" in all_params or "base_color" in all_params:
            r = all_params.get("roughness", 0.5)
            r = float(torch.as_tensor(r).min()) if isinstance(r, Tensor) else float(r)
            ggx_alpha = max(r * r, ALPHA_FLOOR)  # the primary lobe, not the clearcoat
        if sampler == "auto":
            sampler = "mix" if hint is not None else "cosine"
        if sampler == "mix":
            names = ("cosine", "ggx") + (("gtr1",) if a_cc is not None else ())
        elif isinstance(sampler, str):
            names = (sampler,)
        else:
            names = tuple(sampler)
        est = _albedo_mc(f, v, n, _strategies(names, ggx_alpha, a_cc), seed)
    else:
        raise ValueError(f"method: expected 'quadrature' or 'mc', got {method!r}")
    if scalar:
        return Estimate(est.value[0], est.error[0])
    return est


def albedo_curve(
    brdf: BRDF,
    theta_v: Angles | None = None,
    method: str = "quadrature",
    samples: int | tuple[int, int] | None = None,
    *,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> tuple[Tensor, Estimate]:
    """Albedo against the view angle (Burley 2012, Figures 11 and 12).

    Args:
        brdf, method, samples, **params: as in :func:`directional_albedo`.
        theta_v: ``(T,)`` angles; default 0° to 88° every 2° (45 angles).

    Returns:
        ``(theta_v (T,), Estimate((T, 3), (T, 3)))``.
    """
    if theta_v is None:
        theta_v = torch.deg2rad(torch.arange(0.0, 90.0, 2.0, dtype=dtype))
    theta, _ = _theta_tensor(theta_v, dtype, device)
    return theta, directional_albedo(brdf, theta, method, samples, dtype=dtype, device=device, **params)


def white_furnace(
    brdf: BRDF,
    theta_v: Angles | None = None,
    *,
    method: str = "quadrature",
    samples: int | tuple[int, int] | None = None,
    tol: float = 1e-3,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> FurnaceResult:
    """White furnace test: under a uniform white environment the reflected radiance is the albedo.

    With white parameters (e.g. ``base_color=1.0``) an energy-conserving BRDF reflects at most
    what it receives, so ``ρ(v) <= 1`` at every view.

    Args:
        brdf, method, samples, **params: as in :func:`directional_albedo`.
        theta_v: ``(T,)`` view angles; default 0°, 10°, ..., 80°, 89°.
        tol: allowed excess over 1.

    Returns:
        :class:`FurnaceResult`.

    Example:
        >>> from torchbrdf.brdf.lambert import lambert
        >>> white_furnace(lambert, base_color=1.0).passed
        True
    """
    if theta_v is None:
        theta_v = torch.deg2rad(torch.tensor([0.0, 10, 20, 30, 40, 50, 60, 70, 80, 89], dtype=dtype))
    theta, est = albedo_curve(brdf, theta_v, method, samples, dtype=dtype, device=device, **params)
    max_albedo = float(est.value.max())
    passed = bool((est.value - 3 * est.error).max() <= 1 + tol)
    return FurnaceResult(theta, est.value, est.error, max_albedo, passed)


_NDFS = {"ggx": ndf_ggx, "beckmann": ndf_beckmann}
_G1S = {"ggx": smith_g1_ggx, "beckmann": smith_g1_beckmann}


def weak_white_furnace(
    ndf: str | Callable[..., Tensor] = "ggx",
    g1: str | Callable[..., Tensor] | None = None,
    alpha: float = 0.5,
    theta_o: Angles | None = None,
    samples: tuple[int, int] = (24, 128),
    *,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
) -> Estimate:
    """Heitz's weak white furnace test: ``∫ D(h) G1(o) / (4 |n·o|) dω_i = 1`` for every ``o``.

    With the Fresnel factor 1 and the masking-only term ``G1(o)`` in place of ``G2``, a
    microfacet BRDF integrates (cosine-weighted, over the full sphere of ``i``) to exactly 1
    when ``G1`` is the Smith masking function derived from ``D`` (Heitz 2014, "Understanding
    the Masking-Shadowing Function", §4/§5). Substituting ``dω_i = 4 (o·h) dω_h`` gives the
    projected-area form evaluated here, ``G1(o) / (n·o) ∫ D(h) max(o·h, 0) dω_h``, by the
    same graded half-vector quadrature as :func:`directional_albedo`.

    Args:
        ndf: ``"ggx"``, ``"beckmann"`` or a callable ``ndf(n_dot_h, alpha) -> (*, 1)`` (e.g.
            :func:`torchbrdf.ndf_ggx`).
        g1: ``"ggx"``, ``"beckmann"`` or a callable ``g1(n_dot_w, alpha) -> (*, 1)`` (e.g.
            :func:`torchbrdf.smith_g1_beckmann`); default the one named like ``ndf``. A
            mismatched pair (GGX ``D`` with Beckmann ``G1``) fails the test.
        alpha: distribution width.
        theta_o: ``(T,)`` outgoing angles in radians; default 0°, 20°, 40°, 60°, 80°, 89°.
        samples: ``(nodes per θ panel, φ nodes)``, at least ``(2, 8)``.

    Returns:
        :class:`Estimate` of ``(T,)`` tensors: the integral (1 when the test holds) and its
        quadrature error estimate.

    Example:
        >>> est = weak_white_furnace("ggx", alpha=0.3)
        >>> bool(((est.value - 1).abs() < 1e-3).all())
        True
    """
    if isinstance(ndf, str):
        if g1 is None:
            g1 = ndf
        ndf = _NDFS[ndf]
    if isinstance(g1, str):
        g1 = _G1S[g1]
    if g1 is None:
        raise ValueError("g1: pass the masking function that goes with a custom ndf")
    if theta_o is None:
        theta_o = torch.deg2rad(torch.tensor([0.0, 20, 40, 60, 80, 89], dtype=dtype))
    theta, _ = _theta_tensor(theta_o, dtype, device)
    o = view_direction(theta, dtype, device)

    def rule(nt, nphi):
        h, w = _half_vector_grid(alpha, nt, nphi, dtype, device)
        d = ndf(h[:, 2:3], alpha)
        res = []
        for oi in o:
            oh = torch.clamp((h * oi).sum(-1, keepdim=True), min=0.0)
            nz = oi[2:3].reshape(1, 1)
            res.append((g1(nz, alpha) / nz).reshape(()) * (d * oh * w).sum())
        return torch.stack(res)

    n_theta, n_phi = sample_counts("samples", samples, (24, 128), least=(2, 8))
    fine = rule(n_theta, n_phi)
    coarse = rule(max(n_theta // 2, 1), max(n_phi // 2, 4))
    return Estimate(fine, (fine - coarse).abs())


def reciprocity_error(
    brdf: BRDF,
    samples: int = 4096,
    *,
    seed: int = 0,
    floor: float = 1e-6,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> ReciprocityResult:
    """Largest violation of Helmholtz reciprocity ``f(l, v) = f(v, l)`` over random pairs.

    Args:
        brdf, **params: as in :func:`directional_albedo`.
        samples: number of random ``(l, v)`` pairs, uniform on the upper hemisphere.
        seed: random seed.
        floor: added to the denominator of the relative error (where both values are ~0).

    Returns:
        :class:`ReciprocityResult`: ``max |f(l,v) - f(v,l)|`` and the largest
        ``|f(l,v) - f(v,l)| / (max(|f(l,v)|, |f(v,l)|) + floor)``.

    Example:
        >>> from torchbrdf import principled
        >>> reciprocity_error(principled, 256, base_color=0.5).max_rel < 1e-10
        True
    """
    f = bind_brdf(brdf, **params)
    gen = torch.Generator(device=device or "cpu").manual_seed(seed)

    def hemi(m):
        d = torch.randn((m, 3), generator=gen, dtype=dtype, device=device)
        d = torch.nn.functional.normalize(d, dim=-1)
        return torch.cat((d[:, :2], d[:, 2:3].abs()), -1)

    count = sample_counts("samples", samples, (4096, 1), pair=False)[0]
    l, v = hemi(count), hemi(count)
    a, b = _eval(f, l, v), _eval(f, v, l)
    diff = (a - b).abs()
    rel = diff / (torch.maximum(a.abs(), b.abs()) + floor)
    return ReciprocityResult(float(diff.max()), float(rel.max()))


# --------------------------------------------------------------------------------------
# Slices, curves and lobes
# --------------------------------------------------------------------------------------


def image_slice(
    brdf: BRDF,
    resolution: int = 128,
    phi_d: float = math.pi / 2,
    *,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> Tensor:
    """Burley's image slice (Figure 3): ``f`` over ``(θh, θd)`` at fixed ``φd``.

    Thin wrapper of :func:`torchbrdf.slices.image_slice` accepting grey BRDFs too.

    Returns:
        ``(3, resolution, resolution)``: row = θd (top 0, bottom ~90°), column = θh (left 0).
        The left column is the specular peak, the top row retro-reflection (``θd = 0``), the
        bottom row the Fresnel peak (Burley draws θd upward, so flip rows to match his
        figures); where ``l`` or ``v`` is below the horizon the value is 0.
    """
    return _slices.image_slice(bind_brdf(brdf, **params), resolution, phi_d, dtype=dtype, device=device)


def _half_diff_curve(f, theta_h: Tensor, theta_d, phi_d) -> Tensor:
    td = torch.as_tensor(theta_d, dtype=theta_h.dtype, device=theta_h.device).expand_as(theta_h)
    l, v = _slices.half_diff_to_lv(theta_h, td, phi_d)
    return _eval(f, l, v)


def retro_reflection_curve(
    brdf: BRDF,
    theta_h: Angles | None = None,
    *,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> tuple[Tensor, Tensor]:
    """Retro-reflective response ``f(θh, θd = 0)`` (Burley 2012, Figure 6).

    With ``θd = 0`` the light and view coincide (``l = v = h``), so this is the top row of the
    image slice: the specular peak at ``θh = 0`` and grazing retro-reflection near 90°.

    Args:
        theta_h: ``(N,)`` angles; default 0° to 89.5° in 0.5° steps.

    Returns:
        ``(theta_h (N,), f (N, 3))``.
    """
    if theta_h is None:
        theta_h = torch.deg2rad(torch.arange(0.0, 90.0, 0.5, dtype=dtype))
    th, _ = _theta_tensor(theta_h, dtype, device)
    return th, _half_diff_curve(bind_brdf(brdf, **params), th, 0.0, 0.0)


def specular_peak_curve(
    brdf: BRDF,
    theta_h: Angles | None = None,
    theta_d: float = math.radians(10.0),
    phi_d: float = math.pi / 2,
    *,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> tuple[Tensor, Tensor]:
    """Specular peak against ``θh`` at fixed ``(θd, φd)`` (Burley 2012, Figure 9; plot on a log axis).

    Args:
        theta_h: ``(N,)`` angles; default 0° to 40°, square-root spaced (dense at the peak).
        theta_d: difference angle (default 10°, away from retro-reflection and Fresnel).
        phi_d: difference azimuth (default 90°, Burley's slice).

    Returns:
        ``(theta_h (N,), f (N, 3))``.
    """
    if theta_h is None:
        theta_h = torch.linspace(0.0, 1.0, 161, dtype=dtype) ** 2 * math.radians(40.0)
    th, _ = _theta_tensor(theta_h, dtype, device)
    return th, _half_diff_curve(bind_brdf(brdf, **params), th, theta_d, phi_d)


def polar_lobe(
    brdf: BRDF,
    theta_i: float,
    n: int = 361,
    *,
    cosine: bool = True,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> tuple[Tensor, Tensor]:
    """The lobe in the plane of incidence, for a polar plot.

    The light comes from ``l = (-sin θi, 0, cos θi)``; the view sweeps the plane,
    ``v = (sin θo, 0, cos θo)`` for ``θo`` from -90° (back-scatter side) to +90°, so the
    mirror direction is ``θo = θi``.

    Args:
        theta_i: incidence angle in radians.
        n: number of outgoing angles.
        cosine: multiply by ``n·l`` (radiance reflected per unit incident radiance from
            ``l``); ``False`` gives ``f`` itself.

    Returns:
        ``(theta_o (n,), values (n, 3))``.
    """
    theta_o = torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=dtype, device=device)
    v = view_direction(theta_o, dtype, device)
    ti = torch.as_tensor(float(theta_i), dtype=dtype)
    l = torch.stack((-torch.sin(ti), torch.zeros(()), torch.cos(ti))).to(dtype=dtype, device=device).expand_as(v)
    val = _eval(bind_brdf(brdf, **params), l, v)
    if cosine:
        val = val * torch.clamp(l[:, 2:3], min=0.0)
    return theta_o, val


# --------------------------------------------------------------------------------------
# Lit sphere
# --------------------------------------------------------------------------------------

# Burley's lit-sphere view lights the sphere from the upper left, slightly from the front.
DEFAULT_SPHERE_LIGHT = (-1.0, 1.0, 1.2)


def _split_material(params: dict) -> tuple[dict, dict]:
    """Split parameters into g-buffer material entries (numbers, tensors) and bound ones (strings...)."""
    material: dict[str, float | Tensor] = {}
    bound: dict[str, Any] = {}
    for k, p in params.items():
        if isinstance(p, numbers.Real) and not isinstance(p, bool):
            material[k] = float(p)
        elif isinstance(p, Tensor) and p.numel() in (1, 3) and p.is_floating_point():
            material[k] = p.reshape(1, -1, 1, 1) if p.numel() == 3 or k == "base_color" else p.reshape(1, 1, 1, 1)
            if k == "base_color" and p.numel() == 1:
                material[k] = p.reshape(1, 1, 1, 1).expand(1, 3, 1, 1)
        else:
            bound[k] = p
    return material, bound


@overload
def render_sphere(
    brdf: BRDF,
    resolution: int = 128,
    light_direction: Sequence[float] | Tensor = DEFAULT_SPHERE_LIGHT,
    irradiance: float = math.pi,
    *,
    return_mask: Literal[False] = False,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> Tensor: ...
@overload
def render_sphere(
    brdf: BRDF,
    resolution: int = 128,
    light_direction: Sequence[float] | Tensor = DEFAULT_SPHERE_LIGHT,
    irradiance: float = math.pi,
    *,
    return_mask: Literal[True],
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> tuple[Tensor, Tensor]: ...
def render_sphere(
    brdf: BRDF,
    resolution: int = 128,
    light_direction: Sequence[float] | Tensor = DEFAULT_SPHERE_LIGHT,
    irradiance: float = math.pi,
    *,
    return_mask: bool = False,
    dtype: torch.dtype = DEFAULT_DTYPE,
    device: Device = None,
    **params: Any,
) -> Tensor | tuple[Tensor, Tensor]:
    """A sphere lit by one directional light, rendered through :func:`torchbrdf.render.shading.shade`.

    The irradiance defaults to π so a white Lambert surface facing the light has radiance 1.
    When the shader modules (:mod:`torchbrdf.render.shading`, :mod:`torchbrdf.render.geometry`) are not
    available, an orthographic sphere is shaded here with the same formula,
    ``f(l, v) E max(n·l, 0)``.

    Args:
        brdf, **params: as in :func:`directional_albedo` (numbers and tensors become g-buffer
            material entries, other values are bound to the callable).
        resolution: image height and width.
        light_direction: ``(3,)`` direction toward the light in camera space (camera on +z,
            y up); normalised here.
        irradiance: irradiance of the light (grey).
        return_mask: also return the ``(H, W)`` bool coverage of the sphere.

    Returns:
        ``(3, H, W)`` linear radiance, 0 outside the sphere (and the mask when asked).
    """
    ld = torch.nn.functional.normalize(torch.as_tensor(light_direction, dtype=dtype, device=device), dim=0)
    try:
        from torchbrdf.render.geometry import sphere_gbuffer
        from torchbrdf.render.lights import DirectionalLight
        from torchbrdf.render.shading import shade
    except ImportError:
        img, mask = _render_sphere_fallback(bind_brdf(brdf, **params), resolution, ld, irradiance)
        return (img, mask) if return_mask else img
    material, bound = _split_material(params)
    material = {k: (t.to(dtype=dtype, device=device) if isinstance(t, Tensor) else t) for k, t in material.items()}
    g = sphere_gbuffer(resolution, resolution, material=material, dtype=dtype, device=device)

    def f(l, v, n, x=None, y=None, **mat):
        out = brdf(l, v, n, x, y, **bound, **mat)
        return out.expand(*out.shape[:-1], 3) if out.shape[-1] == 1 else out

    f.__name__ = getattr(brdf, "__name__", type(brdf).__name__)
    light = DirectionalLight(ld, torch.full((3,), float(irradiance), dtype=dtype, device=device))
    img = shade(g, light, f)[0]
    mask = cast(Tensor, g.mask)  # sphere_gbuffer always sets the coverage mask
    return (img, mask[0, 0].bool()) if return_mask else img


def _render_sphere_fallback(f, resolution: int, ld: Tensor, irradiance: float) -> tuple[Tensor, Tensor]:
    dtype, device = ld.dtype, ld.device
    c = (torch.arange(resolution, dtype=dtype, device=device) + 0.5) / resolution * 2.2 - 1.1
    yy, xx = torch.meshgrid(-c, c, indexing="ij")
    r2 = xx * xx + yy * yy
    hit = r2 < 1
    n = torch.stack((xx, yy, torch.sqrt(torch.clamp(1 - r2, min=0.0))), -1)
    n = torch.where(hit[..., None], n, torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device))
    from torchbrdf.brdf.frames import frame_from_normal

    x, y = frame_from_normal(n)
    v = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device).expand_as(n)
    l = ld.expand_as(n)
    val = f(l, v, n, x, y) * irradiance * torch.clamp((n * l).sum(-1, keepdim=True), min=0.0)
    val = torch.where(hit[..., None], val, torch.zeros_like(val))
    return val.permute(2, 0, 1), hit
