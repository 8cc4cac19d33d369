"""Metal / dielectric: the per-pixel class choice and the ties that change a pixel's basin.

Evidence decides: the two hypotheses' data costs at the capture's measured noise level
(:func:`residual_variance`) give each pixel's evidence for metal (:func:`class_evidence`), and a
pixel takes the class its evidence and its neighbours' classes support (:func:`choose_class`, an
MRF whose Potts weight is the same likelihood-ratio threshold, :func:`evidence_threshold`).
An unconverged dielectric is refitted before a metal's win counts
(:func:`unconverged_dielectric_rows`), and a glossy dielectric moves to the rough basin where
that fits as well (:func:`rough_basin_tie`).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import pixel_cost, refit_pixels
from torchbrdf.recovery.map_ops import neighbour_count
from torchbrdf.recovery.params import N_PARAMS, R_MAX, R_MIN, decode, logit


def rough_basin_tie(data: LevelData, theta: Tensor, metal: Tensor, idx: list[int], model: str, margin: float,
                    glossy: float = 0.1, rough: float = 0.85, iters: int = 8, max_pixels: int = 4096
                    ) -> tuple[Tensor, Tensor]:
    """Move glossy dielectrics to the rough basin where that fits their data as well.

    A dielectric whose highlights all fall between the lights fits its images as a glossy
    surface (the lobe unseen) and as a rough one (the lobe broad and dim) at the same cost: rough
    dust specks on a metal end glossy where the coarse levels blend them with the
    metal, and with specular held the cost profile over roughness has two basins at the same
    height with a barrier of hundreds of noise variances between them (docs/recovery.md). The
    fit's path decides, and the confidence, linearised in the
    glossy basin, calls the answer measured. Between basins that fit equally well the wider
    one is the likelier (its posterior mass): the rough one, where a small change of roughness
    changes nothing. A glossy surface whose highlight is seen fits far worse rough and stays.
    The price: a truly glossy dielectric whose highlight no light shows anywhere comes out
    rough (the images do not tell it; docs/recovery.md, Known limits).

    The pixels tested: ``metal (P, 1)`` < ½ with roughness below ``glossy``, at most
    ``max_pixels`` of them (the glossiest first: each costs two small refits). Each is refitted
    (:func:`refit_pixels`, data only, lights ``idx``, ``iters`` iterations) with its roughness
    held twice — at its own value and at ``rough`` — and takes the rough fit where its cost is
    at most the glossy fit's plus ``margin`` noise variances (the median dielectric pixel's cost
    per residual). ``theta (P, 7)``.
    Returns ``(theta (P, 7), moved (P,) bool)``, on ``theta``'s device and in its dtype.
    """
    moved = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    diel = metal[:, 0] < 0.5
    zero = torch.zeros_like(metal)
    rough_now = decode(theta, zero)["roughness"][:, 0]
    rows = torch.nonzero(diel & (rough_now < glossy)).flatten()
    if rows.numel() == 0:
        return theta, moved
    if rows.numel() > max_pixels:
        rows = rows[torch.topk(rough_now[rows], max_pixels, largest=False).indices]
    sigma2 = residual_variance(pixel_cost(data.residual(theta, zero, idx, model))[diel], 3 * len(idx))
    held = torch.zeros(rows.numel(), N_PARAMS, dtype=torch.bool, device=theta.device)
    held[:, 4] = True  # the roughness logit
    _, c_glossy = refit_pixels(data, theta, zero, rows, [theta[rows]], idx, model, iters, held=held)
    start = theta[rows].clone()
    start[:, 4] = logit(torch.full_like(start[:, 4], rough), R_MIN, R_MAX)
    t_rough, c_rough = refit_pixels(data, theta, zero, rows, [start], idx, model, iters, held=held)
    take = c_rough <= c_glossy + margin * sigma2  # (a non-finite rough cost only where the glossy's is too)
    theta = theta.clone()
    theta[rows] = torch.where(take, t_rough, theta[rows])
    moved[rows] = take[:, 0]
    return theta, moved


@functools.lru_cache(maxsize=64)
def chi2_quantile(dof: float, p: float) -> float:
    """The ``p`` quantile of the χ² distribution with ``dof`` degrees of freedom (a float).

    Bisection on the regularised incomplete gamma function, ``P(χ²_k ≤ x) = P(k/2, x/2)``, in
    float64 to a relative 1e-10. Remembered per ``(dof, p)``: a fit asks for the same few
    thresholds at every propagation pass (a bisection is some 40 incomplete-gamma calls).
    """
    if not (dof > 0 and 0.0 < p < 1.0):
        raise ValueError(f"chi2_quantile: need dof > 0 and 0 < p < 1, got dof={dof!r}, p={p!r}")
    k = torch.tensor(0.5 * dof, dtype=torch.float64)

    def cdf(x: float) -> float:
        return float(torch.special.gammainc(k, torch.tensor(0.5 * x, dtype=torch.float64)))

    lo, hi = 0.0, max(1.0, 2.0 * dof)
    while cdf(hi) < p:
        lo, hi = hi, 2.0 * hi
    while hi - lo > 1e-10 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return 0.5 * (lo + hi)


def evidence_threshold(extra_params: int, false_positive_rate: float) -> float:
    """The drop of the data cost, in noise variances ``σ²``, that buys ``extra_params`` more
    freedom: ``k · Δp``, the χ²(Δp) quantile at ``1 − false_positive_rate``.

    Why: with Gaussian residuals of variance ``σ²`` the data cost ``C = Σ r²`` is
    ``−2σ² log L`` up to a constant, so ``(C_simple − C_rich) / σ²`` is the log-likelihood-ratio
    statistic. Where the simpler explanation is true, the richer one's ``Δp`` extra unknowns
    absorb only the noise along their own directions, so the statistic is at most χ²(Δp)
    distributed (Wilks; exact for linearised nested fits). Taking the richer explanation only
    above this quantile calls a noise-only pixel richer with probability at most
    ``false_positive_rate``. The threshold is in σ² units, so the cost drop it asks for grows
    with σ²: double the noise deviation, four times the drop. For Δp = 7 (a metal's unknowns
    against a dielectric's) and a rate 1e-4, ``k · Δp`` ≈ 29.9; for Δp = 1 (a fractional
    metallic), ≈ 15.1.
    """
    if not 0.0 < false_positive_rate < 0.5:
        raise ValueError(f"false_positive_rate must be in (0, 0.5), got {false_positive_rate!r}")
    return chi2_quantile(extra_params, 1.0 - false_positive_rate)


def residual_variance(cost: Tensor, n_residuals: int) -> float:
    """The capture's measured noise: ``σ²`` of one residual, the median finite pixel cost
    ``cost (P, 1)`` (or ``(P,)``) per residual (``n_residuals`` per pixel); 0 when none is finite.

    The median pixel of a converged fit is at the noise level (the fit's misfit, where the
    model cannot reproduce the capture, counts as noise too).
    """
    finite = torch.isfinite(cost)
    return float(cost[finite].median()) / max(1, n_residuals) if bool(finite.any()) else 0.0


def pixel_noise_variance(cost_a: Tensor, cost_b: Tensor, sigma2: float, n_residuals: int) -> Tensor:
    """Each pixel's residual variance ``(P, 1)`` for the class test: the capture's ``σ²``, or where
    even the better of the two fits (data costs ``(P, 1)``) is worse than that, its residual
    per degree of freedom ``min(cost) / (n_residuals − 7)``: there the model misses something the
    noise does not explain, and a cost difference of the same size is no evidence (an F test).
    """
    dof = max(1, n_residuals - N_PARAMS)
    better = torch.nan_to_num(torch.minimum(cost_a, cost_b), nan=float("inf"), posinf=float("inf"))
    local = torch.where(torch.isfinite(better), better / dof, torch.full_like(better, float("inf")))
    return local.clamp(min=max(sigma2, 1e-30))


def unconverged_dielectric_rows(cost_diel: Tensor, cost_metal: Tensor, sigma2: float, n_residuals: int,
                                false_positive_rate: float, factor: float = 5.0) -> Tensor:
    """Pixels ``(N,)`` whose metal win is no evidence: the dielectric hypothesis never converged.

    The metal wins the class test (:func:`class_evidence` above :func:`evidence_threshold`;
    data costs ``(P, 1)`` with ``n_residuals`` residuals each, ``sigma2`` the noise variance of
    one), the dielectric fits above ``factor`` × the median pixel's cost (``σ² n``) and the
    metal does not fit at the noise level either (> 2× it; a metal that does is a metal).
    These pick the pixels of a per-pixel refit, which replaces the dielectric only where it
    fits better: they cost time, not accuracy. ``factor`` 5 is below where a dielectric stuck in
    a narrow feature (a grout line at the image edge) fits, 7–11× the median. The χ²(n − 7)
    quantile at the class test's rate (1.8× the median at 36 residuals) as both bounds would
    also pick true metal pixels by the hundreds (their dielectric fits badly because they are
    metal), at no gain.
    Returns int64 indices on the costs' device.
    """
    tau = evidence_threshold(N_PARAMS, false_positive_rate)
    med = sigma2 * n_residuals
    wins = class_evidence(cost_diel, cost_metal, sigma2, n_residuals) > tau
    sus = wins & (cost_diel > factor * med) & (cost_metal > 2.0 * med)
    return torch.nonzero(sus[:, 0]).flatten()


def class_evidence(cost_diel: Tensor, cost_metal: Tensor, sigma2: float, n_residuals: int) -> Tensor:
    """The evidence for metal ``(P, 1)``: the dielectric's data cost minus the metal's, in each
    pixel's noise variances (:func:`pixel_noise_variance`); > 0 favours metal, NaN-free."""
    var = pixel_noise_variance(cost_diel, cost_metal, sigma2, n_residuals)
    ev = (cost_diel - cost_metal) / var
    # A non-finite cost loses to a finite one; both non-finite: no evidence.
    ev = torch.where(torch.isfinite(cost_diel) | torch.isfinite(cost_metal), ev, torch.zeros_like(ev))
    return torch.nan_to_num(ev, nan=0.0, posinf=1e30, neginf=-1e30)


