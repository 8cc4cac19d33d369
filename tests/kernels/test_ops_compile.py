"""``torch.compile`` of ``principled`` with Python-float parameters (torchbrdf/kernels/ops.py)."""

import importlib

import pytest
import torch

import torchbrdf
from torchbrdf.kernels import fused as _fast

from tests.brdf.test_principled import random_case, to_t

P = importlib.import_module("torchbrdf.brdf.principled")

pytestmark = pytest.mark.skipif(not _fast.available(), reason="no C compiler: the fused path is unavailable")


@pytest.mark.parametrize("dynamic", [True, None])
def test_compiled_principled_does_not_recompile_per_float_value(dynamic):
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    vec, base, _ = random_case(51, count=64, min_cos=0.05)
    t = to_t(vec, torch.float32)
    base = torch.as_tensor(base, dtype=torch.float32)
    counter = CompileCounter()

    def user(l, v, n, rough, metal):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=rough, metallic=metal)

    f = torch.compile(user, backend=counter, fullgraph=True, dynamic=dynamic)
    values = [(0.3, 0.2), (0.4, 0.25), (0.5, 0.3), (0.6, 0.35)]
    for rough, metal in values:
        got = f(t["l"], t["v"], t["n"], rough, metal)
        want = user(t["l"], t["v"], t["n"], rough, metal)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    # dynamic=True: symbolic from the first call; by default torch.compile specialises a float
    # once, then makes it symbolic when it changes (one recompile), and never again.
    assert counter.frame_count == (1 if dynamic else 2)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=str)
def test_compiled_principled_with_half_inputs_that_require_grad(dtype):
    """Half inputs needing a gradient pass through the saturating cast: one graph, no breaks,
    values and gradients those of the uncompiled call."""
    torch._dynamo.reset()
    vec, base, _ = random_case(52, count=64, min_cos=0.05)
    t = {k: x.to(dtype) for k, x in to_t(vec, torch.float32).items()}
    rough = torch.rand(64, 1, generator=torch.Generator().manual_seed(1)).to(dtype)

    def user(r):
        return torchbrdf.principled(t["l"], t["v"], t["n"], base_color=0.5, roughness=r)

    explained = torch._dynamo.explain(user)(rough.clone().requires_grad_())
    assert explained.graph_break_count == 0
    got_r, want_r = rough.clone().requires_grad_(), rough.clone().requires_grad_()
    got = torch.compile(user, fullgraph=True)(got_r)
    want = user(want_r)
    got.float().sum().backward()
    want.float().sum().backward()
    assert got.dtype == dtype
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    torch.testing.assert_close(got_r.grad, want_r.grad, rtol=0, atol=0)
