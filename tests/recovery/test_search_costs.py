"""The search's data costs from the fused cost kernel (``LevelData.data_cost``), against the residuals' squares."""

import pytest
import torch

from torchbrdf.kernels import build
from torchbrdf.recovery import search
from torchbrdf.recovery.lm import pixel_cost

from tests.recovery.recovery_fixtures import flat_level


def _state(dtype, size=12, lights=6):
    data, theta, metal = flat_level(size=size, lights=lights)
    gen = torch.Generator().manual_seed(0)
    theta = theta + 0.6 * torch.randn(theta.shape, generator=gen)
    return data, theta.to(dtype), metal.to(dtype)


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_data_cost_is_the_residuals_summed_squares(dtype, monkeypatch):
    data, theta, metal = _state(dtype)
    if dtype == torch.float64:
        data = data.subset(torch.arange(theta.shape[0]))
        data.points = data.points.double()
        data.camera, data.pos, data.inten = (t.double() for t in (data.camera, data.pos, data.inten))
        data.log_obs = data.log_obs.double()
    rows = torch.tensor([5, 0, 5, 77, 143])  # repeats and any order
    calls = []
    real = search.LevelData.data_cost
    monkeypatch.setattr(search.LevelData, "data_cost", lambda *a, **k: calls.append(1) or real(*a, **k))
    for r in (None, rows):
        th, mt = (theta, metal) if r is None else (theta[r], metal[r])
        got = search._data_cost(data, th, mt, "principled", r)
        ref = pixel_cost(data.residual(th, mt, data.train_idx, "principled", rows=r).double())
        assert got.dtype == dtype and got.shape == ref.shape
        torch.testing.assert_close(got.double(), ref, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
        assert (ref > 1e-3).all()
    assert calls and real(data, theta, metal, data.train_idx) is not None  # the fused kernel gave them


def test_a_non_finite_residual_costs_inf():
    # (+inf residuals used to give the dtype's largest finite cost; a cost is +inf there, as pixel_cost)
    data, theta, metal = _state(torch.float32)
    log_obs = data.log_obs.clone()
    log_obs[2, 7, 1] = float("-inf")  # r = +inf at pixel 7
    log_obs[3, 9, 0] = float("nan")
    data.log_obs = log_obs
    got = search._data_cost(data, theta, metal, "principled", None)[:, 0]
    assert got[7] == float("inf") and got[9] == float("inf")
    assert got[[0, 1, 8, 10]].isfinite().all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_subset_cost_bound_from_summed_squares_stays_below_any_rounding(dtype):
    # the bound from the cost kernel's sums (float64 sums in the dtype) as from the residuals
    gen = torch.Generator().manual_seed(10)
    r = (torch.randn(500, 12, generator=gen) * torch.logspace(-6, 1, 500)[:, None]).to(dtype)
    tol = search.BOUND_ULPS * torch.finfo(dtype).eps
    sums = (r.double() ** 2).sum(-1, keepdim=True).to(dtype)
    bound = search.subset_cost_bound(sums, tol, 12)
    worst = r.abs() - tol * (1 + r.abs())  # every residual rounded as far towards 0 as allowed
    assert bool((bound[:, 0] <= (worst.clamp(min=0) ** 2).sum(-1)).all())
    # (near 0 the bound cancels: an absolute tolerance well below tol there)
    torch.testing.assert_close(bound, search.subset_cost_bound(r, tol), rtol=8 * torch.finfo(dtype).eps,
                               atol=1e-2 * tol)
    sums[3, 0] = float("inf")  # (the kernel's non-finite cost: above any finite bound)
    assert search.subset_cost_bound(sums, tol, 12)[3, 0] >= torch.finfo(dtype).max
