"""The fused kernels registered as PyTorch operators: ``torch.ops.torchbrdf.principled_{fwd,bwd,jvp}``.

Three ``torch.library.custom_op`` s, each with a fake (meta) implementation and vmap rules
(``torch.func.vmap``, and the legacy vmap of ``gradcheck``'s batched checks):

* ``principled_fwd(tensors, floats, cfg) -> out (*batch, 3)``;
* ``principled_bwd(tensors, floats, cfg, grad_out, need) -> [grad of tensors[i] for i in need]``
  (recompute: nothing is saved but the inputs);
* ``principled_jvp(tensors, floats, cfg, tangents, tidx, ntan) -> out tangent``: the tangents
  of ``tensors[i] for i in tidx``; with ``ntan = K > 0`` every tangent has a leading ``K``
  dimension and the K output tangents ``(K, *batch, 3)`` come from one pass.

``cfg`` is a :class:`~torchbrdf.kernels.layout.KernelConfig` encoded as a string (the
operators' schema has no structured types). The kernels run through :mod:`.c_runner` or
:mod:`.triton_runner`; their autograd rules are in :mod:`.autograd` (import
:mod:`torchbrdf.kernels.ops`, which loads both).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf.kernels import c_runner, triton_runner
from torchbrdf.kernels.layout import KernelConfig, Plan, nonzero_tangents

__all__ = ["principled_fwd", "principled_bwd", "principled_jvp", "plan_of"]


def plan_of(cfg: str, tensors: list[Tensor], floats: list[float]) -> Plan:
    """The layout of one operator call."""
    return Plan(KernelConfig.decode(cfg), tensors, floats)


_plan = plan_of


def _runner(plan: Plan):
    return triton_runner if plan.backend == "triton" else c_runner


@torch.library.custom_op("torchbrdf::principled_fwd", mutates_args=())
def principled_fwd(tensors: list[Tensor], floats: list[float], cfg: str) -> Tensor:
    """The fused forward kernel: ``(*batch, 3)``."""
    plan = _plan(cfg, tensors, floats)
    return _runner(plan).run_fwd(plan, tensors)


@principled_fwd.register_fake
def _(tensors, floats, cfg):
    plan = _plan(cfg, tensors, floats)
    return tensors[0].new_empty((*plan.batch, 3))


@torch.library.custom_op("torchbrdf::principled_bwd", mutates_args=())
def principled_bwd(tensors: list[Tensor], floats: list[float], cfg: str, grad_out: Tensor,
                   need: list[int]) -> list[Tensor]:
    """The fused recompute-backward: the gradients of ``tensors[i]`` for ``i`` in ``need``."""
    plan = _plan(cfg, tensors, floats)
    if plan.N == 0:
        return [tensors[i].new_zeros(tensors[i].shape) for i in need]
    return _runner(plan).run_bwd(plan, tensors, grad_out, list(need))


@principled_bwd.register_fake
def _(tensors, floats, cfg, grad_out, need):
    return [tensors[i].new_empty(tensors[i].shape) for i in need]  # contiguous, like the real ones


@torch.library.custom_op("torchbrdf::principled_jvp", mutates_args=())
def principled_jvp(tensors: list[Tensor], floats: list[float], cfg: str, tangents: list[Tensor],
                   tidx: list[int], ntan: int) -> Tensor:
    """The fused forward-mode kernel (``ntan`` tangents per input in one pass when > 0)."""
    plan = _plan(cfg, tensors, floats)
    tidx, tangents, nz = nonzero_tangents(tangents, list(tidx), ntan)
    if plan.N == 0 or not tidx:
        shape = (*plan.batch, 3) if ntan == 0 else (ntan, *plan.batch, 3)
        return torch.zeros(shape, dtype=plan.dtype, device=plan.device)
    if plan.backend == "triton":
        return triton_runner.run_jvp(plan, tensors, tangents, tidx, ntan)
    return c_runner.run_jvp(plan, tensors, tangents, tidx, ntan, nz)


@principled_jvp.register_fake
def _(tensors, floats, cfg, tangents, tidx, ntan):
    plan = _plan(cfg, tensors, floats)
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

# (None where this torch has no legacy vmap: nothing to register then)
_LEGACY_BATCHED = getattr(torch._C, "_parse_dispatch_key", lambda key: None)("Batched")


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


if _LEGACY_BATCHED is not None:
    for _name, _rule, _op in (("principled_fwd", _vmap_fwd, principled_fwd),
                              ("principled_bwd", _vmap_bwd, principled_bwd),
                              ("principled_jvp", _vmap_jvp, principled_jvp)):
        torch.library.impl(f"torchbrdf::{_name}", "Batched")(_legacy_kernel(_rule, _op))
