"""The final stage's continuous metallic: candidates, blends of the clear ends, the fits.

A pixel that straddles a metal and a dielectric (an anti-aliased edge, a rust front, a dust
rim) takes a fractional metallic only where that lowers its energy by more than the extra
unknown gains on noise (:func:`soft_metal_fit`); :func:`soft_metal_stage` runs the stage.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.recovery.classes import residual_variance
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import PixelRows, at_rows, keep_better, pixel_cost, soft_lm
from torchbrdf.recovery.map_ops import blur, dilate, neighbour_mean
from torchbrdf.recovery.params import R_MAX, R_MIN, decode, encode, logit


def soft_metal_candidates(cost: Tensor, metal: Tensor, size: int, factor: float, max_frac: float,
                          band: int = 1, base: Tensor | None = None, edge: float = 0.0,
                          context: float = 0.0) -> Tensor:
    """Pixels ``(N,)`` (indices) where metallic may become continuous: the binary choice fits
    poorly (data ``cost (P, 1)`` above ``factor`` × its median, the noise level) or the pixel
    lies within ``band`` pixels of a metal/dielectric boundary (band 1: one of its 8 neighbours
    is of the other class; a soft ramp is several pixels wide, and the binary choice puts its
    boundary anywhere on it), or, with ``base (P, 3)`` and ``edge > 0``, it is a metal within
    ``band`` pixels of a base-colour step larger than ``edge`` between 4-neighbours (a rust
    island called metal has no class boundary, and it fits as a rough dark metal), or, with
    ``context > 0`` as well, a metal whose base colour differs by more than ``edge`` from the
    Gaussian-weighted mean (σ = ``context`` pixels, truncated at 3σ) of the metal around it:
    the inside of a partly rusted plateau called metal has no step, and as a clear metal it
    would be its own rim's metal end (:func:`blend_ends`).

    ``metal (P, 1)`` in {0, 1}. At most ``max_frac`` × P pixels, the worst fitting first;
    int64 indices on ``cost``'s device.
    """
    img = (metal > 0.5).to(cost.dtype).T.reshape(1, 1, size, size)
    k = 2 * band + 1
    hi = F.max_pool2d(img, k, 1, band)  # a metal within the band
    lo = -F.max_pool2d(-img, k, 1, band)  # a dielectric within the band
    boundary = (hi != lo).reshape(-1, 1)
    if base is not None and edge > 0:
        b = base.T.reshape(1, 3, size, size)
        dx = ((b[..., :, 1:] - b[..., :, :-1]) ** 2).sum(1, keepdim=True) > edge**2
        dy = ((b[..., 1:, :] - b[..., :-1, :]) ** 2).sum(1, keepdim=True) > edge**2
        e = torch.zeros_like(img)
        e[..., :, 1:] += dx
        e[..., :, :-1] += dx
        e[..., 1:, :] += dy
        e[..., :-1, :] += dy
        e = F.max_pool2d((e > 0).to(cost.dtype), k, 1, band) * img  # within the band of a metal's colour edge
        boundary = boundary | (e > 0).reshape(-1, 1)
        if context > 0:  # a metal unlike the metal around it
            w = (metal > 0.5).to(base.dtype)
            around = blur(torch.cat((w, base * w), -1), size, context)
            mean = around[:, 1:] / around[:, :1].clamp(min=1e-12)
            unlike = ((base - mean) ** 2).sum(-1, keepdim=True) > edge**2
            boundary = boundary | (unlike & (w > 0))
    finite = torch.isfinite(cost)
    med = float(cost[finite].median()) if bool(finite.any()) else 0.0
    sel = ((cost > factor * med) | boundary)[:, 0]
    rows = torch.nonzero(sel).flatten()
    cap = max(1, int(max_frac * cost.shape[0]))
    if rows.numel() > cap:
        rows = rows[torch.topk(torch.nan_to_num(cost[rows, 0], nan=float("inf")), cap).indices]
    return rows


#: :func:`blend_ends`' Gaussian widths in pixels, nearest first: the clear pixels beside a texel,
#: else the same class further off. A small dust speck on a metal, or a partly rusted plateau, is
#: mixed throughout, with no clear dielectric within the narrow widths' reach, and a blend from
#: the pixel's own values (a metal) would call such a speck mostly metal (docs/recovery.md,
#: "Continuous metallic"). The widest is also the context in which soft_metal_candidates finds a
#: metal unlike the metal around it.
BLEND_SIGMAS = (2.0, 6.0, 24.0)


def blend_ends(theta: Tensor, metal: Tensor, rows: Tensor, size: int, sigmas: tuple = BLEND_SIGMAS
               ) -> tuple[tuple[Tensor, Tensor], Tensor]:
    """The clear dielectric and the clear metal nearest to each pixel of ``rows (N,)``.

    Each end: base colour, specular and roughness ``(N, 5)`` (the quantities a blend mixes
    linearly), the Gaussian-weighted mean (the first width of ``sigmas``, in pixels, that
    reaches one) of the ``metal (P, 1)`` == 0, resp. == 1, pixels not in ``rows``; where no
    width reaches one, the pixel's own values. ``theta (P, 7)``.
    Returns ``((dielectric end, metal end), found (N, 2) bool)``, on ``theta``'s device (the
    ends in its dtype).
    """
    p = decode(theta, metal)
    lin = torch.cat((p["base_color"], p["specular"], p["roughness"]), -1)  # (P, 5)
    clear = torch.ones(theta.shape[0], dtype=torch.bool, device=theta.device)
    clear[rows] = False
    ends, founds = [], []
    for cls in (0.0, 1.0):
        w = (clear & (metal[:, 0] == cls)).to(theta.dtype)[:, None]
        end, found = lin[rows], torch.zeros(rows.shape[0], 1, dtype=torch.bool, device=theta.device)
        for sigma in sigmas:  # the nearest scale that has any; a wider one only where none has yet
            if bool(found.all()) or not bool(w.any()):
                break
            b = blur(torch.cat((w, lin * w), -1), size, sigma)[rows]  # the weight and the weighted sum
            ok = (b[:, :1] > 1e-3) & ~found
            end = torch.where(ok, b[:, 1:] / b[:, :1].clamp(min=1e-12), end)
            found = found | ok
        ends.append(end)
        founds.append(found)
    return (ends[0], ends[1]), torch.cat(founds, -1)


#: :func:`unmix_metallic`'s batch: pixel-values of its coverage grid evaluated per call.
UNMIX_PIXELS = 1 << 17


def unmix_metallic(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   size: int, steps: int = 11, sigmas: tuple = BLEND_SIGMAS) -> tuple[Tensor, Tensor]:
    """Pixels ``rows (N,)`` explained as blends of the clear metal and dielectric beside them.

    Each pixel's coverage ``t``: the best fit to its data (lights ``idx``) of ``steps`` even
    values of [0, 1], moved to the vertex of the parabola through it and its two neighbours.

    A texel that straddles two materials (an anti-aliased edge, a rust front, a dust rim) has
    base colour, roughness and metallic all blended with one weight, its coverage. Free, the
    fit cannot tell a 15 %-metal rough pixel from a rough dielectric (its base colour and
    roughness take up the difference); along the line between its neighbours' two materials
    its base colour tells the coverage. The two ends are :func:`blend_ends` of the
    ``metal (P, 1)`` == 0 and == 1 pixels not in ``rows`` (the candidates are the mixed ones):
    the nearest ones, or the same class further off where none is near (the core of a small
    dust speck is all candidates; a rust island inside a metal has no clear rust beside it;
    ``sigmas``, :data:`BLEND_SIGMAS`), else the pixel's own parameters (the blend is then a
    guess, still a better start than none); the metal end takes the
    dielectric end's specular (a metal's is not observed). The normal is the pixel's own.
    Where no blend has a finite cost, ``t`` and its theta are NaN (no blend). ``theta (P, 7)``.
    Returns ``(theta of the blend (N, 7), t (N, 1))``, on ``theta``'s device and in its dtype.
    """
    n = rows.shape[0]
    if n == 0:
        return theta.new_empty(0, theta.shape[1]), theta.new_empty(0, 1)
    (diel, met), _ = blend_ends(theta, metal, rows, size, sigmas)
    met = torch.cat((met[:, 0:3], diel[:, 3:4], met[:, 4:5]), -1)
    normal, sub = decode(theta[rows], metal[rows])["normal"], data.subset(rows)

    def blend(t: Tensor) -> Tensor:  # theta of the blend at coverages t (k N, 1): k per pixel, value-major
        k = t.shape[0] // n
        v = diel.repeat(k, 1) * (1 - t) + met.repeat(k, 1) * t
        return encode({"base_color": v[:, 0:3], "specular": v[:, 3:4], "roughness": v[:, 4:5],
                       "normal": normal.repeat(k, 1)})

    # Several grid values of every pixel per evaluation: fewer calls' fixed cost, at most
    # UNMIX_PIXELS pixel-values per call (a bounded batch at any size).
    parts = []
    grid = torch.linspace(0, 1, steps, dtype=theta.dtype, device=theta.device)
    for values in grid.split(max(1, UNMIX_PIXELS // n)):
        t_k = values.repeat_interleave(n)[:, None]
        each = torch.arange(n, device=theta.device).repeat(values.shape[0])
        parts.append(pixel_cost(sub.residual(blend(t_k), t_k, idx, model, rows=each)).view(-1, n))
    costs = torch.cat(parts).T  # (N, steps)
    k = costs.argmin(-1, keepdim=True)  # pixel_cost: a NaN cost is already +inf
    t = k.to(theta.dtype) / (steps - 1)
    # Between grid values: the vertex of the parabola through the best and its two neighbours
    # (an end of [0, 1] stays exact: a clear pixel's blend is its own class).
    inner = (k > 0) & (k < steps - 1)
    km, kp = (k - 1).clamp(min=0), (k + 1).clamp(max=steps - 1)
    cm, c0, cp = costs.gather(-1, km), costs.gather(-1, k), costs.gather(-1, kp)
    curv = cm - 2 * c0 + cp
    fit = inner & torch.isfinite(cm) & torch.isfinite(cp) & (curv > 0)
    shift = torch.where(fit, 0.5 * (cm - cp) / torch.where(fit, curv, 1.0), 0.0)  # |shift| ≤ ½: c0 least
    t = t + shift / (steps - 1)
    t = torch.where(torch.isfinite(c0), t, float("nan"))
    return torch.where(torch.isnan(t), float("nan"), blend(t)), t


def may_be_mixed(coverage: Tensor, metal: Tensor, cost: Tensor, quiet: float) -> Tensor:
    """The soft-metal candidates ``(N,)`` bool that stay in the final stage's metallic fits.

    Left out: a candidate whose best blend of its clear neighbours (``coverage (N, 1)``,
    :func:`unmix_metallic`) is its own class ``metal (N, 1)`` and whose data ``cost (N, 1)``
    is at most ``quiet`` (the caller's noise level: 1.5 × the median pixel's, the 98.5th
    percentile of 51 residuals' noise). Nothing in its data asks for a mixture, and one more
    unknown would only fit noise: such a pixel rarely leaves its class in the free fit, and
    one that ends fractional has no better metallic, so leaving them out saves part of the
    stage's time. A candidate with no blend (NaN coverage) stays.
    """
    return ~((coverage == metal) & (cost <= quiet))[:, 0]


def growth_front(metal: Tensor, tried: Tensor, size: int) -> Tensor:
    """Pixels ``(N,)`` (indices) beside a run of fractional metallic that were not refitted yet.

    ``metal (P, 1)``, ``tried (P,)`` bool. A run: a fractional pixel with a fractional
    4-neighbour (an isolated one, on a binary material, is not a ramp and does not grow);
    beside: its 8-neighbourhood (the run's own untried pixels included). int64 indices on
    ``metal``'s device.
    """
    fr = ((metal > 0) & (metal < 1)).to(metal.dtype)
    run = (fr[:, 0] > 0) & (neighbour_mean(fr, size)[:, 0] > 0)
    return torch.nonzero(dilate(run, size) & ~tried).flatten()


def soft_prior(x: Tensor, well: float, target: Tensor | None = None, smooth: float | Tensor = 0.0,
                line: tuple[Tensor, Tensor] | None = None, line_weight: float | Tensor = 0.0
                ) -> tuple[Tensor, Tensor]:
    """The prior residuals of the soft-metal unknowns ``x (N, 8)`` and their Jacobian.

    The double-well term ``√well · m (1 − m)`` (its square is ``well m² (1 − m)²``) on metallic
    ``m = x[:, 7]``; with ``target (N, 1)``, the pull ``√smooth · (m − target)`` toward the
    metallic the neighbours suggest; with ``line = (dielectric, metal)`` base colours ``(N, 3)``
    each, ``√line_weight · (base − ((1 − m) dielectric + m metal))`` per channel (base =
    sigmoid of ``x[:, 0:3]``): the base colour a blend of the two at the pixel's own metallic
    would have. ``smooth``, ``line_weight``: a float or ``(N, 1)``.
    Returns ``(residuals (N, k), Jacobian (N, k, 8))``, k = 1 [+ 1] [+ 3], on ``x``'s device
    and in its dtype.
    """
    m = x[:, 7:8]
    cols = torch.arange(x.shape[1], device=x.device)
    metal_col = (cols == 7).to(x.dtype)  # (8,)
    sw = math.sqrt(well)
    res, jac = [sw * m * (1 - m)], [(sw * (1 - 2 * m))[..., None] * metal_col]
    if target is not None:
        ss = smooth.sqrt() if isinstance(smooth, Tensor) else torch.full_like(m, math.sqrt(smooth))
        res.append(ss * (m - target))
        jac.append(ss[..., None] * metal_col)
    if line is not None:
        sl = (line_weight.sqrt() if isinstance(line_weight, Tensor)
              else torch.full_like(m, math.sqrt(line_weight)))  # (N, 1)
        diel, met = line
        base = torch.sigmoid(x[:, 0:3])
        res.append(sl * (base - (diel + m * (met - diel))))
        jac.append(torch.cat((torch.diag_embed(sl * base * (1 - base)), base.new_zeros(*base.shape, 4),
                              (-sl * (met - diel))[..., None]), -1))  # (N, 3, 8)
    return torch.cat(res, -1), torch.cat(jac, 1)


def snap_metallic(m: Tensor, snap: float) -> Tensor:
    """Metallic ``m (N, 1)`` with values within ``snap`` of 0 or 1 set to them.

    A 1 % lobe is below what the noise can tell apart: a clear pixel. ``m``'s dtype and device.
    """
    return torch.where(m < snap, torch.zeros_like(m), torch.where(m > 1 - snap, torch.ones_like(m), m))


def soft_energy(sub: LevelData, idx: list[int], model: str, well: float, target: Tensor | None = None,
                 smooth: float | Tensor = 0.0, line: tuple[Tensor, Tensor] | None = None,
                 line_weight: float | Tensor = 0.0) -> tuple[Callable, Callable, Callable, Callable]:
    """The final stage's energy of ``sub``'s pixels, as :func:`soft_lm` takes it.

    Returns ``(jvp, prior, cost, normal_eq)`` of some of the pixels' unknowns ``x (n, 8)`` by
    their indices: the data residuals on lights ``idx`` and their derivatives, the prior
    residuals (:func:`soft_prior`; ``target``, ``smooth``, ``line``, ``line_weight`` per pixel
    of ``sub`` or floats) and their Jacobian, the summed cost ``(n, 1)`` of both, and the data
    term's fused normal equations (:meth:`LevelData.normal_equations`), on ``sub``'s device
    and in its dtype.
    """
    def residual(v: Tensor, r: PixelRows) -> Tensor:
        return sub.residual(v[:, :7], v[:, 7:8], idx, model, rows=r)

    def jvp(v: Tensor, tg: Tensor, r: PixelRows) -> tuple[Tensor, Tensor]:
        return sub.residual_jvp(v, v[:, 7:8], idx, model, tg, rows=r)

    def prior(v: Tensor, r: PixelRows) -> tuple[Tensor, Tensor]:
        return soft_prior(v, well, at_rows(target, r), at_rows(smooth, r), at_rows(line, r), at_rows(line_weight, r))

    def normal_eq(v: Tensor, r: PixelRows, n_t: int) -> tuple[Tensor, Tensor, Tensor] | None:
        fused = sub.normal_equations(v, v[:, 7:8], idx, model, n_t, rows=r)
        return None if fused is None else fused[1:]

    return jvp, prior, lambda v, r: pixel_cost(torch.cat((residual(v, r), prior(v, r)[0]), -1)), normal_eq


def soft_metal_fit(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   well: float, gain: float | Tensor, iters: int = 8, starts: tuple = (None, 0.5),
                   target: Tensor | None = None, smooth: float | Tensor = 0.0, refit_reference: bool = True,
                   snap: float = 0.02, line: tuple[Tensor, Tensor] | None = None,
                   line_weight: float | Tensor = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel LM on 8 unknowns — theta (7) and a continuous metallic in [0, 1] — for ``rows (N,)``.

    Energy: data (lights ``idx``) + the double-well prior ``well · m²(1 − m)²`` (minima at exactly
    0 and 1) [+ ``smooth · (m − target)²``, ``target (N, 1)``, ``smooth`` a float or ``(N, 1)``:
    the metallic the neighbours suggest, which decides where the data cannot — a rough metal's
    broad lobe mimics a rough dielectric's diffuse] [+ ``line_weight · |base − ((1 − m) d + m e)|²``,
    ``line = (d, e)`` base colours ``(N, 3)``: the blend of a dielectric and a metal at the
    pixel's own metallic, which holds a fractional pixel's base colour where the data trade it
    against metallic]. Metallic is a bounded value, clamped to
    [0, 1] after each step (projected LM), so
    a pixel can land on exactly 0 or 1. The Jacobian is forward-mode (:func:`fit_jacobian`,
    6 tangents for the 8 unknowns, 5 with metallic held). ``starts``: metallic start values,
    ``None`` = the pixel's own, ``"target"`` = ``target``, a float, or ``(theta start (N, 7),
    one of those)``; the lowest
    energy wins. A fractional result replaces a binary ``metal`` only where it lowers the
    energy — the pulls included: where the data cannot tell, the metallic they suggest is the
    evidence — by more than ``gain`` (a float, or ``(N, 1)`` per pixel; the caller scales it by the
    noise variance) below the same fit with metallic held at its own value (with
    ``refit_reference``; else below ``theta``, ``metal`` as given): one more unknown always
    fits noise a little, and a clear pixel must stay exactly 0 or 1 (it then keeps the better
    of its old and its refitted 7 unknowns — its old ones where the free fit does not beat even
    the unrefitted reference, which is then not refitted — or of its old and the free fit's
    where the free fit ended on its class); a metallic within ``snap`` of 0 or 1 is set to it
    (and judged there).
    ``theta (P, 7)``, ``metal (P, 1)``.
    Returns ``(theta rows (N, 7), metal rows (N, 1), changed (N,))``.
    """
    if rows.numel() == 0:
        return theta[rows], metal[rows], torch.zeros(0, dtype=torch.bool, device=theta.device)
    sub = data.subset(rows)
    t0, m0 = theta[rows], metal[rows]

    jvp, prior, cost, normal_eq = soft_energy(sub, idx, model, well, target, smooth, line, line_weight)

    best, best_c = None, None
    for m_start in starts:
        # Several metallic starts: a pixel that is 30 % metal has another local optimum near
        # the class it was given.
        t_init = t0
        if isinstance(m_start, tuple):  # (theta start (N, 7), metallic start)
            t_init, m_start = m_start
        m_init = m0 if m_start is None else target if m_start == "target" else torch.full_like(m0, m_start)
        assert m_init is not None, "soft_metal_fit: a 'target' start needs `target`"
        x, c = soft_lm(jvp, cost, torch.cat((t_init, m_init), -1), iters, prior=prior, normal_eq=normal_eq)
        best, best_c = keep_better(best, best_c, x, c)
    assert best is not None and best_c is not None, "soft_metal_fit: `starts` must not be empty"
    # Within `snap` of 0 or 1 is a clear pixel: a 1 % lobe is below what the noise can tell
    # apart, so it is set exactly.
    m = best[:, 7:8]
    m_snap = snap_metallic(m, snap)
    snapped = m_snap != m
    best = torch.cat((best[:, :7], m_snap), -1)
    if bool(snapped.any()):  # judged by the energy of what is returned
        best_c = torch.where(snapped, cost(best, None), best_c)
    ref = torch.cat((t0, m0), -1)  # the solution so far (a binary one: no double-well cost)
    c_ref = cost(ref, None)
    keep = torch.zeros_like(c_ref, dtype=torch.bool)
    # The reference a fractional (or other-class) result must beat: the same per-pixel fit
    # with metallic held at the pixel's own value, so it wins by what it explains, not by the
    # refit of the other unknowns (the main fit's priors leave some pixels off their data
    # optimum). Only where the free fit left the pixel's class:
    # one it returned to its own class has nothing to judge, and keeps the better of its old
    # unknowns and the free fit's (snapped to its class).
    # A refit only lowers the reference, so a pixel whose result does not beat even the
    # unrefitted one (by the gain, where newly fractional) is refused either way and keeps its
    # old unknowns: only the others are refitted (about half of the pixels that left their class).
    newly_fractional = (m_snap > 0) & (m_snap < 1) & ((m0 == 0) | (m0 == 1))
    margin = torch.where(newly_fractional, gain, 0.0)
    away = torch.nonzero(((m_snap != m0) & (best_c < c_ref - margin))[:, 0]).squeeze(1) if refit_reference \
        else rows[:0]
    if away.numel():
        jvp_a, prior_a, cost_a, ne_a = soft_energy(sub.subset(away), idx, model, well, at_rows(target, away),
                                              at_rows(smooth, away), at_rows(line, away), at_rows(line_weight, away))
        ref_a, c_fix = soft_lm(jvp_a, cost_a, ref[away], iters, fix_metal=True, prior=prior_a, normal_eq=ne_a)
        keep_a = c_fix < c_ref[away]
        ref[away] = torch.where(keep_a, ref_a, ref[away])
        c_ref[away] = torch.where(keep_a, c_fix, c_ref[away])
        keep[away] = keep_a
    accepted = (best_c < c_ref - margin)[:, 0]
    best = torch.where(accepted[:, None], best, ref)
    accepted = accepted | keep[:, 0]
    return best[:, :7], best[:, 7:8], accepted


def soft_rough_tie(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   well: float, margin: float, glossy: float = 0.2, rough: float = 0.85, iters: int = 8,
                   coverage: Tensor | None = None, snap: float = 0.02) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`rough_basin_tie` in the final stage, where a blend of metal and dielectric is an answer.

    At a metal's edge a rough, partly metal rim (15-25 % metal, roughness 0.8) fits its
    images as well as a glossy dielectric with a strong specular whose lobe falls between the lights:
    the binary tie cannot tell them apart (a dielectric's F0 stops at 0.08) and the final stage's free
    fit stays in the glossy basin, which a held-out light then shows as a firefly. Here each of
    ``rows (N,)`` (int64 indices into the P pixels) with metallic below 1 and roughness below
    ``glossy`` is refitted twice on 8 unknowns (:func:`soft_energy`: data on lights ``idx`` and the
    double-well ``well`` only, none of the stage's pulls; ``iters`` LM iterations, as the binary
    tie's) — with its roughness held at its own value, and free from ``rough`` with metallic from
    ``coverage (P, 1)`` (the blend of its clear neighbours, :func:`unmix_metallic`; ½ where NaN or
    None; clamped to ``[snap, 1 − snap]``) — and takes the second where that stayed rough (above
    ``2 × glossy``) at a finite energy at most ``margin`` (in the energy's units: the caller scales
    it by the noise variance) above the first. A metallic within ``snap`` of 0 or 1 is set to it
    before that comparison (the other unknowns refitted with it held) and judged there. Roughness is
    free on the rough side: held at one value, a rough metal's lobe misses its own roughness.
    ``theta (P, 7)``, ``metal (P, 1)``.
    Returns ``(theta (P, 7), metal (P, 1), moved (P,) bool)`` on ``theta``'s device, in its dtype.
    """
    moved = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    test = rows[(decode(theta[rows], metal[rows])["roughness"][:, 0] < glossy) & (metal[rows, 0] < 1)]
    if test.numel() == 0:
        return theta, metal, moved
    x0 = torch.cat((theta[test], metal[test]), -1)
    start = x0.clone()
    start[:, 4] = logit(torch.full_like(start[:, 4], rough), R_MIN, R_MAX)
    u = torch.full_like(start[:, 7], 0.5) if coverage is None else coverage[test, 0]
    start[:, 7] = torch.nan_to_num(u, nan=0.5).clamp(snap, 1 - snap)
    # Both fits in one LM call (each pixel twice: glossy held, then rough free; the pixels'
    # iterations are independent, so this only saves the calls' fixed cost)
    n = test.numel()
    jvp, prior, cost, normal_eq = soft_energy(data.subset(torch.cat((test, test))), idx, model, well)
    held = torch.zeros(2 * n, x0.shape[1], dtype=torch.bool, device=x0.device)
    held[:n, 4] = True  # the glossy fit's roughness logit
    x, c = soft_lm(jvp, cost, torch.cat((x0, start)), iters, prior=prior, held=held, normal_eq=normal_eq)
    c_glossy, x, c_rough = c[:n], x[n:], c[n:]
    m = x[:, 7:8]
    m_snap = snap_metallic(m, snap)
    snapped = (m_snap != m)[:, 0]
    x = torch.cat((x[:, :7], m_snap), -1)
    if bool(snapped.any()):
        # Judged at the value returned (a 0.985 would become a full metal), after a refit of the
        # others with it held: a rough dielectric left at metallic 0.01 fits a little worse at 0
        # until its base colour follows.
        s_rows = snapped.nonzero()[:, 0]
        jvp_s, prior_s, cost_s, ne_s = soft_energy(data.subset(test[s_rows]), idx, model, well)
        x_s, c_s = soft_lm(jvp_s, cost_s, x[s_rows], iters, fix_metal=True, prior=prior_s, normal_eq=ne_s)
        x[s_rows], c_rough[s_rows] = x_s, c_s
    stayed_rough = decode(x[:, :7], x[:, 7:8])["roughness"][:, 0] > 2 * glossy
    take = (torch.isfinite(c_rough) & (c_rough <= c_glossy + margin))[:, 0] & stayed_rough
    theta, metal = theta.clone(), metal.clone()
    theta[test[take]], metal[test[take]] = x[take, :7], x[take, 7:8]
    moved[test[take]] = True
    return theta, metal, moved


@dataclass
class _Stage:
    """What every pass of :func:`soft_metal_stage` shares: the level, the options, the noise level
    ``sigma2`` (one residual's variance), and the candidates' coverage ``unmix (P, 1)`` as a blend
    of their clear neighbours (NaN where unknown; growth fills it in)."""

    data: LevelData
    cfg: Settings
    sigma2: float
    unmix: Tensor

    @property
    def size(self) -> int:
        return self.data.size

    def well(self) -> float:
        return self.cfg.soft_metal_well * self.sigma2

    def gain(self) -> float:
        """The cost drop that buys a fractional metallic (one extra unknown): ``cfg.soft_metal_gain`` × σ²."""
        return self.cfg.soft_metal_gain * self.sigma2

    def neighbour_fit(self, theta: Tensor, metal: Tensor, rows: Tensor, gain: float | Tensor,
                      warm: bool = False) -> tuple[Tensor, Tensor]:
        """Pass 2 and growth: ``rows`` refitted from the 4-neighbours' mean parameters (with ``warm``:
        from their own), metallic pulled toward the neighbours' (of ``theta``, ``metal``) and, where
        known, toward the blend's: two quadratic pulls, one of their summed weight toward their
        weighted mean. Returns ``(theta rows (N, 7), metal rows (N, 1))``."""
        cfg, size = self.cfg, self.size
        w_nb, w_un = cfg.soft_metal_smooth * self.sigma2, cfg.soft_metal_unmix * self.sigma2
        target, u = neighbour_mean(metal, size)[rows], self.unmix[rows]
        known = ~torch.isnan(u)
        weight = torch.where(known, w_nb + w_un, w_nb).to(u.dtype)
        target = torch.where(known, (w_nb * target + w_un * u) / (w_nb + w_un), target)
        t, m, _ = soft_metal_fit(self.data, theta, metal, rows, self.data.train_idx, cfg.model, self.well(), gain,
                                 cfg.soft_metal_iters,
                                 (None,) if warm else ((neighbour_mean(theta, size)[rows], "target"),),
                                 target, weight, refit_reference=False)
        return t, m


def soft_metal_stage(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings
                     ) -> tuple[Tensor, Tensor, dict[str, int]]:
    """Final stage: continuous metallic where the binary choice fits poorly, at a class
    boundary or at a metal's colour step (:func:`soft_metal_candidates`,
    :func:`soft_metal_fit`), then along runs of fractional pixels (:func:`growth_front`),
    and last the fractional pixels once more with their base colour tied to the blend of
    their clear neighbours (``cfg.soft_metal_line``); a candidate (a metal unlike the metal
    around it is one too) may also change class, and every other pixel keeps its 0 or 1 (a
    candidate whose blend is its own class and that fits at the noise level too,
    :func:`may_be_mixed`, ``cfg.soft_metal_quiet``; only the glossy/rough tie may move it).

    ``data`` a full level (``size × size``), ``theta (P, 7)``, ``metal (P, 1)`` in {0, 1}.
    Returns ``(theta (P, 7), metal (P, 1), counts)``: counts of pixels refitted (growth
    included), fractional, and moved from glossy to rough; ``theta``'s dtype and device.
    """
    size = data.size
    with torch.no_grad():
        r = data.residual(theta, metal, data.train_idx, cfg.model)
    cost = pixel_cost(r)
    sigma2 = residual_variance(cost, r.shape[1])  # the noise variance of one residual
    typical = sigma2 * r.shape[1]
    rows = soft_metal_candidates(cost, metal, size, cfg.soft_metal_factor, cfg.soft_metal_max,
                                 cfg.soft_metal_band, torch.sigmoid(theta[:, 0:3]), cfg.soft_metal_edge,
                                 context=BLEND_SIGMAS[-1])
    counts = {"pixels_refitted": int(rows.numel()), "fractional_pixels": 0, "glossy_to_rough": 0}
    if not (rows.numel() and sigma2 > 0):
        return theta, metal, counts
    stage = _Stage(data, cfg, sigma2, torch.full_like(metal, float("nan")))
    theta, metal, rows, quiet = _candidate_passes(stage, theta, metal, rows, cost, typical)
    counts["pixels_refitted"] = int(rows.numel())
    tried = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    tried[rows] = True
    tried[quiet] = True  # not grown into (the glossy/rough tie below still tests them)
    theta, metal, counts["pixels_refitted"] = _grow(stage, theta, metal, tried, counts["pixels_refitted"])
    if cfg.soft_rough_tie > 0:
        # Glossy or rough, now with a blend as an answer (a rim's glossy fit is a firefly
        # under an unseen light), before the blend line, which then holds the moved
        # pixels' base colour too.
        theta, metal, moved = soft_rough_tie(
            data, theta, metal, torch.nonzero(tried).flatten(), data.train_idx, cfg.model,
            stage.well(), cfg.soft_rough_tie * sigma2, cfg.soft_rough_tie_glossy,
            cfg.rough_tie_start, coverage=stage.unmix)
        counts["glossy_to_rough"] = int(moved.sum())
    theta, metal = _blend_line(stage, theta, metal)
    counts["fractional_pixels"] = int(((metal > 0) & (metal < 1)).sum())
    return theta, metal, counts


def _candidate_passes(stage: _Stage, theta: Tensor, metal: Tensor, rows: Tensor, cost: Tensor, typical: float
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pass 1 (each candidate's free fit) and pass 2 (the neighbours' metallic decides) on ``rows``.

    Returns ``(theta, metal, rows, quiet)``: the maps with the candidates' fractional or
    other-class answers taken, the candidates fitted and those left out (:func:`may_be_mixed`).
    """
    data, cfg, size, sigma2 = stage.data, stage.cfg, stage.size, stage.sigma2
    theta0, metal0 = theta, metal
    # One start, metallic ½: the own-class optimum is already the reference fit's (metallic
    # held), so a second start there adds time and no information. With the blend of the clear
    # neighbours known, the other unknowns start from it, and its coverage pulls.
    start: tuple = (0.5,)
    pull: dict = {}
    quiet = rows[:0]  # the candidates left out of the metallic fits and growth
    w_un = cfg.soft_metal_unmix * sigma2
    if w_un > 0:
        t_blend, u = unmix_metallic(data, theta, metal, rows, data.train_idx, cfg.model, size)
        stage.unmix[rows] = u
        # Not the clear pixels that fit at the noise level (about half the candidates).
        if cfg.soft_metal_quiet > 0:
            keep = may_be_mixed(u, metal[rows], cost[rows], cfg.soft_metal_quiet * typical)
            quiet, rows, t_blend, u = rows[~keep], rows[keep], t_blend[keep], u[keep]
        known = ~torch.isnan(u)  # else the pixel's own unknowns, metallic ½ and no pull
        start = ((torch.where(known, t_blend, theta[rows]), 0.5),)
        pull = {"target": torch.nan_to_num(u), "smooth": torch.where(known, w_un, 0.0).to(u.dtype)}
    t_new, m_new, _ = soft_metal_fit(
        data, theta, metal, rows, data.train_idx, cfg.model, stage.well(),
        stage.gain(), cfg.soft_metal_iters, starts=start, **pull)
    theta, metal = theta.clone(), metal.clone()
    theta[rows], metal[rows] = t_new, m_new
    if cfg.soft_metal_smooth > 0:
        # Second pass: where the data cannot tell (a rough metal's lobe mimics a rough
        # dielectric's diffuse), the neighbours' metallic decides.
        # Start: its 4-neighbours' mean parameters (a rust pixel that pass 1 left in the
        # metal mode starts from the rust beside it), metallic = target; kept only if better.
        target = neighbour_mean(metal, size)[rows]
        m1 = metal[rows]
        # Only where the neighbours say something the pixel does not (another metallic
        # beside it, or itself fractional): inside a uniform binary region the pull and
        # the start equal the pixel's own, and the fit would only repeat pass 1.
        ctx = ((target - m1).abs() > 1e-6) | ((m1 > 0) & (m1 < 1))
        rows2 = rows[ctx[:, 0]]
        # Beside a pixel pass 1 made fractional, a ramp is likely to go on: a smaller gain.
        fr = ((metal > 0) & (metal < 1)).to(theta.dtype)
        near = neighbour_mean(fr, size)[rows2] > 0
        ctx_scale = torch.where(near, cfg.soft_metal_context, 1.0).to(theta.dtype)
        gain2 = stage.gain() * ctx_scale
        # Repeated, each round pulled toward the neighbours' metallic of the round
        # before: a ramp's values settle from both of its ends (Jacobi smoothing). A
        # pixel an earlier round made fractional is no longer asked for the gain (it is
        # not newly fractional): only its energy decides between its values. Rounds
        # after the first go on from the round before's answers: most pixels are settled
        # and leave the LM early, and the others continue where they were instead of
        # starting over from their neighbours' (moved) mean; a pixel the round before
        # refused gets no new neighbour start (its refusal stands).
        for k in range(cfg.soft_metal_passes if rows2.numel() else 0):
            theta[rows2], metal[rows2] = stage.neighbour_fit(theta, metal, rows2, gain2, warm=k > 0)
        t_new, m_new = theta[rows], metal[rows]
    # Only a fractional or other-class answer is taken: a pixel that stays its class
    # keeps the fit it had, with the priors' regularisation (a data-only refit would lose the
    # ties that hold a metal's weakly observed F0). One that changed class beat
    # its own class in soft_metal_fit's judgement (in pass 1 its own class's refit; in the
    # second pass its answer before, the neighbours' pull included): a thin dielectric
    # scratch the binary choice called metal.
    take = ((metal[rows] > 0) & (metal[rows] < 1)) | (metal[rows] != metal0[rows])
    theta, metal = theta0.clone(), metal0.clone()
    theta[rows] = torch.where(take, t_new, theta0[rows])
    metal[rows] = torch.where(take, m_new, metal0[rows])
    return theta, metal, rows, quiet


def _grow(stage: _Stage, theta: Tensor, metal: Tensor, tried: Tensor, refitted: int
          ) -> tuple[Tensor, Tensor, int]:
    """Growth: a ramp runs on past the candidates (a dust speck's soft rim, wider than the band on
    its dielectric side). The untried pixels beside a run of fractional ones (a fractional pixel
    with a fractional 4-neighbour; an isolated one on a binary material is not a ramp) get the
    second pass's fit, ``cfg.soft_metal_grow`` rounds. ``tried (P,)`` is updated in place;
    returns the maps and ``refitted`` plus the pixels grown into."""
    data, cfg, size = stage.data, stage.cfg, stage.size
    for _ in range(cfg.soft_metal_grow):
        front = growth_front(metal, tried, size)
        if front.numel() == 0:
            break
        tried[front] = True
        if cfg.soft_metal_unmix * stage.sigma2 > 0:  # their coverage pulls too (a speck's core, from its rim)
            _, stage.unmix[front] = unmix_metallic(data, theta, metal, front, data.train_idx, cfg.model, size)
        t_f, m_f = stage.neighbour_fit(theta, metal, front, stage.gain() * cfg.soft_metal_context)
        ff = (m_f > 0) & (m_f < 1)
        theta[front] = torch.where(ff, t_f, theta[front])
        metal[front] = torch.where(ff, m_f, metal[front])
        refitted += int(front.numel())
    return theta, metal, refitted


def _blend_line(stage: _Stage, theta: Tensor, metal: Tensor) -> tuple[Tensor, Tensor]:
    """Last: the fractional pixels refitted with their base colour tied to the blend of the clear
    dielectric and metal beside them at their own metallic (``cfg.soft_metal_line``; only where
    both ends are within reach: elsewhere there is no line). Alone, the data trade a little
    metallic for a lot of base colour (a 90 %-metal rust-front pixel fits as well 0.005 less
    metal and 0.05 darker); the blend line crosses that valley at a steep angle. Twice the
    stage's iterations: the valley is long."""
    data, cfg = stage.data, stage.cfg
    frac_rows = torch.nonzero(((metal > 0) & (metal < 1))[:, 0]).flatten()
    if not (cfg.soft_metal_line > 0 and frac_rows.numel()):
        return theta, metal
    (diel, met), found = blend_ends(theta, metal, frac_rows, stage.size)
    both = found.all(-1)
    frac_rows, diel, met = frac_rows[both], diel[both, 0:3], met[both, 0:3]
    t_p, m_p, _ = soft_metal_fit(data, theta, metal, frac_rows, data.train_idx, cfg.model, stage.well(), 0.0,
                                 2 * cfg.soft_metal_iters, starts=(None,), refit_reference=False,
                                 line=(diel, met), line_weight=cfg.soft_metal_line * stage.sigma2)
    theta[frac_rows], metal[frac_rows] = t_p, m_p
    return theta, metal
