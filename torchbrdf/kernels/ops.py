"""The fused kernels as PyTorch operators: ``torch.ops.torchbrdf.principled_{fwd,bwd,jvp}``.

Three ``torch.library.custom_op`` s, each with a fake (meta) implementation and a vmap rule:

* ``principled_fwd(tensors, floats, cfg) -> out (*batch, 3)``;
* ``principled_bwd(tensors, floats, cfg, grad_out, need) -> [grad of tensors[i] for i in need]``
  (recompute: nothing is saved but the inputs);
* ``principled_jvp(tensors, floats, cfg, tangents, tidx, ntan) -> out tangent``: the tangents
  of ``tensors[i] for i in tidx``; with ``ntan = K > 0`` every tangent has a leading ``K``
  dimension and the K output tangents ``(K, *batch, 3)`` come from one pass.

``cfg`` names the kernel family's structure (tensor and float parameter names, lobes, tint,
frame). Autograd: ``principled_fwd`` has ``register_autograd`` (what ``torch.compile`` traces);
eager calls and ``torch.func`` go through :class:`_PrincipledFunction` (same ops, plus a
forward-mode ``jvp`` and ``generate_vmap_rule``), because Dynamo does not trace an
``autograd.Function`` with a custom ``jvp``. Under ``vmap`` the batch dimension becomes more
lanes (a batched tangent over unbatched primals becomes K tangents of one pass).

If a kernel cannot be built, the ops evaluate the shared formula eagerly instead (one warning
from the build).
"""

from __future__ import annotations

import ctypes
import functools
import math
from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

from torchbrdf._checks import broadcast_shapes
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels import graphs
from torchbrdf.kernels.fused import _KernelSpec, _load, _pool

__all__ = ["principled_fast", "capture_fast", "capture_jvp", "CAPTURE_INPUTS"]

SCALAR_NAMES = SCALAR_PARAMS

# Lanes per backward chunk when some input's gradient is summed over all lanes (reduced
# chunk by chunk, so the buffers stay small: 2^16 lanes × 3 × 8 B = 1.5 MiB).
BWD_CHUNK = 1 << 16
# Tangents per pass of the JVP kernel (jacfwd over K parameters runs ceil(K / 8) passes): the
# generated code grows with the tangents, and 8 already share most of the primal work.
TANGENTS_PER_PASS = 8


# ---------------------------------------------------------------------------------------------
# Layout of one call
# ---------------------------------------------------------------------------------------------

def _merges(t: Tensor, dims: int) -> bool:
    """Whether ``t``'s first ``dims`` dimensions merge into one without a copy (``view`` works).

    They do when each one that is not 1 long steps over the next such one whole. Asked
    instead of trying ``view``: a failed view raises, and building that error cost 40 µs a
    time, 8700 times in a recovery (0.35 s).
    """
    if t.numel() == 0:
        return True
    step = None  # the stride the next dimension that is not 1 long must have
    for i in range(dims - 1, -1, -1):
        if t.size(i) == 1:
            continue
        if step is not None and t.stride(i) != step:
            return False
        step = t.stride(i) * t.size(i)
    return True


