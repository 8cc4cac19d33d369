"""The solver's Gauss–Newton terms through the fused normal-equations operator.

``gauss_newton`` (and through it ``lm_step`` and ``refit_pixels``) and ``soft_lm`` (the
soft-metal stage) linearise the principled fit in one pass of
``torch.ops.torchbrdf.normal_equations``; the unfused path (``fit_jacobian`` of the residual's
forward-mode Jacobian, then batched products) stays as the fallback and is the reference here,
in float64, with non-finite residuals and Jacobians.
"""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.kernels import build
from torchbrdf.recovery import lm, soft_metal
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData

from tests.recovery.recovery_fixtures import flat_level

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")
needs_c = pytest.mark.skipif(not build.available(), reason="needs the C kernels")


@pytest.fixture
def op_calls(monkeypatch):
    """The linearisations through the fused operator (counted, then run): its calls with
    unknowns (those with none are the log residuals' evaluations)."""
    calls = []
    real = ne_ops.normal_equations_op

    def spy(*args):
        if args[-1].split("|")[4] != "0":
            calls.append(args[-1])
        return real(*args)

    monkeypatch.setattr(ne_ops, "normal_equations_op", spy)
    return calls


def _level(dtype=torch.float64):
    data, theta, metal = flat_level(size=6, lights=5, normal_tilt_deg=10.0)
    gen = torch.Generator().manual_seed(1)
    theta = (theta + 0.4 * torch.randn(theta.shape, generator=gen)).to(dtype)
    metal = metal.clone().to(dtype)
    metal[::3] = 1.0
    for k in ("points", "camera", "pos", "inten", "inten_stated", "pos_stated"):
        setattr(data, k, getattr(data, k).to(dtype))
    log_obs = data.log_obs.to(dtype).clone()  # (L, P, 3)
    log_obs[1, 7, 0] = float("nan")  # residual NaN: its Jacobian row is finite
    log_obs[2, 9, 1] = float("inf")  # residual -inf
    log_obs[0, 11, 2] = float("-inf")  # residual +inf
    data.log_obs = log_obs
    theta[4, 5] = float("nan")  # every residual and derivative of pixel 4 NaN
    return data, theta, metal


def _eager(fn):
    torchbrdf.set_fast_path(False)
    try:
        return fn()
    finally:
        torchbrdf.set_fast_path(None)


def _unfused(fn, monkeypatch):
    """``fn()`` on the solver's fallback: the Jacobian by forward mode, then its products."""
    with monkeypatch.context() as m:
        m.setattr(LevelData, "normal_equations", lambda *a, **k: None)
        return fn()


@needs_c
def test_gauss_newton_through_the_operator_equals_the_unfused_normal_equations(op_calls, monkeypatch):
    data, theta, metal = _level()
    idx = data.train_idx
    r_ref, jtj_ref, jtr_ref = _unfused(lambda: lm.gauss_newton(data, theta, metal, idx, "principled"),
                                       monkeypatch)
    assert not op_calls  # the reference is the unfused path
    r, jtj, jtr = lm.gauss_newton(data, theta, metal, idx, "principled")
    assert len(op_calls) == 1  # one fused pass, no Jacobian
    fused = data.normal_equations(theta, metal, idx, "principled", 7)
    assert fused is not None and len(op_calls) == 2
    # residuals as they come: NaN, ±inf where the targets make them so
    torch.testing.assert_close(r, r_ref, rtol=1e-10, atol=1e-12, equal_nan=True)
    assert r[7, 3].isnan() and r[9, 7] == float("-inf") and r[11, 2] == float("inf")
    torch.testing.assert_close(fused[1], (r_ref * r_ref).sum(-1), rtol=1e-10, atol=1e-12, equal_nan=True)
    # non-finite Jacobian entries and residuals count as 0 in JᵀJ and Jᵀr
    assert torch.isfinite(jtj).all() and torch.isfinite(jtr).all()
    assert (jtj[4] == 0).all() and (jtr[4] == 0).all()
    assert jtj[7].abs().max() > 1e-3 and jtr[7].abs().max() > 1e-6  # the NaN residual's pixel still counts
    scale = float(jtj_ref.abs().max())
    torch.testing.assert_close(jtj, jtj_ref, rtol=1e-10, atol=1e-12 * scale)
    torch.testing.assert_close(jtr, jtr_ref, rtol=1e-10, atol=1e-12 * float(jtr_ref.abs().max()))
    torch.testing.assert_close(fused[2], jtj, rtol=0, atol=0)


