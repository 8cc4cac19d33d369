"""The roughness profile likelihood and the silent-region diagnostic built on it.

A pixel's profile is its data cost with the roughness held at each grid value and its other
unknowns refitted; summed over pixels of one material it is the material's profile, whose
minimum is the roughness they support together.
"""

import math

import pytest
import torch

from torchbrdf.bench import silent_profile as sp
from torchbrdf.bench.recovery_panel import PanelCase
from torchbrdf.recovery.params import R_MAX, R_MIN, logit
from torchbrdf.recovery.profile import pooled_minimum, roughness_profile

from tests.recovery.recovery_fixtures import flat_level

GRID = (0.1, 0.2, 0.3, 0.4, 0.6)


def test_the_profile_holds_roughness_refits_the_rest_and_pools_to_the_truth():
    """A glossy dielectric (roughness 0.3, noise-free) started at roughness 0.6 with a wrong specular:
    the held roughness is each grid value exactly, the refit at the truth's value fits to the noise
    floor where the unrefitted start does not, and the pooled minimum is the truth's roughness.
    Fails without the hold (every column the same fit), without the refit (the wrong specular
    stays: the cost at 0.3 is that of the start), or with a pooled argmax."""
    data, theta, metal = flat_level(size=8, lights=8)
    start = theta.clone()
    start[:, 3] += 1.5  # specular off its truth
    start[:, 4] = logit(torch.tensor(0.6), R_MIN, R_MAX)
    rows = torch.arange(theta.shape[0])
    with torch.no_grad():
        costs, fits = roughness_profile(data, start, metal, rows, GRID)
        unrefitted, _ = roughness_profile(data, start, metal, rows, GRID, iters=0)
    assert costs.shape == (theta.shape[0], len(GRID)) and fits.shape == (theta.shape[0], len(GRID), 7)
    for k, r in enumerate(GRID):
        assert torch.equal(fits[:, k, 4], torch.full_like(fits[:, k, 4], float(logit(torch.tensor(r), R_MIN, R_MAX))))
    at_truth = costs[:, GRID.index(0.3)].sum()
    assert at_truth < 1e-3 * unrefitted[:, GRID.index(0.3)].sum()
    assert (costs.sum(0) > 10 * at_truth).sum() == len(GRID) - 1  # every other value fits worse
    r, k = pooled_minimum(GRID, costs)
    assert GRID[k] == 0.3 and abs(r - 0.3) < 0.05  # the parabola: within half a grid cell


def test_the_pooled_minimum_is_the_parabola_vertex_on_an_uneven_grid():
    """Exact for a quadratic sampled unevenly; the grid value at an end of the grid; non-finite costs
    count as +inf."""
    grid = (0.1, 0.15, 0.3, 0.5, 0.9)
    quad = torch.tensor([[(g - 0.27) ** 2 for g in grid]], dtype=torch.float64)
    r, k = pooled_minimum(grid, torch.cat((quad, 2 * quad)))
    assert k == 2 and r == pytest.approx(0.27, abs=1e-9)
    r, k = pooled_minimum(grid, torch.tensor([[(g - 0.05) ** 2 for g in grid]]))
    assert (r, k) == (0.1, 0)
    costs = torch.tensor([[1.0, float("nan"), 0.5, 0.7, 2.0]])
    r, k = pooled_minimum(grid, costs)
    assert (r, k) == (0.3, 2)  # its left neighbour is not finite: no parabola


def test_a_grid_outside_the_roughness_range_is_refused():
    data, theta, metal = flat_level(size=4, lights=8)
    with pytest.raises(ValueError, match="grid"):
        roughness_profile(data, theta, metal, torch.arange(4), (0.01, 0.5))
    with pytest.raises(ValueError, match="grid"):
        roughness_profile(data, theta, metal, torch.arange(4), ())


def test_each_pixels_posterior_mean_weighs_its_likelihood_and_the_cells():
    """A flat profile gives the uniform prior's mean over the grid's cells (map units); a sharp one,
    its minimum."""
    grid = (0.1, 0.2, 0.4, 0.8)
    flat = torch.zeros(1, 4)
    # cells [0.1, 0.15], [0.15, 0.3], [0.3, 0.6], [0.6, 0.8]: widths 0.05, 0.15, 0.3, 0.2
    expected = (0.1 * 0.05 + 0.2 * 0.15 + 0.4 * 0.3 + 0.8 * 0.2) / 0.7
    assert float(sp.posterior_mean(grid, flat, 1.0)[0]) == pytest.approx(expected)
    sharp = torch.tensor([[100.0, 0.0, 100.0, 100.0]])
    assert float(sp.posterior_mean(grid, sharp, 1.0)[0]) == pytest.approx(0.2, abs=1e-9)
    # No finite cost: no likelihood, the prior's mean; a non-finite cell among finite ones weighs 0.
    inf, nan = float("inf"), float("nan")
    means = sp.posterior_mean(grid, torch.tensor([[inf, nan, inf, inf], [inf, 0.0, nan, 100.0]]), 1.0)
    assert float(means[0]) == pytest.approx(expected) and float(means[1]) == pytest.approx(0.2, abs=1e-9)


def test_material_regions_are_the_large_sets_of_one_truth_value():
    spec = torch.full((1, 16, 16), 0.35)
    spec[:, :8, :8] = 0.5
    spec[:, 0, 15] = 0.7  # one pixel (under 1/64 of the image): a blend, not a material
    regions = sp.material_regions(spec)
    assert [r.numel() for r in regions] == [191, 64]
    assert bool((spec.reshape(-1)[regions[1]] == 0.5).all())


def test_report_cases_are_refused():
    with pytest.raises(ValueError, match="report case"):
        sp.silent_profile(PanelCase("lacquer", 2, 17, "exact_fresnel", False), size=16)
    assert sp.main(["--case", "not a case"]) == 2


def test_the_diagnostic_runs_on_a_tuning_case():
    """End to end at 16²: a lacquer (one material) is one region, profiled and scored three ways."""
    out = sp.silent_profile(PanelCase("lacquer", 1, 8, "principled", True), size=16)
    assert [r["pixels"] for r in out["regions"]] == [256]
    r = out["regions"][0]
    assert sp.GRID[0] <= r["pooled"] <= sp.GRID[-1] and sp.GRID[0] <= r["posterior_mean"] <= sp.GRID[-1]
    assert abs(r["true"] - r["fitted"]) < 0.1
    for key in ("scores", "oracle_scores", "posterior_scores"):
        assert math.isfinite(out[key]["roughness_rmse"]) and math.isfinite(out[key]["heldout_worst_db"])
