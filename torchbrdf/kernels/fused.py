"""Fused CPU kernels for :func:`torchbrdf.principled`: one pass forward, one pass backward.

Why: the eager path launches ~150 ATen kernels per call and autograd keeps dozens of
``(N, 1)`` intermediates alive (several GiB at N = 2^22). Here the whole per-lane formula
is one C loop (OpenMP over lanes, auto-vectorised by gcc), the backward recomputes the
forward inside the same loop and writes each input's gradient directly, so the evaluation
holds no intermediate tensors at all: memory = inputs + gradients + output.

How (the kernels package):

* :mod:`torchbrdf.brdf.formula` — the principled formula, written once over an ``ops``
  namespace; on torch tensors it is the eager path;
* :mod:`torchbrdf.kernels.trace` — runs that formula on graph nodes (the IR) and
  differentiates the graph (reverse and forward mode as graph transforms);
* :mod:`torchbrdf.kernels.graphs` — the graph of each kernel (forward, backward, JVP) of a
  kernel family, with abstract loads and stores, for any emitter;
* :mod:`torchbrdf.kernels.codegen_c` — prints the graph as one C lane loop (forward,
  recompute-backward, several-tangent JVP);
* this module — the kernel spec, build and on-disk cache, and the buffer pool;
* :mod:`torchbrdf.kernels.layout`, :mod:`~torchbrdf.kernels.c_runner`,
  :mod:`~torchbrdf.kernels.triton_runner` — one call's memory layout and the kernels' calls;
* :mod:`torchbrdf.kernels.registration` and :mod:`~torchbrdf.kernels.autograd` — the kernels
  as ``torch.library`` custom operators with fake implementations, vmap rules and autograd
  (reverse, forward and second order), so that ``torch.compile`` and ``torch.func`` see them;
  :mod:`torchbrdf.kernels.ops` is the entry point.

Compilation: ``gcc -O3 -march=native -fopenmp -ffp-contract=off`` (no ``-ffast-math``: the
kernels keep IEEE semantics so values match eager), once per *kernel family* — dtype,
which parameters are tensors vs Python floats (floats are runtime arguments, so sweeping a
float parameter does not recompile), active lobes, tint/frame use, broadcast pattern and,
for the backward, which inputs need gradients. :mod:`torchbrdf.kernels.build` caches the shared
library per user (``$TORCHBRDF_CACHE_DIR/kernels``, default ``~/.cache/torchbrdf/kernels``), so
the ~1–3 s build is paid once per machine and family; loading a cached kernel takes
milliseconds. No compiler, or any build/cache failure → eager (one warning). The OpenMP loops
run on PyTorch's own OpenMP runtime and thread count (see ``build``).

Limits: CPU float32/float64 only (CUDA tensors use the Triton kernels printed from the same
graphs, :mod:`torchbrdf.kernels.codegen_triton`; other devices eager), first-order kernels (the
backward kernel also runs under ``create_graph=True`` and ``torch.func.grad``; differentiating
it again runs the eager formula's second-order vjp).
"""

from __future__ import annotations

import ctypes
import math
import mmap
import os
import threading
import weakref
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from torchbrdf.kernels import build as _build
from torchbrdf.kernels import codegen_c

if TYPE_CHECKING:  # codegen_shade's kernels are loaded here too; it is imported lazily by callers
    from torchbrdf.kernels.codegen_shade import ShadeSpec

__all__ = ["available", "kernel_cache_dir", "compiled_kernels", "empty_cache", "KernelSpec", "load", "buffer_pool"]


def _generate(spec: KernelSpec | ShadeSpec, backward: bool | str) -> str:
    """C source of the forward (``backward=False``), backward (``True``) or JVP (``"jvp"``) kernel."""
    if hasattr(spec, "generate"):  # other kernel families (fused shading) print themselves
        return spec.generate("jvp" if backward == "jvp" else ("bwd" if backward else "fwd"))
    return codegen_c.generate(spec, "jvp" if backward == "jvp" else ("bwd" if backward else "fwd"))


# ---------------------------------------------------------------------------------------------
# Compilation and caching
# ---------------------------------------------------------------------------------------------

class KernelSpec:
    """Everything that changes the generated code (and nothing else).

    ``tensors``: ``(name, mode, C)`` per tensor input; ``floats``: names of the runtime
    Python floats; backward: ``go_strides`` and ``grad_mask`` (indices needing gradients);
    JVP: ``tangent_inputs`` (indices with tangents), ``tangent_modes`` (one per tangent slot,
    ``ntan`` × ``len(tangent_inputs)``; ``"zero"``: that input has no tangent in that
    direction, pruned from the kernel) and ``ntan`` (tangents per pass); ``family``: the
    formula (:data:`torchbrdf.brdf.formula.FAMILIES`).
    """

    def __init__(self, ctype: str, tensors: Iterable[tuple[str, str, int]], floats: Iterable[str],
                 active: Iterable[str], need_tint: bool, frame: bool, go_strides: Iterable[int] = (3, 1),
                 grad_mask: Iterable[int] = (), tangent_inputs: Iterable[int] = (),
                 tangent_modes: Iterable[str] = (), ntan: int = 0, family: str = "principled") -> None:
        self.ctype = ctype
        self.family = family  # which formula (torchbrdf.brdf.formula.FAMILIES)
        self.hi_double = ctype == "float"
        self.tensors = tuple(tensors)  # (name, mode, C)
        self.floats = tuple(floats)
        self.active = tuple(active)
        self.need_tint = bool(need_tint)
        self.frame = bool(frame)
        self.go_strides = tuple(go_strides)
        self.grad_mask = tuple(grad_mask)
        self.tangent_inputs = tuple(tangent_inputs)
        self.tangent_modes = tuple(tangent_modes)
        self.ntan = int(ntan)
        # Set by the backward kernel's generator: the inputs whose gradient it writes.
        self.written: tuple[int, ...] = ()

    def key(self, backward: bool | str) -> tuple[Any, ...]:
        base: tuple[Any, ...] = (self.ctype, self.tensors, self.floats, self.active, self.need_tint,
                                 self.frame)
        if self.family != "principled":
            base = base + (self.family,)
        if backward == "jvp":
            return base + ("jvp", self.tangent_inputs, self.tangent_modes, self.ntan)
        return base + ((self.go_strides, self.grad_mask) if backward else ())


