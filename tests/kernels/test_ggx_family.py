"""The fused kernels of ``svbrdf_ggx`` (the ``svbrdf_ggx`` kernel family) against its eager path.

Both come from ``torchbrdf.brdf.formula.svbrdf_ggx``; the independent float64 reference of the
model is in ``tests/brdf/test_svbrdf_ggx.py``. Sizes are small (each new kernel family costs one
gcc build, cached on disk afterwards).
"""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.brdf import formula
from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx
from torchbrdf.kernels import fused as _fast
from torchbrdf.kernels import ops as _ops

from tests.kernels.test_fast_path import fast  # noqa: F401  (fixture: the fused path at every size)

P = importlib.import_module("torchbrdf.brdf.principled")

pytestmark = pytest.mark.skipif(not _fast.available(), reason="no C compiler: the fused path is unavailable")

MAPS = ("diffuse_albedo", "specular_albedo", "roughness")
FLOORS = [{}, {"roughness_floor": 1e-3}, {"alpha_floor": 0.02}]


def _unit(x):
    return x / x.norm(dim=-1, keepdim=True)


def _case(seed, count, dtype=torch.float64):
    """Random directions mostly above the horizon, with the model's edge lanes first: normal
    incidence (``h = n``: the cosines' clamps at 1 kink there), ``l = -v`` (no half vector),
    below the horizon, roughness 0 and 1."""
    g = torch.Generator().manual_seed(seed)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = _unit(torch.randn(count, 3, generator=g, dtype=torch.float64) * 0.4 + up)
    l = _unit(torch.randn(count, 3, generator=g, dtype=torch.float64) * 0.7 + up)
    v = _unit(torch.randn(count, 3, generator=g, dtype=torch.float64) * 0.7 + up)
    l[:4], v[:4] = n[:4], n[:4]
    l[4:6] = -v[4:6]
    l[6:8, 2] = -l[6:8, 2]
    rough = torch.rand(count, 1, generator=g, dtype=torch.float64)
    rough[8:10], rough[10:12] = 0.0, 1.0
    maps = {"diffuse_albedo": torch.rand(count, 3, generator=g, dtype=torch.float64),
            "specular_albedo": torch.rand(count, 3, generator=g, dtype=torch.float64), "roughness": rough}
    return {k: t.to(dtype) for k, t in {"l": l, "v": v, "n": n, **maps}.items()}


def _eval(fast_path, inputs, grad_out=None, **extra):
    """Forward (+ backward with ``grad_out``) on clones of ``inputs``: ``(out, grads)``."""
    old = P.fast_path_enabled()
    P.set_fast_path(fast_path)
    try:
        ins = {k: t.detach().clone().requires_grad_(grad_out is not None) for k, t in inputs.items()}
        out = svbrdf_ggx(**ins, **extra)
        grads = {}
        if grad_out is not None:
            out.backward(grad_out)
            grads = {k: t.grad for k, t in ins.items()}
        return out.detach(), grads
    finally:
        P.set_fast_path(old)


def _count_calls(monkeypatch, name):
    """The ``svbrdf_ggx``-family plans that reach ``c_runner.<name>``."""
    from torchbrdf.kernels import c_runner

    calls = []
    real = getattr(c_runner, name)

    def spy(plan, *a, **k):
        if plan.family == "svbrdf_ggx":
            calls.append((plan, *a))
        return real(plan, *a, **k)

    monkeypatch.setattr(c_runner, name, spy)
    return calls


@pytest.mark.parametrize("floor", FLOORS, ids=["default", "roughness_floor", "alpha_floor"])
@pytest.mark.parametrize("dtype, vtol, gtol", [(torch.float64, 1e-13, 1e-12), (torch.float32, 2e-6, 2e-6)],
                         ids=["float64", "float32"])
