"""Discrete moves between LM iterations: neighbour propagation and the normal search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.recovery.classes import chi2_quantile, evidence_threshold, pixel_noise_variance
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import pixel_cost, unary_cost
from torchbrdf.recovery.map_ops import dilate
from torchbrdf.recovery.params import N_PARAMS
from torchbrdf.recovery.smoothness_prior import edge_weights, joined_channels, local_prior, row_neighbours


def propagate(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
              class_sigma2: float | None = None,
              unary: tuple[Tensor, Tensor] | None = None,
              active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """PatchMatch-style propagation: each pixel tries its 8 neighbours' parameters.

    A pixel stuck in a bad local optimum (typically on a material edge, where upsampling a
    coarse level blends two materials) adopts the parameters of a neighbour when they
    explain its own observations better — data cost on the training lights plus the
    smoothness prior, so where the data cannot tell two solutions apart (a dielectric whose
    specular went to 0 leaves roughness free) the one agreeing with its neighbours wins.
    Cheap: 8 renders of the level, no Jacobian. With ``class_sigma2`` (the noise variance of
    one residual measured at the class choice), a neighbour of the other class is a candidate
    too, judged on data by the class choice's evidence test: becoming metal needs a cost below
    the pixel's own by the evidence threshold ``τ`` (:func:`evidence_threshold`, Δp = 7 at
    ``cfg.false_metal_rate``) in the pixel's noise variances (:func:`pixel_noise_variance`),
    becoming dielectric one at most ``τ`` of them above it.

    ``active (P,)`` (bool, optional): only these pixels try their neighbours (the renders
    shrink to them); the others keep their parameters. A pass after a pass can give a new
    answer only where something in the pixel's 3×3 neighbourhood changed (its candidates,
    the prior's neighbours and edge weights are all there), so ``active =``
    :func:`dilate` ``(changed)`` gives the same result as a full pass
    (:func:`propagate_passes` runs such passes).

    Returns ``(theta (P, 7), metal (P, 1), changed (P,) bool)``.
    """
    return _pass(data, theta, metal, cfg, class_sigma2, unary, active, None)


def propagate_passes(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings, passes: int,
                     class_sigma2: float | None = None, unary: tuple[Tensor, Tensor] | None = None,
                     active: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Up to ``passes`` passes of :func:`propagate`, each after the first on the pixels near the last one's changes.

    Without ``active``, the same maps as ``passes`` full passes (it stops when a pass changes
    nothing; but for rounding where a pass on more than :data:`FULL_PASS_SHARE` of the pixels
    runs as a full one). With ``active``, the first pass tries only those pixels, unless they
    are more than :data:`FULL_PASS_SHARE` of the map: then it is a full pass. From the third
    on, a pass renders only what is new: a neighbour's parameters that a pass on some pixels
    rendered at the pixel keep their cost (each pixel renders alone, at lights that do not
    change between the passes), and so does the pixel's own. Arguments as for
    :func:`propagate` (``active (P,)`` bool: the first pass only on these pixels; None: all);
    returns ``(theta (P, 7), metal (P, 1))``.
    """
    known = None
    for _ in range(passes):
        if active is not None and int(active.sum()) > FULL_PASS_SHARE * active.numel():
            active = None
        theta, metal, changed = _pass(data, theta, metal, cfg, class_sigma2, unary, active, known)
        if not bool(changed.any()):
            break
        if known is None:  # (the first pass renders all candidates in the maps' layout: none kept)
            known = _PassCosts.empty(theta)
        elif active is None:  # (a full pass keeps no cost: the own ones of the pixels it moved are stale)
            known.own_known &= ~changed
        active = dilate(changed, data.size)
    return theta, metal


#: A pass on more than this share of the pixels runs as a full pass, the cheaper one there: a
#: pass on some pixels renders every candidate of theirs, a full one bounds them on a few lights
#: first. Per pixel the first costs about 2.5× the second (at 256², 17 lights, a pass on 97 %
#: of the pixels took 2.4× a full pass's time), so they break even at 1 / 2.5 of the pixels.
FULL_PASS_SHARE = 1 / 2.5


