"""The Triton kernels' calls (CUDA tensors; CPU tensors under ``TRITON_INTERPRET=1``).

The same operations as :mod:`.c_runner`, printed from the same graphs by
:mod:`.codegen_triton`; a kernel that fails to build or launch warns once and the call
evaluates the shared formula eagerly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf.kernels.fused import KernelSpec
from torchbrdf.kernels.layout import Plan, flatten, formula_eager, grad_mode, grad_out_lanes, to_shape, written_inputs

__all__ = ["run_fwd", "run_bwd", "run_jvp", "launch", "floats_tensor", "needs_64bit_index"]

# Lanes per backward launch when some input's gradient is summed over all lanes (the per-lane
# gradient of a chunk is reduced before the next: 2^20 lanes x 3 x 4 B = 12 MiB per input).
TRITON_BWD_CHUNK = 1 << 20
# Tangents per pass of the Triton JVP kernel: the generated code grows with the tangents, and 8
# already share most of the primal work (jacfwd over K parameters runs ceil(K / 8) passes).
TRITON_TANGENTS_PER_PASS = 8

_FLOATS_ON_DEVICE: dict = {}


def _codegen():
    from torchbrdf.kernels import codegen_triton

    return codegen_triton


def needs_64bit_index(N: int) -> bool:
    """64-bit lane indices needed (``i * 3`` past int32)."""
    return 3 * N >= 2 ** 31 - 1


def floats_tensor(plan: Plan) -> Tensor:
    """The runtime Python floats as a float64 tensor on the device (cached: no copy per call)."""
    key = (tuple(plan.floats), str(plan.device))
    t = _FLOATS_ON_DEVICE.get(key)
    if t is None:
        if len(_FLOATS_ON_DEVICE) > 256:
            _FLOATS_ON_DEVICE.clear()
        t = torch.tensor(plan.floats or [0.0], dtype=torch.float64).to(plan.device)
        _FLOATS_ON_DEVICE[key] = t
    return t


def launch(spec: KernelSpec, kind: str, N: int, plan: Plan, args: list[Tensor]) -> bool:
    """Load and launch one Triton kernel; ``False`` (after one warning) when that fails."""
    tl_ = _codegen()
    wide = needs_64bit_index(N)
    hit = tl_.load(spec, kind, wide)
    if hit is None:
        return False
    try:
        if plan.device.type == "cuda":
            with torch.cuda.device(plan.device):  # Triton launches on the current device
                tl_.launch(hit[0], kind, N, floats_tensor(plan), args)
        else:
            tl_.launch(hit[0], kind, N, floats_tensor(plan), args)
    except Exception as e:  # noqa: BLE001 - a compile error shows at the first launch
        import warnings

        tl_.failed(spec, kind, wide)
        warnings.warn(f"torchbrdf: the Triton {kind} kernel failed; using eager.\n{e!r}"[:2000],
                      RuntimeWarning, stacklevel=3)
        return False
    return True


def run_fwd(plan: Plan, tensors: list[Tensor]) -> Tensor:
    out = torch.empty(plan.N, 3, dtype=plan.dtype, device=plan.device)
    if plan.N == 0:
        return out.view(*plan.batch, 3)
    flat, modes = plan.flat(tensors)
    if launch(plan.spec(modes), "fwd", plan.N, plan, [*flat, out]):
        return out.view(*plan.batch, 3)
    with torch.no_grad():
        return formula_eager(plan, tensors, plan.floats).expand(*plan.batch, 3).contiguous()


def run_bwd(plan: Plan, tensors: list[Tensor], grad_out: Tensor, need: list[int]) -> list[Tensor]:
    N, dtype, dev = plan.N, plan.dtype, plan.device
    go, (gls, gcs) = grad_out_lanes(plan, grad_out)
    flat, modes = plan.flat(tensors)
    spec = plan.spec(modes, go_strides=(gls, gcs), grad_mask=tuple(need))
    written = set(written_inputs((spec.ctype, modes, tuple(plan.float_names), plan.active, plan.need_tint,
                            plan.frame, (gls, gcs), tuple(need)), plan.family))
    gmode = {i: grad_mode(tensors[i], plan.C[i], N) for i in need}
    full = {i: torch.empty(N, plan.C[i], dtype=dtype, device=dev) for i in need
            if gmode[i] == "full" and i in written}
    red = {i: torch.zeros(plan.C[i], dtype=dtype, device=dev) for i in need
           if gmode[i] == "red" and i in written}
    chunk = N if not red else TRITON_BWD_CHUNK
    bufs = {i: torch.empty(min(chunk, N), plan.C[i], dtype=dtype, device=dev) for i in red}
    for s in range(0, N, chunk):
        m = min(chunk, N - s)
        gouts = [full[i][s:s + m] if i in full else bufs[i][:m] for i in sorted(written)]
        if not launch(spec, "bwd", m, plan, [*(f[s:s + m] for f in flat), go[s:s + m], *gouts]):
            with torch.enable_grad():
                ts = [t.detach().requires_grad_(i in need) for i, t in enumerate(tensors)]
                out = formula_eager(plan, ts, plan.floats)
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
        grads.append(to_shape(g, tensors[i]).contiguous())
    return grads


def run_jvp(plan: Plan, tensors: list[Tensor], tangents: list[Tensor], tidx: list[int], ntan: int) -> Tensor:
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
                f, m = flatten((t[j] if ntan else t).to(dtype), plan.C[i], plan.batch, N)
                tflat.append(f)
                tmodes.append(m)
        spec = plan.spec(modes, tangent_inputs=tuple(tidx), tangent_modes=tuple(tmodes), ntan=len(js))
        if launch(spec, "jvp", N, plan, [*flat, *tflat, *(out[j] for j in js)]):
            continue
        primals = tuple(t.detach() for t in tensors)  # no kernel: forward-mode AD of the formula
        for j in js:
            tj = {i: (t[j] if ntan else t) for i, t in zip(tidx, tangents)}
            tans = tuple(tj.get(i, torch.zeros_like(t)).to(dtype) for i, t in enumerate(primals))
            o = torch.func.jvp(lambda *ts: formula_eager(plan, ts, plan.floats), primals, tans)[1]
            out[j] = o.expand(*plan.batch, 3).reshape(N, 3)
    return out.view(shape)