# Building, caching and loading live in :mod:`torchbrdf.kernels.build` (per-user cache, atomic
# writes, validated loads, locks, PyTorch's OpenMP runtime); these names stay for callers.
_CFLAGS = _build.CFLAGS
_lock = threading.Lock()
_libs: dict = {}  # spec key -> (cdll, fn, written)
_failed: set = set()
kernel_cache_dir = _build.kernel_cache_dir
available = _build.available

_FWD_ARGS = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
_BWD_ARGS = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]


def compiled_kernels() -> int:
    """Number of kernel libraries loaded in this process."""
    return len(_libs)


def load(spec: KernelSpec | ShadeSpec, backward: bool | str) -> tuple[Any, Any, tuple[int, ...]] | None:
    """``(cdll, fn, written)`` for the kernel of ``spec`` (``backward``: False forward, True
    backward, ``"jvp"``), or None (then run eager)."""
    key = spec.key(backward)
    lib = _libs.get(key)
    if lib is not None:
        return lib
    with _lock:
        lib = _libs.get(key)
        if lib is not None:
            return lib
        if key in _failed:
            return None
        src = _generate(spec, backward)
        written = getattr(spec, "written", ())
        kind = "jvp" if backward == "jvp" else ("bwd" if backward else "fwd")
        sym = f"tb_{kind}"
        cdll = _build.load_kernel(src, f"principled_{kind}", {sym: (_BWD_ARGS if backward else _FWD_ARGS, None)})
        if cdll is None:
            _failed.add(key)
            return None
        lib = (cdll, getattr(cdll, sym), written)
        _libs[key] = lib
        return lib


# ---------------------------------------------------------------------------------------------
# Tensor plumbing and the autograd Function
# ---------------------------------------------------------------------------------------------

class _BufferPool:
    """Recycles the large output/gradient buffers of the fused path (a small caching allocator).

    torch's CPU allocator returns every large block to the OS, so each call would pay a page
    fault per 4 KiB of fresh output and gradient memory (0.45 GiB of gradients at N = 2^22),
    which costs more than the kernels themselves. Buffers handed out here are
    anonymous ``mmap`` regions wrapped by ``torch.frombuffer``; when the last tensor using one
    is freed it comes back to the pool (at most ``TORCHBRDF_POOL_MB`` MiB, default 2048, are
    kept; :func:`empty_cache` drops them). Only blocks of at least 1 MiB are pooled.
    """

    MIN_BYTES = 1 << 20

    def __init__(self) -> None:
        self.free: dict[int, list[mmap.mmap]] = {}
        self.cached = 0
        self.lock = threading.Lock()

    def limit(self) -> int:
        try:
            return int(os.environ.get("TORCHBRDF_POOL_MB", "2048")) << 20
        except ValueError:
            return 2048 << 20

    def empty(self, shape: tuple[int, ...] | list[int], dtype: torch.dtype) -> Tensor:
        n = math.prod(shape)
        nbytes = n * torch.empty((), dtype=dtype).element_size()
        if nbytes < self.MIN_BYTES or self.limit() <= 0:
            return torch.empty(shape, dtype=dtype)
        with self.lock:
            lst = self.free.get(nbytes)
            mm = lst.pop() if lst else None
            if mm is not None:
                self.cached -= nbytes
        if mm is None:
            mm = mmap.mmap(-1, nbytes)
        mv = memoryview(mm)
        t = torch.frombuffer(mv, dtype=dtype, count=n).view(shape)
        weakref.finalize(mv, self._release, mm, nbytes)
        return t

    def _release(self, mm, nbytes):
        with self.lock:
            if self.cached + nbytes <= self.limit():
                self.free.setdefault(nbytes, []).append(mm)
                self.cached += nbytes
                return
        mm.close()

    def clear(self) -> None:
        with self.lock:
            lists, self.free, self.cached = self.free, {}, 0
        for lst in lists.values():
            for mm in lst:
                mm.close()


buffer_pool = _BufferPool()


def empty_cache() -> None:
    """Release the fused path's cached output/gradient buffers to the OS."""
    buffer_pool.clear()


# The earlier private names, for code written against them.
_KernelSpec, _load, _pool = KernelSpec, load, buffer_pool
