"""The fused CPU kernels of ``principled`` (torchbrdf/kernels/fused.py) against the eager reference path.

Kept cheap for CI: small batches, and the tests reuse a handful of kernel families (each new
family costs one ~1-3 s gcc build, cached on disk afterwards).
"""

import importlib
import math

import numpy as np
import pytest
import torch

import torchbrdf
from torchbrdf.kernels import fused as _fast

from tests.reference import principled_ref
from tests.brdf.test_principled import SCALARS, random_case, to_t

P = importlib.import_module("torchbrdf.brdf.principled")

pytestmark = pytest.mark.skipif(not _fast.available(), reason="no C compiler: the fused path is unavailable")


@pytest.fixture
def fast():
    """Force the fused path for every batch size during the test."""
    old = P.fast_path_enabled()
    P.set_fast_path(True)
    yield
    P.set_fast_path(old)


def _eval(fast_path: bool, inputs: dict, grad_out=None, **extra):
    """Forward (+ backward with ``grad_out``) on clones of ``inputs``; returns (out, grads)."""
    old = P.fast_path_enabled()
    P.set_fast_path(fast_path)
    try:
        ins = {k: (t.detach().clone().requires_grad_(grad_out is not None) if isinstance(t, torch.Tensor) else t)
               for k, t in inputs.items()}
        out = torchbrdf.principled(**ins, **extra)
        grads = {}
        if grad_out is not None:
            out.backward(grad_out)
            grads = {k: t.grad for k, t in ins.items() if isinstance(t, torch.Tensor)}
        return out.detach(), grads, out
    finally:
        P.set_fast_path(old)


def _case(seed, count, dtype, min_cos=0.0):
    vec, base, params = random_case(seed, count=count, min_cos=min_cos)
    return {**to_t(vec, dtype), "base_color": torch.as_tensor(base, dtype=dtype), **to_t(params, dtype)}


def _rel(a, b):
    return ((a - b).abs() / b.abs().clamp_min(1e-30)).max().item()


def _grad_close(gf, ge, rtol):
    for k in ge:
        assert (gf[k] is None) == (ge[k] is None), (k, gf[k] is None)
        if ge[k] is None:
            continue
        scale = ge[k].abs().max().clamp_min(1e-30)
        err = ((gf[k] - ge[k]).abs() / scale).max().item()
        assert err <= rtol, (k, err)


@pytest.mark.parametrize("dtype, vtol, gtol", [(torch.float32, 1e-6, 2e-6), (torch.float64, 1e-12, 1e-12)])
def test_fast_equals_eager_values_and_gradients(dtype, vtol, gtol):
    inputs = _case(0, 4096, dtype)
    go = torch.randn(4096, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    of, gf, graph = _eval(True, inputs, go)
    assert "PrincipledFunction" in graph.grad_fn.name()  # really the fused path
    oe, ge, _ = _eval(False, inputs, go)
    assert _rel(of, oe) <= vtol
    _grad_close(gf, ge, gtol)


def test_float32_accuracy_at_the_narrowest_peak():
    # α = 0.001 (roughness ≈ 0.0316) near the mirror direction: the float64 half-vector
    # projections keep float32 within 1e-4 of a float64 reference (judged on rounded inputs).
    rng = np.random.default_rng(5)
    count = 2048
    n = np.tile([0.0, 0.0, 1.0], (count, 1))
    x = np.tile([1.0, 0.0, 0.0], (count, 1))
    y = np.tile([0.0, 1.0, 0.0], (count, 1))
    th = rng.uniform(0.1, 1.2, count)
    ph = rng.uniform(0, 2 * np.pi, count)
    v = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    jitter = rng.normal(scale=1e-3, size=(count, 3))
    l = np.stack([-v[:, 0], -v[:, 1], v[:, 2]], -1) + jitter
    l /= np.linalg.norm(l, axis=-1, keepdims=True)
    vec = {k: torch.as_tensor(a, dtype=torch.float32) for k, a in dict(l=l, v=v, n=n, x=x, y=y).items()}
    rough = torch.full((count, 1), math.sqrt(0.001), dtype=torch.float32)
    base = torch.full((count, 3), 0.5, dtype=torch.float32)
    P.set_fast_path(True)
    try:
        out = torchbrdf.principled(**vec, base_color=base, roughness=rough, anisotropic=0.0)
    finally:
        P.set_fast_path(None)
    up = {k: t.double().numpy() for k, t in vec.items()}
    ref = principled_ref(up["l"], up["v"], up["n"], up["x"], up["y"], base.double().numpy(),
                         roughness=rough.double().numpy())
    err = np.abs(out.double().numpy() - ref) / np.abs(ref)
    assert err.max() <= 1e-4


def test_gradcheck_float64_on_the_fast_path(fast):
    vec, base, params = random_case(12, count=5, min_cos=0.1)
    t = {k: a.requires_grad_() for k, a in to_t(vec, torch.float64).items()}
    p = {k: (a * 0.8 + 0.1).requires_grad_() for k, a in to_t(params, torch.float64).items()}
    b = torch.as_tensor(base).requires_grad_()
    names = list(p)

    def fn(l, v, n, x, y, b, *ps):
        return torchbrdf.principled(l, v, n, x, y, base_color=b, **dict(zip(names, ps)))

    assert "PrincipledFunction" in fn(t["l"], t["v"], t["n"], t["x"], t["y"], b, *p.values()).grad_fn.name()
    assert torch.autograd.gradcheck(fn, (t["l"], t["v"], t["n"], t["x"], t["y"], b, *p.values()))


def test_gradcheck_float64_pruned_and_broadcast(fast):
    # Python-float parameters (lobes pruned / constants in the kernel), a shared normal (3,),
    # a 0-d roughness and a (3,) colour: gradients are reduced over the lanes.
    vec, _, _ = random_case(13, count=4, min_cos=0.1)
    l, v = (torch.as_tensor(vec[k]).requires_grad_() for k in ("l", "v"))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, requires_grad=True)
    l = torch.nn.functional.normalize(l.detach().abs(), dim=-1).requires_grad_()
    v = torch.nn.functional.normalize(v.detach().abs(), dim=-1).requires_grad_()
    rough = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    base = torch.tensor([0.7, 0.4, 0.2], dtype=torch.float64, requires_grad=True)
    sheen = torch.full((4, 1), 0.6, dtype=torch.float64, requires_grad=True)

    def fn(l, v, n, rough, base, sheen):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=rough, sheen=sheen, clearcoat=0.0,
                                    metallic=0.25, specular_tint=0.5)

    assert "PrincipledFunction" in fn(l, v, n, rough, base, sheen).grad_fn.name()
    assert torch.autograd.gradcheck(fn, (l, v, n, rough, base, sheen))


