"""The C kernels' calls: forward, recompute-backward and several-tangent JVP on CPU tensors.

Each function takes a :class:`~torchbrdf.kernels.layout.Plan` and the operator's tensors,
loads (building once) the kernel of that layout (:func:`torchbrdf.kernels.fused.load`) and
runs it on PyTorch's thread count; without a kernel it evaluates the shared formula eagerly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf.kernels.fused import buffer_pool, load
from torchbrdf.kernels.layout import Plan, dparams, flatten, formula_eager, grad_mode, grad_out_lanes, ptrs, to_shape

__all__ = ["run_fwd", "run_bwd", "run_jvp", "BWD_CHUNK", "TANGENTS_PER_PASS"]

# Lanes per backward chunk when some input's gradient is summed over all lanes (reduced
# chunk by chunk, so the buffers stay small: 2^16 lanes × 3 × 8 B = 1.5 MiB).
BWD_CHUNK = 1 << 16
# Tangents per pass of the JVP kernel (jacfwd over K parameters runs ceil(K / 12) passes): the
# generated code grows with the tangents; 12 take a joint light step's directions (5 + 4, the
# base colour in one) in one pass, one primal instead of two (15 % less CPU than passes of 8 + 3).
TANGENTS_PER_PASS = 12


def run_fwd(plan: Plan, tensors: list[Tensor]) -> Tensor:
    """The forward kernel: ``(*batch, 3)``."""
    flat, modes = plan.flat(tensors, s2=True)
    lib = load(plan.spec(modes), backward=False) if plan.N > 0 else None
    if lib is None:
        if plan.N > 0:  # no kernel: the same formula, eagerly
            with torch.no_grad():
                return formula_eager(plan, tensors, plan.floats).expand(*plan.batch, 3).contiguous()
        return torch.empty(*plan.batch, 3, dtype=plan.dtype, device=plan.device)
    out = buffer_pool.empty((plan.N, 3), plan.dtype)
    P = dparams(plan.params(zip(flat, (m for _, m, _ in modes))))
    lib[1](plan.N, ptrs([f.data_ptr() for f in flat]), P, out.data_ptr(), torch.get_num_threads())
    return out.view(*plan.batch, 3)


def run_bwd(plan: Plan, tensors: list[Tensor], grad_out: Tensor, need: list[int]) -> list[Tensor]:
    """The recompute-backward kernel on ``plan.N > 0`` lanes: the gradients of ``tensors[i]``, ``i`` in ``need``."""
    N, dtype = plan.N, plan.dtype
    go, (gls, gcs) = grad_out_lanes(plan, grad_out)
    gmode = {i: grad_mode(tensors[i], plan.C[i], N) for i in need}
    # Chunked (a gradient summed over all lanes): lane offsets move the pointers, so no 's2'.
    chunked = any(m == "red" for m in gmode.values())
    flat, modes = plan.flat(tensors, s2=not chunked)
    lib = load(plan.spec(modes, go_strides=(gls, gcs), grad_mask=tuple(need)), backward=True)
    if lib is None:
        # No kernel (no compiler, a cache fault): the vjp of the shared formula. torch.func, not
        # autograd: inside an operator's implementation the autograd keys are switched off.
        def f(*wrt):
            ts = list(tensors)
            for i, t in zip(need, wrt):
                ts[i] = t
            return formula_eager(plan, ts, plan.floats)

        vjp_fn = torch.func.vjp(f, *[tensors[i] for i in need])[1]
        gs = vjp_fn(grad_out.to(dtype))
        return [g.contiguous() for g in gs]
    fn = lib[1]
    P = dparams(plan.params(zip(flat, (m for _, m, _ in modes))))
    nt = torch.get_num_threads()
    full = {i: buffer_pool.empty((N, plan.C[i]), dtype) for i in need if gmode[i] == "full"}
    red = {i: torch.zeros(plan.C[i], dtype=dtype) for i in need if gmode[i] == "red"}
    chunk = N if not red else BWD_CHUNK
    bufs = {i: torch.empty(min(chunk, N), plan.C[i], dtype=dtype) for i in red}
    item = flat[0].element_size()
    for s in range(0, N, chunk):
        m = min(chunk, N - s)
        ins = [f.data_ptr() + (s * C * item if mode == "full" else 0) for f, (_, mode, C) in zip(flat, modes)]
        gouts: list[int | None] = []
        for i in range(len(tensors)):
            if i in full:
                gouts.append(full[i].data_ptr() + s * plan.C[i] * item)
            elif i in red:
                gouts.append(bufs[i].data_ptr())
            else:
                gouts.append(None)
        go_ptr = go.data_ptr() + (s * 3 * item if gls == 3 else 0)
        fn(m, ptrs(ins), P, go_ptr, ptrs(gouts), nt)
        for i in red:
            red[i] += bufs[i][:m].sum(0)
    grads = []
    for i in need:
        g = full[i].view(*plan.batch, plan.C[i]) if i in full else red[i]
        grads.append(to_shape(g, tensors[i]).contiguous())
    return grads


def run_jvp(plan: Plan, tensors: list[Tensor], tangents: list[Tensor], tidx: list[int], ntan: int,
            nz: list[list[bool]]) -> Tensor:
    """Output tangents: ``(*batch, 3)``, or ``(ntan, *batch, 3)`` when ``ntan > 0``.

    The ``K`` directions run in passes of up to :data:`TANGENTS_PER_PASS`, the primal computed
    once per pass. Each direction carries only the tangents that are nonzero in it (the others
    are pruned from the kernel, tangent mode ``"zero"``): a Gauss–Newton Jacobian's directions
    are unit vectors in one unknown each (a base colour, the roughness, a normal slope), so its
    six directions cost one primal and six narrow tangent chains, less than one pass per tangent
    input or one pass with every tangent in every direction. A tangent that is zero in every
    direction (one a caller passes explicitly; torch.func's own arrive as None, see
    ``torchbrdf.kernels.autograd._PrincipledFunction.setup_context``) is dropped altogether
    before (:func:`torchbrdf.kernels.layout.nonzero_tangents` gives ``nz``).
    """
    K = max(1, ntan)
    N, dtype = plan.N, plan.dtype
    shape = (*plan.batch, 3) if ntan == 0 else (ntan, *plan.batch, 3)
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
                f, m = flatten((t[j] if ntan else t).to(dtype), plan.C[tidx[k]], plan.batch, N, s2=True)
                tflat.append(f)
                tmodes.append(m)
        spec = plan.spec(modes, tangent_inputs=tuple(tidx[k] for k in ks), tangent_modes=tuple(tmodes),
                         ntan=len(js))
        lib = load(spec, backward="jvp")
        if lib is None:  # no kernel: forward-mode AD of the same formula, eagerly
            primals = tuple(t.detach() for t in tensors)
            for j in js:
                tj = {tidx[k]: (tangents[k][j] if ntan else tangents[k]) for k in ks}
                tans = tuple(tj.get(i, torch.zeros_like(t)).to(dtype) for i, t in enumerate(primals))
                o = torch.func.jvp(lambda *ts: formula_eager(plan, ts, plan.floats), primals, tans)[1]
                out[j] = o.expand(*plan.batch, 3).reshape(N, 3)
            continue
        ins, tins = ptrs([f.data_ptr() for f in flat]), ptrs([f.data_ptr() for f in tflat])
        outs = ptrs([out[j].data_ptr() for j in js])
        P = dparams(plan.params(zip(flat, (m for _, m, _ in modes)), zip(tflat, tmodes)))
        lib[1](N, ins, P, tins, outs, torch.get_num_threads())
    return out.view(shape)
