"""The Triton kernels of ``principled`` (kernels/codegen_triton.py), run by Triton's CPU interpreter.

No GPU is needed: with ``TRITON_INTERPRET=1`` the generated ``@triton.jit`` kernels run on CPU
tensors through NumPy (the interpreter flag is read when a kernel is decorated, i.e. when the
generated module is imported, so the module fixture sets it before any kernel is loaded and
restores it afterwards). Batches are small: the interpreter is slow, but its cost per launch
barely depends on the lanes (one NumPy pass per block of 4096 lanes).
"""

import importlib
import math
import os

import numpy as np
import pytest
import torch

import torchbrdf

from tests.reference import principled_ref
from tests.brdf.test_principled import SCALARS, random_case, to_t

triton = pytest.importorskip("triton")

from tests.kernels.triton_interpreter import interpreter, launches  # noqa: E402,F401  (fixtures)

P = importlib.import_module("torchbrdf.brdf.principled")
formula = importlib.import_module("torchbrdf.brdf.formula")
ct = importlib.import_module("torchbrdf.kernels.codegen_triton")
ops_mod = importlib.import_module("torchbrdf.kernels.ops")
triton_runner = importlib.import_module("torchbrdf.kernels.triton_runner")
backend_mod = importlib.import_module("torchbrdf.kernels.backend")


def _case(seed, count, dtype, min_cos=0.0):
    vec, base, params = random_case(seed, count=count, min_cos=min_cos)
    return {**to_t(vec, dtype), "base_color": torch.as_tensor(base, dtype=dtype), **to_t(params, dtype)}


def _run(backend, inputs, grad_out=None, **extra):
    """Forward (+ backward) with ``backend`` on clones of ``inputs``: ``(out, grads)``."""
    old = backend_mod.get_backend()
    torchbrdf.set_backend(backend)
    try:
        ins = {k: (t.detach().clone().requires_grad_(grad_out is not None and t.is_floating_point())
                   if isinstance(t, torch.Tensor) else t) for k, t in inputs.items()}
        out = torchbrdf.principled(**ins, **extra)
        grads = {}
        if grad_out is not None:
            out.backward(grad_out)
            grads = {k: t.grad for k, t in ins.items() if isinstance(t, torch.Tensor)}
        return out.detach(), grads
    finally:
        torchbrdf.set_backend(old)


def _rel(a, b):
    return ((a - b).abs() / b.abs().clamp_min(1e-30)).max().item()


def _grads_close(gt, ge, rtol):
    for k in ge:
        assert (gt[k] is None) == (ge[k] is None), k
        if ge[k] is None:
            continue
        assert gt[k].shape == ge[k].shape, k
        scale = ge[k].abs().max().clamp_min(1e-30)
        err = ((gt[k] - ge[k]).abs() / scale).max().item()
        assert err <= rtol, (k, err)