@pytest.mark.parametrize("params", [
    dict(clearcoat=0.0, sheen=0.0, subsurface=0.0),           # diffuse + specular only
    dict(metallic=1.0, clearcoat=0.0),                          # pure metal
    dict(roughness=0.3, anisotropic=0.0, sheen_tint=0.0),       # constants in the kernel
])
def test_pruned_variants_match_eager(params):
    inputs = {k: t for k, t in _case(2, 1024, torch.float32).items() if k not in params}
    go = torch.ones(1024, 3)
    of, gf, _ = _eval(True, inputs, go, **params)
    oe, ge, _ = _eval(False, inputs, go, **params)
    assert _rel(of, oe) <= 1e-6
    _grad_close(gf, ge, 2e-6)


def test_float_parameter_values_share_one_kernel(fast):
    inputs = {k: t for k, t in _case(2, 256, torch.float32).items() if k != "roughness"}
    torchbrdf.principled(**inputs, roughness=0.3)
    before = _fast.compiled_kernels()
    out = torchbrdf.principled(**inputs, roughness=0.7)
    assert _fast.compiled_kernels() == before
    P.set_fast_path(False)
    assert _rel(out, torchbrdf.principled(**inputs, roughness=0.7)) <= 1e-6


def test_broadcast_shapes_match_eager():
    g = torch.Generator().manual_seed(3)
    l = torch.nn.functional.normalize(torch.rand(4, 5, 3, generator=g) + 0.2, dim=-1)
    inputs = dict(
        l=l,
        v=torch.nn.functional.normalize(torch.tensor([0.1, 0.2, 1.0]), dim=-1).expand(1, 1, 3),
        n=torch.tensor([0.0, 0.0, 1.0]),
        base_color=torch.tensor([0.5, 0.4, 0.3]),
        roughness=torch.rand(4, 1, 1, generator=g),
        metallic=torch.tensor(0.3),
        clearcoat=torch.rand(5, 1, generator=g),
    )
    go = torch.rand(4, 5, 3, generator=g)
    of, gf, graph = _eval(True, inputs, go)
    assert "PrincipledFunction" in graph.grad_fn.name()
    oe, ge, _ = _eval(False, inputs, go)
    assert of.shape == (4, 5, 3)
    assert _rel(of, oe) <= 1e-6
    for k in ge:
        assert gf[k].shape == inputs[k].shape, k
    _grad_close(gf, ge, 2e-6)


@pytest.mark.parametrize("pixels_first", [True, False])
def test_values_broadcast_over_one_of_two_batch_dims_are_read_in_place(pixels_first, monkeypatch):
    # Per-pixel material under every light, a per-light direction at every pixel: the kernels
    # read them through two lane strides (mode 's2', no (P, L) copies). Values, gradients
    # and forward-mode tangents must equal eager's.
    from torchbrdf.kernels import layout as ops_mod

    modes = []
    real = ops_mod.flatten
    monkeypatch.setattr(ops_mod, "flatten", lambda *a, **k: (lambda r: modes.append(r[1]) or r)(real(*a, **k)))
    g = torch.Generator().manual_seed(11)
    P, L = 700, 6
    px = (lambda t: t[:, None]) if pixels_first else (lambda t: t[None])
    lt = (lambda t: t[None]) if pixels_first else (lambda t: t[:, None])
    n = torch.nn.functional.normalize(torch.rand(P, 3, generator=g, dtype=torch.float64) + torch.tensor([0, 0, 1.0]), dim=-1)
    inputs = dict(
        l=lt(torch.nn.functional.normalize(torch.rand(L, 3, generator=g, dtype=torch.float64) + torch.tensor([0, 0, .5]), dim=-1)),
        v=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
        n=px(n),
        base_color=px(torch.rand(P, 3, generator=g, dtype=torch.float64)),
        roughness=px(0.1 + 0.8 * torch.rand(P, 1, generator=g, dtype=torch.float64)),
        metallic=px(torch.rand(P, 1, generator=g, dtype=torch.float64)),
    )
    go = torch.rand((P, L, 3) if pixels_first else (L, P, 3), generator=g, dtype=torch.float64)
    of, gf, _ = _eval(True, inputs, go)
    assert "s2" in modes
    oe, ge, _ = _eval(False, inputs, go)
    assert _rel(of, oe) <= 1e-12
    _grad_close(gf, ge, 1e-12)
    tang = {k: torch.randn(inputs[k].shape, generator=g, dtype=torch.float64) for k in ("n", "base_color", "roughness")}
    rest = {k: t for k, t in inputs.items() if k not in tang}

    def f(*ts):
        return torchbrdf.principled(**rest, **dict(zip(tang, ts)))

    out = {}
    for fast in (True, False):
        torchbrdf.set_fast_path(fast)
        try:
            out[fast] = torch.func.jvp(f, tuple(inputs[k] for k in tang), tuple(tang.values()))[1]
        finally:
            torchbrdf.set_fast_path(None)
    assert _rel(out[True], out[False]) <= 1e-10