def _flatten(t: Tensor, C: int, batch: tuple, N: int, s2: bool = False):
    """View ``t`` as ``(N, C)`` lanes: mode 'full' (lane-dense), 'b1'/'b0' (same for all lanes).

    With ``s2`` (kernels that support it), a value broadcast over one of two batch dims — a
    per-pixel value under every light, or a per-light value at every pixel — is not copied
    out to all lanes: mode 's2' returns the ``(N / B, B, C)`` strided view (``B = batch[-1]``),
    and lane ``(q, r)`` reads row ``q·sA + r·sB`` (:meth:`_Plan.params` passes the strides).
    """
    e = t.expand(*batch, C) if t.dim() > 0 else t.reshape(1).expand(*batch, C)
    f = e.view(N, C) if _merges(e, len(batch)) else None
    if f is not None:
        ls, cs = f.stride()
        if N > 1 and ls == 0:
            if C == 1 or cs == 1:
                return f, "b1"
            if cs == 0:
                return f, "b0"
        if (ls == C or N <= 1) and (cs == 1 or C == 1):
            return f, "full"
    if s2 and C > 1 and t.dim() > 0 and t.size(-1) > 1 and t.stride(-1) != 1 and t.numel() < N * C:
        # Channels not adjacent (a slice of a transposed tensor): make the small tensor dense,
        # not its broadcast to every lane (that also kept a second kernel variant).
        return _flatten(t.contiguous(), C, batch, N, s2)
    if s2 and len(batch) >= 2 and batch[-1] > 1 and N > batch[-1] and (C == 1 or e.stride(-1) == 1) \
            and _merges(e, len(batch) - 1):  # (else the leading batch dims do not collapse: copy)
        return e.view(N // batch[-1], batch[-1], C), "s2"
    return (f if f is not None else e).reshape(N, C).contiguous(), "full"


def make_cfg(tensor_names: Iterable[str], float_names: Iterable[str], active: Iterable[str], need_tint: bool,
             frame: bool, backend: str = "c", family: str = "principled") -> str:
    """The ``cfg`` string of the operators.

    ``backend``: ``"c"`` (CPU kernels) or ``"triton"``; ``family``: the formula
    (:data:`torchbrdf.brdf.formula.FAMILIES`).
    """
    parts = [",".join(tensor_names), ",".join(float_names), ",".join(active), str(int(need_tint)),
             str(int(frame)), backend]
    return "|".join(parts + ([family] if family != "principled" else []))


#: Channels of each tensor input that is not a scalar principled parameter (all others: 3).
_ONE_CHANNEL = frozenset(SCALAR_PARAMS)


class _Plan:
    """One call's layout, from ``cfg`` and the tensors' shapes."""

    def __init__(self, cfg: str, tensors, floats):
        tn, fn, act, tint, frame, backend, *rest = cfg.split("|")
        self.cfg = cfg
        self.backend = backend  # which kernels: "c" or "triton"
        self.family = rest[0] if rest else "principled"  # which formula
        self.tensor_names = tn.split(",") if tn else []
        self.float_names = fn.split(",") if fn else []
        self.active = tuple(act.split(",")) if act else ()
        self.need_tint, self.frame = tint == "1", frame == "1"
        self.C = [1 if k in _ONE_CHANNEL else 3 for k in self.tensor_names]
        shapes = [t.shape[:-1] if t.dim() > 0 else () for t in tensors]
        self.batch = tuple(broadcast_shapes(*shapes))
        self.N = math.prod(self.batch)
        self.dtype = tensors[0].dtype
        self.device = tensors[0].device
        for k, t in zip(self.tensor_names, tensors):
            # The kernels read every input's memory in one dtype on one device: a mismatch here
            # would be misread silently (the public entry points cast or check before).
            if t.dtype != self.dtype or t.device != self.device:
                raise TypeError(f"fused {self.family} kernel: input {k!r} is {t.dtype} on {t.device}, "
                                f"expected {self.dtype} on {self.device} like {self.tensor_names[0]!r}")
        self.floats = [float(x) for x in floats]

    def params(self, *flats) -> list[float]:
        """The kernel's runtime parameter row.

        The Python floats, then, when some input of ``flats`` (iterables of ``(flat, mode)``, in
        the kernel's slot order) is 's2', the inner batch size and each such input's two lane
        strides (see :func:`_flatten`).
        """
        s2 = [f for fl in flats for f, m in fl if m == "s2"]
        if not s2:
            return self.floats
        return self.floats + [float(self.batch[-1])] + [float(x) for f in s2 for x in f.stride()[:2]]

    def flat(self, tensors, s2: bool = False):
        out = [_flatten(t, C, self.batch, self.N, s2) for t, C in zip(tensors, self.C)]
        modes = tuple((k, m, C) for k, (_, m), C in zip(self.tensor_names, out, self.C))
        return [f for f, _ in out], modes

    def spec(self, modes, **kw):
        ctype = "float" if self.dtype == torch.float32 else "double"
        kw["family"] = self.family
        return _KernelSpec(ctype, modes, self.float_names, self.active, self.need_tint, self.frame, **kw)


def _ptrs(ptrs):
    return (ctypes.c_void_p * max(1, len(ptrs)))(*ptrs)


def _dparams(vals):
    return (ctypes.c_double * max(1, len(vals)))(*vals)


def _formula_eager(plan: _Plan, tensors, floats):
    """The shared formula on torch tensors (the eager path), for fallbacks and double backward."""
    from torchbrdf.brdf import formula

    c = dict(zip(plan.float_names, floats))
    c.update(zip(plan.tensor_names, tensors))
    c.setdefault("x", None)
    c.setdefault("y", None)
    ops = formula.TorchOps(plan.dtype, tensors[0].device)
    return formula.FAMILIES[plan.family](ops, c, plan.active, plan.need_tint, plan.frame)


@functools.lru_cache(maxsize=None)
def _written(spec_args: tuple, family: str = "principled") -> tuple:
    """Inputs (indices) whose gradient the backward kernel writes (those with a path to the output)."""
    ctype, tensors, floats, active, tint, frame, go_strides, grad_mask = spec_args
    spec = _KernelSpec(ctype, tensors, floats, active, tint, frame, go_strides, grad_mask, family=family)
    return graphs.build(spec, "bwd").written


# ---------------------------------------------------------------------------------------------
# Kernel calls
# ---------------------------------------------------------------------------------------------

def _run_fwd(plan: _Plan, tensors) -> Tensor:
    if plan.backend == "triton":
        return _triton_fwd(plan, tensors)
    flat, modes = plan.flat(tensors, s2=True)
    lib = _load(plan.spec(modes), backward=False) if plan.N > 0 else None
    if lib is None:
        if plan.N > 0:  # no kernel: the same formula, eagerly
            with torch.no_grad():
                return _formula_eager(plan, tensors, plan.floats).expand(*plan.batch, 3).contiguous()
        return torch.empty(*plan.batch, 3, dtype=plan.dtype, device=plan.device)
    out = _pool.empty((plan.N, 3), plan.dtype)
    P = _dparams(plan.params(zip(flat, (m for _, m, _ in modes))))
    lib[1](plan.N, _ptrs([f.data_ptr() for f in flat]), P, out.data_ptr(), torch.get_num_threads())
    return out.view(*plan.batch, 3)


def _grad_mode(t: Tensor, C: int, N: int) -> str:
    """How an input's gradient is formed: ``'red'`` or ``'full'``.

    ``'red'``: the input is one value for all lanes, its gradient is the sum over the lanes
    (reduced chunk by chunk); ``'full'``: a lane-dense gradient, then summed to the input's
    shape (an input that is an expanded view of one value still needs its per-lane gradient).
    """
    lanes = math.prod(t.shape[:-1]) if t.dim() > 0 else 1
    return "red" if lanes == 1 and N > 1 else "full"


def _to_shape(g: Tensor, t: Tensor) -> Tensor:
    """Sum a gradient ``(*batch, C)`` or ``(C,)`` (summed over lanes) down to ``t``'s shape."""
    if t.dim() == 0:
        return g.sum().reshape(())
    if g.dim() == 1:
        g = g.reshape((1,) * (t.dim() - 1) + (g.shape[0],))
    return g.sum_to_size(t.shape) if tuple(g.shape) != tuple(t.shape) else g


def _grad_out_lanes(plan: _Plan, grad_out: Tensor) -> tuple[Tensor, tuple[int, int]]:
    """The output gradient as ``(N, 3)`` lanes in the compute dtype, and its ``(lane, channel)``
    strides: a broadcast gradient (a ``sum``'s) keeps stride 0, anything else is made contiguous."""
    go = grad_out.expand(*plan.batch, 3).reshape(plan.N, 3)
    if go.dtype != plan.dtype:
        go = go.to(plan.dtype)
    gls, gcs = go.stride()
    if plan.N == 1:
        gls = 3
    if (gls, gcs) not in ((3, 1), (0, 0), (0, 1)):
        go = go.contiguous()
        gls, gcs = 3, 1
    return go, (gls, gcs)


def _run_bwd(plan: _Plan, tensors, grad_out: Tensor, need) -> list:
    N, dtype = plan.N, plan.dtype
    if N == 0:
        return [tensors[i].new_zeros(tensors[i].shape) for i in need]
    if plan.backend == "triton":
        return _triton_bwd(plan, tensors, grad_out, need)
    go, (gls, gcs) = _grad_out_lanes(plan, grad_out)
    gmode = {i: _grad_mode(tensors[i], plan.C[i], N) for i in need}
    # Chunked (a gradient summed over all lanes): lane offsets move the pointers, so no 's2'.
    chunked = any(m == "red" for m in gmode.values())
    flat, modes = plan.flat(tensors, s2=not chunked)
    lib = _load(plan.spec(modes, go_strides=(gls, gcs), grad_mask=tuple(need)), backward=True)
    if lib is None:
        # No kernel (no compiler, a cache fault): the vjp of the shared formula. torch.func, not
        # autograd: inside an operator's implementation the autograd keys are switched off.
        def f(*wrt):
            ts = list(tensors)
            for i, t in zip(need, wrt):
                ts[i] = t
            return _formula_eager(plan, ts, plan.floats)

        vjp_fn = torch.func.vjp(f, *[tensors[i] for i in need])[1]
        gs = vjp_fn(grad_out.to(dtype))
        return [g.contiguous() for g in gs]
    fn = lib[1]
    P = _dparams(plan.params(zip(flat, (m for _, m, _ in modes))))
    nt = torch.get_num_threads()
    full = {i: _pool.empty((N, plan.C[i]), dtype) for i in need if gmode[i] == "full"}
    red = {i: torch.zeros(plan.C[i], dtype=dtype) for i in need if gmode[i] == "red"}
    chunk = N if not red else BWD_CHUNK
    bufs = {i: torch.empty(min(chunk, N), plan.C[i], dtype=dtype) for i in red}
    item = flat[0].element_size()
    for s in range(0, N, chunk):
        m = min(chunk, N - s)
        ins = [f.data_ptr() + (s * C * item if mode == "full" else 0) for f, (_, mode, C) in zip(flat, modes)]
        gouts = []
        for i in range(len(tensors)):
            if i in full:
                gouts.append(full[i].data_ptr() + s * plan.C[i] * item)
            elif i in red:
                gouts.append(bufs[i].data_ptr())
            else:
                gouts.append(None)
        go_ptr = go.data_ptr() + (s * 3 * item if gls == 3 else 0)
        fn(m, _ptrs(ins), P, go_ptr, _ptrs(gouts), nt)
        for i in red:
            red[i] += bufs[i][:m].sum(0)
    grads = []
    for i in need:
        g = full[i].view(*plan.batch, plan.C[i]) if i in full else red[i]
        grads.append(_to_shape(g, tensors[i]).contiguous())
    return grads


def _directions_per_tangent(tangents: list[Tensor], ntan: int, K: int) -> list[list[bool]]:
    """``nz[j][k]``: whether tangent ``k`` is nonzero in direction ``j``.

    ``K`` directions (``ntan = 0``: one). A scan on the CPU; on CUDA every nonempty tangent
    counts as nonzero in every direction (the scan would be a host sync per tangent).
    """
    if not tangents:
        return [[] for _ in range(K)]
    if any(t.device.type != "cpu" for t in tangents):
        return [[bool(t.numel()) for t in tangents] for _ in range(K)]
    if ntan == 0:  # one direction
        return [[bool(t.numel()) and bool(t.ne(0).any()) for t in tangents]]
    return torch.stack([t.reshape(K, -1).ne(0).any(1) for t in tangents], 1).tolist()


def _run_jvp(plan: _Plan, tensors, tangents, tidx, ntan: int) -> Tensor:
    """Output tangents: ``(*batch, 3)``, or ``(ntan, *batch, 3)`` when ``ntan > 0``.

    The ``K`` directions run in passes of up to :data:`TANGENTS_PER_PASS`, the primal computed
    once per pass. Each direction carries only the tangents that are nonzero in it (the others
    are pruned from the kernel, tangent mode ``"zero"``): a Gauss–Newton Jacobian's directions
    are unit vectors in one unknown each (a base colour, the roughness, a normal slope), so its
    six directions cost one primal and six narrow tangent chains — 14 ms at 16384 pixels ×
    16 lights, where one pass per tangent input took 32 ms and one pass with every tangent in
    every direction 45 ms (float32, 2 threads). A tangent that is zero in every direction (one
    a caller passes explicitly; torch.func's own arrive as None, see
    :meth:`_PrincipledFunction.setup_context`) is dropped altogether.
    """
    K = max(1, ntan)
    N, dtype = plan.N, plan.dtype
    shape = (*plan.batch, 3) if ntan == 0 else (ntan, *plan.batch, 3)
    nz = _directions_per_tangent(tangents, ntan, K)  # (K, T)
    used = [k for k in range(len(tangents)) if any(row[k] for row in nz)]
    tidx, tangents = [tidx[k] for k in used], [tangents[k] for k in used]
    nz = [[row[k] for k in used] for row in nz]
    if N == 0 or not tidx:
        return torch.zeros(shape, dtype=dtype, device=plan.device)
    if plan.backend == "triton":
        return _triton_jvp(plan, tensors, tangents, tidx, ntan)
    flat, modes = plan.flat(tensors, s2=True)
    out = torch.empty((K, N, 3), dtype=dtype)
    for j0 in range(0, K, TANGENTS_PER_PASS):
        js = range(j0, min(K, j0 + TANGENTS_PER_PASS))
        ks = [k for k in range(len(tangents)) if any(nz[j][k] for j in js)]
        if not ks:  # every input's tangent is zero in these directions
            out[list(js)] = 0
            continue
        tflat, tmodes = [], []
        for j in js:
            for k in ks:
                if not nz[j][k]:  # pruned: no load, no tangent chain (the pointer is not read)
                    tflat.append(flat[0])
                    tmodes.append("zero")
                    continue
                t = tangents[k]
                f, m = _flatten((t[j] if ntan else t).to(dtype), plan.C[tidx[k]], plan.batch, N, s2=True)
                tflat.append(f)
                tmodes.append(m)
        spec = plan.spec(modes, tangent_inputs=tuple(tidx[k] for k in ks), tangent_modes=tuple(tmodes),
                         ntan=len(js))
        lib = _load(spec, backward="jvp")
        if lib is None:  # no kernel: forward-mode AD of the same formula, eagerly
            primals = tuple(t.detach() for t in tensors)
            for j in js:
                tj = {tidx[k]: (tangents[k][j] if ntan else tangents[k]) for k in ks}
                tans = tuple(tj.get(i, torch.zeros_like(t)).to(dtype) for i, t in enumerate(primals))
                o = torch.func.jvp(lambda *ts: _formula_eager(plan, ts, plan.floats), primals, tans)[1]
                out[j] = o.expand(*plan.batch, 3).reshape(N, 3)
            continue
        ins, tins = _ptrs([f.data_ptr() for f in flat]), _ptrs([f.data_ptr() for f in tflat])
        outs = _ptrs([out[j].data_ptr() for j in js])
        P = _dparams(plan.params(zip(flat, (m for _, m, _ in modes)), zip(tflat, tmodes)))
        lib[1](N, ins, P, tins, outs, torch.get_num_threads())
    return out.view(shape)


# ---------------------------------------------------------------------------------------------
# Triton kernel calls (CUDA tensors; CPU tensors under TRITON_INTERPRET=1)
# ---------------------------------------------------------------------------------------------

# Lanes per backward launch when some input's gradient is summed over all lanes (the per-lane
# gradient of a chunk is reduced before the next: 2^20 lanes x 3 x 4 B = 12 MiB per input).
TRITON_BWD_CHUNK = 1 << 20
# Tangents per pass of the Triton JVP kernel: the generated code grows with the tangents, and 8
# already share most of the primal work (jacfwd over K parameters runs ceil(K / 8) passes).
TRITON_TANGENTS_PER_PASS = 8

_P_CACHE: dict = {}


def _triton():
    from torchbrdf.kernels import codegen_triton

    return codegen_triton


def _wide(N: int) -> bool:
    """64-bit lane indices needed (``i * 3`` past int32)."""
    return 3 * N >= 2 ** 31 - 1


def _floats_tensor(plan: _Plan) -> Tensor:
    """The runtime Python floats as a float64 tensor on the device (cached: no copy per call)."""
    key = (tuple(plan.floats), str(plan.device))
    t = _P_CACHE.get(key)
    if t is None:
        if len(_P_CACHE) > 256:
            _P_CACHE.clear()
        t = torch.tensor(plan.floats or [0.0], dtype=torch.float64).to(plan.device)
        _P_CACHE[key] = t
    return t


def _triton_launch(spec, kind: str, N: int, plan: _Plan, args) -> bool:
    """Load and launch one Triton kernel; ``False`` (after one warning) when that fails."""
    tl_ = _triton()
    wide = _wide(N)
    hit = tl_.load(spec, kind, wide)
    if hit is None:
        return False
    try:
        if plan.device.type == "cuda":
            with torch.cuda.device(plan.device):  # Triton launches on the current device
                tl_.launch(hit[0], kind, N, _floats_tensor(plan), args)
        else:
            tl_.launch(hit[0], kind, N, _floats_tensor(plan), args)
    except Exception as e:  # noqa: BLE001 - a compile error shows at the first launch
        import warnings

        tl_.failed(spec, kind, wide)
        warnings.warn(f"torchbrdf: the Triton {kind} kernel failed; using eager.\n{e!r}"[:2000],
                      RuntimeWarning, stacklevel=3)
        return False
    return True


def _triton_fwd(plan: _Plan, tensors) -> Tensor:
    out = torch.empty(plan.N, 3, dtype=plan.dtype, device=plan.device)
    if plan.N == 0:
        return out.view(*plan.batch, 3)
    flat, modes = plan.flat(tensors)
    if _triton_launch(plan.spec(modes), "fwd", plan.N, plan, [*flat, out]):
        return out.view(*plan.batch, 3)
    with torch.no_grad():
        return _formula_eager(plan, tensors, plan.floats).expand(*plan.batch, 3).contiguous()


def _triton_bwd(plan: _Plan, tensors, grad_out: Tensor, need) -> list:
    N, dtype, dev = plan.N, plan.dtype, plan.device
    go, (gls, gcs) = _grad_out_lanes(plan, grad_out)
    flat, modes = plan.flat(tensors)
    spec = plan.spec(modes, go_strides=(gls, gcs), grad_mask=tuple(need))
    written = set(_written((spec.ctype, modes, tuple(plan.float_names), plan.active, plan.need_tint,
                            plan.frame, (gls, gcs), tuple(need)), plan.family))
    gmode = {i: _grad_mode(tensors[i], plan.C[i], N) for i in need}
    full = {i: torch.empty(N, plan.C[i], dtype=dtype, device=dev) for i in need
            if gmode[i] == "full" and i in written}
    red = {i: torch.zeros(plan.C[i], dtype=dtype, device=dev) for i in need
           if gmode[i] == "red" and i in written}
    chunk = N if not red else TRITON_BWD_CHUNK
    bufs = {i: torch.empty(min(chunk, N), plan.C[i], dtype=dtype, device=dev) for i in red}
    for s in range(0, N, chunk):
        m = min(chunk, N - s)
        gouts = [full[i][s:s + m] if i in full else bufs[i][:m] for i in sorted(written)]
        if not _triton_launch(spec, "bwd", m, plan, [*(f[s:s + m] for f in flat), go[s:s + m], *gouts]):
            with torch.enable_grad():
                ts = [t.detach().requires_grad_(i in need) for i, t in enumerate(tensors)]
                out = _formula_eager(plan, ts, plan.floats)
                gs = torch.autograd.grad(out, [ts[i] for i in need], grad_out, allow_unused=True)
            return [g.contiguous() if g is not None else tensors[i].new_zeros(tensors[i].shape)
                    for i, g in zip(need, gs)]
        for i in red:
            red[i] += bufs[i][:m].sum(0)
    grads = []
    for i in need:
        if i not in written:  # no path to the output: zeros (the autograd wrapper passes None)
            grads.append(tensors[i].new_zeros(tensors[i].shape))
            continue
        g = full[i].view(*plan.batch, plan.C[i]) if i in full else red[i]
        grads.append(_to_shape(g, tensors[i]).contiguous())
    return grads


def _triton_jvp(plan: _Plan, tensors, tangents, tidx, ntan: int) -> Tensor:
    K = max(1, ntan)
    N, dtype = plan.N, plan.dtype
    shape = (*plan.batch, 3) if ntan == 0 else (ntan, *plan.batch, 3)
    flat, modes = plan.flat(tensors)
    out = torch.empty((K, N, 3), dtype=dtype, device=plan.device)
    for j0 in range(0, K, TRITON_TANGENTS_PER_PASS):
        js = range(j0, min(K, j0 + TRITON_TANGENTS_PER_PASS))
        tflat, tmodes = [], []
        for j in js:
            for i, t in zip(tidx, tangents):
                f, m = _flatten((t[j] if ntan else t).to(dtype), plan.C[i], plan.batch, N)
                tflat.append(f)
                tmodes.append(m)
        spec = plan.spec(modes, tangent_inputs=tuple(tidx), tangent_modes=tuple(tmodes), ntan=len(js))
        if _triton_launch(spec, "jvp", N, plan, [*flat, *tflat, *(out[j] for j in js)]):
            continue
        primals = tuple(t.detach() for t in tensors)  # no kernel: forward-mode AD of the formula
        for j in js:
            tj = {i: (t[j] if ntan else t) for i, t in zip(tidx, tangents)}
            tans = tuple(tj.get(i, torch.zeros_like(t)).to(dtype) for i, t in enumerate(primals))
            o = torch.func.jvp(lambda *ts: _formula_eager(plan, ts, plan.floats), primals, tans)[1]
            out[j] = o.expand(*plan.batch, 3).reshape(N, 3)
    return out.view(shape)


# ---------------------------------------------------------------------------------------------
# The custom operators
# ---------------------------------------------------------------------------------------------

@torch.library.custom_op("torchbrdf::principled_fwd", mutates_args=())
def principled_fwd(tensors: list[Tensor], floats: list[float], cfg: str) -> Tensor:
    """The fused forward kernel: ``(*batch, 3)``."""
    return _run_fwd(_Plan(cfg, tensors, floats), tensors)


@principled_fwd.register_fake
def _(tensors, floats, cfg):
    plan = _Plan(cfg, tensors, floats)
    return tensors[0].new_empty((*plan.batch, 3))


@torch.library.custom_op("torchbrdf::principled_bwd", mutates_args=())
def principled_bwd(tensors: list[Tensor], floats: list[float], cfg: str, grad_out: Tensor,
                   need: list[int]) -> list[Tensor]:
    """The fused recompute-backward: the gradients of ``tensors[i]`` for ``i`` in ``need``."""
    return _run_bwd(_Plan(cfg, tensors, floats), tensors, grad_out, list(need))


@principled_bwd.register_fake
def _(tensors, floats, cfg, grad_out, need):
    return [tensors[i].new_empty(tensors[i].shape) for i in need]  # contiguous, like the real ones


@torch.library.custom_op("torchbrdf::principled_jvp", mutates_args=())
def principled_jvp(tensors: list[Tensor], floats: list[float], cfg: str, tangents: list[Tensor],
                   tidx: list[int], ntan: int) -> Tensor:
    """The fused forward-mode kernel (``ntan`` tangents per input in one pass when > 0)."""
    return _run_jvp(_Plan(cfg, tensors, floats), tensors, tangents, list(tidx), ntan)


@principled_jvp.register_fake
def _(tensors, floats, cfg, tangents, tidx, ntan):
    plan = _Plan(cfg, tensors, floats)
    return tensors[0].new_empty((*plan.batch, 3) if ntan == 0 else (ntan, *plan.batch, 3))


# vmap: the vmapped dimension becomes leading lanes. A batched input (bdim moved to 0) gets 1s
# inserted after it so its own batch dims line up with the others' (right-aligned broadcast).

def _logical_rank(t: Tensor, bdim, lead: int) -> int:
    return t.dim() - 1 - lead - (bdim is not None)


def _fold(t: Tensor, bdim, B: int, L: int, lead: int = 0, force: bool = False) -> Tensor:
    """``t`` (optionally with ``lead`` leading tangent dims) as ``(lead…, B, 1…, *batch, C)``."""
    if bdim is None:
        if not force:
            if lead:  # a K-led tangent: (K, *shape) -> (K, 1, 1…, *shape)
                k = t.dim() - lead
                return t.reshape(t.shape[:lead] + (1,) * (L + 1 - (k - 1)) + t.shape[lead:])
            return t
        t = t.unsqueeze(lead).expand(*t.shape[:lead], B, *t.shape[lead:])
        bdim = lead
    else:
        t = t.movedim(bdim, lead)
    k = t.dim() - lead - 1  # logical rank incl. C
    return t.reshape(t.shape[:lead + 1] + (1,) * (L + 1 - k) + t.shape[lead + 1:])


def _batch(info, in_dims, tensors):
    dims = in_dims[0] or [None] * len(tensors)
    L = max((t.dim() - (d is not None) - 1 for t, d in zip(tensors, dims)), default=0)
    return dims, max(L, 0), info.batch_size


def _vmap_fwd(info, in_dims, tensors, floats, cfg):
    dims, L, B = _batch(info, in_dims, tensors)
    ts = [_fold(t, d, B, L) for t, d in zip(tensors, dims)]
    return principled_fwd(ts, floats, cfg), 0


def _vmap_bwd(info, in_dims, tensors, floats, cfg, grad_out, need):
    dims, L, B = _batch(info, in_dims, tensors)
    L = max(L, grad_out.dim() - (in_dims[3] is not None) - 1)
    ts = [_fold(t, d, B, L, force=i in need) for i, (t, d) in enumerate(zip(tensors, dims))]
    go = _fold(grad_out, in_dims[3], B, L, force=True)
    grads = principled_bwd(ts, floats, cfg, go, need)
    out = []
    for i, g in zip(need, grads):
        logical = tensors[i].shape if dims[i] is None else tensors[i].movedim(dims[i], 0).shape[1:]
        out.append(g.reshape(B, *logical))
    return out, [0] * len(out)


def _vmap_jvp(info, in_dims, tensors, floats, cfg, tangents, tidx, ntan):
    dims, L, B = _batch(info, in_dims, tensors)
    tdims = in_dims[3] or [None] * len(tangents)
    lead = 1 if ntan else 0
    if ntan == 0 and all(d is None for d in dims):
        # Only the tangents are batched (jacfwd, several directions): K tangents in one pass.
        ts = [t.movedim(d, 0) if d is not None else t.unsqueeze(0).expand(B, *t.shape)
              for t, d in zip(tangents, tdims)]
        return principled_jvp(list(tensors), floats, cfg, ts, tidx, B), 0
    L = max([L] + [t.dim() - lead - (d is not None) - 1 for t, d in zip(tangents, tdims)])
    # Some primal must carry the vmapped dimension into the lanes: expand the first if none does.
    none_batched = all(d is None for d in dims)
    ps = [_fold(t, d, B, L, force=none_batched and i == 0) for i, (t, d) in enumerate(zip(tensors, dims))]
    ts = [_fold(t, d, B, L, lead=lead) for t, d in zip(tangents, tdims)]
    out = principled_jvp(ps, floats, cfg, ts, tidx, ntan)
    return out, lead


torch.library.register_vmap("torchbrdf::principled_fwd", _vmap_fwd)
torch.library.register_vmap("torchbrdf::principled_bwd", _vmap_bwd)
torch.library.register_vmap("torchbrdf::principled_jvp", _vmap_jvp)


# The same rules under the legacy vmap (``torch._vmap_internals``, what ``gradcheck``'s
# batched-gradient checks use): its fallback cannot loop over an operator with a tensor list.

_LEGACY_BATCHED = torch._C._parse_dispatch_key("Batched")


class _LegacyVmapInfo:
    randomness = "error"

    def __init__(self, batch_size: int):
        self.batch_size = batch_size


def _legacy_level() -> int:
    """The innermost legacy vmap level (the counter returns the level it opens)."""
    level = torch._C._vmapmode_increment_nesting()
    torch._C._vmapmode_decrement_nesting()
    return level - 1


def _legacy_kernel(rule, op):
    """A ``Batched``-key kernel of ``op`` that unwraps the legacy batched tensors and runs ``rule``."""

    def kernel(*args):
        level = _legacy_level()
        sizes = []

        def unwrap(t):
            if isinstance(t, Tensor) and torch._C._dispatch_keys(t).has(_LEGACY_BATCHED):
                u = torch._remove_batch_dim(t, level, 0, 0)
                sizes.append(u.shape[0])
                return u, 0
            return t, None

        plain, in_dims = [], []
        for a in args:
            if isinstance(a, (list, tuple)) and any(isinstance(t, Tensor) for t in a):
                pairs = [unwrap(t) for t in a]
                plain.append([u for u, _ in pairs])
                in_dims.append([d for _, d in pairs])
            else:
                u, d = unwrap(a)
                plain.append(u)
                in_dims.append(d)
        if not sizes:
            return op(*plain)
        out, out_dims = rule(_LegacyVmapInfo(sizes[0]), tuple(in_dims), *plain)
        if isinstance(out, Tensor):
            return torch._add_batch_dim(out, out_dims, level)
        return [torch._add_batch_dim(o, d, level) for o, d in zip(out, out_dims)]

    return kernel


for _name, _rule, _op in (("principled_fwd", _vmap_fwd, principled_fwd), ("principled_bwd", _vmap_bwd, principled_bwd),
                          ("principled_jvp", _vmap_jvp, principled_jvp)):
    torch.library.impl(f"torchbrdf::{_name}", "Batched")(_legacy_kernel(_rule, _op))


# ---------------------------------------------------------------------------------------------
# Autograd
# ---------------------------------------------------------------------------------------------

def _backward(tensors, floats, cfg, needs, grad_out):
    """Gradients of the inputs (``None`` where not needed or with no path to the output)."""
    need = [i for i, n in enumerate(needs) if n]
    if not need:
        return [None] * len(tensors)
    plan = _Plan(cfg, tensors, floats)
    if _forward_mode_over(tensors, grad_out):
        # Forward mode over this backward (hessian = jacfwd(jacrev)): the backward kernel has no
        # forward-mode rule of its own, so the backward of the same formula runs eagerly.
        _, vjp_fn = torch.func.vjp(lambda *ts: _formula_eager(plan, ts, floats), *tensors)
        gs = vjp_fn(grad_out.expand(*plan.batch, 3))
        return [g if i in need else None for i, g in enumerate(gs)]
    ctype = "float" if plan.dtype == torch.float32 else "double"
    modes = tuple((k, "full", C) for k, C in zip(plan.tensor_names, plan.C))
    written = set(_written((ctype, modes, tuple(plan.float_names), plan.active, plan.need_tint, plan.frame,
                            (3, 1), tuple(need)), plan.family))
    need = [i for i in need if i in written]
    grads = [None] * len(tensors)
    if need:
        for i, g in zip(need, _principled_bwd_differentiable(tensors, floats, cfg, grad_out, need)):
            grads[i] = g
    return grads


def _forward_mode_over(tensors, grad_out) -> bool:
    """True when forward-mode AD (``torch.func.jvp``/``jacfwd``, dual tensors) is around a backward."""
    from torch._C._functorch import TransformType
    from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters

    if any(i.key() == TransformType.Jvp for i in retrieve_all_functorch_interpreters()):
        return True
    if torch._C._is_fwd_grad_enabled():
        from torch.autograd import forward_ad

        return any(forward_ad.unpack_dual(t).tangent is not None for t in (*tensors, grad_out))
    return False


def _setup_context(ctx, inputs, output):
    tensors, floats, cfg = inputs
    ctx.save_for_backward(*tensors)
    ctx.floats, ctx.cfg = floats, cfg


def _op_backward(ctx, grad_out):
    tensors = ctx.saved_tensors
    needs = ctx.needs_input_grad[0]
    if isinstance(needs, bool):
        needs = [needs] * len(tensors)
    # The same structure as the inputs (tensors, floats, cfg): torch.library flattens a float
    # list to one leaf, but an empty list to an empty list.
    return _backward(tensors, ctx.floats, ctx.cfg, needs, grad_out), (None if ctx.floats else []), None


principled_fwd.register_autograd(_op_backward, setup_context=_setup_context)


# Double backward. The first backward always runs the kernel (``principled_bwd``), also when
# autograd records it (``create_graph=True``, and every ``torch.func.grad``, which records in
# case a transform around it differentiates again); differentiating that backward is the vjp
# of the formula's eager vjp (in the output gradient it is linear: the same thing).

def _second_order(tensors, grad_out, floats, cfg, need, grads_of_grads):
    """The vjp of ``principled_bwd``: gradients of ``tensors`` and of ``grad_out``."""
    plan = _Plan(cfg, tensors, floats)

    def first_backward(*args):
        ts, go = list(args[:-1]), args[-1]

        def f(*wrt):
            full = list(ts)
            for i, t in zip(need, wrt):
                full[i] = t
            return _formula_eager(plan, full, floats)

        _, vjp_fn = torch.func.vjp(f, *[ts[i] for i in need])
        return vjp_fn(go.to(plan.dtype).expand(*plan.batch, 3))

    outs, vjp_fn = torch.func.vjp(first_backward, *tensors, grad_out)
    ggs = tuple(torch.zeros_like(o) if g is None else g for o, g in zip(outs, grads_of_grads))
    *g_tensors, g_grad_out = vjp_fn(ggs)
    return list(g_tensors), g_grad_out


def _bwd_setup_context(ctx, inputs, output):
    tensors, floats, cfg, grad_out, need = inputs
    ctx.save_for_backward(*tensors, grad_out)
    ctx.floats, ctx.cfg, ctx.need = floats, cfg, list(need)


def _bwd_op_backward(ctx, grads_of_grads):
    *tensors, grad_out = ctx.saved_tensors
    g_tensors, g_grad_out = _second_order(tensors, grad_out, ctx.floats, ctx.cfg, ctx.need, grads_of_grads)
    return g_tensors, (None if ctx.floats else []), None, g_grad_out, None


class _PrincipledBwdFunction(torch.autograd.Function):
    """``principled_bwd`` with its vjp, for eager calls and ``torch.func`` (as :class:`_PrincipledFunction`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(cfg, consts, *tensors_and_grad_out):
        floats, need = consts.values
        return tuple(principled_bwd(list(tensors_and_grad_out[:-1]), floats, cfg, tensors_and_grad_out[-1], need))

    @staticmethod
    def setup_context(ctx, inputs, output):
        cfg, consts, *rest = inputs
        ctx.save_for_backward(*rest)
        ctx.cfg, ctx.consts = cfg, consts.values

    @staticmethod
    def backward(ctx, *grads_of_grads):
        *tensors, grad_out = ctx.saved_tensors
        floats, need = ctx.consts
        g_tensors, g_grad_out = _second_order(tensors, grad_out, floats, ctx.cfg, need, grads_of_grads)
        return (None, None, *g_tensors, g_grad_out)


def _principled_bwd_differentiable(tensors, floats, cfg, grad_out, need) -> list[Tensor]:
    """``principled_bwd``, recorded by autograd when grad mode is on (a differentiable backward)."""
    if torch.compiler.is_compiling() or not torch.is_grad_enabled():
        return principled_bwd(list(tensors), list(floats), cfg, grad_out, need)
    return list(_PrincipledBwdFunction.apply(cfg, _Floats((list(floats), list(need))), *tensors, grad_out))


principled_bwd.register_autograd(_bwd_op_backward, setup_context=_bwd_setup_context)


def _jvp_vjp(tensors, tangents, floats, cfg, tidx, ntan, grad):
    """Reverse mode over the forward-mode kernel (``jacrev(jacfwd(f))``).

    There is no kernel for this second-order quantity: it is the vjp of the formula's eager jvp.
    """
    plan = _Plan(cfg, tensors, floats)

    def out_tangent(ts, tans):
        def one(tj):
            full = [torch.zeros_like(t) for t in ts]
            for i, t in zip(tidx, tj):
                full[i] = t
            _, o = torch.func.jvp(lambda *x: _formula_eager(plan, x, floats), tuple(ts), tuple(full))
            return o.expand(*plan.batch, 3)

        if ntan:
            return torch.stack([one([t[j] for t in tans]) for j in range(ntan)])
        return one(tans)

    _, vjp_fn = torch.func.vjp(out_tangent, list(tensors), list(tangents))
    return vjp_fn(grad)


class _PrincipledJvpFunction(torch.autograd.Function):
    """The forward-mode kernel with a (formula-eager) reverse mode, for ``grad``/``jacrev`` over ``jvp``."""

    generate_vmap_rule = True

    @staticmethod
    def forward(cfg, consts, n, *tensors_and_tangents):
        tensors, tangents = list(tensors_and_tangents[:n]), list(tensors_and_tangents[n:])
        floats, tidx, ntan = consts.values
        return principled_jvp(tensors, floats, cfg, tangents, tidx, ntan)

    @staticmethod
    def setup_context(ctx, inputs, output):
        cfg, consts, n, *rest = inputs
        ctx.save_for_backward(*rest)
        ctx.cfg, ctx.consts, ctx.n = cfg, consts.values, n

    @staticmethod
    def backward(ctx, grad):
        saved = ctx.saved_tensors
        floats, tidx, ntan = ctx.consts
        g_t, g_tan = _jvp_vjp(saved[:ctx.n], saved[ctx.n:], floats, ctx.cfg, tidx, ntan, grad)
        return (None, None, None, *g_t, *g_tan)




class _Floats:
    """Constant arguments (the runtime floats, ...) as one opaque value.

    Not a pytree: torch.func's generated vmap rule of a ``jvp`` cannot hold per-element dims for
    a list of floats.
    """

    __slots__ = ("values",)

    def __init__(self, values):
        self.values = list(values)


class _PrincipledFunction(torch.autograd.Function):
    """The fused ops with reverse and forward mode, for eager calls and ``torch.func``."""

    generate_vmap_rule = True

    @staticmethod
    def forward(cfg, floats, *tensors):
        return principled_fwd(list(tensors), floats.values, cfg)

    @staticmethod
    def setup_context(ctx, inputs, output):
        cfg, floats, *tensors = inputs
        ctx.save_for_backward(*tensors)
        ctx.save_for_forward(*tensors)
        ctx.floats, ctx.cfg = floats.values, cfg
        # Inputs that are not being differentiated reach jvp as None, not as materialised zeros
        # (a fit's targets and geometry: a (7, P, L, 3) fill, then a scan to prune it).
        ctx.set_materialize_grads(False)

    @staticmethod
    def backward(ctx, grad_out):
        tensors = ctx.saved_tensors
        if grad_out is None:  # undefined (not materialised, see setup_context): no gradient
            return (None, None, *([None] * len(tensors)))
        return (None, None, *_backward(tensors, ctx.floats, ctx.cfg, ctx.needs_input_grad[2:], grad_out))

    @staticmethod
    def jvp(ctx, _cfg, _floats, *tangents):
        tensors = ctx.saved_tensors
        tidx = [i for i, t in enumerate(tangents) if t is not None]
        consts = _Floats((list(ctx.floats), tidx, 0))
        tans = [tangents[i] for i in tidx]
        return _PrincipledJvpFunction.apply(ctx.cfg, consts, len(tensors), *tensors, *tans)


def principled_fast(c: dict[str, Any], active: Iterable[str], need_tint: bool, frame: bool, backend: str = "c") -> Tensor:
    """Fused evaluation on checked, compute-dtype inputs ``c`` (see ``principled._prepare``).

    ``backend``: ``"c"`` (the CPU kernels) or ``"triton"`` (CUDA tensors, or CPU tensors under
    ``TRITON_INTERPRET=1``). ``x``/``y`` must already be filled in when ``frame`` is true.
    Returns ``(*, 3)``.
    """
    return _fused(c, ("l", "v", "n"), active, need_tint, frame, backend, "principled")


#: The non-material inputs of the recovery's residual
#: (:func:`torchbrdf.brdf.formula.capture_log_residual`).
CAPTURE_INPUTS = ("pos", "n", "camera", "light_pos", "light_int", "log_obs", "eps")


def capture_fast(c: dict[str, Any], active: Iterable[str], need_tint: bool, frame: bool,
                 backend: str = "c") -> Tensor:
    """Fused :func:`torchbrdf.brdf.formula.capture_log_residual` on compute-dtype inputs ``c``.

    ``c``: :data:`CAPTURE_INPUTS` and the principled material (broadcastable tensors or
    floats). Returns ``(*, 3)``; reverse and forward mode as for :func:`principled_fast`.
    """
    return _fused(c, CAPTURE_INPUTS, active, need_tint, frame, backend, "capture")


def capture_jvp(c: dict[str, Any], tangents: dict[str, Tensor], active: Iterable[str], need_tint: bool,
                frame: bool, backend: str = "c") -> tuple[Tensor, Tensor]:
    """:func:`capture_fast` and its derivatives along ``K`` directions, from one call of each operator.

    ``tangents``: ``{name: (K, *c[name].shape)}`` for some tensor inputs of ``c`` (the others
    are held). Returns ``(out (*, 3), out tangents (K, *, 3))`` in the inputs' dtype, on their
    device (the operators' rules: one dtype and device for all). The same operators that
    ``torch.func.vmap`` over ``torch.func.jvp`` reaches (``principled_fwd`` and
    ``principled_jvp`` with ``ntan = K``), called directly: without the transforms' work per
    call on the whole ``(K, *, 3)`` tangent (wrapping, batching rules, concatenations), which
    took longer than the kernels themselves (a fit's 6-direction Jacobian of 16384 pixels ×
    16 lights: 50 ms through the transforms, of which 14 ms kernel). Not differentiable: for a
    fit's Jacobian, whose inputs need no gradient.
    """
    tensor_names, tensors, floats, cfg = _operator_args(c, CAPTURE_INPUTS, active, need_tint, frame, backend,
                                                        "capture")
    if any(t.requires_grad for t in tensors) and torch.is_grad_enabled():
        raise RuntimeError("capture_jvp: inputs that require grad (it is not differentiable)")
    unknown = set(tangents) - set(tensor_names)
    if unknown:
        raise ValueError(f"capture_jvp: tangents for {sorted(unknown)}, which are not tensor inputs")
    tidx = [i for i, k in enumerate(tensor_names) if k in tangents]
    K = next(iter(tangents.values())).shape[0] if tangents else 0
    # (K, *shape) with the operators' (1,) for a 0-d input
    tans = [tangents[tensor_names[i]].reshape(K, *tensors[i].shape) for i in tidx]
    out = principled_fwd(tensors, floats, cfg)
    if K == 0:
        return out, out.new_zeros(0, *out.shape)
    return out, principled_jvp(tensors, floats, cfg, tans, tidx, K)


def _operator_args(c: dict[str, Any], lead: tuple[str, ...], active: Iterable[str], need_tint: bool,
                   frame: bool, backend: str, family: str
                   ) -> tuple[list[str], list[Tensor], list[float], str]:
    """The operators' ``(tensor names, tensors, floats, cfg)`` for inputs ``c``."""
    names = [k for k in lead + (("x", "y") if frame else ()) + ("base_color",) + SCALAR_NAMES]
    if torch.compiler.is_compiling():
        # Python floats enter as one-element tensors: once torch.compile makes a float symbolic
        # (a value that changed between calls), a float argument of an operator would
        # specialise it again, one recompile per value.
        like = c[lead[0]]
        c = {k: torch.full((1,), v, dtype=like.dtype, device=like.device)
             if k in SCALAR_NAMES and not isinstance(v, Tensor) else v for k, v in c.items()}
    tensor_names = [k for k in names if isinstance(c.get(k), Tensor)]
    float_names = [k for k in names if k not in tensor_names]
    # 0-d tensors become (1,) so that every tensor has its channel dimension (vmap rules).
    tensors = [c[k] if c[k].dim() > 0 else c[k].reshape(1) for k in tensor_names]
    floats = [float(c[k]) for k in float_names]
    cfg = make_cfg(tensor_names, float_names, active, need_tint, frame, backend, family)
    return tensor_names, tensors, floats, cfg


def _fused(c: dict[str, Any], lead: tuple[str, ...], active: Iterable[str], need_tint: bool, frame: bool,
           backend: str, family: str) -> Tensor:
    _, tensors, floats, cfg = _operator_args(c, lead, active, need_tint, frame, backend, family)
    if torch.compiler.is_compiling():
        return principled_fwd(tensors, floats, cfg)
    return _PrincipledFunction.apply(cfg, _Floats(floats), *tensors)