def test_fused_equals_eager_values_and_gradients(monkeypatch, floor, dtype, vtol, gtol):
    inputs = _case(1, 700, dtype)
    go = torch.rand(700, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    fwd, bwd = _count_calls(monkeypatch, "run_fwd"), _count_calls(monkeypatch, "run_bwd")
    out_f, g_f = _eval(True, inputs, go, **floor)
    assert len(fwd) == 1 and len(bwd) == 1
    out_e, g_e = _eval(False, inputs, go, **floor)
    assert len(fwd) == 1  # the eager call ran no kernel
    torch.testing.assert_close(out_f, out_e, rtol=vtol, atol=0)
    assert (out_f[6:8] == 0).all()  # below the horizon: exactly 0
    for k in inputs:
        scale = float(g_e[k].abs().max())
        torch.testing.assert_close(g_f[k], g_e[k], rtol=0, atol=gtol * scale, msg=k)


def test_maximum_ties_split_the_gradient_as_aten(monkeypatch):
    """With the denominator's floor raised to its tie value (``min(alpha^2, 1)``, reached at
    normal incidence and at roughness 1), the kernels' ``maximum`` gives each side half the
    gradient at a tie, as ATen's does on the eager path."""
    monkeypatch.setattr(_fast, "_libs", {})
    monkeypatch.setattr(formula, "GGX_DEN_FLOOR", 1.0)
    inputs = _case(18, 64)
    go = torch.ones(64, 3, dtype=torch.float64)
    out_f, g_f = _eval(True, inputs, go)
    out_e, g_e = _eval(False, inputs, go)
    lanes = list(range(4)) + [10, 11]  # h = n, roughness 1
    for k in inputs:
        torch.testing.assert_close(g_f[k][lanes], g_e[k][lanes], rtol=1e-12, atol=1e-12, msg=k)
    # and the tie is real: the default floor gives another gradient in those lanes
    monkeypatch.undo()
    _, g_smooth = _eval(False, inputs, go)
    assert not torch.allclose(g_smooth["roughness"][[10, 11]], g_e["roughness"][[10, 11]], rtol=1e-3)


def test_gradcheck_float64_on_the_fused_path(fast, monkeypatch):
    # past the normal-incidence lanes (the cosines' clamps at 1 kink there)
    inputs = {k: t[4:].clone().requires_grad_() for k, t in _case(3, 28).items()}
    names = list(inputs)

    def f(*ts):
        return svbrdf_ggx(**dict(zip(names, ts)), roughness_floor=1e-3)

    inputs["roughness"].data.clamp_(0.05, 1.0)  # keep the roughness floor's kink out of reach
    bwd = _count_calls(monkeypatch, "run_bwd")
    assert torch.autograd.gradcheck(f, tuple(inputs.values()), eps=1e-7, atol=1e-6, rtol=1e-5)
    assert bwd


def test_gradcheck_broadcast_maps_and_some_inputs_without_grad(fast, monkeypatch):
    """One material for all lanes (``(3,)``, 0-d), the directions without gradient: the backward
    kernel writes only the gradients that are asked for, reduced over the lanes."""
    c = _case(4, 20)
    rough = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    spec = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
    bwd = _count_calls(monkeypatch, "run_bwd")

    def f(r, s):
        return svbrdf_ggx(c["l"], c["v"], c["n"], diffuse_albedo=0.3, specular_albedo=s, roughness=r)

    assert torch.autograd.gradcheck(f, (rough, spec), eps=1e-7, atol=1e-7, rtol=1e-6)
    assert bwd and all(sorted(call[3]) == [4, 5] for call in bwd)  # specular_albedo, roughness


def test_noncontiguous_and_broadcast_inputs_match_eager(monkeypatch):
    c = _case(5, 64)
    fwd = _count_calls(monkeypatch, "run_fwd")
    wide = {k: torch.cat([t, t], -1)[..., ::2] for k, t in c.items()}  # channel-strided views
    pix = {k: t[:8, None] for k, t in c.items() if k in MAPS + ("n",)}  # (8, 1, C) over 8 lights
    light = {"l": c["l"][None, :8], "v": c["v"][None, :8]}
    for inputs, shape in ((wide, (64, 3)), ({**pix, **light}, (8, 8, 3))):
        go = torch.rand(shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
        out_f, g_f = _eval(True, inputs, go)
        assert fwd and fwd[-1][0].batch == shape[:-1]
        out_e, g_e = _eval(False, inputs, go)
        torch.testing.assert_close(out_f, out_e, rtol=1e-13, atol=0)
        for k in inputs:
            torch.testing.assert_close(g_f[k], g_e[k], rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=str)
def test_half_types_are_evaluated_in_float32(monkeypatch, dtype):
    inputs = _case(6, 64, dtype)
    calls = _count_calls(monkeypatch, "run_fwd")
    out_f, g_f = _eval(True, inputs, torch.ones(64, 3, dtype=dtype))
    assert len(calls) == 1 and calls[0][0].dtype == torch.float32
    out_e, g_e = _eval(False, inputs, torch.ones(64, 3, dtype=dtype))
    assert out_f.dtype == dtype
    torch.testing.assert_close(out_f, out_e, rtol=1e-2, atol=1e-3)
    for k in inputs:
        assert g_f[k].dtype == dtype
        torch.testing.assert_close(g_f[k].float(), g_e[k].float(), rtol=2e-2, atol=2e-2 * float(g_e[k].abs().max()))


def test_dispatch_follows_the_fast_path_rules(monkeypatch):
    """Automatic mode: fused from FAST_PATH_MIN_LANES lanes (vmapped dims included), eager below
    unless inside ``fused_at_every_size``; ``set_fast_path(False)`` and ``TORCHBRDF_EAGER``
    keep it eager."""
    calls = _count_calls(monkeypatch, "run_fwd")
    big, small = _case(7, P.FAST_PATH_MIN_LANES, torch.float32), _case(7, 64, torch.float32)
    P.set_fast_path(None)
    svbrdf_ggx(**big)
    assert len(calls) == 1
    svbrdf_ggx(**small)
    assert len(calls) == 1
    with P.fused_at_every_size():
        svbrdf_ggx(**small)
    assert len(calls) == 2
    quarter = {k: t.reshape(4, -1, t.shape[-1]) for k, t in big.items()}
    torch.func.vmap(lambda kw: svbrdf_ggx(**kw))(quarter)
    assert len(calls) == 3
    try:
        P.set_fast_path(False)
        svbrdf_ggx(**big)
        assert len(calls) == 3
        P.set_fast_path(None)
        monkeypatch.setenv("TORCHBRDF_EAGER", "1")
        svbrdf_ggx(**big)
        assert len(calls) == 3
    finally:
        P.set_fast_path(None)


def test_rendering_loss_ggx_layout_runs_the_fused_kernels(monkeypatch):
    """A ``rendering_loss(layout="svbrdf_ggx")`` step at a training batch's size takes the fused
    forward and backward, with the eager path's loss and gradient."""
    from torchbrdf.losses import GGX_LAYOUT, rendering_loss

    g = torch.Generator().manual_seed(8)
    C = sum(GGX_LAYOUT.values())
    pred = torch.rand(2, C, 64, 64, generator=g)
    target = torch.rand(2, C, 64, 64, generator=g)
    fwd, bwd = _count_calls(monkeypatch, "run_fwd"), _count_calls(monkeypatch, "run_bwd")
    results = []
    for fast_path in (None, False):
        P.set_fast_path(fast_path)
        p = pred.clone().requires_grad_()
        loss = rendering_loss(p, target, layout="svbrdf_ggx", generator=torch.Generator().manual_seed(9))
        loss.backward()
        results.append((loss.detach(), p.grad))
        if fast_path is None:
            assert fwd and bwd
            n_calls = (len(fwd), len(bwd))
    P.set_fast_path(None)
    assert (len(fwd), len(bwd)) == n_calls
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-5, atol=0)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-4, atol=1e-4 * float(results[1][1].abs().max()))