def test_jvp_kernel_carries_only_the_differentiated_inputs(monkeypatch):
    # torch.func.jvp passes zero tangents for every other tensor input; the kernel must not
    # propagate them (its spec lists only base_color), and the result still equals eager.
    from torchbrdf.kernels import c_runner as ops_mod

    specs = []
    real = ops_mod.load
    monkeypatch.setattr(ops_mod, "load", lambda spec, backward: (specs.append(spec), real(spec, backward))[1])
    inputs = _case(5, 9000, torch.float64)
    base = inputs.pop("base_color")

    def f(b):
        return torchbrdf.principled(**inputs, base_color=b)

    out = {}
    for fast in (True, False):
        torchbrdf.set_fast_path(fast)
        try:
            out[fast] = torch.func.jvp(f, (base,), (torch.ones_like(base),))[1]
        finally:
            torchbrdf.set_fast_path(None)
    jvp_specs = [sp for sp in specs if sp.ntan or sp.tangent_inputs]
    names = [sp.tensors[k][0] for sp in jvp_specs for k in sp.tangent_inputs]
    assert names == ["base_color"]
    assert _rel(out[True], out[False]) <= 1e-10


def test_jvp_directions_pass_only_their_nonzero_inputs(monkeypatch):
    # A Gauss-Newton Jacobian's directions are unit vectors in one unknown each: one pass
    # computes the primal once, and each direction carries only the tangents it moves (the
    # others' tangent mode "zero": pruned from the kernel).
    from torchbrdf.kernels import c_runner as ops_mod

    specs = []
    real = ops_mod.load

    def load(spec, backward):
        specs.append(spec)
        return real(spec, backward)

    monkeypatch.setattr(ops_mod, "load", load)
    inputs = _case(31, 9000, torch.float64, min_cos=0.05)
    base, rough = inputs.pop("base_color"), inputs.pop("roughness")
    K = 6
    tb, tr = torch.zeros(K, *base.shape, dtype=base.dtype), torch.zeros(K, *rough.shape, dtype=rough.dtype)
    tb[0] = torch.rand_like(base)        # base colour only
    tr[1] = torch.rand_like(rough)       # roughness only
    tb[2], tr[2] = torch.rand_like(base), torch.rand_like(rough)  # both
    #                                      direction 3: nothing moves
    tb[4, :, 1] = 1.0                      # base colour only, like direction 0
    tr[5] = -1.0                           # roughness only, like direction 1

    def f(b, r):
        return torchbrdf.principled(**inputs, base_color=b, roughness=r)

    def jvps():
        return torch.func.vmap(lambda u, w: torch.func.jvp(f, (base, rough), (u, w))[1])(tb, tr)

    fused = jvps()
    P.set_fast_path(False)
    try:
        ref = jvps()
    finally:
        P.set_fast_path(None)
    torch.testing.assert_close(fused, ref, rtol=1e-10, atol=1e-12)
    assert float(fused[3].abs().max()) == 0.0
    passes = [sp for sp in specs if sp.ntan]
    assert [(sp.ntan, tuple(sp.tensors[k][0] for k in sp.tangent_inputs)) for sp in passes] == [
        (6, ("base_color", "roughness"))]
    zero = [[m == "zero" for m in passes[0].tangent_modes[2 * j:2 * j + 2]] for j in range(K)]
    assert zero == [[False, True], [True, False], [False, False], [True, True], [False, True], [True, False]]


def test_a_channel_strided_per_pixel_input_is_not_copied_to_every_lane():
    # A per-pixel (P, 1, 3) value broadcast over lights whose channels are not adjacent (a slice
    # of a transposed tensor) is made dense at its own size, and read broadcast ('s2').
    from torchbrdf.kernels.layout import flatten as _flatten

    P_, L = 50, 4
    strided = torch.rand(3, P_).T[:, None]  # (P, 1, 3), channel stride P
    flat, mode = _flatten(strided, 3, (P_, L), P_ * L, s2=True)
    assert mode == "s2" and flat.shape == (P_, L, 3)
    torch.testing.assert_close(flat, strided.expand(P_, L, 3))
    # One value for all three channels, its size-1 last dim strided: already "contiguous".
    one = torch.rand(3, 4, 5).permute(1, 2, 0)[..., :1]
    flat, mode = _flatten(one, 3, (4, 5), 20, s2=True)
    torch.testing.assert_close(flat.reshape(4, 5, 3), one.expand(4, 5, 3))


