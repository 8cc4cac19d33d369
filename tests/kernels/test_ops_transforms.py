"""The fused operators under ``torch.func`` and batched gradient checks (torchbrdf/kernels/ops.py).

Kept cheap: 16 to 64 lanes in float64, a few kernel families (cached on disk after the first build).
"""

import importlib

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

import torchbrdf

from tests.kernels.test_fast_path import fast, pytestmark  # noqa: F401  (the fused-path fixture and skip mark)
from tests.brdf.test_principled import random_case, to_t

P = importlib.import_module("torchbrdf.brdf.principled")
c_runner = importlib.import_module("torchbrdf.kernels.c_runner")


def _inputs(seed, count):
    vec, base, params = random_case(seed, count=count, min_cos=0.05)
    t = to_t(vec, torch.float64)
    return t["l"], t["v"], t["n"], torch.as_tensor(base), torch.as_tensor(params["roughness"])


@pytest.fixture
def backward_kernel_calls(monkeypatch):
    """How many times the fused backward kernel runs."""
    calls = []
    run = c_runner.run_bwd

    def counted(*args, **kw):
        calls.append(1)
        return run(*args, **kw)

    monkeypatch.setattr(c_runner, "run_bwd", counted)
    return calls


@pytest.mark.parametrize("transform", ["grad", "vjp", "vmap(grad)", "jacrev", "grad(grad)"])
def test_torch_func_reverse_mode_runs_the_backward_kernel(fast, backward_kernel_calls, transform):
    # torch.func.grad records its backward (create_graph) in case a transform around it
    # differentiates again: the backward must still be the kernel, not the eager formula.
    l, v, n, base, rough = _inputs(41, 32)

    def loss(r):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=r).square().sum()

    def out(r):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=r)

    batch = torch.rand(3, 32, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    run = {
        "grad": lambda: torch.func.grad(loss)(rough),
        "vjp": lambda: torch.func.vjp(out, rough)[1](torch.ones(32, 3, dtype=torch.float64))[0],
        "vmap(grad)": lambda: torch.func.vmap(torch.func.grad(loss))(batch),
        "jacrev": lambda: torch.func.jacrev(lambda r: out(r).sum(0))(rough),
        "grad(grad)": lambda: torch.func.grad(lambda r: torch.func.grad(loss)(r).sum())(rough),
    }[transform]
    got = run()
    assert backward_kernel_calls, f"{transform}: the fused backward kernel never ran"
    P.set_fast_path(False)
    want = run()
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12 * float(want.abs().max()))


def test_create_graph_backward_runs_the_kernel_and_differentiates(fast, backward_kernel_calls):
    l, v, n, base, rough = _inputs(42, 16)
    rough = rough.clone().requires_grad_()
    base = base.clone().requires_grad_()
    out = torchbrdf.principled(l, v, n, base_color=base, roughness=rough)
    g_r, g_b = torch.autograd.grad(out.square().sum(), (rough, base), create_graph=True)
    assert backward_kernel_calls
    h_r, h_b = torch.autograd.grad(g_r.sum() + g_b.square().sum(), (rough, base))
    P.set_fast_path(False)
    out = torchbrdf.principled(l, v, n, base_color=base, roughness=rough)
    e_r, e_b = torch.autograd.grad(out.square().sum(), (rough, base), create_graph=True)
    w_r, w_b = torch.autograd.grad(e_r.sum() + e_b.square().sum(), (rough, base))
    for got, want in ((g_r, e_r), (g_b, e_b), (h_r, w_r), (h_b, w_b)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_gradcheck_with_batched_gradients_on_the_fused_path(fast):
    # gradcheck's batched checks run under the legacy vmap (torch._vmap_internals), whose
    # fallback cannot loop over an operator with tensor-list arguments.
    l, v, n, base, rough = _inputs(43, 8)
    metal = torch.rand(8, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(3))

    def f(b, r, m):
        return torchbrdf.principled(l, v, n, base_color=b, roughness=r, metallic=m, clearcoat=0.4)

    args = tuple(t.clone().requires_grad_() for t in (base, rough, metal))
    assert "PrincipledFunction" in f(*args).grad_fn.name()
    assert gradcheck(f, args, check_batched_grad=True, check_forward_ad=True, check_batched_forward_grad=True)
    assert gradgradcheck(f, args, check_batched_grad=True, check_fwd_over_rev=True)
