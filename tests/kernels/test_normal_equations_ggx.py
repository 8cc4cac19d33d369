"""The one-pass kernels (normal equations, data cost) for the recovery's GGX model.

``family="svbrdf_ggx"`` renders the recovery's principled unknowns with the SVBRDF GGX. The
reference is written here, independently of ``formula.ggx_albedos``: the albedos
``base (1 − m)`` and ``0.08 s (1 − m) + base m``, rendered by the torch ``svbrdf_ggx`` under
each point light, then ``log(max(L + ε, ε/2)) − log_obs``. It is differentiated by
``torch.func.jacfwd`` in float64.
"""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx
from torchbrdf.kernels import build
from torchbrdf.kernels.normal_eq_ops import data_cost, normal_equations, unpack_jtj
from torchbrdf.recovery.params import decode

from tests.kernels.normal_eq_cases import EPS, capture_case, interpreted_triton

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")
needs_c = pytest.mark.skipif(not build.available(), reason="needs the C kernels")


def _ggx_residual(theta, metal, points, cam, lpos, lint, log_obs):
    """One pixel's log residuals ``(3 L,)`` under the GGX model (``theta (7,)``, ``metal (1,)``)."""
    p = decode(theta[None], metal[None])
    base, m, s = p["base_color"][0], p["metallic"][0], p["specular"][0]
    d = lpos - points  # (L, 3)
    d2 = (d * d).sum(-1, keepdim=True)
    l = d / d2.sqrt()
    v = (cam - points) / torch.linalg.vector_norm(cam - points)
    n = p["normal"][0].expand_as(l)
    f = svbrdf_ggx(l, v.expand_as(l), n, diffuse_albedo=base * (1 - m),
                   specular_albedo=0.08 * s * (1 - m) + base * m, roughness=p["roughness"][0].expand(l.shape[0], 1))
    rad = f * lint * (n * l).sum(-1, keepdim=True).clamp_min(0) / d2
    return (torch.log(torch.clamp(rad + EPS, min=0.5 * EPS)) - log_obs).reshape(-1)


def _reference(theta, metal, points, cam, lpos, lint, log_obs):
    old = torchbrdf.get_backend()
    torchbrdf.set_backend("eager")
    try:
        def res(th, me, pt, lo):
            return _ggx_residual(th, me, pt, cam, lpos, lint, lo)

        r = torch.vmap(res)(theta, metal, points, log_obs)
        J = torch.vmap(torch.func.jacfwd(res))(theta, metal, points, log_obs)
    finally:
        torchbrdf.set_backend(None if old == "auto" else old)
    return (r * r).sum(-1), J.transpose(1, 2) @ J, (J.transpose(1, 2) @ r[..., None])[..., 0]


def _fused(theta, metal, points, cam, lpos, lint, log_obs):
    K = theta.shape[1]
    eye = torch.eye(K, dtype=theta.dtype)[:, None].expand(K, theta.shape[0], K)
    p, dp = torch.func.vmap(lambda t: torch.func.jvp(lambda x: decode(x, metal), (theta,), (t,)),
                            out_dims=(None, 0))(eye)
    sums = normal_equations(p, {k: v for k, v in dp.items() if k != "metallic"}, points, cam, lpos, lint,
                            log_obs, EPS, family="svbrdf_ggx")
    return (*sums, data_cost(p, points, cam, lpos, lint, log_obs, EPS, family="svbrdf_ggx"))


def _check(case, got, tol=1e-10):
    cost, jtj, jtr, c_only = got
    rc, rjtj, rjtr = _reference(*case)
    torch.testing.assert_close(cost, rc, rtol=tol, atol=tol)
    torch.testing.assert_close(c_only[:, 0], rc, rtol=tol, atol=0)
    torch.testing.assert_close(unpack_jtj(jtj, 7), rjtj, rtol=tol, atol=tol)
    torch.testing.assert_close(jtr, rjtr, rtol=tol, atol=tol)
    metal = case[1][:, 0] == 1
    assert metal.any() and (~metal).any() and (rjtj[metal].abs().amax((1, 2)) > 1e-3).all()


@needs_c
def test_c_kernels_match_jacfwd_of_the_ggx_residual():
    case = capture_case(40, 5, torch.float64, seed=6)
    _check(case, _fused(*case))
    assert any(k[0] == "c" and v is not None and "svbrdf_ggx" in k[1] for k, v in ne_ops._kernels.items())


def test_eager_fallback_matches_jacfwd_of_the_ggx_residual(monkeypatch):
    monkeypatch.setattr(ne_ops, "_c_kernel", lambda spec: None)
    case = capture_case(12, 4, torch.float64, seed=7)
    _check(case, _fused(*case))