def _layouts():
    """Tensors of many layouts: sliced, transposed, expanded, zero-size, one-element dims."""
    g = torch.Generator().manual_seed(0)

    def randint(lo, hi):
        return int(torch.randint(lo, hi, (1,), generator=g))

    out = []
    for _ in range(300):
        shape = [randint(0, 5) for _ in range(randint(1, 5))]
        t = torch.rand([s + 2 for s in shape], generator=g)
        t = t[tuple(slice(randint(0, 2), None, randint(1, 3)) for _ in shape)]
        t = t.permute(*torch.randperm(t.dim(), generator=g).tolist())
        if bool(torch.rand(1, generator=g) < 0.4):  # one dim broadcast (stride 0)
            d = randint(0, t.dim())
            t = t.narrow(d, 0, min(1, t.size(d))).expand(*t.shape[:d], 3, *t.shape[d + 1:])
        out.append(t)
    # no elements: any view works
    return out + [torch.rand(4, 0, 3).transpose(0, 2), torch.empty(0, 2).expand(3, 0, 2)]


def test_merge_check_agrees_with_view():
    """``_merges`` (asked instead of a view that may raise) says exactly when ``view`` works."""
    from torchbrdf.kernels.layout import merges as _merges

    seen = set()
    for t in _layouts():
        for dims in range(1, t.dim() + 1):
            try:
                t.view(-1 if t.numel() else 0, *t.shape[dims:])
                ok = True
            except RuntimeError:
                ok = False
            seen.add(ok)
            assert _merges(t, dims) == ok, (t.shape, t.stride(), dims)
    assert seen == {True, False}


def test_fast_broadcast_shapes_match_torch():
    """``_checks.broadcast_shapes`` gives torch's result, and raises where torch's raises."""
    from torchbrdf._checks import broadcast_shapes

    g = torch.Generator().manual_seed(1)

    def randint(lo, hi):
        return int(torch.randint(lo, hi, (1,), generator=g))

    results = set()
    for _ in range(500):
        shapes = [tuple(randint(0, 4) for _ in range(randint(0, 4))) for _ in range(randint(1, 4))]
        try:
            want = torch.broadcast_shapes(*shapes)
        except RuntimeError:
            want = None
        try:
            got = broadcast_shapes(*shapes)
        except RuntimeError:
            got = None
        results.add(want is None)
        assert got == want and (got is None or type(got) is torch.Size), shapes
    assert results == {True, False}
    assert broadcast_shapes() == torch.Size([])


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_types_round_trip(dtype):
    inputs = _case(4, 512, dtype, min_cos=0.05)
    go = torch.ones(512, 3, dtype=dtype)
    of, gf, _ = _eval(True, inputs, go)
    oe, ge, _ = _eval(False, inputs, go)
    assert of.dtype == dtype and all(t.dtype == dtype for t in gf.values())
    torch.testing.assert_close(of, oe, rtol=0, atol=0)  # same float32 math, same rounding
    for k in ge:
        torch.testing.assert_close(gf[k], ge[k], rtol=1e-2, atol=1e-2 * float(ge[k].abs().max()))


def test_below_horizon_zero_with_finite_gradients(fast):
    inputs = _case(8, 256, torch.float32)
    inputs["l"][:128] *= -1.0
    below = (inputs["n"] * inputs["l"]).sum(-1) <= 0
    of, gf, _ = _eval(True, inputs, torch.ones(256, 3))
    assert (of[below] == 0).all()
    for k, g in gf.items():
        assert torch.isfinite(g).all(), k
    assert (gf["base_color"][below] == 0).all() and (gf["roughness"][below] == 0).all()


def test_double_backward_falls_back_to_a_differentiable_graph(fast):
    vec, base, params = random_case(14, count=3, min_cos=0.1)
    rough = torch.full((3, 1), 0.5, dtype=torch.float64, requires_grad=True)
    t = to_t(vec, torch.float64)

    def f(r):
        return torchbrdf.principled(**t, base_color=torch.as_tensor(base), roughness=r).sum()

    (g,) = torch.autograd.grad(f(rough), rough, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), rough)
    P.set_fast_path(False)
    (ge,) = torch.autograd.grad(f(rough), rough, create_graph=True)
    (he,) = torch.autograd.grad(ge.sum(), rough)
    torch.testing.assert_close(g, ge, rtol=1e-10, atol=0)
    torch.testing.assert_close(h, he, rtol=1e-10, atol=0)


def test_dispatch_switches(monkeypatch):
    inputs = _case(6, 64, torch.float32)
    P.set_fast_path(None)
    assert "PrincipledFunction" not in torchbrdf.principled(**{k: t.requires_grad_() for k, t in inputs.items()}).grad_fn.name()
    big = _case(6, P.FAST_PATH_MIN_LANES, torch.float32)
    big = {k: t.requires_grad_() for k, t in big.items()}
    assert "PrincipledFunction" in torchbrdf.principled(**big).grad_fn.name()
    monkeypatch.setenv("TORCHBRDF_EAGER", "1")
    assert "PrincipledFunction" not in torchbrdf.principled(**big).grad_fn.name()
    monkeypatch.delenv("TORCHBRDF_EAGER")
    P.set_fast_path(False)
    try:
        assert "PrincipledFunction" not in torchbrdf.principled(**big).grad_fn.name()
    finally:
        P.set_fast_path(None)
    with pytest.raises(ValueError, match="enabled"):
        P.set_fast_path("yes")


