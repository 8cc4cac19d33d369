"""Autograd of the fused operators: reverse mode, forward mode, double backward.

``principled_fwd`` has ``register_autograd`` (what ``torch.compile`` traces); eager calls and
``torch.func`` go through ``_PrincipledFunction`` (:func:`apply_principled`) (same operators, plus a forward-mode
``jvp`` and ``generate_vmap_rule``), because Dynamo does not trace an ``autograd.Function``
with a custom ``jvp``. The backward is always the kernel (``principled_bwd``), also when
autograd records it (``create_graph=True``, every ``torch.func.grad``); differentiating it
again is the eager formula's second-order vjp (:func:`_second_order`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf.kernels.layout import formula_eager, written_inputs
from torchbrdf.kernels.registration import plan_of, principled_bwd, principled_fwd, principled_jvp

__all__ = ["apply_principled"]


def _backward(tensors, floats, cfg, needs, grad_out):
    """Gradients of the inputs (``None`` where not needed or with no path to the output)."""
    need = [i for i, n in enumerate(needs) if n]
    if not need:
        return [None] * len(tensors)
    plan = plan_of(cfg, tensors, floats)
    if _forward_mode_over(tensors, grad_out):
        # Forward mode over this backward (hessian = jacfwd(jacrev)): the backward kernel has no
        # forward-mode rule of its own, so the backward of the same formula runs eagerly.
        _, vjp_fn = torch.func.vjp(lambda *ts: formula_eager(plan, ts, floats), *tensors)
        gs = vjp_fn(grad_out.expand(*plan.batch, 3))
        return [g if i in need else None for i, g in enumerate(gs)]
    ctype = "float" if plan.dtype == torch.float32 else "double"
    modes = tuple((k, "full", C) for k, C in zip(plan.tensor_names, plan.C))
    written = set(written_inputs((ctype, modes, tuple(plan.float_names), plan.active, plan.need_tint, plan.frame,
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
    plan = plan_of(cfg, tensors, floats)

    def first_backward(*args):
        ts, go = list(args[:-1]), args[-1]

        def f(*wrt):
            full = list(ts)
            for i, t in zip(need, wrt):
                full[i] = t
            return formula_eager(plan, full, floats)

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
    plan = plan_of(cfg, tensors, floats)

    def out_tangent(ts, tans):
        def one(tj):
            full = [torch.zeros_like(t) for t in ts]
            for i, t in zip(tidx, tj):
                full[i] = t
            _, o = torch.func.jvp(lambda *x: formula_eager(plan, x, floats), tuple(ts), tuple(full))
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


def apply_principled(cfg: str, floats: list[float], tensors: list[Tensor]) -> Tensor:
    """``principled_fwd`` with reverse and forward mode, for eager calls and ``torch.func``."""
    return _PrincipledFunction.apply(cfg, _Floats(floats), *tensors)