def choose_class(cost_diel: Tensor, cost_metal: Tensor, size: int, sigma2: float, n_residuals: int,
                 false_positive_rate: float) -> Tensor:
    """Per-pixel metal (1) / dielectric (0) choice ``(P, 1)`` from the two hypotheses' data costs.

    ``cost_diel``, ``cost_metal (P, 1)``: each fit's sum of squared residuals over
    ``n_residuals`` residuals; ``sigma2`` the capture's noise variance of one residual
    (:func:`residual_variance`); ``size`` the map's side (``P = size²``).

    The labelling minimises an MRF energy by iterated conditional modes: each pixel's evidence
    for metal ``e`` (:func:`class_evidence`, in noise variances) against a Potts term over its 8
    neighbours (5 on an edge, 3 in a corner) whose weight is the same evidence threshold ``τ``
    (:func:`evidence_threshold`, Δp = 7 at ``false_positive_rate``) shared among them: a pixel
    is metal when ``e > τ · (1 − 2 m / n)`` with ``m`` of its ``n`` neighbours metal. So a pixel
    against a unanimous neighbourhood changes class only on evidence ``τ`` — what noise alone
    gives at most at ``false_positive_rate`` — one with its neighbours on its side keeps their
    class unless its data say otherwise by ``τ``, and pixels the data cannot decide (a metal
    far from every highlight, whose tail a black glossy dielectric reproduces as well) follow
    the majority. Pixels with ``|e| > τ`` hold their class whatever their neighbours. The
    start is the evidence alone (metal above ``τ``: dielectric is the common case); sweeps
    update one of the four 2×2 parity classes at a time (no two of them neighbours) until
    nothing changes, at most ``size`` sweeps (a region grows by a pixel per sweep).
    Returns ``cost_diel``'s dtype and device.
    """
    tau = evidence_threshold(N_PARAMS, false_positive_rate)
    ev = class_evidence(cost_diel, cost_metal, sigma2, n_residuals)
    label = (ev > tau).to(cost_diel.dtype)
    undecided = ev.abs() <= tau
    if not bool(undecided.any()):
        return label
    pix = torch.arange(label.shape[0], device=label.device)
    parity = ((pix // size) % 2 * 2 + (pix % size) % 2)[:, None]
    for _ in range(max(1, size)):
        before = label
        for colour in range(4):
            metal_nb, n_nb = neighbour_count(label, size)
            pull = tau * (1.0 - 2.0 * metal_nb / n_nb.clamp(min=1.0))
            label = torch.where((parity == colour) & undecided, (ev > pull).to(label.dtype), label)
        if torch.equal(label, before):
            break
    return label
