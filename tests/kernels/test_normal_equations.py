"""The fused normal-equations pass (kernels/codegen_normal_eq.py) against jacfwd of the torch residual.

Per pixel the kernel sums, over the lights, the data cost Σ r², JᵀJ and Jᵀr of the recovery's
log residuals in the recovery's parametrisation (the decode's Jacobian given as tangents).
The reference differentiates the eager residual (``log_residual_points`` of ``decode``) with
``torch.func.jacfwd`` in float64.
"""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.capture.synthetic import log_residual_points
from torchbrdf.kernels import build
from torchbrdf.kernels.normal_eq_ops import normal_equations, unpack_jtj
from torchbrdf.recovery.params import decode

from tests.kernels.normal_eq_cases import EPS, capture_case as _capture, interpreted_triton, op_calls

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")


def _reference(theta, metal, points, cam, lpos, lint, log_obs):
    """cost, JᵀJ (N, K, K), Jᵀr with J from torch.func.jacfwd of the eager residual."""
    r, J = _jacobian(theta, metal, points, cam, lpos, lint, log_obs)
    return (r * r).sum(-1), J.transpose(1, 2) @ J, (J.transpose(1, 2) @ r[..., None])[..., 0]


def _jacobian(theta, metal, points, cam, lpos, lint, log_obs):
    """The eager residuals (N, M) and their Jacobian (N, M, K) by torch.func.jacfwd."""
    def res(th, me, pt, lo):  # one pixel
        p = decode(th[None], me[None])
        return log_residual_points(p["normal"], pt[None], cam, lpos, lint, p, lo[None], EPS).reshape(-1)

    old = torchbrdf.get_backend()
    torchbrdf.set_backend("eager")
    try:
        r = torch.vmap(res)(theta, metal, points, log_obs)
        J = torch.vmap(torch.func.jacfwd(res))(theta, metal, points, log_obs)
    finally:
        torchbrdf.set_backend(None if old == "auto" else old)
    return r, J


