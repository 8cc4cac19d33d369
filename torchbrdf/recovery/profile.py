"""Profile likelihood of roughness: what the data say about one unknown when the others are free.

A pixel whose highlight no light shows fits its images about as well over a range of roughness
(its specular and normal trading against it), so its fitted value is where the fit stopped, not
what the data support. The profile makes that visible: the data cost with the roughness held at
each value of a grid and the pixel's other unknowns refitted. Summed over pixels known to share a
material, it is the material's log-likelihood (``−cost / 2σ²``, Gaussian noise of variance
``σ²``) for a common roughness; its minimum is the value all of them support together, which
none of them determines alone. ``docs/recovery_silent.md``
measures it on the recovery panel's tuning captures.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import pixel_cost, refit_pixels
from torchbrdf.recovery.params import R_MAX, R_MIN, logit

__all__ = ["roughness_profile", "pooled_minimum"]


def roughness_profile(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, grid: Sequence[float],
                      model: str = "principled", iters: int = 10) -> tuple[Tensor, Tensor]:
    """Data cost of each listed pixel with its roughness held at each value of ``grid``.

    ``theta (P, 7)`` the fitted unknowns, ``metal (P, 1)``, ``rows (N,)`` (int64) the pixels,
    ``grid`` (``K`` roughness values in map units, within ``[R_MIN, R_MAX]``). At each value the
    pixel's other unknowns are refitted to the data alone (``iters`` Levenberg–Marquardt
    iterations of :func:`refit_pixels` from the fitted values) on ``data.train_idx``; a refit
    that does not lower the cost keeps the start. Returns ``(costs (N, K), unknowns (N, K, 7))``
    in ``theta``'s dtype and device: each pixel's squared-residual sum (``pixel_cost``) and its
    refitted unknowns at each grid value.

    Raises:
        ValueError: a grid value outside ``[R_MIN, R_MAX]``, or an empty grid.
    """
    if len(grid) == 0 or any(not R_MIN <= float(r) <= R_MAX for r in grid):
        raise ValueError(f"grid: expected roughness values in [{R_MIN}, {R_MAX}], got {list(grid)}")
    start = theta[rows]
    held = torch.zeros_like(start, dtype=torch.bool)
    held[:, 4] = True
    costs, fits = [], []
    for r in grid:
        s = start.clone()
        s[:, 4] = logit(torch.tensor(float(r), dtype=theta.dtype), R_MIN, R_MAX)
        t, c = refit_pixels(data, theta, metal, rows, [s], data.train_idx, model, iters, held=held)
        costs.append(c[:, 0])
        fits.append(t)
    return torch.stack(costs, 1), torch.stack(fits, 1)


def pooled_minimum(grid: Sequence[float], costs: Tensor) -> tuple[float, int]:
    """Where a pooled profile is lowest: ``(roughness, grid index)``.

    ``costs (N, K)`` the profiles of pixels sharing a material (:func:`roughness_profile`) on
    the ``K`` values of ``grid`` (ascending); their sum over the pixels is the material's
    profile. The minimum is refined by the parabola through the lowest grid value and its two
    neighbours (in map units; the grid value itself at an end of the grid, or where the three
    are not convex). Non-finite costs count as +inf.
    """
    total = torch.nan_to_num(costs.double(), nan=float("inf")).sum(0)
    k = int(total.argmin())
    g = [float(x) for x in grid]
    if 0 < k < len(g) - 1 and bool(torch.isfinite(total[k - 1:k + 2]).all()):
        (x0, x1, x2), (y0, y1, y2) = g[k - 1:k + 2], [float(v) for v in total[k - 1:k + 2]]
        # the vertex of the parabola through three points (uneven spacing)
        den = (x0 - x1) * (x0 - x2) * (x1 - x2)
        a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
        b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
        if a > 0:
            return min(max(-b / (2 * a), x0), x2), k
    return g[k], k