def test_triton_kernels_match_jacfwd_of_the_ggx_residual(monkeypatch, tmp_path):
    case = capture_case(16, 3, torch.float64, seed=8)
    got, built = interpreted_triton(monkeypatch, tmp_path, lambda: _fused(*case))
    assert built and all(hit is not None and spec.family == "svbrdf_ggx" for spec, hit in built)
    _check(case, got)


@needs_c
def test_the_principled_residual_is_another_kernel():
    """Not vacuous: the same case under the principled residual gives other sums."""
    case = capture_case(8, 3, torch.float64, seed=9)
    p = decode(case[0], case[1])
    ggx = data_cost(p, *case[2:], EPS, family="svbrdf_ggx")
    principled = data_cost(p, *case[2:], EPS)
    assert ((ggx - principled).abs() > 1e-3 * principled.abs()).any()


@needs_c
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_per_lane_kernels_of_the_ggx_residual_value_jvp_and_gradient(dtype, tol):
    """``log_residual_points(family="svbrdf_ggx")`` on the per-lane kernels (``capture_ggx``):
    the residual, its JVP along the light step's directions and its gradient, against the
    independent residual above (float64)."""
    from torchbrdf.capture.synthetic import log_residual_points, log_residual_points_jvp

    case = capture_case(20, 4, torch.float64, seed=10)
    theta, metal, points, cam, lpos, lint, log_obs = case
    ref = torch.vmap(lambda th, me, pt, lo: _ggx_residual(th, me, pt, cam, lpos, lint, lo))(theta, metal, points,
                                                                                             log_obs)
    cast = [t.to(dtype) for t in case]
    p = decode(cast[0], cast[1])
    got = log_residual_points(p["normal"], *cast[2:6], p, cast[6], EPS, any_size=True, family="svbrdf_ggx")
    torch.testing.assert_close(got.reshape(20, -1).double(), ref, rtol=tol, atol=tol)
    # d/d(light position x of every light) and d/d(roughness), as the light step asks for them
    tangents = {"light_pos": torch.zeros(2, 4, 3, dtype=dtype), "roughness": torch.zeros(2, 20, 1, dtype=dtype)}
    tangents["light_pos"][0, :, 0] = 1.0
    tangents["roughness"][1] = 1.0
    r, dr = log_residual_points_jvp(p["normal"], *cast[2:6], p, cast[6], EPS, tangents, any_size=True,
                                    family="svbrdf_ggx")

    def by_light_x(dx):
        moved = lpos + torch.stack((dx.expand(4), torch.zeros(4, dtype=torch.float64),
                                    torch.zeros(4, dtype=torch.float64)), -1)
        return torch.vmap(lambda th, me, pt, lo: _ggx_residual(th, me, pt, cam, moved, lint, lo))(
            theta, metal, points, log_obs)

    want = torch.func.jvp(by_light_x, (torch.zeros((), dtype=torch.float64),), (torch.ones((), dtype=torch.float64),))[1]
    torch.testing.assert_close(dr[0].reshape(20, -1).double(), want, rtol=tol * 10, atol=tol * 10)
    rough = p["roughness"].detach().clone().requires_grad_()
    loss = log_residual_points(p["normal"], *cast[2:6], {**p, "roughness": rough}, cast[6], EPS, any_size=True,
                               family="svbrdf_ggx").square().sum()
    (g,) = torch.autograd.grad(loss, rough)
    torch.testing.assert_close(g[:, 0].double(), (2 * r.reshape(20, -1) * dr[1].reshape(20, -1)).sum(-1).double(),
                               rtol=tol * 10, atol=tol * 10)


@pytest.mark.parametrize("fast", [False, None])
def test_the_ggx_residual_off_the_fast_path_and_in_float16(fast):
    """``set_fast_path(False)`` (the formula on torch tensors) and float16 inputs (evaluated in
    float32) give the independent GGX residual too."""
    from torchbrdf.capture.synthetic import log_residual_points

    case = capture_case(10, 3, torch.float64, seed=11)
    theta, metal, points, cam, lpos, lint, log_obs = case
    ref = torch.vmap(lambda th, me, pt, lo: _ggx_residual(th, me, pt, cam, lpos, lint, lo))(theta, metal, points,
                                                                                             log_obs)
    torchbrdf.set_fast_path(fast)
    try:
        p = decode(theta, metal)
        got = log_residual_points(p["normal"], points, cam, lpos, lint, p, log_obs, EPS, family="svbrdf_ggx")
        torch.testing.assert_close(got.reshape(10, -1), ref, rtol=1e-10, atol=1e-10)
        with pytest.raises(ValueError, match="family"):
            log_residual_points(p["normal"], points, cam, lpos, lint, p, log_obs, EPS, family="ggx")
    finally:
        torchbrdf.set_fast_path(None)