def test_no_grad_and_scalar_inputs(fast):
    inputs = _case(7, 128, torch.float32)
    with torch.no_grad():
        out = torchbrdf.principled(**inputs)
    assert out.grad_fn is None and out.shape == (128, 3)
    grey = torchbrdf.principled(inputs["l"], inputs["v"], inputs["n"], base_color=0.5)
    P.set_fast_path(False)
    assert _rel(grey, torchbrdf.principled(inputs["l"], inputs["v"], inputs["n"], base_color=0.5)) <= 1e-6
    assert SCALARS  # the shared parameter list is the one the reference tests use


# ---------------------------------------------------------------------------------------------
# One definition, the operator, expanded inputs, zero lanes, torch.func, torch.compile
# ---------------------------------------------------------------------------------------------

from torchbrdf.brdf import formula  # noqa: E402
from torchbrdf.kernels import ops as _ops  # noqa: E402

BIG = P.FAST_PATH_MIN_LANES  # the default dispatch takes the fused path from here


def _one(t):
    """``t``'s first lane, expanded back over all lanes (an expanded view, stride 0)."""
    return t[:1].clone()


@pytest.mark.parametrize("expanded", ["roughness", "base_color", "all"])
def test_inputs_expanded_from_one_element_get_correct_gradients(expanded):
    # The ordinary way to fit one global material: roughness=r.expand(N, 1). The old fused
    # backward raised "shape '[N, 3]' is invalid for input of size 3" for these.
    inputs = _case(21, BIG, torch.float32, min_cos=0.05)
    names = list(inputs) if expanded == "all" else [expanded]
    names = [k for k in names if k != "l"]  # keep the lanes different from each other
    leaves = {k: _one(inputs[k]).requires_grad_() for k in names}
    go = torch.rand(BIG, 3, generator=torch.Generator().manual_seed(2))
    res = {}
    for fast in (None, False):
        P.set_fast_path(fast)
        try:
            for t in leaves.values():
                t.grad = None
            args = {**inputs, **{k: t.expand(BIG, t.shape[-1]) for k, t in leaves.items()}}
            out = torchbrdf.principled(**args)
            assert ("PrincipledFunction" in out.grad_fn.name()) == (fast is None)
            out.backward(go)
            res[fast] = (out.detach(), {k: t.grad.clone() for k, t in leaves.items()})
        finally:
            P.set_fast_path(None)
    assert _rel(res[None][0], res[False][0]) <= 1e-6
    for k in leaves:
        assert res[None][1][k].shape == leaves[k].shape
        torch.testing.assert_close(res[None][1][k], res[False][1][k], rtol=1e-4, atol=0)


def test_expanded_leaf_keeps_per_lane_gradients(fast):
    # A leaf that *is* an expanded view (stride 0) still gets one gradient per lane.
    inputs = _case(22, 64, torch.float64, min_cos=0.05)
    rough = torch.tensor([[0.4]], dtype=torch.float64).expand(64, 1).requires_grad_()
    torchbrdf.principled(**{**inputs, "roughness": rough}).sum().backward()
    P.set_fast_path(False)
    ref = torch.full((64, 1), 0.4, dtype=torch.float64, requires_grad=True)
    torchbrdf.principled(**{**inputs, "roughness": ref}).sum().backward()
    torch.testing.assert_close(rough.grad, ref.grad, rtol=1e-12, atol=0)


def test_zero_lanes_forward_and_backward(fast):
    inputs = {k: t.requires_grad_() for k, t in _case(23, 0, torch.float32).items()}
    out = torchbrdf.principled(**inputs)
    assert out.shape == (0, 3) and "PrincipledFunction" in out.grad_fn.name()
    out.sum().backward()  # the old code: "range() arg 3 must not be zero"
    for k, t in inputs.items():
        assert t.grad is not None and t.grad.shape == t.shape and not t.grad.any(), k
    shared = torch.tensor(0.5, requires_grad=True)  # broadcast over zero lanes: zero gradient
    torchbrdf.principled(inputs["l"], inputs["v"], inputs["n"], base_color=0.5, roughness=shared).sum().backward()
    assert shared.grad == 0


def test_eager_and_kernels_come_from_one_definition(monkeypatch):
    # Perturb one constant of the shared formula: the eager path and a freshly generated kernel
    # family both change by exactly the same factor.
    inputs = {k: t for k, t in _case(24, 512, torch.float64, min_cos=0.05).items()
              if k in ("l", "v", "n", "base_color", "roughness")}
    kw = dict(lobes=("diffuse",), subsurface=0.0, metallic=0.0)
    before = {fast: _eval(fast, inputs, **kw)[0] for fast in (True, False)}
    monkeypatch.setattr(_fast, "_libs", {})  # this process's loaded kernels: rebuild from the formula
    monkeypatch.setattr(formula, "INV_PI", 2.0 * formula.INV_PI)
    after = {fast: _eval(fast, inputs, **kw)[0] for fast in (True, False)}
    for fast in (True, False):
        torch.testing.assert_close(after[fast], 2.0 * before[fast], rtol=1e-14, atol=0)
    monkeypatch.undo()
    assert _rel(_eval(True, inputs, **kw)[0], before[True]) == 0


