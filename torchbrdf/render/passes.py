"""One accumulation pass of the shader: a light's term at the shaded pixels, recomputed in backward.

:func:`checkpointed_pass` runs one pass under ``torch.utils.checkpoint`` (non-reentrant), so a
pass's intermediates are dropped after the forward and recomputed during backward: the
forward+backward peak is that of one pass, whatever the number of lights. :func:`point_term`
and :func:`directional_term` are the per-light terms of :mod:`torchbrdf.brdf.formula` over
``(P, 3)`` channel-last pixels.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from torchbrdf import _checks
from torchbrdf._types import BRDF
from torchbrdf.brdf import formula

__all__ = ["checkpointed_pass", "point_term", "directional_term", "TRIM_MIN_ELEMENTS"]


def _load_malloc_trim():
    """Glibc's ``malloc_trim`` through ctypes, or ``None`` where it does not exist."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
        fn.argtypes = [ctypes.c_size_t]
        fn.restype = ctypes.c_int
        return fn
    except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows, musl)
        return None


_MALLOC_TRIM = _load_malloc_trim()
# Passes at least this large (elements) release freed heap pages before their backward.
TRIM_MIN_ELEMENTS = 1 << 16


class _ReleaseFreedMemory(torch.autograd.Function):
    """Identity whose backward first returns freed heap pages to the OS (glibc, CPU).

    glibc serves tensors below its (self-raising) mmap threshold from the heap, and the small
    long-lived autograd records of each pass land among the freed intermediates of the pass
    before, so freed pages stay resident and the next pass's large tensors go on top: the
    resident set would creep up pass after pass even though live memory does not (measured
    in docs/shading.md). ``malloc_trim`` returns those free pages.
    """

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        _MALLOC_TRIM(0)
        return grad


def checkpointed_pass(elements: int, fn: Callable[..., Tensor], *args: Any, **kwargs: Any) -> Tensor:
    """Run one accumulation pass of ``elements`` BRDF evaluations.

    Under autograd the pass is checkpointed (non-reentrant): nothing inside it is stored, and
    it is recomputed during backward. Under ``torch.func`` transforms it is not: they refuse
    saved-tensor hooks (hence checkpointing), so there a pass keeps its intermediates. Nor
    under ``torch.compile(..., dynamic=True)``: Dynamo fails on checkpoint's subgraph there
    (an internal assertion), so the compiled graph's partitioner decides what the backward
    keeps.
    """
    if not torch.is_grad_enabled() or torch._C._are_functorch_transforms_active():
        return fn(*args, **kwargs)
    if _compiling_dynamic():
        return fn(*args, **kwargs)
    out = checkpoint(fn, *args, use_reentrant=False, **kwargs)
    if (
        _MALLOC_TRIM is not None
        and not torch.compiler.is_compiling()  # a ctypes call, and a guard on the pass size
        and out.requires_grad
        and out.device.type == "cpu"
        and elements >= TRIM_MIN_ELEMENTS
    ):
        # The small autograd records of this pass were allocated among the freed
        # intermediates; give the freed pages back now and again before its backward.
        _MALLOC_TRIM(0)
        out = _ReleaseFreedMemory.apply(out)
    return out


@_checks.constant_while_tracing
def _dynamic_shapes_config() -> bool:
    """Whether Dynamo's config in force makes every size symbolic (``torch.compile(..., dynamic=True)``).

    Run once while tracing, not traced (:func:`~torchbrdf._checks.constant_while_tracing`).
    """
    config = sys.modules.get("torch._dynamo.config")
    return config is not None and not config.assume_static_by_default



def _compiling_dynamic() -> bool:
    """Whether this is traced by ``torch.compile(..., dynamic=True)``."""
    return torch.compiler.is_compiling() and _dynamic_shapes_config()


def _per_pixel(t: Tensor, bidx: Tensor) -> Tensor:
    """A ``(3,)`` / ``(1, 3)`` / ``(B, 3)`` light parameter broadcast to the shaded pixels."""
    if t.dim() == 2 and t.shape[0] > 1:
        return t[bidx]
    return t.reshape(1, 3)


def point_term(
    brdf: BRDF,
    pos: Tensor,
    n: Tensor,
    v: Tensor,
    x: Tensor | None,
    y: Tensor | None,
    mat: dict[str, Any],
    q: Tensor,
    intensity: Tensor,
    bidx: Tensor,
) -> Tensor:
    """``f(l, v) I max(n·l, 0) / |q - P|²`` at ``(P, 3)`` points (:func:`formula.point_light`)."""
    ops = formula.TorchOps(pos.dtype, pos.device)
    return formula.point_light(
        ops, pos, n, _per_pixel(q, bidx), _per_pixel(intensity, bidx), lambda l: brdf(l, v, n, x, y, **mat)
    )


def directional_term(
    brdf: BRDF,
    pos: Tensor,
    n: Tensor,
    v: Tensor,
    x: Tensor | None,
    y: Tensor | None,
    mat: dict[str, Any],
    direction: Tensor,
    irradiance: Tensor,
    bidx: Tensor,
) -> Tensor:
    """``f(d, v) E max(n·d, 0)`` at ``(P, 3)`` points (:func:`formula.directional_light`)."""
    ops = formula.TorchOps(n.dtype, n.device)
    return formula.directional_light(
        ops,
        n,
        _per_pixel(direction, bidx),
        _per_pixel(irradiance, bidx),
        lambda l: brdf(l.expand_as(n), v, n, x, y, **mat),
    )
