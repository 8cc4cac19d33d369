"""The light-loop kernel's cost-only variant (``torch.ops.torchbrdf.data_cost``) against the residuals' squares.

Per pixel the kernel sums ``r²`` over every light and channel of the capture's log residual in
float64 and writes a non-finite sum as +inf. The reference is ``pixel_cost`` of the eager
float64 residuals (``log_residual_points`` of ``decode`` on the eager backend); float32 inputs
are compared with their float64 reference (the residuals' own rounding) and with the
float32 residuals' summed squares (the summation order).
"""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.capture.synthetic import log_residual_points
from torchbrdf.kernels import build
from torchbrdf.kernels.normal_eq_ops import data_cost, make_cfg
from torchbrdf.recovery.lm import pixel_cost
from torchbrdf.recovery.params import decode

from tests.kernels.normal_eq_cases import EPS, capture_case as _capture, interpreted_triton, op_calls

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")
needs_c = pytest.mark.skipif(not build.available(), reason="needs the C kernels")


def _residuals(theta, metal, points, cam, lpos, lint, log_obs, backend=None):
    """The log residuals ``(N, 3 L)`` on ``backend`` (None: the automatic one)."""
    old = torchbrdf.get_backend()
    torchbrdf.set_backend(backend)
    try:
        p = decode(theta, metal)
        return log_residual_points(p["normal"], points, cam, lpos, lint, p, log_obs, EPS).reshape(theta.shape[0], -1)
    finally:
        torchbrdf.set_backend(None if old == "auto" else old)


def _cost(theta, metal, points, cam, lpos, lint, log_obs):
    return data_cost(decode(theta, metal), points, cam, lpos, lint, log_obs, EPS)


def _check(case, got):
    """``got`` against the float64 eager reference; float32 also against its own residuals."""
    ref = pixel_cost(_residuals(*[t.double() for t in case], backend="eager"))
    assert got.shape == ref.shape and got.dtype == case[-1].dtype
    if got.dtype == torch.float64:
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=0)
    else:
        # the float32 residuals round to ~1e-6 of their size; the float64 sum adds no more
        torch.testing.assert_close(got.double(), ref, rtol=2e-5, atol=1e-6)
        own = _residuals(*case).double()
        # the same float32 residuals' squares summed exactly (float64), to ~M ulps of the sum
        torch.testing.assert_close(got.double(), (own * own).sum(-1, keepdim=True), rtol=1e-5, atol=1e-7)
    assert (ref > 1e-2).all()  # not vacuous: every pixel has a cost to get wrong


@needs_c
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("lights", [1, 17])
def test_c_kernel_matches_the_residuals_squares(dtype, lights):
    # 70 pixels: a block of 64 and a partial one (masked lanes)
    case = [t.to(dtype) for t in _capture(70, lights, seed=lights)]
    got = _cost(*case)
    assert any(k[0] == "c" and k[1][9] and v is not None for k, v in ne_ops._kernels.items())  # the kernel ran
    _check(case, got)


@needs_c
def test_a_light_or_pixel_mixed_up_fails():
    # the sums over lights must read each light's own uniforms and targets: the same case with
    # two lights' targets swapped, or one pixel's, costs something else
    case = _capture(9, 17, seed=3)
    got = _cost(*case)
    swapped = [t.clone() for t in case]
    swapped[-1][:, [2, 5]] = case[-1][:, [5, 2]]
    assert not torch.allclose(_cost(*swapped), got, rtol=1e-6)
    shifted = [t.clone() for t in case]
    shifted[-1] = case[-1].roll(1, 0)
    assert ((_cost(*shifted) - got).abs() > 1e-6 * got).all()


def _non_finite_case():
    """NaN, -inf and +inf residuals at pixels 2, 3, 5 (their targets); a NaN and an infinite
    residual at pixel 6."""
    case = _capture(10, 3, seed=6)
    case[-1][2, 1, 0] = float("nan")
    case[-1][3, 0, 2] = float("inf")  # r = -inf
    case[-1][5, 2, 1] = float("-inf")  # r = +inf
    case[-1][6, 0, 0], case[-1][6, 2, 2] = float("nan"), float("inf")
    return case


def _check_non_finite(got):
    inf = float("inf")
    assert (got[[2, 3, 5, 6], 0] == inf).all()
    finite = [0, 1, 4, 7, 8, 9]
    assert got[finite].isfinite().all()
    ref = pixel_cost(_residuals(*_non_finite_case(), backend="eager"))
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=0)


@needs_c
def test_c_kernel_writes_a_non_finite_cost_as_inf():
    _check_non_finite(_cost(*_non_finite_case()))


def test_eager_fallback_is_pixel_cost_of_the_residuals(monkeypatch):
    monkeypatch.setattr(ne_ops, "_c_kernel", lambda spec: None)
    _check_non_finite(_cost(*_non_finite_case()))
    case = _capture(12, 4, seed=2)
    _check(case, _cost(*case))