N = 2048


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-4), (torch.float64, 1e-10)])
def test_values_match_the_float64_reference(dtype, tol, launches):
    # All eleven parameters per lane (plus l, v, n, x, y): every lobe, tint and the frame.
    inputs = _case(0, N, dtype, min_cos=0.02)
    out, _ = _run("triton", inputs)
    assert launches == ["fwd"]
    up = {k: t.double().numpy() for k, t in inputs.items()}  # judged on the rounded inputs
    ref = principled_ref(up["l"], up["v"], up["n"], up["x"], up["y"], up["base_color"],
                         **{k: up[k] for k in SCALARS})
    err = np.abs(out.double().numpy() - ref) / np.maximum(np.abs(ref), 1e-6)
    assert err.max() <= tol


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-3), (torch.float64, 1e-10)])
def test_gradients_and_jvp_match_eager(dtype, tol, launches):
    inputs = _case(1, N, dtype)
    go = torch.randn(N, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    ot, gt = _run("triton", inputs, go)
    oe, ge = _run("eager", inputs, go)
    assert launches == ["fwd", "bwd"]
    assert _rel(ot, oe) <= (1e-5 if dtype == torch.float32 else 1e-12)
    _grads_close(gt, ge, tol)

    names = list(inputs)
    tans = tuple(torch.randn(t.shape, generator=torch.Generator().manual_seed(i), dtype=dtype)
                 for i, t in enumerate(inputs.values()))

    def f(*a):
        return torchbrdf.principled(**dict(zip(names, a)))

    _, jt = torch.func.jvp(f, tuple(inputs.values()), tans)
    assert launches[-1] == "jvp"
    torchbrdf.set_backend("eager")
    try:
        _, je = torch.func.jvp(f, tuple(inputs.values()), tans)
    finally:
        torchbrdf.set_backend("triton")
    assert (jt - je).abs().max() / je.abs().max() <= tol


def test_every_lobe_combination_matches_eager(launches):
    inputs = _case(2, 512, torch.float32)
    lobes = torchbrdf.LOBES
    for mask in range(1, 1 << len(lobes)):
        subset = tuple(lb for j, lb in enumerate(lobes) if mask >> j & 1)
        ot, _ = _run("triton", inputs, lobes=subset)
        oe, _ = _run("eager", inputs, lobes=subset)
        torch.testing.assert_close(ot, oe, rtol=1e-5, atol=1e-6, msg=str(subset))
    assert len(launches) == 31


@pytest.mark.parametrize("params", [
    dict(metallic=1.0),  # metal: diffuse, subsurface and sheen pruned
    dict(subsurface=0.0, sheen=0.0, clearcoat=0.0, specular_tint=0.0),  # no tint, specular + diffuse
    dict(subsurface=1.0, sheen_tint=0.0, anisotropic=0.0),  # no diffuse; no frame
    dict(roughness=0.3, clearcoat_gloss=0.7, anisotropic=0.5),  # runtime floats, float anisotropy
])
def test_pruned_and_float_parameters_match_eager(params):
    inputs = _case(3, 1024, torch.float64)
    for k in params:
        inputs.pop(k)
    if params.get("anisotropic", 1.0) == 0.0:
        inputs.pop("x"), inputs.pop("y")
    go = torch.randn(1024, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    ot, gt = _run("triton", inputs, go, **params)
    oe, ge = _run("eager", inputs, go, **params)
    assert _rel(ot, oe) <= 1e-12
    _grads_close(gt, ge, 1e-10)


def test_broadcasting_matches_eager():
    # l, v (4, 5, 3); a shared normal (3,); base colour per row (4, 1, 3); 0-d and (1, 1) parameters.
    g = torch.Generator().manual_seed(4)
    dt = torch.float64
    n = torch.tensor([0.1, 0.2, 1.0], dtype=dt)
    n = n / n.norm()

    def up(*shape):
        w = torch.randn(*shape, 3, generator=g, dtype=dt) * 0.5 + n
        return w / w.norm(dim=-1, keepdim=True)

    inputs = dict(l=up(4, 5), v=up(4, 5), n=n, base_color=torch.rand(4, 1, 3, generator=g, dtype=dt),
                  roughness=torch.tensor(0.4, dtype=dt), metallic=torch.rand(1, 1, generator=g, dtype=dt),
                  clearcoat=torch.rand(4, 5, 1, generator=g, dtype=dt),
                  sheen=torch.rand(5, 1, generator=g, dtype=dt))
    go = torch.randn(4, 5, 3, generator=g, dtype=dt)
    ot, gt = _run("triton", inputs, go)
    oe, ge = _run("eager", inputs, go)
    assert ot.shape == (4, 5, 3)
    assert _rel(ot, oe) <= 1e-12
    _grads_close(gt, ge, 1e-10)


def test_expanded_inputs_and_chunked_reductions_match_eager(monkeypatch):
    # An expanded leaf keeps per-lane gradients (summed by autograd); a (1,)-shaped shared
    # parameter is reduced over the lanes in chunks (made small here to cover the chunk loop).
    monkeypatch.setattr(triton_runner, "TRITON_BWD_CHUNK", 1000)
    inputs = _case(5, 2500, torch.float32)
    r = torch.tensor([[0.35]])
    go = torch.randn(2500, 3, generator=torch.Generator().manual_seed(5))
    res = {}
    for backend in ("triton", "eager"):
        rough = r.clone().requires_grad_()
        spec = torch.tensor([0.6], requires_grad=True)
        old = backend_mod.get_backend()
        torchbrdf.set_backend(backend)
        try:
            rest = {k: t for k, t in inputs.items() if k not in ("roughness", "specular")}
            out = torchbrdf.principled(**rest, roughness=rough.expand(2500, 1), specular=spec)
            out.backward(go)
        finally:
            torchbrdf.set_backend(old)
        res[backend] = (out.detach(), rough.grad, spec.grad)
    for a, b in zip(res["triton"], res["eager"]):
        assert a.shape == b.shape
        assert ((a - b).abs().max() / b.abs().max()).item() <= 1e-4


def test_zero_lanes_and_half_types():
    z = torch.zeros(0, 3)
    ins = dict(l=z.clone(), v=z.clone(), n=z.clone(), base_color=z.clone().requires_grad_(),
               roughness=torch.zeros(0, 1, requires_grad=True))
    out = torchbrdf.principled(**ins)
    assert out.shape == (0, 3)
    out.sum().backward()
    assert ins["base_color"].grad.shape == (0, 3) and ins["roughness"].grad.shape == (0, 1)
    inputs = _case(6, 256, torch.float32, min_cos=0.05)
    for dt in (torch.float16, torch.bfloat16):  # evaluated in float32, as on every path
        half = {k: t.to(dt) for k, t in inputs.items()}
        ot, _ = _run("triton", half)
        oe, _ = _run("eager", half)
        assert ot.dtype == dt
        torch.testing.assert_close(ot, oe, rtol=1e-3, atol=0)


def test_triton_source_comes_from_the_one_formula(monkeypatch):
    # Perturb one constant of torchbrdf/brdf/formula.py: eager, the C kernels and freshly
    # generated Triton kernels all change by exactly the same factor.
    from torchbrdf.kernels import fused

    inputs = {k: t for k, t in _case(7, 512, torch.float64, min_cos=0.05).items()
              if k in ("l", "v", "n", "base_color", "roughness")}
    kw = dict(lobes=("diffuse",), subsurface=0.0, metallic=0.0)
    backends = ["eager", "triton"] + (["cpu"] if fused.available() else [])
    before = {b: _run(b, inputs, **kw)[0] for b in backends}
    src_before = _diffuse_source()
    monkeypatch.setattr(ct, "_kernels", {})
    monkeypatch.setattr(fused, "_libs", {})
    monkeypatch.setattr(formula, "INV_PI", 2.0 * formula.INV_PI)
    after = {b: _run(b, inputs, **kw)[0] for b in backends}
    for b in backends:
        torch.testing.assert_close(after[b], 2.0 * before[b], rtol=1e-14, atol=0, msg=b)
    assert repr(2.0 * (1.0 / math.pi)) in _diffuse_source() and _diffuse_source() != src_before


def _diffuse_source():
    from torchbrdf.kernels.fused import _KernelSpec

    spec = _KernelSpec("double", [("l", "full", 3), ("v", "full", 3), ("n", "full", 3),
                                  ("base_color", "full", 3), ("roughness", "full", 1)],
                       [k for k in SCALARS if k != "roughness"], ("diffuse",), False, False)
    return ct.generate(spec, "fwd")[0]


def test_shade_point_and_directional_lights_match_eager(launches):
    # shade evaluates the BRDF through principled, so its passes take the Triton kernels.
    from torchbrdf.render.geometry import sphere_gbuffer

    lights = [torchbrdf.PointLight(position=torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64),
                                   intensity=torch.tensor([5.0, 4.0, 3.0], dtype=torch.float64)),
              torchbrdf.DirectionalLight(direction=torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64),
                                         irradiance=torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64))]
    res = {}
    for backend in ("triton", "eager"):
        rough = torch.full((1, 1, 24, 24), 0.4, dtype=torch.float64, requires_grad=True)
        g = sphere_gbuffer(24, 24, dtype=torch.float64,
                           material={"roughness": rough, "clearcoat": 0.5, "base_color": 0.6})
        old = backend_mod.get_backend()
        torchbrdf.set_backend(backend)
        try:
            img = torchbrdf.shade(g, lights)
            img.sum().backward()
        finally:
            torchbrdf.set_backend(old)
        res[backend] = (img.detach(), rough.grad)
    assert "fwd" in launches and "bwd" in launches
    for a, b in zip(res["triton"], res["eager"]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_backend_selection(monkeypatch):
    with pytest.raises(ValueError, match="backend"):
        torchbrdf.set_backend("cuda")
    torchbrdf.set_backend(None)
    monkeypatch.setenv("TORCHBRDF_BACKEND", "eager")
    assert torchbrdf.get_backend() == "eager"
    assert backend_mod.resolve(torch.device("cpu")) == "eager"
    monkeypatch.setenv("TORCHBRDF_BACKEND", "triton")
    assert backend_mod.resolve(torch.device("cpu")) == "triton"  # interpreter on
    monkeypatch.setenv("TORCHBRDF_BACKEND", "bogus")
    with pytest.raises(ValueError, match="TORCHBRDF_BACKEND"):
        torchbrdf.get_backend()
    monkeypatch.delenv("TORCHBRDF_BACKEND")
    assert torchbrdf.get_backend() == "auto"
    # auto: C kernels (or eager) on CPU, never the interpreter; Triton on CUDA.
    assert backend_mod.resolve(torch.device("cpu")) in ("c", "eager")
    assert backend_mod.resolve(torch.device("cuda")) == "triton" if not ct.interpret_mode() else True
    monkeypatch.setenv("TORCHBRDF_BACKEND", "cpu")
    assert backend_mod.resolve(torch.device("cuda")) == "eager"
    monkeypatch.delenv("TORCHBRDF_BACKEND")
    torchbrdf.set_backend("triton")
    # set_fast_path(False) still means eager, whatever the backend.
    inputs = _case(8, 64, torch.float32)
    P.set_fast_path(False)
    try:
        calls = []
        monkeypatch.setattr(ct, "launch", lambda *a: calls.append(a))
        torchbrdf.principled(**inputs)
        assert calls == []
    finally:
        P.set_fast_path(None)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_auto_backend_matches_cpu_eager(monkeypatch):
    monkeypatch.delenv("TRITON_INTERPRET")
    torchbrdf.set_backend("auto")
    try:
        inputs = _case(9, 1 << 14, torch.float32)
        go = torch.randn(1 << 14, 3, generator=torch.Generator().manual_seed(9))
        oc, gc = _run("auto", {k: t.cuda() for k, t in inputs.items()}, go.cuda())
        oe, ge = _run("eager", inputs, go)
    finally:  # the module's other tests run the Triton backend (seen on a GPU machine: they ran C)
        torchbrdf.set_backend("triton")
    assert _rel(oc.cpu(), oe) <= 1e-5
    _grads_close({k: g.cpu() for k, g in gc.items()}, ge, 1e-4)


def test_kernels_compile_for_a_gpu_without_one():
    # The interpreter accepts some things the compiler does not: compile the float32 forward to
    # PTX/cubin for sm_90 (no GPU needed), as the CUDA path will on first use.
    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler import ASTSource
    except ImportError:
        pytest.skip("this Triton has no compiler API")
    import inspect

    from torchbrdf.kernels.fused import _KernelSpec

    names = ["l", "v", "n", "x", "y", "base_color", *SCALARS]
    spec = _KernelSpec("float", [(k, "full", 1 if k in SCALARS else 3) for k in names], [],
                       torchbrdf.LOBES, True, True)
    old = os.environ.pop("TRITON_INTERPRET")
    try:
        kern, _ = ct.load(spec, "fwd")
        sig = {a: "i32" if a == "n" else "*fp64" if a == "P" else "constexpr" if a == "BLOCK" else "*fp32"
               for a in inspect.signature(kern.fn).parameters}
        try:
            block = ct.block_size("fwd")  # what a GPU launch uses
            cc = triton.compile(ASTSource(fn=kern, signature=sig, constexprs={"BLOCK": block}),
                                target=GPUTarget("cuda", 90, 32),
                                options={"enable_fp_fusion": False, "num_warps": block // 32})
        except (RuntimeError, FileNotFoundError) as e:  # e.g. no ptxas for this platform
            if "ptxas" in str(e):
                pytest.skip(str(e))
            raise
    finally:
        os.environ["TRITON_INTERPRET"] = old
    ptx = cc.asm["ptx"]
    assert "div.rn.f32" in ptx and "sqrt.rn.f32" in ptx and "fma.rn.f32" not in ptx


def test_jacfwd_and_vmap_run_the_triton_kernels(launches, monkeypatch):
    # jacfwd over a shared 3-number material: 3 tangents, here 2 per pass of the JVP kernel
    # (2 launches); vmap folds the vmapped dimension into the lanes.
    monkeypatch.setattr(triton_runner, "TRITON_TANGENTS_PER_PASS", 2)
    drop = ("metallic", "roughness", "sheen")
    inputs = {k: t for k, t in _case(10, 256, torch.float64).items() if k not in drop}
    p = torch.tensor([0.3, 0.6, 0.2], dtype=torch.float64)

    def f(q):
        return torchbrdf.principled(**inputs, metallic=q[0:1], roughness=q[1:2], sheen=q[2:3])

    jt = torch.func.jacfwd(f)(p)
    assert launches.count("jvp") == 2
    vt = torch.func.vmap(f)(torch.stack([p, p.flip(0)]))
    torchbrdf.set_backend("eager")
    try:
        je = torch.func.jacfwd(f)(p)
        ve = torch.func.vmap(f)(torch.stack([p, p.flip(0)]))
    finally:
        torchbrdf.set_backend("triton")
    assert jt.shape == (256, 3, 3)
    torch.testing.assert_close(jt, je, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(vt, ve, rtol=1e-12, atol=1e-14)


def test_triton_operators_pass_opcheck(launches):
    # The same torch.library operators with cfg naming the Triton backend: schema, fake
    # implementations, autograd registration and AOT dispatch hold for them too.
    inputs = _case(27, 16, torch.float64, min_cos=0.05)
    names = ["l", "v", "n", "base_color", "roughness", "metallic"]
    tensors = [inputs[k].requires_grad_() for k in names]
    floats = [0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 1.0]
    float_names = ["subsurface", "specular", "specular_tint", "anisotropic", "sheen", "sheen_tint",
                   "clearcoat", "clearcoat_gloss"]
    cfg = ops_mod.make_cfg(names, float_names, ("diffuse", "specular"), False, False, backend="triton")
    torch.library.opcheck(torch.ops.torchbrdf.principled_fwd, (tensors, floats, cfg))
    go = torch.ones(16, 3, dtype=torch.float64)
    plain = [t.detach() for t in tensors]
    torch.library.opcheck(torch.ops.torchbrdf.principled_bwd, (plain, floats, cfg, go, [0, 4]))
    tans = [torch.ones_like(tensors[4])]
    torch.library.opcheck(torch.ops.torchbrdf.principled_jvp, (plain, floats, cfg, tans, [4], 0))
    assert {"fwd", "bwd", "jvp"} <= set(launches)


def test_64_bit_lane_indices(monkeypatch):
    # From 3 N >= 2^31 lanes the kernels index in int64; forced here on a small batch.
    monkeypatch.setattr(triton_runner, "needs_64bit_index", lambda N: True)
    inputs = _case(11, 300, torch.float64)
    ot, _ = _run("triton", inputs)
    oe, _ = _run("eager", inputs)
    assert _rel(ot, oe) <= 1e-12
    src = ct.generate(_full_spec(), "fwd", wide=True)[0]
    assert "tl.program_id(0).to(tl.int64)" in src


def _full_spec():
    from torchbrdf.kernels.fused import _KernelSpec

    names = ["l", "v", "n", "x", "y", "base_color", *SCALARS]
    return _KernelSpec("float", [(k, "full", 1 if k in SCALARS else 3) for k in names], [], torchbrdf.LOBES,
                       True, True)
