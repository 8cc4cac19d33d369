"""The fused kernels' entry points: :func:`principled_fast`, :func:`svbrdf_ggx_fast`, :func:`capture_fast`,
:func:`capture_jvp`.

They turn a call's inputs into the operators' arguments (tensors, runtime floats, an encoded
:class:`~torchbrdf.kernels.layout.KernelConfig`) and call the operators of
:mod:`.registration` with the autograd rules of :mod:`.autograd`. The pieces:

* :mod:`.layout` — the configuration, one call's layout, lane views of the inputs;
* :mod:`.c_runner` / :mod:`.triton_runner` — the kernels' calls on CPU / CUDA tensors;
* :mod:`.registration` — ``torch.ops.torchbrdf.principled_{fwd,bwd,jvp}`` with fake
  implementations and vmap rules;
* :mod:`.autograd` — reverse, forward and second-order rules.

If a kernel cannot be built, the operators evaluate the shared formula eagerly instead (one
warning from the build).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

from torchbrdf.kernels.autograd import apply_principled
from torchbrdf.kernels.layout import SCALAR_NAMES, KernelConfig
from torchbrdf.kernels.registration import principled_bwd, principled_fwd, principled_jvp

__all__ = ["principled_fast", "svbrdf_ggx_fast", "capture_fast", "capture_jvp", "CAPTURE_INPUTS", "GGX_INPUTS",
           "make_cfg", "principled_fwd", "principled_bwd", "principled_jvp", "SCALAR_NAMES"]


def make_cfg(tensor_names: Iterable[str], float_names: Iterable[str], active: Iterable[str], need_tint: bool,
             frame: bool, backend: str = "c", family: str = "principled") -> str:
    """The operators' ``cfg`` string (:meth:`KernelConfig.encode`).

    ``backend``: ``"c"`` (CPU kernels) or ``"triton"``; ``family``: the formula
    (:data:`torchbrdf.brdf.formula.FAMILIES`).
    """
    return KernelConfig(tuple(tensor_names), tuple(float_names), tuple(active), bool(need_tint), bool(frame),
                        backend, family).encode()


def principled_fast(c: dict[str, Any], active: Iterable[str], need_tint: bool, frame: bool, backend: str = "c") -> Tensor:
    """Fused evaluation on checked, compute-dtype inputs ``c`` (see ``principled._prepare``).

    ``backend``: ``"c"`` (the CPU kernels) or ``"triton"`` (CUDA tensors, or CPU tensors under
    ``TRITON_INTERPRET=1``). ``x``/``y`` must already be filled in when ``frame`` is true.
    Returns ``(*, 3)``.
    """
    return _fused(c, ("l", "v", "n"), active, need_tint, frame, backend, "principled")


#: The inputs of :func:`torchbrdf.brdf.formula.svbrdf_ggx`, in the kernels' slot order (the floor
#: that is given travels as a runtime float).
GGX_INPUTS = ("l", "v", "n", "diffuse_albedo", "specular_albedo", "roughness", "alpha_floor", "roughness_floor")


def svbrdf_ggx_fast(c: dict[str, Any], backend: str = "c") -> Tensor:
    """Fused :func:`torchbrdf.brdf.formula.svbrdf_ggx` on checked, compute-dtype inputs ``c``.

    ``c``: ``l, v, n``, ``diffuse_albedo``, ``specular_albedo`` ``(*, 3)`` and ``roughness``
    ``(*, 1)`` tensors, and one floor (``alpha_floor`` or ``roughness_floor``, a number).
    Returns ``(*, 3)``; reverse and forward mode as for :func:`principled_fast`.
    """
    c = {k: x for k, x in c.items() if x is not None}
    return _fused(c, GGX_INPUTS, (), False, False, backend, "svbrdf_ggx", material=())


#: The non-material inputs of the recovery's residual
#: (:func:`torchbrdf.brdf.formula.capture_log_residual`).
CAPTURE_INPUTS = ("pos", "n", "camera", "light_pos", "light_int", "log_obs", "eps")


def capture_fast(c: dict[str, Any], active: Iterable[str], need_tint: bool, frame: bool,
                 backend: str = "c", family: str = "capture") -> Tensor:
    """Fused :func:`torchbrdf.brdf.formula.capture_log_residual` on compute-dtype inputs ``c``.

    ``c``: :data:`CAPTURE_INPUTS` and the principled material (broadcastable tensors or
    floats). ``family``: ``"capture"`` (the principled model) or ``"capture_ggx"`` (the
    recovery's GGX model). Returns ``(*, 3)``; reverse and forward mode as for
    :func:`principled_fast`.
    """
    return _fused(c, CAPTURE_INPUTS, active, need_tint, frame, backend, family)


def capture_jvp(c: dict[str, Any], tangents: dict[str, Tensor], active: Iterable[str], need_tint: bool,
                frame: bool, backend: str = "c", family: str = "capture") -> tuple[Tensor, Tensor]:
    """:func:`capture_fast` and its derivatives along ``K`` directions, from one call of each operator.

    ``tangents``: ``{name: (K, *c[name].shape)}`` for some tensor inputs of ``c`` (the others
    are held). Returns ``(out (*, 3), out tangents (K, *, 3))`` in the inputs' dtype, on their
    device (the operators' rules: one dtype and device for all). The same operators that
    ``torch.func.vmap`` over ``torch.func.jvp`` reaches (``principled_fwd`` and
    ``principled_jvp`` with ``ntan = K``), called directly: without the transforms' work per
    call on the whole ``(K, *, 3)`` tangent (wrapping, batching rules, concatenations), which
    costs more than the kernels themselves at a fit's sizes. Not differentiable: for a
    fit's Jacobian, whose inputs need no gradient. ``family`` as for :func:`capture_fast`.
    """
    tensor_names, tensors, floats, cfg = _operator_args(c, CAPTURE_INPUTS, active, need_tint, frame, backend,
                                                        family)
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
                   frame: bool, backend: str, family: str, material: tuple[str, ...] = ("base_color",) + SCALAR_NAMES
                   ) -> tuple[list[str], list[Tensor], list[float], str]:
    """The operators' ``(tensor names, tensors, floats, cfg)`` for inputs ``c``.

    ``lead``, then the frame (when ``frame``), then ``material``: the slot order; names that
    ``c`` lacks are left out.
    """
    names = [k for k in lead + (("x", "y") if frame else ()) + material if k in c]
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
           backend: str, family: str, material: tuple[str, ...] = ("base_color",) + SCALAR_NAMES) -> Tensor:
    _, tensors, floats, cfg = _operator_args(c, lead, active, need_tint, frame, backend, family, material)
    if torch.compiler.is_compiling():
        return principled_fwd(tensors, floats, cfg)
    return apply_principled(cfg, floats, tensors)
