"""Metal / dielectric: the per-pixel class choice and the ties that change a pixel's basin.

The two hypotheses' costs decide the class (:func:`choose_class`, with the neighbours for the
pixels the data cannot decide), isolated choices are removed (:func:`despeckle`,
:func:`majority_vote`), an unconverged dielectric is refitted before a metal's win counts
(:func:`unconverged_dielectric_rows`), and a glossy dielectric moves to the rough basin where
that fits as well (:func:`rough_basin_tie`).
"""

from __future__ import annotations

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
    dust specks on a metal came out glossy where the coarse levels blended them with the
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
    cost = pixel_cost(data.residual(theta, zero, idx, model))[diel]
    finite = torch.isfinite(cost)
    sigma2 = float(cost[finite].median()) / (3 * len(idx)) if bool(finite.any()) else 0.0
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


def unconverged_dielectric_rows(cost_diel: Tensor, cost_metal: Tensor, margin: float,
                                factor: float = 5.0) -> Tensor:
    """Pixels ``(N,)`` whose metal win is no evidence: the dielectric hypothesis never converged.

    The metal wins (``cost_metal < margin × cost_diel``, data costs ``(P, 1)``), the dielectric
    fits above ``factor`` × its median cost (the noise level) and the metal does not fit at the
    noise level either (> 2× that median; a metal that does is a metal, and skipping it keeps
    metal-heavy captures cheap — the border rims' metal fits were 2–10× it). ``factor`` 5: a
    narrow grout line at the image edge had its dielectric stuck at 7–11× the median and was
    called metal with 10. Returns int64 indices on the costs' device.
    """
    med = float(cost_diel.median())
    sus = (cost_metal < margin * cost_diel) & (cost_diel > factor * med) & (cost_metal > 2.0 * med)
    return torch.nonzero(sus[:, 0]).flatten()


def choose_class(cost_diel: Tensor, cost_metal: Tensor, margin: float, size: int, sweeps: int = 8) -> Tensor:
    """Per-pixel metal (1) / dielectric (0) choice ``(P, 1)`` from the two hypotheses' data costs.

    Decisive pixels follow the data: metal when its cost is below ``margin`` × the
    dielectric's, dielectric when above ``1 / margin`` × it. The pixels in between are ones the
    data cannot decide — typically a metal far from every highlight, whose tail a black
    glossy dielectric reproduces as well — and take the majority class of their
    neighbours (8 inside the image, 5 on an edge, 3 in a corner; a few
    iterated-conditional-modes sweeps grow the decisive regions into them); with no
    decisive neighbourhood they stay dielectric, the common case.
    """
    ratio = cost_metal / cost_diel.clamp(min=1e-30)
    sure_metal = ratio < margin
    ambiguous = ~sure_metal & (ratio <= 1.0 / margin)
    label = sure_metal.to(cost_diel.dtype)
    for _ in range(sweeps if bool(ambiguous.any()) else 0):
        metal_nb, n_nb = neighbour_count(label, size)
        label = torch.where(ambiguous, (metal_nb > 0.5 * n_nb).to(label.dtype), label)
    return label


def majority_vote(metal: Tensor, size: int) -> Tensor:
    """3×3 majority vote ``(P, 1)`` over the pixel and its neighbours that exist."""
    metal_nb, n_nb = neighbour_count(metal, size)
    return ((metal_nb + metal) > 0.5 * (n_nb + 1)).to(metal.dtype)


def despeckle(metal: Tensor, size: int) -> Tensor:
    """Flip isolated choices ``(P, 1)``: at most one in 8 of the pixel's neighbours agrees with it
    (on an edge: none of its 5; keeps one-pixel-wide lines, which have 2 agreeing neighbours)."""
    metal_nb, n_nb = neighbour_count(metal, size)
    agree = torch.where(metal > 0.5, metal_nb, n_nb - metal_nb)
    return torch.where(agree * 8 <= n_nb, 1 - metal, metal)