def test_torch_func_transforms_run_fused_and_match_eager(monkeypatch):
    c = _case(10, 256)
    tan = torch.randn(256, 1, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    rest = {k: t for k, t in c.items() if k != "roughness"}

    def f(r):
        return svbrdf_ggx(**rest, roughness=r)

    def g(p):  # one shared material (7 numbers)
        return svbrdf_ggx(c["l"], c["v"], c["n"], diffuse_albedo=p[:3], specular_albedo=p[3:6], roughness=p[6:])

    p = torch.tensor([0.6, 0.4, 0.2, 0.05, 0.04, 0.03, 0.3], dtype=torch.float64)
    jvps, fwds = _count_calls(monkeypatch, "run_jvp"), _count_calls(monkeypatch, "run_fwd")
    results = {}
    for fast_path in (True, False):
        P.set_fast_path(fast_path)
        try:
            results[fast_path] = [
                torch.func.jvp(f, (c["roughness"],), (tan,))[1],
                torch.func.jacfwd(g)(p),
                torch.func.jacrev(g)(p),
                torch.func.grad(lambda r: f(r).square().sum())(c["roughness"]),
                torch.func.vjp(f, c["roughness"])[1](torch.ones(256, 3, dtype=torch.float64))[0],
                torch.func.vmap(lambda l: svbrdf_ggx(l, **{k: t for k, t in c.items() if k != "l"}))(
                    torch.stack([c["l"], c["l"].flip(0)])),
            ]
        finally:
            P.set_fast_path(None)
        if fast_path:
            assert len(jvps) == 2 and jvps[1][4] == 7  # jacfwd: seven tangents in one pass
            assert len(fwds) >= 4
    for got, want in zip(results[True], results[False]):
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-11 * float(want.abs().max()))


