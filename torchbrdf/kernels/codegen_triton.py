"""Triton code generation: prints the traced graphs (see :mod:`.graphs`) as ``@triton.jit`` kernels.

The same graphs as the C kernels — forward, reverse-mode backward (recompute: nothing saved but
the inputs) and forward-mode JVP — printed as one Triton program per ``BLOCK`` of lanes:
masked loads and stores, ``tl.where`` for selects, float64 nodes (kind ``'d'``, and the runtime
Python floats, kind ``'p'``) as ``tl.float64``. Nothing here knows the formula or a derivative
rule.

Kernels (``ins`` one pointer per tensor input of the family, ``P`` a float64 tensor holding the
runtime Python floats, ``n`` the lanes):

* ``tb_fwd(n, P, *ins, out, BLOCK)``: ``out`` ``(n, 3)``;
* ``tb_bwd(n, P, *ins, go, *grads, BLOCK)``: ``go`` the output gradient (strides
  ``spec.go_strides``), one lane-dense ``(n, C_k)`` gradient per written input;
* ``tb_jvp(n, P, *ins, *tans, *touts, BLOCK)``: tangent ``j`` of slot ``i`` is ``tans[j * T + i]``
  (``T = len(spec.tangent_inputs)``), ``touts[j]`` its ``(n, 3)`` output tangent.

Why the runtime floats travel in a float64 tensor rather than as scalar arguments: Triton passes
a Python float as float32 (and the interpreter as a Python scalar), while the formula folds them
in double as eager Python does; ``tl.load(P + j)`` is float64 in both modes.

Rounding choices that keep IEEE semantics (as the C kernels' ``-ffp-contract=off``): float32
``/`` and ``sqrt`` are printed as ``tl.div_rn`` / ``tl.sqrt_rn`` (Triton's plain ``/`` and
``tl.sqrt`` are approximate on NVIDIA GPUs), FMA contraction is disabled at launch, and the
single ``log`` / ``log1p`` of the clearcoat lobe is evaluated in float64 and rounded once.

Other fused kernels: a single-phase graph (built with :class:`.trace.TraceOps`,
:func:`.trace.reverse` / :func:`.trace.tangents`) prints with :func:`print_kernel`, imports with
:func:`compile_source` and runs with :func:`launch`; register it in the same ``torch.library``
operator as the C kernel, choosing by ``cfg``'s backend field as :mod:`.ops` does for
``principled``. Light-loop kernels (fused shading, the recovery's normal equations) print with
:func:`torchbrdf.kernels.light_loop.print_triton`, which reuses this module's node printer.

Compilation: the source is written to ``<kernel cache dir>/triton/`` (Triton's ``@jit`` reads
its function's source file) and imported; Triton then compiles it on first launch and keeps
its own binary cache. Under ``TRITON_INTERPRET=1`` the same source runs on CPU tensors through
Triton's interpreter (how the tests run without a GPU).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import threading
import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from torchbrdf.kernels.graphs import build
from torchbrdf.kernels.trace import Graph, Node, live_order

if TYPE_CHECKING:  # fused imports the kernels package at run time
    from torch import Tensor

    from torchbrdf.kernels.fused import KernelSpec

__all__ = ["generate", "print_kernel", "compile_source", "load", "launch", "interpret_mode", "available",
           "block_size"]

_CMP = {"gt": ">", "lt": "<", "ge": ">=", "le": "<=", "eq": "=="}
_ARITH = {"add": "+", "sub": "-", "mul": "*"}

PRELUDE = '''import triton
import triton.language as tl


@triton.jit
def _log1p64(t):
    # log(1 + t) in float64, Goldberg's trick: exact where 1 + t is (as the C kernels' tb_log1p).
    u = 1.0 + t
    one = u == 1.0
    lu = tl.log(tl.where(one, 2.0, u))
    return tl.where(one, t, lu * (t / tl.where(one, 1.0, u - 1.0)))

'''


def lit(x: float) -> str:
    r = repr(float(x))
    if r in ("inf", "-inf", "nan"):
        raise ValueError(f"non-finite constant {x} in a kernel graph")
    return r


class Printer:
    """Prints nodes as Triton expressions for a compute type ``DT`` (``tl.float32``/``tl.float64``)."""

    def __init__(self, ctype: str, go_strides: tuple[int, ...] = (3, 1)) -> None:
        self.go_strides = tuple(go_strides)
        self.f32 = ctype == "float"
        self.DT = "tl.float32" if self.f32 else "tl.float64"

    def ty(self, kind: str) -> str:
        return self.DT if kind == "r" else "tl.float64"

    def load(self, nd: Node) -> str:
        a = nd.attr
        role = a["role"]
        if role == "go":
            gsl, gsc = self.go_strides
            return f"tl.load(go + (i * {gsl} + {a['c'] * gsc}), mask=m, other=0.0)"
        ptr = f"x{a['k']}" if role == "x" else f"t{a['j']}_{a['i']}"
        mode, C, c = a["mode"], a["C"], a["c"]
        if mode == "full":
            return f"tl.load({ptr} + (i * {C} + {c}), mask=m, other=0.0)" if C > 1 else \
                f"tl.load({ptr} + i, mask=m, other=0.0)"
        return f"tl.load({ptr} + {c})" if mode == "b1" else f"tl.load({ptr})"

    def expr(self, nd: Node, v: Callable[[Any], str]) -> str:
        a = [v(x) for x in nd.args]
        op, k = nd.op, nd.kind
        hi32 = k == "r" and self.f32  # a float32 value
        if op == "in":
            return self.load(nd)
        if op == "P":
            return f"tl.load(P + {nd.attr})"
        if op == "const":
            return f"tl.full([BLOCK], {lit(nd.attr)}, {self.ty(k)})"
        if op in _ARITH:
            return f"{a[0]} {_ARITH[op]} {a[1]}"
        if op == "div":
            return f"tl.div_rn({a[0]}, {a[1]})" if hi32 else f"{a[0]} / {a[1]}"
        if op in _CMP:
            return f"{a[0]} {_CMP[op]} {a[1]}"
        if op == "and":
            return f"{a[0]} & {a[1]}"
        if op == "neg":
            return f"-{a[0]}"
        if op == "recip":
            return f"tl.div_rn(tl.full([BLOCK], 1.0, tl.float32), {a[0]})" if hi32 else f"1.0 / {a[0]}"
        if op == "sqrt":
            return f"tl.sqrt_rn({a[0]})" if hi32 else f"tl.sqrt({a[0]})"
        if op == "rsqrt":
            return (f"tl.div_rn(tl.full([BLOCK], 1.0, tl.float32), tl.sqrt_rn({a[0]}))" if hi32
                    else f"1.0 / tl.sqrt({a[0]})")
        if op in ("log", "log1p"):
            fn = "tl.log" if op == "log" else "_log1p64"
            return f"{fn}({a[0]}.to(tl.float64)).to(tl.float32)" if hi32 else f"{fn}({a[0]})"
        if op == "exp2":  # float32: in float64, rounded once (tl.exp2 of float32 is approximate on GPUs)
            return f"tl.exp2({a[0]}.to(tl.float64)).to(tl.float32)" if hi32 else f"tl.exp2({a[0]})"
        if op == "abs":
            return f"tl.where({a[0]} < 0.0, -{a[0]}, {a[0]})"
        if op == "max2":
            return f"tl.where({a[0]} < {a[1]}, {a[1]}, {a[0]})"
        if op == "maxc":
            return f"tl.where({a[0]} < {a[1]}, {a[1]}, {a[0]})"
        if op == "pmax":
            return f"tl.where({a[1]} > {a[0]}, {a[1]}, {a[0]})"
        if op == "clamp":
            return f"tl.where({a[0]} < {a[1]}, {a[1]}, tl.where({a[0]} > {a[2]}, {a[2]}, {a[0]}))"
        if op == "where":
            return f"tl.where({a[0]}, {a[1]}, {a[2]})"
        if op == "tod":
            return f"{a[0]}.to(tl.float64)"
        if op == "tor":
            return f"{a[0]}.to({self.DT})"
        raise NotImplementedError(op)


def _target(t) -> str:
    """Address of a store target ``("ptr", argument name, channels, channel)`` (lane-dense)."""
    _, name, C, c = t
    return f"{name} + (i * {C} + {c})" if C > 1 else f"{name} + i"


def _family_target(spec, t) -> tuple:
    """A store target of :mod:`.graphs` as ``("ptr", argument, channels, channel)``."""
    if t[0] == "out":
        return ("ptr", "out", 3, t[1])
    if t[0] == "grad":
        return ("ptr", f"g{t[1]}", spec.tensors[t[1]][2], t[2])
    if t[0] == "tout":
        return ("ptr", f"to{t[1]}", 3, t[2])
    raise ValueError(f"unknown store target {t!r}")


def generate(spec: KernelSpec, kind: str, wide: bool = False) -> tuple[str, tuple[int, ...]]:
    """Triton source of one kernel (``kind`` = ``"fwd"``, ``"bwd"`` or ``"jvp"``) of a family.

    Args:
        spec: the kernel family (:class:`torchbrdf.kernels.fused.KernelSpec`).
        kind: which kernel.
        wide: 64-bit lane indices (needed from ``n * 3 >= 2**31``).

    Returns:
        ``(source, written)``: ``written`` the inputs whose gradient the backward writes.
    """
    kg = build(spec, kind)
    written = tuple(kg.written)
    stores = [(_family_target(spec, t), val) for t, val in kg.stores]
    ins = [f"x{k}" for k in range(len(spec.tensors))]
    if kind == "fwd":
        args = ins + ["out"]
    elif kind == "bwd":
        args = ins + ["go"] + [f"g{k}" for k in written]
    else:
        T = len(spec.tangent_inputs)
        args = ins + [f"t{j}_{i}" for j in range(spec.ntan) for i in range(T)]
        args += [f"to{j}" for j in range(spec.ntan)]
    return print_kernel(f"tb_{kind}", kg.graph, stores, args, spec.ctype, spec.go_strides, wide), written


def print_kernel(name: str, g: Graph, stores: Sequence[tuple[tuple[Any, ...], Node | float]], args: Sequence[str],
                 ctype: str, go_strides: tuple[int, ...] = (3, 1), wide: bool = False) -> str:
    """Triton source of a kernel ``name(n, P, *args, BLOCK)`` computing ``stores`` of graph ``g``.

    The generic entry (used by :func:`generate`; a fused shading graph prints the same way):
    ``stores`` are ``(("ptr", argument name, channels, channel), node or float)`` pairs (a
    lane-dense ``(n, channels)`` output), ``in`` nodes carry the symbolic load
    attributes of :mod:`.graphs`, ``P`` nodes index the float64 runtime-float tensor ``P``, and
    ``ctype`` (``"float"``/``"double"``) is the compute type of kind-``'r'`` nodes.
    """
    pr = Printer(ctype, go_strides)
    names: dict[int, str] = {}

    def v(nd):
        return names[nd.id] if isinstance(nd, Node) else f"tl.full([BLOCK], {lit(nd)}, {pr.DT})"

    body = []
    for nd in live_order(g, [val for _, val in stores]):
        names[nd.id] = f"v{nd.id}"
        body.append(f"v{nd.id} = {pr.expr(nd, v)}")
    for tgt, val in stores:
        body.append(f"tl.store({_target(tgt)}, tl.broadcast_to({v(val)}, [BLOCK]), mask=m)")
    pid = "tl.program_id(0).to(tl.int64)" if wide else "tl.program_id(0)"
    src = [
        PRELUDE,
        "@triton.jit",
        f"def {name}(n, P, {', '.join(args)}, BLOCK: tl.constexpr):",
        f"    i = {pid} * BLOCK + tl.arange(0, BLOCK)",
        "    m = i < n",
        *("    " + b for b in body),
    ]
    return "\n".join(src) + "\n"


# ---------------------------------------------------------------------------------------------
# Availability, build (write + import) and cache
# ---------------------------------------------------------------------------------------------

_state: dict = {"checked": False, "ok": False}
_lock = threading.Lock()
_kernels: dict = {}
_failed: set = set()


def available() -> bool:
    """True when ``triton`` imports."""
    if not _state["checked"]:
        _state["checked"] = True
        try:
            import triton  # noqa: F401
            import triton.language  # noqa: F401

            _state["ok"] = True
        except Exception:  # noqa: BLE001 - any import failure means "no Triton"
            _state["ok"] = False
    return _state["ok"]


def interpret_mode() -> bool:
    """True when Triton runs kernels in its CPU interpreter (``TRITON_INTERPRET=1``)."""
    return os.environ.get("TRITON_INTERPRET", "").lower() in ("1", "true", "on", "yes")


def block_size(kind: str) -> int:
    """Lanes per Triton program.

    On a GPU: 128 lanes on 4 warps, one lane per thread. ptxas (sm_90a, Triton 3.9, no GPU
    needed) gives one lane per thread 75 / 209 / 64 registers for the float32 forward / backward
    / JVP of the full model without spills, while two lanes per thread (256 lanes, 4 warps)
    need 155 / 255 registers and the backward spills 780 bytes; float64 backward spills ~380
    bytes even at one lane per thread. In the interpreter every program is a NumPy pass over
    its block, so large blocks are much faster.
    """
    if interpret_mode():
        return 4096
    return 128


def _cache_dir() -> str:
    from torchbrdf.kernels.fused import kernel_cache_dir  # lazily: fused pulls in the C side

    d = os.path.join(kernel_cache_dir(), "triton")
    try:
        os.makedirs(d, exist_ok=True)
    except OSError:
        uid = os.getuid() if hasattr(os, "getuid") else 0
        d = os.path.join(tempfile.gettempdir(), f"torchbrdf-triton-{uid}")
        os.makedirs(d, exist_ok=True)
    return d


def load(spec: KernelSpec, kind: str, wide: bool = False) -> tuple[Any, tuple[int, ...]] | None:
    """The ``@triton.jit`` kernel of a family, or ``None`` when it cannot be built.

    Returns:
        ``(kernel, written)`` (see :func:`generate`).
    """
    key = (spec.key("jvp" if kind == "jvp" else kind == "bwd"), kind, wide, interpret_mode())
    hit = _kernels.get(key)
    if hit is not None:
        return hit
    with _lock:
        hit = _kernels.get(key)
        if hit is not None:
            return hit
        if key in _failed:
            return None
        try:
            src, written = generate(spec, kind, wide)
            kernel = compile_source(src, f"tb_{kind}")
        except Exception as e:  # noqa: BLE001 - any failure: this family runs eagerly
            _failed.add(key)
            warnings.warn(f"torchbrdf: building the Triton kernel failed; using eager.\n{e!r}"[:2000],
                          RuntimeWarning, stacklevel=3)
            return None
        hit = (kernel, written)
        _kernels[key] = hit
        return hit


def compile_source(src: str, fn_name: str) -> Any:
    """Write ``src`` to the per-user cache (named by its hash) and import it; returns ``fn_name``.

    Triton's ``@jit`` reads its function's source file, so the kernel must live in a real
    module. Whether the kernel is interpreted is fixed here (``TRITON_INTERPRET`` at import).
    """
    import triton

    tag = hashlib.sha1((src + triton.__version__).encode()).hexdigest()[:20]
    path = os.path.join(_cache_dir(), f"{fn_name}_{tag}.py")
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(suffix=".py", dir=os.path.dirname(path))
        with os.fdopen(fd, "w") as fh:
            fh.write(src)
        os.replace(tmp, path)  # atomic: concurrent processes never import a partial file
    name = f"torchbrdf_triton_{fn_name}_{tag}_{int(interpret_mode())}"
    mod = sys.modules.get(name)
    if mod is None:
        mspec = importlib.util.spec_from_file_location(name, path)
        if mspec is None or mspec.loader is None:
            raise ImportError(f"cannot import the generated Triton module {path}")
        mod = importlib.util.module_from_spec(mspec)
        sys.modules[name] = mod  # Triton resolves the kernel's globals through its module
        mspec.loader.exec_module(mod)
    return getattr(mod, fn_name)


def launch(kernel: Any, kind: str, n: int, P: Tensor, args: Sequence[Tensor]) -> None:
    """Run ``kernel`` over ``n`` lanes (one program per block). ``args`` after ``n, P``."""
    import triton

    block = block_size(kind)
    grid = (triton.cdiv(n, block),)
    if interpret_mode():
        import numpy as np

        with np.errstate(all="ignore"):  # lanes past n and masked lanes may divide by zero (never stored)
            kernel[grid](n, P, *args, BLOCK=block)
    else:
        kernel[grid](n, P, *args, BLOCK=block, num_warps=max(1, block // 32), enable_fp_fusion=False)


def failed(spec: KernelSpec, kind: str, wide: bool = False) -> None:
    """Mark a family as failed (its first launch raised): later calls run eagerly."""
    key = (spec.key("jvp" if kind == "jvp" else kind == "bwd"), kind, wide, interpret_mode())
    with _lock:
        _failed.add(key)
        _kernels.pop(key, None)