def _fused(theta, metal, points, cam, lpos, lint, log_obs, pattern=None):
    K = theta.shape[1]
    eye = torch.eye(K, dtype=theta.dtype)[:, None].expand(K, theta.shape[0], K)
    p, dp = torch.func.vmap(lambda t: torch.func.jvp(lambda x: decode(x, metal), (theta,), (t,)),
                            out_dims=(None, 0))(eye)
    return normal_equations(p, {k: v for k, v in dp.items() if k != "metallic"}, points, cam, lpos, lint,
                            log_obs, EPS, pattern)


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
def test_c_kernel_matches_jacfwd_float64_dielectric_and_metal():
    case = _capture(40, 5, torch.float64)
    cost, jtj, jtr = _fused(*case)
    assert any(k[0] == "c" and v is not None for k, v in ne_ops._kernels.items())  # the kernel ran
    rc, rjtj, rjtr = _reference(*case)
    K = 7
    assert jtj.shape == (40, K * (K + 1) // 2) and jtr.shape == (40, K)
    torch.testing.assert_close(cost, rc, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(unpack_jtj(jtj, K), rjtj, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(jtr, rjtr, rtol=1e-10, atol=1e-10)
    metal = case[1][:, 0] == 1
    assert metal.any() and (~metal).any()
    assert rjtj[metal].abs().max() > 1e-3 and rjtj[~metal].abs().max() > 1e-3  # not vacuous


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
def test_known_pattern_equals_read_pattern_and_float32_is_close():
    case = _capture(16, 3, torch.float64, seed=1)
    pattern = {"base_color": [(0, 0), (1, 1), (2, 2)], "specular": [(3, 0)], "roughness": [(4, 0)],
               "normal": [(j, c) for j in (5, 6) for c in range(3)]}
    a = _fused(*case)
    b = _fused(*case, pattern=pattern)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    c32 = _fused(*[t.float() for t in case], pattern=pattern)
    for x, y in zip(c32, a):
        torch.testing.assert_close(x.double(), y, rtol=2e-3, atol=2e-3)


def test_eager_fallback_matches_jacfwd(monkeypatch):
    monkeypatch.setattr(ne_ops, "_c_kernel", lambda spec: None)
    case = _capture(12, 4, torch.float64, seed=2)
    cost, jtj, jtr = _fused(*case)
    rc, rjtj, rjtr = _reference(*case)
    torch.testing.assert_close(cost, rc, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(unpack_jtj(jtj, 7), rjtj, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(jtr, rjtr, rtol=1e-10, atol=1e-10)


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
def test_operator_passes_opcheck_and_compiles():
    case = _capture(8, 2, torch.float64, seed=3)
    theta, metal, points, cam, lpos, lint, log_obs = case
    calls = op_calls("normal_equations_op", lambda: _fused(*case))
    torch.library.opcheck(torch.ops.torchbrdf.normal_equations, calls[0])


def test_bad_inputs_name_the_argument():
    case = _capture(4, 2, torch.float64)
    theta, metal, points, cam, lpos, lint, log_obs = case
    with pytest.raises(ValueError, match="log_obs"):
        _fused(theta, metal, points, cam, lpos, lint, log_obs[:, :, :2])
    p = decode(theta, metal)
    with pytest.raises(ValueError, match="tangents"):
        normal_equations(p, {"sheen": torch.zeros(7, 4, 1, dtype=torch.float64)}, points, cam, lpos, lint,
                         log_obs, EPS)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_other_dtypes_and_short_operands_are_refused(dtype):
    # the kernels read and write float or double rows of the sizes cfg names, without bounds
    # checks: anything else must fail before a kernel runs
    case = _capture(4, 2, torch.float64)
    with pytest.raises(ValueError, match="normal_equations: log_obs must be float32 or float64"):
        _fused(*[t.to(dtype) for t in case])
    theta, metal, points, cam, lpos, lint, log_obs = case
    with pytest.raises(ValueError, match="light_pos must be \\(2, 3\\)"):
        _fused(theta, metal, points, cam, lpos[:1], lint[:1], log_obs)
    calls = []
    real = ne_ops.normal_equations_op
    ne_ops.normal_equations_op = lambda *args: calls.append(args) or real(*args)
    try:
        _fused(*case)
    finally:
        ne_ops.normal_equations_op = real
    tensors, tangents, floats, uniforms, log_obs, cfg = calls[0]
    op = torch.ops.torchbrdf.normal_equations
    with pytest.raises(ValueError, match="normal_equations_op: log_obs"):
        op([t.to(dtype) for t in tensors], [t.to(dtype) for t in tangents], floats, uniforms.to(dtype),
           log_obs.to(dtype), cfg)
    with pytest.raises(ValueError, match="normal_equations_op: the tangents of"):
        op(tensors, [t[:1] for t in tangents], floats, uniforms, log_obs, cfg)
    with pytest.raises(ValueError, match="normal_equations_op: uniforms"):
        op(tensors, tangents, floats, uniforms[:-6], log_obs, cfg)


def test_triton_kernel_matches_jacfwd_under_the_interpreter(monkeypatch, tmp_path):
    case = _capture(24, 4, torch.float64, seed=4)
    (cost, jtj, jtr), built = interpreted_triton(monkeypatch, tmp_path, lambda: _fused(*case))
    assert built and built[0][1] is not None  # the Triton kernel ran
    rc, rjtj, rjtr = _reference(*case)
    torch.testing.assert_close(cost, rc, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(unpack_jtj(jtj, 7), rjtj, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(jtr, rjtr, rtol=1e-10, atol=1e-10)


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
def test_shared_tangent_slots_give_the_same_sums():
    # the decode's three tangents (the five one-channel unknowns share one) as the recovery's
    # bench passes them: the same sums as seven separate directions, and as jacfwd
    from torchbrdf.bench.recovery import DECODE_PATTERN, DECODE_SLOTS

    case = _capture(20, 4, torch.float64, seed=5)
    theta, metal, points, cam, lpos, lint, log_obs = case
    dirs = torch.zeros(3, 7, dtype=torch.float64)
    for s, cols in enumerate(DECODE_SLOTS):
        dirs[s, list(cols)] = 1.0
    p, dp = torch.func.vmap(lambda t: torch.func.jvp(lambda x: decode(x, metal), (theta,), (t,)),
                            out_dims=(None, 0))(dirs[:, None].expand(-1, *theta.shape))
    got = normal_equations(p, {k: v for k, v in dp.items() if k in DECODE_PATTERN}, points, cam, lpos, lint,
                           log_obs, EPS, DECODE_PATTERN, unknowns=7)
    rc, rjtj, rjtr = _reference(*case)
    torch.testing.assert_close(got[0], rc, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(unpack_jtj(got[1], 7), rjtj, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got[2], rjtr, rtol=1e-10, atol=1e-10)


def _non_finite_case(seed):
    """A case whose Jacobian has non-finite entries (NaN and inf tangents) and whose residuals
    have NaN and ±inf (targets), with its residual-returning normal equations and a reference
    from the same Jacobian by jacfwd, non-finite entries taken as 0 in JᵀJ and Jᵀr."""
    case = _capture(10, 3, torch.float64, seed=seed)
    theta, metal, points, cam, lpos, lint, log_obs = case
    log_obs[2, 1, 0] = float("nan")
    log_obs[3, 0, 2] = float("inf")
    log_obs[5, 2, 1] = float("-inf")
    eye = torch.eye(7, dtype=theta.dtype)[:, None].expand(7, theta.shape[0], 7)
    p, dp = torch.func.vmap(lambda t: torch.func.jvp(lambda x: decode(x, metal), (theta,), (t,)),
                            out_dims=(None, 0))(eye)
    dp = {k: v.clone() for k, v in dp.items() if k != "metallic"}
    dp["roughness"][4, 6, 0] = float("nan")  # pixel 6's roughness column
    dp["normal"][5, 7, 1] = float("inf")  # pixel 7's first slope column
    got = normal_equations(p, dp, points, cam, lpos, lint, log_obs, EPS, residuals=True)
    r, J = _jacobian(theta, metal, points, cam, lpos, lint, log_obs)  # (N, M), (N, M, 7)
    J[6, :, 4] = float("nan")
    J[7, :, 5] = float("inf")
    Jc, rc = J.nan_to_num(0.0, 0.0, 0.0), r.nan_to_num(0.0, 0.0, 0.0)
    ref = ((r * r).sum(-1), Jc.transpose(1, 2) @ Jc, (Jc.transpose(1, 2) @ rc[..., None])[..., 0], r)
    return got, ref


def _check_non_finite(got, ref):
    cost, jtj, jtr, r = got
    assert r.shape == (10, 9)
    torch.testing.assert_close(r, ref[3], rtol=1e-10, atol=1e-10, equal_nan=True)
    assert r[2, 3].isnan() and r[3, 2] == float("-inf") and r[5, 7] == float("inf")
    torch.testing.assert_close(cost, ref[0], rtol=1e-10, atol=1e-10, equal_nan=True)
    assert not cost[[2, 3, 5]].isfinite().any() and cost[[0, 1, 4, 6, 7]].isfinite().all()
    assert jtj.isfinite().all() and jtr.isfinite().all()
    torch.testing.assert_close(unpack_jtj(jtj, 7), ref[1], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(jtr, ref[2], rtol=1e-10, atol=1e-10)
    assert (unpack_jtj(jtj, 7)[6, 4] == 0).all() and (jtr[7, 5] == 0) and jtr[6, 6] != 0


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
def test_c_kernel_returns_residuals_and_takes_non_finite_terms_as_zero():
    got, ref = _non_finite_case(6)
    assert any(k[0] == "c" and k[1][8] and v is not None for k, v in ne_ops._kernels.items())
    _check_non_finite(got, ref)


def test_eager_fallback_returns_residuals_and_takes_non_finite_terms_as_zero(monkeypatch):
    monkeypatch.setattr(ne_ops, "_c_kernel", lambda spec: None)
    _check_non_finite(*_non_finite_case(7))


def test_triton_kernel_returns_residuals_under_the_interpreter(monkeypatch, tmp_path):
    (got, ref), built = interpreted_triton(monkeypatch, tmp_path, lambda: _non_finite_case(8))
    assert built and built[0][0].residuals and built[0][1] is not None  # the Triton kernel with residuals ran
    _check_non_finite(got, ref)