def test_forward_ad_dual_tensors_use_the_fused_jvp(fast, monkeypatch):
    import torch.autograd.forward_ad as fwAD

    c = _case(12, 128)
    t = torch.randn(128, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(13))
    calls = _count_calls(monkeypatch, "run_jvp")
    with fwAD.dual_level():
        out = svbrdf_ggx(**{**c, "specular_albedo": fwAD.make_dual(c["specular_albedo"], t)})
        tan = fwAD.unpack_dual(out).tangent
    assert len(calls) == 1
    P.set_fast_path(False)
    _, ref = torch.func.jvp(lambda s: svbrdf_ggx(**{**c, "specular_albedo": s}), (c["specular_albedo"],), (t,))
    torch.testing.assert_close(tan, ref, rtol=1e-12, atol=1e-12)


def test_custom_ops_pass_opcheck(fast):
    c = _case(14, 16)
    names = ["l", "v", "n", *MAPS]
    tensors = [c[k].requires_grad_() for k in names]
    cfg = _ops.make_cfg(names, ["roughness_floor"], (), False, False, family="svbrdf_ggx")
    floats = [1e-3]
    torch.library.opcheck(torch.ops.torchbrdf.principled_fwd, (tensors, floats, cfg))
    plain = [t.detach() for t in tensors]
    go = torch.ones(16, 3, dtype=torch.float64)
    torch.library.opcheck(torch.ops.torchbrdf.principled_bwd, (plain, floats, cfg, go, [2, 5]))
    tans = [torch.ones_like(plain[5])]
    torch.library.opcheck(torch.ops.torchbrdf.principled_jvp, (plain, floats, cfg, tans, [5], 0))


def test_torch_compile_fullgraph_runs_the_fused_operator():
    from torch._dynamo.utils import counters
    from torch._inductor.compile_fx import compile_fx

    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return compile_fx(gm, example_inputs)

    def user(l, v, n, diffuse, specular, rough):
        return svbrdf_ggx(l, v, n, diffuse_albedo=diffuse, specular_albedo=specular, roughness=rough) * 2.0

    fn = torch.compile(user, fullgraph=True, backend=backend)
    module = torch.compile(torchbrdf.SVBRDFGGX(roughness_floor=1e-3), fullgraph=True, backend=backend)
    counters.clear()
    for lanes in (100, 8192):
        # past the normal-incidence lanes: at the cosines' kinks float32 rounding picks the branch
        c = {k: t[4:] for k, t in _case(15, lanes + 4, torch.float32).items()}
        args = [c["l"], c["v"], c["n"], c["diffuse_albedo"], c["specular_albedo"].requires_grad_(),
                c["roughness"].requires_grad_()]
        graphs.clear()
        out = fn(*args)
        out_m = module(*args[:3], diffuse_albedo=args[3], specular_albedo=args[4], roughness=args[5])
        grads = torch.autograd.grad(out.sum(), args[4:])
        assert graphs
        for gm in graphs:
            fused = [nd for nd in gm.graph.nodes if "torchbrdf.principled_fwd" in str(nd.target)]
            assert fused and all("svbrdf_ggx" in str(nd.args) for nd in fused), gm.code
        P.set_fast_path(False)
        try:
            ref = user(*args)
            ref_m = svbrdf_ggx(*args[:3], diffuse_albedo=args[3], specular_albedo=args[4], roughness=args[5],
                               roughness_floor=1e-3)
            grads_e = torch.autograd.grad(ref.sum(), args[4:])
        finally:
            P.set_fast_path(None)
        torch.testing.assert_close(out, ref, rtol=2e-6, atol=0)
        torch.testing.assert_close(out_m, ref_m, rtol=2e-6, atol=0)
        for a, b in zip(grads, grads_e):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))
    assert not counters["graph_break"]