def _count_calls(monkeypatch, name):
    from torchbrdf.kernels import c_runner

    calls = []
    real = getattr(c_runner, name)

    def spy(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(c_runner, name, spy)
    return calls


def test_func_jvp_jacfwd_vmap_run_fused_and_match_eager(monkeypatch):
    inputs = _case(25, BIG, torch.float32, min_cos=0.05)
    rough = inputs.pop("roughness")
    tangent = torch.randn(BIG, 1, generator=torch.Generator().manual_seed(3))

    def f(r):
        return torchbrdf.principled(**inputs, roughness=r)

    calls = _count_calls(monkeypatch, "run_jvp")
    out_f, jvp_f = torch.func.jvp(f, (rough,), (tangent,))
    assert len(calls) == 1
    P.set_fast_path(False)
    out_e, jvp_e = torch.func.jvp(f, (rough,), (tangent,))
    P.set_fast_path(None)
    assert _rel(out_f, out_e) <= 1e-6
    torch.testing.assert_close(jvp_f, jvp_e, rtol=1e-4, atol=1e-5 * float(jvp_e.abs().max()))

    # jacfwd w.r.t. one shared material (5 numbers): five tangents in one fused pass.
    base = {k: t for k, t in inputs.items() if k not in ("base_color", "metallic", "sheen")}

    def g(p):
        return torchbrdf.principled(**base, roughness=rough, base_color=p[:3], metallic=p[3:4], sheen=p[4:5])

    p = torch.tensor([0.6, 0.4, 0.2, 0.3, 0.5])
    calls.clear()
    jac_f = torch.func.jacfwd(g)(p)
    assert len(calls) == 1 and calls[0][4] == 5  # ntan = 5
    P.set_fast_path(False)
    jac_e = torch.func.jacfwd(g)(p)
    P.set_fast_path(None)
    assert jac_f.shape == (BIG, 3, 5)
    torch.testing.assert_close(jac_f, jac_e, rtol=1e-4, atol=1e-5 * float(jac_e.abs().max()))

    # vmap over a leading batch of light directions (folded into the lanes).
    ls = torch.stack([inputs["l"], inputs["l"].flip(0)])
    rest = {k: t for k, t in inputs.items() if k != "l"}
    calls = _count_calls(monkeypatch, "run_fwd")
    vm_f = torch.func.vmap(lambda l: torchbrdf.principled(l, roughness=rough, **rest))(ls)
    assert len(calls) == 1
    P.set_fast_path(False)
    vm_e = torch.func.vmap(lambda l: torchbrdf.principled(l, roughness=rough, **rest))(ls)
    P.set_fast_path(None)
    assert _rel(vm_f, vm_e) <= 1e-6


def test_vmapped_dims_count_toward_the_fused_threshold(monkeypatch):
    """Under automatic dispatch, ``vmap`` over 4 samples of BIG / 4 lanes is BIG lanes for the
    operator (its vmap rule folds them): fused, as the same batch without vmap is."""
    inputs = _case(27, BIG, torch.float32, min_cos=0.05)
    quarter = {k: t.reshape(4, BIG // 4, t.shape[-1]) for k, t in inputs.items()}
    calls = _count_calls(monkeypatch, "run_fwd")
    P.set_fast_path(None)
    out = torch.func.vmap(lambda kw: torchbrdf.principled(**kw))(quarter)
    assert len(calls) == 1
    torch.testing.assert_close(out.reshape(BIG, 3), _eval(False, inputs)[0], rtol=1e-6, atol=0)
    calls.clear()
    torch.func.vmap(lambda kw: torchbrdf.principled(**kw))({k: t[:, :8] for k, t in quarter.items()})
    assert not calls  # 4 x 8 lanes: eager, as without vmap


def test_forward_ad_dual_tensors_use_the_fused_jvp(fast):
    import torch.autograd.forward_ad as fwAD

    inputs = _case(26, 256, torch.float64, min_cos=0.05)
    t = torch.randn(256, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    with fwAD.dual_level():
        out = torchbrdf.principled(**{**inputs, "base_color": fwAD.make_dual(inputs["base_color"], t)})
        tan = fwAD.unpack_dual(out).tangent
    P.set_fast_path(False)
    _, ref = torch.func.jvp(lambda b: torchbrdf.principled(**{**inputs, "base_color": b}),
                            (inputs["base_color"],), (t,))
    torch.testing.assert_close(tan, ref, rtol=1e-12, atol=1e-12)


def test_custom_ops_pass_opcheck(fast):
    inputs = _case(27, 16, torch.float64, min_cos=0.05)
    names = ["l", "v", "n", "base_color", "roughness", "metallic"]
    tensors = [inputs[k].requires_grad_() for k in names]
    floats = [0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 1.0]
    float_names = ["subsurface", "specular", "specular_tint", "anisotropic", "sheen", "sheen_tint",
                   "clearcoat", "clearcoat_gloss"]
    cfg = _ops.make_cfg(names, float_names, ("diffuse", "specular"), False, False)
    torch.library.opcheck(torch.ops.torchbrdf.principled_fwd, (tensors, floats, cfg))
    go = torch.ones(16, 3, dtype=torch.float64)
    torch.library.opcheck(torch.ops.torchbrdf.principled_bwd, ([t.detach() for t in tensors], floats, cfg, go, [0, 4]))
    tans = [torch.ones_like(tensors[4])]
    torch.library.opcheck(torch.ops.torchbrdf.principled_jvp, ([t.detach() for t in tensors], floats, cfg, tans, [4], 0))


def test_torch_compile_fullgraph_runs_the_fused_operator():
    import torch._dynamo
    from torch._dynamo.utils import counters
    from torch._inductor.compile_fx import compile_fx

    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return compile_fx(gm, example_inputs)

    def user(l, v, n, base, rough):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=rough, clearcoat=0.3) * 2.0

    module = torch.compile(torchbrdf.PrincipledBRDF(), fullgraph=True, backend=backend)
    fn = torch.compile(user, fullgraph=True, backend=backend)
    counters.clear()
    for lanes in (100, 65536):
        inputs = _case(28, lanes, torch.float32, min_cos=0.05)
        args = (inputs["l"], inputs["v"], inputs["n"])
        base = inputs["base_color"].requires_grad_()
        rough = inputs["roughness"].requires_grad_()
        graphs.clear()
        out_m = module(*args, base_color=base, roughness=rough, clearcoat=0.3)
        out_u = fn(*args, base, rough)
        for gm in graphs:
            assert any("torchbrdf.principled_fwd" in str(nd.target) for nd in gm.graph.nodes), gm.code
        (gb,) = torch.autograd.grad(out_u.sum(), base)
        P.set_fast_path(False)
        ref = torchbrdf.principled(*args, base_color=base, roughness=rough, clearcoat=0.3)
        (gbe,) = torch.autograd.grad((ref * 2.0).sum(), base)
        P.set_fast_path(None)
        assert _rel(out_m, ref) <= 1e-6 and _rel(out_u, 2.0 * ref) <= 1e-6
        torch.testing.assert_close(gb, gbe, rtol=1e-4, atol=1e-6 * float(gbe.abs().max()))
    assert not counters["graph_break"]


@pytest.mark.parametrize("mode", ["jvp", "jvp_of_vmap", "jacfwd", "forward_ad"])
def test_forward_mode_inside_torch_compile_matches_eager(mode):
    """Forward mode traced by torch.compile (fullgraph) gives eager's tangents, not zeros: the
    fused operator has no forward-mode rule, so the compiled graph takes the eager formula
    there (a ``torch.func`` forward transform at any depth, or a ``forward_ad`` dual level)."""
    import torch.autograd.forward_ad as fwad
    import torch._dynamo

    inputs = _case(31, 64, torch.float32, min_cos=0.05)
    l, v, n, base, rough = inputs["l"], inputs["v"], inputs["n"], inputs["base_color"], inputs["roughness"]

    def f(r):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=r)

    def tangent(r):
        one = torch.ones_like(r)
        if mode == "jvp":
            return torch.func.jvp(f, (r,), (one,))[1]
        if mode == "jvp_of_vmap":  # the forward transform below the top of the stack
            g = torch.func.vmap(lambda rr: torchbrdf.principled(l[:1], v[:1], n[:1], base_color=base[:1],
                                                                roughness=rr))
            return torch.func.jvp(g, (r[:, None],), (one[:, None],))[1][:, 0]
        if mode == "jacfwd":
            return torch.func.jacfwd(lambda r: f(r).sum(0))(r).sum(1)[..., 0].T
        with fwad.dual_level():
            return fwad.unpack_dual(f(fwad.make_dual(r, one))).tangent

    torch._dynamo.reset()
    ref = tangent(rough)
    out = torch.compile(tangent, fullgraph=True, backend="aot_eager")(rough)
    assert float(ref.abs().max()) > 0
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()))


