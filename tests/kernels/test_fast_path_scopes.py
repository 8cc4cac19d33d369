"""Scoped dispatch: ``fused_at_every_size`` takes small calls to the fused kernels in the automatic
mode only, within its block and its thread; callers that repeat small calls use it."""

import threading

import torch

import torchbrdf
from torchbrdf.brdf import principled as P


def _small_call(lanes=64, dtype=torch.float32):
    g = torch.Generator().manual_seed(0)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(lanes, 3)
    l = torch.nn.functional.normalize(torch.rand(lanes, 3, generator=g) + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    rough = torch.rand(lanes, 1, generator=g).to(dtype).requires_grad_()
    return torchbrdf.principled(l.to(dtype), n, n, base_color=torch.rand(lanes, 3, generator=g).to(dtype),
                                roughness=rough)


def _fused(out):
    """Whether the fused operator's autograd node is in ``out``'s graph (below a dtype cast or clamp)."""
    todo, seen = [out.grad_fn], set()
    while todo:
        fn = todo.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        if "PrincipledFunction" in fn.name():
            return True
        todo.extend(f for f, _ in fn.next_functions)
    return False


def test_small_calls_are_fused_inside_the_block_only():
    assert not _fused(_small_call())
    with P.fused_at_every_size():
        inside = _small_call()
        assert _fused(inside)
    assert not _fused(_small_call())
    P.set_fast_path(None)
    torch.testing.assert_close(inside, _small_call(), rtol=2e-6, atol=0)


def test_the_switches_still_win(monkeypatch):
    P.set_fast_path(False)
    try:
        with P.fused_at_every_size():
            assert not _fused(_small_call())
    finally:
        P.set_fast_path(None)
    monkeypatch.setenv("TORCHBRDF_EAGER", "1")
    with P.fused_at_every_size():
        assert not _fused(_small_call())
    monkeypatch.delenv("TORCHBRDF_EAGER")
    with P.fused_at_every_size():  # float16 is evaluated in float32 and stays fused
        assert _fused(_small_call(dtype=torch.float16))


def test_another_thread_keeps_the_threshold():
    seen = []
    with P.fused_at_every_size():
        t = threading.Thread(target=lambda: seen.append(_fused(_small_call())))
        t.start()
        t.join()
        assert _fused(_small_call())
    assert seen == [False]