def test_eager_and_kernels_come_from_one_definition(monkeypatch):
    # Perturb one constant of the shared formula (the Fresnel fit's exponent): the eager path and
    # a freshly generated kernel family change alike.
    c = _case(16, 64)
    before = {fast: _eval(fast, c)[0] for fast in (True, False)}
    monkeypatch.setattr(_fast, "_libs", {})  # this process's loaded kernels: rebuild from the formula
    monkeypatch.setattr(formula, "SG_B", 0.5 * formula.SG_B)
    after = {fast: _eval(fast, c)[0] for fast in (True, False)}
    assert (after[True] - before[True]).abs().max() > 1e-3
    torch.testing.assert_close(after[True], after[False], rtol=1e-13, atol=0)
    monkeypatch.undo()
    torch.testing.assert_close(_eval(True, c)[0], before[True], rtol=0, atol=0)


def test_zero_lanes_forward_and_backward(fast, monkeypatch):
    c = {k: t[:0].requires_grad_() for k, t in _case(17, 4).items()}
    fwd = _count_calls(monkeypatch, "run_fwd")
    out = svbrdf_ggx(**c)
    assert out.shape == (0, 3) and len(fwd) == 1
    out.sum().backward()
    assert c["roughness"].grad.shape == (0, 1)


def test_c_exp2_is_within_two_ulp_over_the_normal_range():
    """The kernels' branch-free ``tb_exp2`` / ``tb_exp2f`` against the correctly rounded value
    (float64 ``exp2`` of the float32 argument for ``tb_exp2f``), over the whole normal range and
    the Fresnel fit's ``[-12.54, 0]``."""
    import ctypes

    from torchbrdf.kernels import build, codegen_c

    src = codegen_c.PRELUDE + codegen_c.EXP2_PRELUDE + """
void e64(long n, const double* x, double* y) { for (long i = 0; i < n; ++i) y[i] = tb_exp2(x[i]); }
void e32(long n, const float* x, float* y) { for (long i = 0; i < n; ++i) y[i] = tb_exp2f(x[i]); }
"""
    args = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
    lib = build.load_kernel(src, "test_exp2", {"e64": (args, None), "e32": (args, None)})
    assert lib is not None
    g = torch.Generator().manual_seed(19)
    for dtype, fn, lo, hi in ((torch.float64, lib.e64, -1022.0, 1023.0), (torch.float32, lib.e32, -126.0, 127.0)):
        x = torch.cat([torch.rand(20000, generator=g, dtype=torch.float64) * (hi - lo) + lo,
                       -12.54 * torch.rand(20000, generator=g, dtype=torch.float64),
                       torch.tensor([lo, hi, 0.0, -0.5, 0.5, -1.0, 1.0], dtype=torch.float64)]).to(dtype)
        y = torch.empty_like(x)
        fn(x.numel(), x.data_ptr(), y.data_ptr())
        exact = torch.exp2(x.double())
        ulp = torch.finfo(dtype).eps
        err = ((y.double() - exact).abs() / exact).max().item()
        assert err <= 2 * ulp, (dtype, err / ulp)