def test_triton_kernel_matches_under_the_interpreter(monkeypatch, tmp_path):
    case = [t.float() for t in _capture(70, 5, seed=4)]
    (got32, got_nf), built = interpreted_triton(
        monkeypatch, tmp_path, lambda: (_cost(*case), _cost(*_non_finite_case())))
    assert built and all(spec.cost_only and hit is not None for spec, hit in built)  # the Triton kernels ran
    _check(case, got32)
    _check_non_finite(got_nf)


@needs_c
def test_operator_passes_opcheck_and_refuses_other_configurations():
    case = _capture(8, 2, seed=3)
    calls = op_calls("data_cost_op", lambda: _cost(*case))
    real = ne_ops.data_cost_op
    torch.library.opcheck(torch.ops.torchbrdf.data_cost, calls[0])
    tensors, floats, uniforms, log_obs, cfg = calls[0]
    not_cost = make_cfg(*[f.split(",") if f else [] for f in cfg.split("|")[:3]], False, 0, [])
    with pytest.raises(ValueError, match="cost-only"):
        real(tensors, floats, uniforms, log_obs, not_cost)


@needs_c
def test_compiles_in_one_graph():
    # the entry point traces to the operator with no graph break (fullgraph) and the compiled
    # call returns the eager call's costs (the fake implementation's shapes: opcheck above)
    case = [t.float() for t in _capture(16, 3, seed=5)]
    p = decode(case[0], case[1])

    def cost(p, points, cam, lpos, lint, log_obs):
        return data_cost(p, points, cam, lpos, lint, log_obs, EPS)

    torch._dynamo.reset()
    got = torch.compile(cost, backend="aot_eager", fullgraph=True)(p, *case[2:])
    torch.testing.assert_close(got, cost(p, *case[2:]), rtol=0, atol=0)


def test_bad_inputs_name_the_argument():
    theta, metal, points, cam, lpos, lint, log_obs = _capture(4, 2)
    with pytest.raises(ValueError, match="log_obs"):
        _cost(theta, metal, points, cam, lpos, lint, log_obs[:, :, :2])
    with pytest.raises(ValueError, match="'pos'"):
        _cost(theta, metal, points.float(), cam, lpos, lint, log_obs)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_other_dtypes_are_refused_before_a_kernel_runs(dtype):
    # the kernels read and write float or double: a half tensor would be read past its end
    # and the (N, 1) output written past it
    case = [t.to(dtype) for t in _capture(4, 2)]
    with pytest.raises(ValueError, match="data_cost: log_obs must be float32 or float64"):
        _cost(*case)
    names, tensors, floats, uniforms, head = ne_ops._operator_inputs("test", decode(*_capture(4, 2)[:2]),
                                                                     *_capture(4, 2)[2:], EPS)
    cfg = make_cfg(*head, 0, [], cost_only=True)
    with pytest.raises(ValueError, match="data_cost_op: log_obs"):
        torch.ops.torchbrdf.data_cost([t.to(dtype) for t in tensors], floats, uniforms.to(dtype),
                                      case[-1], cfg)


def test_inputs_the_kernel_would_read_past_are_refused():
    # a light count or channel count other than log_obs' and cfg's: the kernel indexes them
    # without bounds, so the call must fail rather than read other memory
    theta, metal, points, cam, lpos, lint, log_obs = _capture(4, 3)
    with pytest.raises(ValueError, match="light_pos must be \\(3, 3\\)"):
        _cost(theta, metal, points, cam, lpos[:1], lint[:1], log_obs)
    with pytest.raises(ValueError, match="light_int must be \\(3, 3\\)"):
        _cost(theta, metal, points, cam, lpos, lint[:2], log_obs)
    p = decode(theta, metal)
    with pytest.raises(ValueError, match="'base_color' must be \\(4, 3\\)"):
        data_cost({**p, "base_color": p["base_color"][:, :1]}, points, cam, lpos, lint, log_obs, EPS)
    names, tensors, floats, uniforms, head = ne_ops._operator_inputs("test", p, points, cam, lpos, lint,
                                                                     log_obs, EPS)
    cfg = make_cfg(*head, 0, [], cost_only=True)
    with pytest.raises(ValueError, match="data_cost_op: uniforms"):
        torch.ops.torchbrdf.data_cost(tensors, floats, uniforms[:-6], log_obs, cfg)
    bad = [t[:, :1] if name == "base_color" else t for name, t in zip(names, tensors)]
    with pytest.raises(ValueError, match="data_cost_op: tensor 'base_color'"):
        torch.ops.torchbrdf.data_cost(bad, floats, uniforms, log_obs, cfg)


def test_generated_float32_cost_kernels_sum_in_float64():
    # (the float32 residuals are widened before squaring: the accumulator is a double in C and
    # a float64 tensor in Triton)
    dtype = torch.float32
    from torchbrdf.kernels.codegen_normal_eq import generate, generate_triton

    case = [t.to(dtype) for t in _capture(4, 2)]
    p = decode(case[0], case[1])
    cfg = make_cfg(*ne_ops._operator_inputs("test", p, *case[2:], EPS)[4], 0, [], cost_only=True)
    spec, _ = ne_ops._parse(cfg, dtype)
    assert "double a_out_0[" in generate(spec)
    assert "a_out_0 = tl.full([BLOCK], 0.0, tl.float64)" in generate_triton(spec)