@dataclass
class _PassCosts:
    """Data costs the passes on some pixels rendered, for the next pass at the same lights.

    ``cost[k, p] (8, P, 1)`` is pixel ``p``'s at the parameters ``values[k, p] (8, P, 7)`` and
    ``metal[k, p] (8, P, 1)`` of its neighbour ``k`` (:data:`NEIGHBOURS` order; NaN: none yet),
    ``own[p] (P, 1)`` its at the parameters the last pass returned, where ``own_known[p]``.
    Only renders of gathered pixel rows are kept: a full pass renders the maps in their own
    layout, whose sums can round otherwise.
    """
    own: Tensor
    own_known: Tensor
    values: Tensor
    metal: Tensor
    cost: Tensor

    @staticmethod
    def empty(theta: Tensor) -> "_PassCosts":
        p_all, c = theta.shape
        nan = torch.full((len(NEIGHBOURS), p_all, c + 1), float("nan"), dtype=theta.dtype, device=theta.device)
        return _PassCosts(theta.new_zeros(p_all, 1), torch.zeros(p_all, dtype=torch.bool, device=theta.device),
                          nan[..., :c], nan[..., c:], theta.new_zeros(len(NEIGHBOURS), p_all, 1))


def _pass(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings, class_sigma2: float | None,
          unary: tuple[Tensor, Tensor] | None, active: Tensor | None, known: _PassCosts | None
          ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`propagate`; with ``active``, reusing and adding to ``known`` (the passes before's, at ``theta``, ``metal``)."""
    size = data.size
    p_all = theta.shape[0]
    rows = torch.arange(p_all, device=theta.device) if active is None else active.nonzero()[:, 0]
    if rows.numel() == 0:
        return theta, metal, torch.zeros(p_all, dtype=torch.bool, device=theta.device)
    un = unary if unary is None or active is None else (unary[0][rows], unary[1][rows])
    wx, wy = edge_weights(theta, metal, size, cfg)
    n, c = rows.numel(), theta.shape[1]
    if active is None:
        # Every pixel: the candidates are the map shifted by one pixel (replicated border), as
        # channel planes (8, 7, P) viewed (8, P, 7): slices, no gather. The maps that come out
        # keep that layout (later float sums over a pixel's unknowns round by it), and the
        # decode and the kernels read each unknown as one contiguous run.
        own, own_metal = theta, metal
        pad = F.pad(torch.cat((theta, metal), 1).T.reshape(1, c + 1, size, size), (1, 1, 1, 1), mode="replicate")[0]
        shifted = torch.stack([pad[:, 1 + dy: 1 + dy + size, 1 + dx: 1 + dx + size] for dy, dx in NEIGHBOURS])
        shifted = shifted.view(len(NEIGHBOURS), c + 1, n).transpose(1, 2)  # (8, P, 8)
        cand, cm = shifted[..., :c], shifted[..., c:]
    else:
        own, own_metal = theta.index_select(0, rows), metal.index_select(0, rows)
        nb = neighbour_rows(rows, size).reshape(-1)  # (8 N,)
        cand = theta.index_select(0, nb).view(-1, n, c)  # (8, N, 7)
        cm = metal.index_select(0, nb).view(-1, n, 1)
    same = cm == own_metal
    at = None if active is None else rows
    # (the neighbours of the active rows, gathered once for the own and the candidates' terms)
    around = None if active is None or size < 2 else row_neighbours(theta, wx, wy, size, rows)
    ch = joined_channels(wx, wy)
    own_prior = local_prior(own, theta, wx, wy, size, at, around, ch) + unary_cost(own, un)
    prior = local_prior(cand, theta, wx, wy, size, at, around, ch) + unary_cost(cand, un)  # (8, N, 1)
    if active is None:
        # Every pixel: each candidate set is rendered at the level's own targets, with no gather.
        # (Stacking the 9 sets into one call renders the same lanes but gathers 9 × P rows of
        # targets, 192 bytes each at 16 lights: that took more time than the 8 calls it saved.)
        own_cost = _data_cost(data, own, own_metal, cfg.model, None)
    else:
        own_cost, data_cost = _active_costs(data, rows, own, own_metal, cand, cm, cfg.model,
                                            class_sigma2 is not None, known)
    best_score = own_cost + own_prior
    tau = evidence_threshold(N_PARAMS, cfg.false_metal_rate)
    n_res = 3 * len(data.train_idx)

    def score(cost: Tensor, k: int | slice) -> Tensor:  # candidates k's scores from their data costs
        if class_sigma2 is None:
            return torch.where(same[k], cost + prior[k], float("inf"))
        # the prior's weights join pixels of one class: a class change is judged on data
        price = tau * pixel_noise_variance(own_cost, cost, class_sigma2, n_res)
        return torch.where(same[k], cost + prior[k],
                           cost + torch.where(cm[k] > 0.5, price, -price) + own_prior)

    if active is None:
        best, best_metal, best_cost = own, own_metal, own_cost
        # (becoming metal costs at least τ noise variances of the smallest the test allows)
        floor = None if class_sigma2 is None else tau * max(class_sigma2, 1e-30)
        renders = _BoundedRenders(data, cand, cm, same, prior, own_prior, best_score, cfg.model, floor)
        for k in range(cand.shape[0]):  # in the neighbours' order: the first of equal scores wins
            data_cost_k = renders.cost(k, best_score)  # (its bound needs the best score so far)
            score_k = score(data_cost_k, k)
            better = score_k < best_score
            best = torch.where(better, cand[k], best)
            best_metal = torch.where(better, cm[k], best_metal)
            best_score = torch.where(better, score_k, best_score)
            best_cost = torch.where(better, data_cost_k, best_cost)
    else:  # every candidate's cost is known: the same choice for all 8 at once
        best, best_metal, best_cost = choose_candidate(score(data_cost, slice(None)), best_score,
                                                       (cand, cm, data_cost), (own, own_metal, own_cost))
        best = theta.index_copy(0, rows, best)
        best_metal = metal.index_copy(0, rows, best_metal)
        if known is not None:
            known.own.index_copy_(0, rows, best_cost)
            known.own_known[rows] = True
    return best, best_metal, (best != theta).any(-1)


def unexplained(cost: Tensor, sigma2: float, n_residuals: int, rate: float) -> Tensor:
    """Pixels ``(P,)`` bool whose data cost ``cost (P, 1)`` noise alone reaches with probability < ``rate``.

    A converged pixel's cost is ``σ²`` times a χ² of ``n_residuals − 7`` degrees of freedom
    (``sigma2``: the noise variance of one residual, measured); above that χ²'s ``1 − rate``
    quantile the model misses something at the pixel, and a neighbour's parameters may explain
    it. NaN counts as unexplained (a non-finite cost is no fit).
    """
    limit = max(sigma2, 1e-30) * chi2_quantile(max(1, n_residuals - N_PARAMS), 1.0 - rate)
    return ~(cost[:, 0] <= limit)


def choose_candidate(scores: Tensor, own_score: Tensor, cands: tuple[Tensor, ...],
                     owns: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Each pixel's winner of ``K`` candidates, as trying them in order and keeping a strictly lower score.

    ``scores (K, N, 1)`` the candidates', ``own_score (N, 1)`` the pixel's own (it wins a tie);
    ``cands`` tensors ``(K, N, *)`` of the candidates' values, ``owns`` the pixel's own ``(N, *)``.
    The first of equal lowest scores wins; a NaN score never does (nor does any against a NaN
    own score). Returns the winners' values, one ``(N, *)`` per entry of ``cands``.
    """
    low, k = torch.where(torch.isnan(scores), float("inf"), scores).min(0)  # (the first minimum's index)
    better = low < own_score  # (N, 1)
    return tuple(torch.where(better, c.gather(0, k.expand(c.shape[1:])[None])[0], o)
                 for c, o in zip(cands, owns))


#: The rounding the light-subset bound allows, in units of the dtype's machine epsilon: two
#: renders of one residual (another layout, another light set) differ by a few ulps of its log.
BOUND_ULPS = 256.0


class _BoundedRenders:
    """A full pass's data costs of candidate set ``k`` ``(P, 1)``, rendered when the choice reaches it.

    A candidate can win only with a score below the pixel's best so far. Where a few lights
    (:func:`pruning_lights`) show for most candidates that their residuals there already
    cost more than that allows, each set is rendered on those lights first and in full only
    where that bound does not rule it out (+inf elsewhere: it would not have won). The
    full renders keep the candidates' layout, so their costs are those of rendering all.
    ``floor``: the least price of becoming metal (None: no candidate of the other class).
    """

    def __init__(self, data: LevelData, cand: Tensor, cm: Tensor, same: Tensor, prior: Tensor, own_prior: Tensor,
                 own_score: Tensor, model: str, floor: float | None):
        self.data, self.cand, self.cm, self.same, self.prior = data, cand, cm, same, prior
        self.own_prior, self.model, self.floor = own_prior, model, floor
        self.lights = pruning_lights(data, cand, cm, torch.where(same, own_score - prior, float("inf")), model)

    def cost(self, k: int, best_score: Tensor) -> Tensor:
        """Set ``k``'s data costs ``(P, 1)`` (+inf: cannot beat ``best_score (P, 1)``, or of the other class and not a candidate)."""
        cand, cm, same = self.cand[k], self.cm[k], self.same[k]
        consider = same if self.floor is None else torch.ones_like(same)
        if self.lights is None:
            keep = consider
        else:
            inf = torch.full_like(best_score, float("inf"))
            bound = torch.where(same, best_score - self.prior[k], inf)
            scale = torch.where(same, best_score.abs() + self.prior[k].abs(), inf)
            if self.floor is not None:  # becoming metal: data + price + own prior must stay below
                metal = ~same & (cm > 0.5)
                bound = torch.where(metal, best_score - self.own_prior - self.floor, bound)
                scale = torch.where(metal, best_score.abs() + self.own_prior.abs() + self.floor, scale)
            tol = BOUND_ULPS * torch.finfo(cand.dtype).eps
            low = _subset_bound(self.data, cand, cm, self.lights, self.model, None, tol)
            keep = consider & ~(low > bound + tol * scale)
        return _kept_costs(self.data, cand, cm, keep[:, 0], self.model)


def _kept_costs(data: LevelData, theta: Tensor, metal: Tensor, keep: Tensor, model: str) -> Tensor:
    """The data costs ``(P, 1)`` of every pixel at ``theta (P, 7)``, ``metal (P, 1)`` where ``keep (P,)``, else +inf.

    The kept rows are gathered in ``theta``'s own layout (rows or channel planes): the kernels'
    sums round by it.
    """
    if bool(keep.all()):
        return _data_cost(data, theta, metal, model, None)
    out = torch.full_like(metal, float("inf"))
    rows = keep.nonzero()[:, 0]
    if rows.numel():
        sub = theta.T.index_select(1, rows).T if theta.stride(0) == 1 else theta.index_select(0, rows)
        out[rows] = _data_cost(data, sub, metal.index_select(0, rows), model, rows)
    return out


def subset_cost_bound(r: Tensor, tol: float, m: int | None = None) -> Tensor:
    """A lower bound ``(N, 1)`` of a data cost from residuals ``r (N, M)`` on some of its lights.

    Another render may round each residual ``r_i`` differently by up to ``tol (1 + |r_i|)``;
    the bound holds for it: ``((1 − tol) |r| − tol √M)²``, less ``tol`` of itself for the sum's
    rounding. NaN (a cost that is +inf): +inf. With ``m``, ``r (N, 1)`` holds the summed
    squares of ``M = m`` residuals (:meth:`LevelData.data_cost`; +inf where not finite).
    """
    norm = torch.linalg.vector_norm(r, dim=-1, keepdim=True) if m is None else r.sqrt()
    low = (norm * (1 - tol) - tol * math.sqrt(r.shape[-1] if m is None else m)).clamp(min=0)
    return torch.nan_to_num(low * low * (1 - tol), nan=float("inf"))


def _subset_bound(data: LevelData, theta: Tensor, metal: Tensor, lights: list[int], model: str,
                  rows: Tensor | None, tol: float) -> Tensor:
    """:func:`subset_cost_bound` ``(N, 1)`` of the data costs on ``lights``, from the fused cost kernel where it applies."""
    cost = data.data_cost(theta, metal, lights, model, rows=rows)
    if cost is None:
        return subset_cost_bound(data.residual(theta, metal, lights, model, rows=rows), tol)
    return subset_cost_bound(cost, tol, 3 * len(lights))


def pruning_lights(data: LevelData, cand: Tensor, cm: Tensor, need: Tensor, model: str, rows: Tensor | None = None,
                   most: int = 4, sample: int = 1024) -> list[int] | None:
    """A few training lights whose residuals alone rule out most candidates, or None where that would not pay.

    ``cand (K, N, 7)``, ``cm (K, N, 1)``: candidate sets of pixels ``rows (N,)`` (None: every
    pixel); ``need (K, N, 1)``: the data cost each must stay below to win (+inf: no bound).
    Every ``K N / sample``-th candidate
    is rendered on all training lights; up to ``most`` lights are picked greedily, each the one
    that rules out the most of them with those before. Kept: the set with the least expected
    render time (a render costs about 3 + its lights, in light units; a gathered one a tenth
    more), if below 0.85 of rendering all.
    """
    k_all, n = cand.shape[:2]
    lights_all = len(data.train_idx)
    if lights_all <= most or k_all * n < 4 * sample:
        return None
    pick = torch.arange(0, k_all * n, max(1, k_all * n // sample), device=cand.device)
    kk, pp = pick // n, pick % n
    r = data.residual(cand[kk, pp], cm[kk, pp], data.train_idx, model, rows=pp if rows is None else rows[pp])
    per_light = torch.nan_to_num((r * r).reshape(pick.numel(), lights_all, 3).sum(-1), nan=float("inf"))
    need_s = need[kk, pp, 0]
    full = 3.0 + lights_all
    chosen: list[int] = []
    out: list[int] | None = None
    best, partial = 0.85 * full, torch.zeros_like(need_s)
    for m in range(1, most + 1):
        ruled = ((partial[:, None] + per_light) > need_s[:, None]).sum(0)
        ruled[chosen] = -1
        light = int(ruled.argmax())
        chosen.append(light)
        partial = partial + per_light[:, light]
        time = 3.0 + m + float((partial <= need_s).float().mean()) * full * 1.1
        if time < best:
            best, out = time, sorted(chosen)
    return None if out is None else [data.train_idx[i] for i in out]


def _active_costs(data: LevelData, rows: Tensor, own: Tensor, own_metal: Tensor, cand: Tensor, cm: Tensor,
                  model: str, cross: bool, known: _PassCosts | None) -> tuple[Tensor, Tensor]:
    """The data costs of pixels ``rows (N,)`` at their own parameters ``(N, 1)`` and at their candidates ``(8, N, 1)``.

    Every render in one fused call, the own parameters and then the candidates stacked along
    the pixel axis (one gather of their targets). Not rendered (+inf): a neighbour of the
    other class unless ``cross`` (it never competes), and one of the pixel's class with the
    pixel's own parameters (a region that took one value in the last pass): its score would
    equal the pixel's own, which a candidate must beat. Taken from ``known`` (and written
    there when rendered): the costs it holds at the same parameters.
    """
    n = rows.numel()
    same = cm == own_metal
    own_again = same & rows_equal(cand, own)
    wanted = (torch.ones_like(same) if cross else same) & ~own_again
    if known is None:
        own_rows = torch.arange(n, device=rows.device)
    else:
        own_rows = (~known.own_known.index_select(0, rows)).nonzero()[:, 0]
        seen = rows_equal(cand, known.values.index_select(1, rows))
        seen &= cm == known.metal.index_select(1, rows)
        wanted, cached = wanted & ~seen, wanted & seen
    k_idx, n_idx = wanted[..., 0].nonzero(as_tuple=True)
    n_own = own_rows.numel()
    c_all = _data_cost(data, torch.cat((own.index_select(0, own_rows), cand[k_idx, n_idx])),
                       torch.cat((own_metal.index_select(0, own_rows), cm[k_idx, n_idx])), model,
                       torch.cat((rows.index_select(0, own_rows), rows.index_select(0, n_idx))))
    if known is None:
        own_cost, data_cost = c_all[:n], torch.full_like(same, float("inf"), dtype=own.dtype)
    else:
        own_cost = known.own.index_select(0, rows).index_copy_(0, own_rows, c_all[:n_own])
        data_cost = torch.where(cached, known.cost.index_select(1, rows), float("inf"))
        pix = rows.index_select(0, n_idx)
        known.values[k_idx, pix] = cand[k_idx, n_idx]
        known.metal[k_idx, pix] = cm[k_idx, n_idx]
        known.cost[k_idx, pix] = c_all[n_own:]
    data_cost[k_idx, n_idx] = c_all[n_own:]
    return own_cost, data_cost


def rows_equal(a: Tensor, b: Tensor) -> Tensor:
    """``(a == b).all(-1, keepdim=True)`` for ``a``, ``b`` broadcasting to ``(*, C)``: ``(*, 1)`` bool.

    One comparison per channel, and-ed in place (an ``all`` over a last dim of 7 took 1.5 to 2.5
    times as long on a pass's ``(8, N, 7)`` candidates).
    """
    eq = a[..., :1] == b[..., :1]
    for ch in range(1, max(a.shape[-1], b.shape[-1])):
        eq &= a[..., ch:ch + 1] == b[..., ch:ch + 1]
    return eq


def _data_cost(data: LevelData, theta: Tensor, metal: Tensor, model: str, rows: Tensor | None) -> Tensor:
    """The summed squared residuals ``(N, 1)`` on the training lights (non-finite: +inf), as :meth:`LevelData.residual`.

    From the fused cost kernel where it applies (:meth:`LevelData.data_cost`: no residuals
    written, the squares summed in float64), else from the residuals.
    """
    if theta.shape[0] == 0:
        return theta.new_empty(0, 1)
    cost = data.data_cost(theta, metal, data.train_idx, model, rows=rows)
    if cost is not None:
        return cost
    return pixel_cost(data.residual(theta, metal, data.train_idx, model, rows=rows))


#: The 8 neighbours' offsets ``(dy, dx)`` in the order :func:`propagate` tries them.
NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def neighbour_rows(rows: Tensor, size: int) -> Tensor:
    """The 8 neighbours (:data:`NEIGHBOURS` order) of pixels ``rows (N,)`` of a ``size²`` map ``(8, N)``.

    Row-major pixel indices (int64, ``rows``' device); at the border the nearest pixel inside
    (replicated edge), so a border pixel may list itself.
    """
    r, col = rows // size, rows % size
    off = torch.tensor(NEIGHBOURS, device=rows.device)
    return ((r + off[:, :1]).clamp(0, size - 1) * size + (col + off[:, 1:]).clamp(0, size - 1))


def candidate_slopes(dtype: torch.dtype, device: torch.device | str,
                     tilts: tuple[float, ...] = (8.0, 16.0, 24.0, 32.0, 40.0),
                     azimuths: int = 8) -> Tensor:
    """Normal slopes ``(K, 2)`` of :func:`normal_search`: the flat normal and a polar grid of tilts (degrees)."""
    out = [torch.zeros(1, 2, dtype=torch.float64)]
    for k, t in enumerate(tilts):
        az = (torch.arange(azimuths, dtype=torch.float64) + 0.5 * (k % 2)) * (2 * math.pi / azimuths)
        out.append(math.tan(math.radians(t)) * torch.stack((az.cos(), az.sin()), -1))
    return torch.cat(out).to(dtype=dtype, device=device)


#: A pixel whose data cost exceeds this × the median pixel's (the noise level) is badly fitted:
#: the model misses it, not the noise (:func:`normal_search` re-seeds it).
BADLY_FITTED = 10.0


def search_bases(data: LevelData, theta: Tensor, metal: Tensor, model: str, factor: float = BADLY_FITTED,
                 max_pixels: int = 4096) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """The pixels :func:`normal_search` searches and the parameters it starts from, or None (no such pixel).

    Arguments as there. Returns ``(cost (P,), bad (B,), bases (B, 9, 7), valid (B, 9))``: every
    pixel's data cost, the searched pixels (int64), their own and 8 neighbours' parameters
    (replicated border) and whether each base is of the pixel's class.
    """
    size = data.size
    cost = _data_cost(data, theta, metal, model, None)[:, 0]
    thr = factor * float(cost[torch.isfinite(cost)].median()) if bool(torch.isfinite(cost).any()) else float("inf")
    bad = torch.nonzero(cost > thr).flatten()
    if bad.numel() == 0:
        return None
    if bad.numel() > max_pixels:
        bad = bad[torch.topk(cost[bad], max_pixels).indices]
    r, col = bad // size, bad % size
    base_list, valid_list = [], []
    for dy, dx in ((0, 0), (-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        q = (r + dy).clamp(0, size - 1) * size + (col + dx).clamp(0, size - 1)
        base_list.append(theta[q])
        valid_list.append(metal[q, 0] == metal[bad, 0])
    return cost, bad, torch.stack(base_list, 1), torch.stack(valid_list, 1)


def normal_search(data: LevelData, theta: Tensor, metal: Tensor, model: str, factor: float = BADLY_FITTED,
                  max_pixels: int = 4096) -> tuple[Tensor, int]:
    """Re-seed badly fitted pixels by a discrete search over normals and neighbours' parameters.

    Gauss–Newton only walks downhill: a glossy pixel whose normal starts 30° off (the steep
    rim of an inlay, where the upsampled coarse level is flat) never finds its highlight.
    Pixels whose data cost exceeds ``factor`` × the median cost (the noise level) try every
    combination of {their own, their 8 same-class neighbours'} parameters × a grid of
    normals (flat, tilts 8–40°, 8 azimuths), and keep the best if it lowers their cost.
    At most ``max_pixels`` (the worst) are searched per call.

    Returns ``(theta (P, 7), number of pixels changed)``.
    """
    c = theta.shape[1]
    found = search_bases(data, theta, metal, model, factor, max_pixels)
    if found is None:
        return theta, 0
    cost, bad, bases, valid = found
    slopes = candidate_slopes(theta.dtype, theta.device)  # (K, 2)
    nb, nbase, k = bad.numel(), bases.shape[1], slopes.shape[0]
    cand = bases[:, :, None, :].expand(nb, nbase, k + 1, c).clone()
    cand[:, :, 1:, 5:7] = slopes[None, None]  # index 0 keeps the base's own normal
    # Rendered: the candidates of same-class bases, except repeats of an earlier base's (a
    # neighbour with the same parameters as one before it; with the same material, the
    # normal grid's candidates repeat). A repeat's cost equals its first's, which comes first
    # and wins a tie, so leaving it out changes nothing.
    earlier = torch.ones(nbase, nbase, dtype=torch.bool, device=theta.device).tril(-1)  # [j, i]: i < j
    same_material = (bases[:, :, None, :5] == bases[:, None, :, :5]).all(-1) & earlier & valid[:, None, :]
    same_base = same_material & (bases[:, :, None, 5:] == bases[:, None, :, 5:]).all(-1)
    render = valid[:, :, None].expand(nb, nbase, k + 1).clone()
    render[:, :, 0] &= ~same_base.any(-1)
    render[:, :, 1:] &= ~same_material.any(-1, keepdim=True)
    cand = cand.reshape(nb, -1, c)
    b_idx, j_idx = render.reshape(nb, -1).nonzero(as_tuple=True)
    pix = bad.index_select(0, b_idx)
    flat = cand[b_idx, j_idx]
    m_flat = metal.index_select(0, pix)
    cost_flat = torch.full((b_idx.numel(),), float("inf"), dtype=theta.dtype, device=theta.device)
    # A candidate wins only below its pixel's cost: where a few lights show that for most,
    # each chunk is rendered on them first and in full only where the bound leaves it open.
    need = cost.index_select(0, pix)
    lights = pruning_lights(data, flat[None], m_flat[None], need[None, :, None], model, pix)
    tol = BOUND_ULPS * torch.finfo(theta.dtype).eps
    chunk = 65536  # candidate pixels per render
    for s0 in range(0, b_idx.numel(), chunk):
        sl: slice | Tensor = slice(s0, s0 + chunk)
        if lights is not None:
            low = _subset_bound(data, flat[sl], m_flat[sl], lights, model, pix[sl], tol)
            sl = (low[:, 0] <= need[sl]).nonzero()[:, 0] + s0
        cost_flat[sl] = _data_cost(data, flat[sl], m_flat[sl], model, pix[sl])[:, 0]
    ccost = torch.full(cand.shape[:2], float("inf"), dtype=theta.dtype, device=theta.device)
    ccost[b_idx, j_idx] = cost_flat
    best_cost, best = ccost.min(1)
    better = best_cost < cost[bad]
    theta = theta.clone()
    theta[bad[better]] = cand[better, best[better]]
    return theta, int(better.sum())
