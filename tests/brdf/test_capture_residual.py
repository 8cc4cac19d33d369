"""The capture residual's dispatch: the light-loop kernel gives the per-lane kernel's bits."""

from __future__ import annotations

import math

import pytest
import torch

from torchbrdf.brdf import capture_residual
from torchbrdf.kernels import build
from torchbrdf.kernels import normal_eq_ops
from torchbrdf.kernels.ops import capture_fast

pytestmark = pytest.mark.skipif(not build.available(), reason="no C compiler for the fused kernels")

EPS = 1e-3


def _case(n: int, lights: int, dtype: torch.dtype, seed: int, extra: bool = False):
    """Recovery-like inputs (a plane under a ring of lights, decoded maps) or, with ``extra``,
    every lobe on with per-pixel maps and targets far from the model (large residuals)."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.cat([torch.rand(n, 2, generator=g) * 2 - 1, torch.zeros(n, 1)], -1).to(dtype)
    ang = torch.arange(lights) * 2 * math.pi / lights
    lpos = torch.stack([1.5 * torch.cos(ang), 1.5 * torch.sin(ang), 2.0 + 0 * ang], -1).to(dtype)
    lint = (2.0 + 4 * torch.rand(lights, 3, generator=g)).to(dtype)
    normal = torch.randn(n, 3, generator=g) * 0.3
    normal[:, 2] = 1.0
    normal = (normal / normal.norm(dim=-1, keepdim=True)).to(dtype)
    params = {"base_color": torch.rand(n, 3, generator=g).to(dtype),
              "specular": torch.rand(n, 1, generator=g).to(dtype),
              "roughness": (0.02 + torch.rand(n, 1, generator=g)).clamp(max=1).to(dtype),
              "metallic": (torch.rand(n, 1, generator=g) > 0.6).to(dtype)}
    if extra:
        params.update({k: torch.rand(n, 1, generator=g).to(dtype)
                       for k in ("subsurface", "sheen", "clearcoat")})
        params["clearcoat_gloss"] = 0.3
    log_obs = (torch.randn(n, lights, 3, generator=g) * (4.0 if extra else 0.5) - 2).to(dtype)
    cam = torch.tensor([0.1, -0.2, 3.0], dtype=dtype)
    return normal, pts, cam, lpos, lint, params, log_obs


def _per_lane(inputs):
    c, active, need_tint, frame, backend, _ = inputs
    return capture_fast(c, active, need_tint, frame, backend)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("extra", [False, True])
def test_light_loop_residual_is_bit_identical(dtype, extra, monkeypatch):
    calls = []
    real = normal_eq_ops.normal_equations
    monkeypatch.setattr(normal_eq_ops, "normal_equations", lambda *a, **k: calls.append(1) or real(*a, **k))
    for seed, (n, lights) in enumerate([(1, 1), (77, 5), (3000, 17)]):
        inputs = capture_residual.residual_inputs(*_case(n, lights, dtype, seed, extra), EPS, any_size=True)
        assert inputs[4] == "c"
        got = capture_residual.log_residual(inputs)
        assert got.shape == (n, lights, 3) and got.dtype == dtype
        assert torch.equal(got, _per_lane(inputs))
    assert len(calls) == 3  # each went through the light-loop kernel


def test_light_loop_residual_non_finite_targets_and_empty():
    normal, pts, cam, lpos, lint, params, log_obs = _case(40, 6, torch.float32, 7)
    log_obs[3, 2, 0], log_obs[5, 1, 1], log_obs[9, 0, 2] = float("nan"), float("inf"), float("-inf")
    params["roughness"][11] = 0.0  # a degenerate lobe
    inputs = capture_residual.residual_inputs(normal, pts, cam, lpos, lint, params, log_obs, EPS,
                                              any_size=True)
    got, want = capture_residual.log_residual(inputs), _per_lane(inputs)
    assert torch.equal(got.isnan(), want.isnan()) and got.isnan().any()
    assert torch.equal(got.nan_to_num(), want.nan_to_num())
    empty = capture_residual.residual_inputs(*(t[:0] for t in (normal, pts)), cam, lpos, lint,
                                             {k: v[:0] for k, v in params.items()}, log_obs[:0], EPS,
                                             any_size=True)
    assert capture_residual.log_residual(empty).shape == (0, 6, 3)


def test_inputs_the_light_loop_does_not_take_stay_per_lane(monkeypatch):
    """A gradient, a tint, a broadcast map: the per-lane kernel, as before."""
    monkeypatch.setattr(normal_eq_ops, "normal_equations", lambda *a, **k: pytest.fail("light loop taken"))
    normal, pts, cam, lpos, lint, params, log_obs = _case(50, 4, torch.float64, 3)

    def residual(p):
        inputs = capture_residual.residual_inputs(normal, pts, cam, lpos, lint, p, log_obs, EPS,
                                                  any_size=True)
        return capture_residual.log_residual(inputs)

    assert residual({**params, "roughness": params["roughness"].clone().requires_grad_()}).requires_grad
    residual({**params, "sheen": 0.5, "sheen_tint": 0.9})
    residual({**params, "specular": params["specular"][:1]})


def test_forward_mode_keeps_the_differentiable_kernel():
    """Under ``torch.func.jvp`` and dual tensors the residual's tangent is the per-lane kernel's
    (the light-loop kernel has no derivative: taken there, the tangent would be lost)."""
    normal, pts, cam, lpos, lint, params, log_obs = _case(60, 5, torch.float64, 5)
    rough = params.pop("roughness")

    def res(r):
        inputs = capture_residual.residual_inputs(normal, pts, cam, lpos, lint, {**params, "roughness": r},
                                                  log_obs, EPS, any_size=True)
        return capture_residual.log_residual(inputs)

    inputs = capture_residual.residual_inputs(normal, pts, cam, lpos, lint, {**params, "roughness": rough},
                                              log_obs, EPS, any_size=True)
    with torch.enable_grad():
        r0 = rough.clone().requires_grad_()
        want = torch.autograd.grad(res(r0).sum(), r0)[0]
    _, tangent = torch.func.jvp(res, (rough,), (torch.ones_like(rough),))
    assert tangent.abs().sum() > 0
    torch.testing.assert_close(tangent.sum((1, 2))[:, None], want, rtol=1e-9, atol=1e-12)
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        dual = res(fwAD.make_dual(rough, torch.ones_like(rough)))
        assert torch.equal(fwAD.unpack_dual(dual).tangent, tangent)
    assert torch.equal(res(rough), _per_lane(inputs))