@needs_c
def test_float32_fused_normal_equations_stay_close_to_the_eager_ones(op_calls):
    data, theta, metal = _level(torch.float32)
    theta[4, 5] = 0.1
    idx = data.train_idx
    r_ref, jtj_ref, jtr_ref = _eager(lambda: lm.gauss_newton(data, theta, metal, idx, "principled"))
    r, jtj, jtr = lm.gauss_newton(data, theta, metal, idx, "principled")
    assert len(op_calls) == 1 and op_calls[0].split("|")[6] == "c"  # the float32 C kernel
    torch.testing.assert_close(r, r_ref, rtol=1e-4, atol=1e-5, equal_nan=True)
    torch.testing.assert_close(jtj, jtj_ref, rtol=1e-3, atol=1e-5 * float(jtj_ref.abs().max()))
    torch.testing.assert_close(jtr, jtr_ref, rtol=1e-3, atol=1e-5 * float(jtr_ref.abs().max()))


@needs_c
def test_lm_step_and_the_refit_take_the_operator(op_calls, monkeypatch):
    data, theta, metal = _level()
    theta[4, 5] = 0.1
    lam = torch.full((theta.shape[0], 1), 1e-2, dtype=theta.dtype)
    cfg = Settings(seed=0)
    extra: dict = {}
    out = lm.lm_step(data, theta, metal, lam, cfg, 1.0, extra=extra)
    assert len(op_calls) == 1 and extra["residual"].shape == (theta.shape[0], 3 * len(data.train_idx))
    ref = _unfused(lambda: lm.lm_step(data, theta, metal, lam, cfg, 1.0), monkeypatch)
    torch.testing.assert_close(out[0], ref[0], rtol=1e-8, atol=1e-8)
    rows = torch.tensor([1, 2, 5])
    lm.refit_pixels(data, theta, metal, rows, [theta[rows]], data.train_idx, "principled", iters=2)
    assert len(op_calls) == 3  # one linearisation per iteration


@needs_c
def test_soft_lm_through_the_operator_equals_its_jacobian_path(op_calls, monkeypatch):
    data, theta, metal = _level()
    theta[4, 5] = 0.1
    rows = torch.arange(0, theta.shape[0], 2)
    args = (data, theta, metal, rows, data.train_idx, "principled", 1e-3, 0.0)
    got = soft_metal.soft_metal_fit(*args, iters=3, starts=(0.5,))
    n_fused = len(op_calls)
    assert n_fused >= 3  # the free fit (8 unknowns) and the held reference (7)
    assert {cfg.split("|")[4] for cfg in op_calls} == {"8", "7"}
    monkeypatch.setattr(LevelData, "normal_equations", lambda *a, **k: None)  # the fallback
    ref = soft_metal.soft_metal_fit(*args, iters=3, starts=(0.5,))
    assert len(op_calls) == n_fused
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-8)


def test_the_ggx_model_takes_the_kernel_and_the_eager_path_agrees(op_calls):
    data, theta, metal = _level()
    theta[4, 5] = 0.1
    fused = data.normal_equations(theta, metal, data.train_idx, "svbrdf_ggx", 7)
    assert fused is not None and op_calls
    op_calls.clear()
    r, jtj, jtr = lm.gauss_newton(data, theta, metal, data.train_idx, "svbrdf_ggx", fused=False)
    assert not op_calls
    torch.testing.assert_close(fused[2], jtj, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(fused[3], jtr, rtol=1e-9, atol=1e-9)


def test_other_dtypes_take_the_eager_path(op_calls):
    data, theta, metal = _level()
    assert _eager(lambda: data.normal_equations(theta, metal, data.train_idx, "principled", 7)) is None
    assert not op_calls