def test_jacfwd_over_many_parameters_runs_in_passes_of_a_few_tangents(fast, monkeypatch):
    # jacfwd w.r.t. a per-lane map: K = lanes tangents, split into passes of TANGENTS_PER_PASS.
    from torchbrdf.kernels import c_runner

    monkeypatch.setattr(c_runner, "TANGENTS_PER_PASS", 4)
    inputs = _case(29, 10, torch.float64, min_cos=0.05)
    rough = inputs.pop("roughness")

    def f(r):
        return torchbrdf.principled(**inputs, roughness=r)

    jac = torch.func.jacfwd(f)(rough)  # K = 10: passes of 4, 4 and 2 tangents
    P.set_fast_path(False)
    ref = torch.func.jacfwd(f)(rough)
    assert jac.shape == (10, 3, 10, 1)
    torch.testing.assert_close(jac, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_torch_compile_every_parameter_a_tensor(dtype):
    # No Python-float parameter at all (an empty float list in the operator's inputs), the
    # anisotropic frame, and a half type evaluated in float32.
    inputs = {k: t.requires_grad_() for k, t in _case(30, 300, dtype, min_cos=0.05).items()}
    fn = torch.compile(lambda **kw: torchbrdf.principled(**kw), fullgraph=True, backend="aot_eager")
    out = fn(**inputs)
    grads = torch.autograd.grad(out.sum(), list(inputs.values()))
    P.set_fast_path(False)
    ref = torchbrdf.principled(**inputs)
    refs = torch.autograd.grad(ref.sum(), list(inputs.values()))
    P.set_fast_path(None)
    tol = 1e-12 if dtype == torch.float64 else 2e-3
    assert _rel(out.double(), ref.double().clamp_min(1e-3)) <= tol or torch.allclose(out, ref, rtol=tol, atol=tol)
    for g, r in zip(grads, refs):
        assert ((g - r).abs().max() / r.abs().max().clamp_min(1e-30)).item() <= tol


def test_brdf_does_not_import_the_kernels_at_import_time():
    # brdf <- kernels, never the other way round at import: the kernels import the formula.
    # Only the backend switch (a settings module that imports nothing of torchbrdf) is loaded
    # with the package, for torchbrdf.set_backend.
    import subprocess
    import sys

    code = ("import sys, torchbrdf; "
            "loaded = [m for m in sys.modules if m.startswith('torchbrdf.kernels')];"
            "assert set(loaded) <= {'torchbrdf.kernels', 'torchbrdf.kernels.backend'}, loaded")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_torch_func_compositions_match_eager(fast):
    # Per-sample gradients, jacrev, per-lane Jacobians (vmap of jacfwd / jacrev over lanes),
    # jvp of a vmap, forward over reverse (hessian: the backward then runs the same formula
    # eagerly under forward mode, instead of silently dropping the tangent) and reverse over
    # forward (the vjp of the formula's eager jvp).
    inputs = _case(31, 16, torch.float64, min_cos=0.05)
    r, b = inputs.pop("roughness"), inputs.pop("base_color")

    def f(r):
        return torchbrdf.principled(**inputs, base_color=b, roughness=r)

    def loss(r):
        return f(r).square().sum()

    def one(l, v, n, p):
        return torchbrdf.principled(l, v, n, base_color=p[:3], roughness=p[3:4], metallic=p[4:5])

    batch = torch.rand(4, 16, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    per_lane = torch.rand(16, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    lanes = (inputs["l"], inputs["v"], inputs["n"], per_lane)
    cases = {
        "vmap(grad)": lambda: torch.func.vmap(torch.func.grad(loss))(batch),
        "jacrev": lambda: torch.func.jacrev(f)(r),
        "vmap(jacfwd)": lambda: torch.func.vmap(torch.func.jacfwd(one, argnums=3))(*lanes),
        "vmap(jacrev)": lambda: torch.func.vmap(torch.func.jacrev(one, argnums=3))(*lanes),
        "jvp(vmap)": lambda: torch.func.jvp(torch.func.vmap(f), (batch,), (torch.ones_like(batch),))[1],
        "hessian": lambda: torch.func.hessian(loss)(r),
        "jacrev(jacfwd)": lambda: torch.func.jacrev(torch.func.jacfwd(loss))(r),
        "grad(jvp)": lambda: torch.func.grad(lambda r: torch.func.jvp(f, (r,), (torch.ones_like(r),))[1].sum())(r),
    }
    for name, fn in cases.items():
        P.set_fast_path(True)
        got = fn()
        P.set_fast_path(False)
        ref = fn()
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12 * float(ref.abs().max()), msg=name)


_SMALL_STACK_JVP = r"""
import sys, threading, torch, torchbrdf
from torch.func import jvp, vmap
g = torch.Generator().manual_seed(0)
dt, P, L = torch.float64, 64, 8
z = torch.tensor([0.0, 0.0, 2.0], dtype=dt)
l = torch.nn.functional.normalize(torch.randn(1, L, 3, dtype=dt, generator=g) + z, dim=-1)  # per light
v = torch.nn.functional.normalize(torch.randn(P, 1, 3, dtype=dt, generator=g) + z, dim=-1)  # per pixel
n = torch.nn.functional.normalize(torch.randn(P, 1, 3, dtype=dt, generator=g) + z, dim=-1)
th = torch.rand(P, 1, 5, dtype=dt, generator=g)

def f(t):
    return torchbrdf.principled(l, v, n, base_color=t[..., :3], roughness=t[..., 3:4], metallic=t[..., 4:5])

torchbrdf.set_fast_path(True)
tg = torch.eye(5, dtype=dt)[:, None, None, :].expand(5, P, 1, 5)
run = lambda: vmap(lambda t: jvp(f, (th,), (t,))[1])(tg)
want = run()  # compiles in the main thread
threading.stack_size(128 * 1024)  # musl's default thread stack
got = []
t = threading.Thread(target=lambda: got.append(run()))
t.start()
t.join()
sys.exit(0 if got and torch.equal(got[0], want) else 3)
"""


def test_broadcast_reads_fit_a_small_thread_stack():
    # Inputs broadcast over one of two batch dims ('s2') are gathered per block of lanes. The
    # gather buffers lived on the stack: a JVP pass with 5 tangents of per-pixel inputs under
    # per-light directions needed ~150 KiB (0.5 MiB with 8 tangents and every parameter), and
    # a thread with a 128 KiB stack (musl's default; a 512 KiB macOS pthread with more
    # tangents) crashed with SIGSEGV. They are now one heap block per thread.
    import os
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-c", _SMALL_STACK_JVP], env=env, capture_output=True, timeout=600)
    assert r.returncode == 0, (r.returncode, r.stderr.decode()[-2000:])
