"""The Triton kernels of ``svbrdf_ggx`` (the ``svbrdf_ggx`` family), run by Triton's CPU interpreter.

As ``tests/kernels/test_triton_backend.py`` for ``principled``: ``TRITON_INTERPRET=1`` on CPU
tensors, small batches (the interpreter is slow).
"""

import importlib
import os

import pytest
import torch

import torchbrdf
from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx

from tests.kernels.test_ggx_family import MAPS, _case

triton = pytest.importorskip("triton")

from tests.kernels.triton_interpreter import interpreter, launches  # noqa: E402,F401  (fixtures)

ct = importlib.import_module("torchbrdf.kernels.codegen_triton")
ops_mod = importlib.import_module("torchbrdf.kernels.ops")
backend_mod = importlib.import_module("torchbrdf.kernels.backend")


def _run(backend, inputs, grad_out=None, **extra):
    """Forward (+ backward) with ``backend`` on clones of ``inputs``: ``(out, grads)``."""
    old = backend_mod.get_backend()
    torchbrdf.set_backend(backend)
    try:
        ins = {k: t.detach().clone().requires_grad_(grad_out is not None) for k, t in inputs.items()}
        out = svbrdf_ggx(**ins, **extra)
        grads = {}
        if grad_out is not None:
            out.backward(grad_out)
            grads = {k: t.grad for k, t in ins.items()}
        return out.detach(), grads
    finally:
        torchbrdf.set_backend(old)


@pytest.mark.parametrize("dtype, vtol, gtol", [(torch.float64, 1e-13, 1e-10), (torch.float32, 2e-6, 2e-6)],
                         ids=["float64", "float32"])
def test_values_gradients_and_jvp_match_eager(dtype, vtol, gtol, launches):
    # Without the normal-incidence lanes: the cosines' clamps at 1 kink there, and NumPy's
    # rounding may pick the other branch (another subgradient).
    inputs = {k: t[4:] for k, t in _case(20, 516, dtype).items()}
    go = torch.rand(512, 3, generator=torch.Generator().manual_seed(21), dtype=dtype)
    out_t, g_t = _run("triton", inputs, go, roughness_floor=1e-3)
    assert launches == ["fwd", "bwd"]
    out_e, g_e = _run("eager", inputs, go, roughness_floor=1e-3)
    torch.testing.assert_close(out_t, out_e, rtol=vtol, atol=0)
    for k in inputs:
        torch.testing.assert_close(g_t[k], g_e[k], rtol=0, atol=gtol * float(g_e[k].abs().max()), msg=k)

    names = list(inputs)
    tans = tuple(torch.randn(t.shape, generator=torch.Generator().manual_seed(i), dtype=dtype)
                 for i, t in enumerate(inputs.values()))

    def f(*a):
        return svbrdf_ggx(**dict(zip(names, a)))

    _, jt = torch.func.jvp(f, tuple(inputs.values()), tans)
    assert launches[-1] == "jvp"
    torchbrdf.set_backend("eager")
    try:
        _, je = torch.func.jvp(f, tuple(inputs.values()), tans)
    finally:
        torchbrdf.set_backend("triton")
    torch.testing.assert_close(jt, je, rtol=0, atol=gtol * float(je.abs().max()))


def test_triton_operators_pass_opcheck(launches):
    c = _case(22, 16)
    names = ["l", "v", "n", *MAPS]
    tensors = [c[k].requires_grad_() for k in names]
    cfg = ops_mod.make_cfg(names, ["alpha_floor"], (), False, False, backend="triton", family="svbrdf_ggx")
    floats = [1e-3]
    torch.library.opcheck(torch.ops.torchbrdf.principled_fwd, (tensors, floats, cfg))
    plain = [t.detach() for t in tensors]
    go = torch.ones(16, 3, dtype=torch.float64)
    torch.library.opcheck(torch.ops.torchbrdf.principled_bwd, (plain, floats, cfg, go, [0, 5]))
    tans = [torch.ones_like(plain[5])]
    torch.library.opcheck(torch.ops.torchbrdf.principled_jvp, (plain, floats, cfg, tans, [5], 0))
    assert {"fwd", "bwd", "jvp"} <= set(launches)


@pytest.mark.parametrize("kind", ["fwd", "bwd"])
def test_kernels_compile_for_a_gpu_without_one(kind):
    # The interpreter accepts things the compiler does not (float64 exp2, the tie masks): compile
    # to PTX for sm_90, as the CUDA path will on first use.
    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler import ASTSource
    except ImportError:
        pytest.skip("this Triton has no compiler API")
    import inspect

    from torchbrdf.kernels.fused import KernelSpec

    names = ["l", "v", "n", *MAPS]
    spec = KernelSpec("float", [(k, "full", 1 if k == "roughness" else 3) for k in names], ["alpha_floor"],
                      (), False, False, grad_mask=tuple(range(len(names))) if kind == "bwd" else (),
                      family="svbrdf_ggx")
    old = os.environ.pop("TRITON_INTERPRET")
    try:
        kern, _ = ct.load(spec, kind)
        sig = {a: "i32" if a == "n" else "*fp64" if a == "P" else "constexpr" if a == "BLOCK" else "*fp32"
               for a in inspect.signature(kern.fn).parameters}
        try:
            block = ct.block_size(kind)
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
    assert "div.rn.f32" in ptx and "fma.rn.f32" not in ptx
    assert "ex2.approx.f32" not in ptx  # exp2 in float64, rounded once
