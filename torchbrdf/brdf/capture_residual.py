"""The capture's log residual dispatched to the fused kernels or evaluated eagerly.

:func:`torchbrdf.brdf.formula.capture_log_residual` is the one definition of the residual a
capture fit minimises (the point-light image formation with the principled BRDF, then the
log). This module prepares its inputs (:func:`residual_inputs`) and runs it on the fused
kernels when they apply (without a derivative taken, on the CPU, the light-loop kernel, which
computes each pixel's terms once for all its lights), or eagerly (:func:`log_residual`,
:func:`log_residual_jvp`), and a
Gauss–Newton fit's per-pixel normal equations or data costs in one fused pass
(:func:`normal_equations`, :func:`data_cost`); the
kernels are imported here, at dispatch, so the capture layer above never imports them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import Tensor

from torchbrdf import _checks
from torchbrdf.brdf import formula
from torchbrdf.brdf import principled as _p

__all__ = ["ResidualInputs", "residual_inputs", "log_residual", "log_residual_jvp", "normal_equations",
           "data_cost", "light_schur"]

#: ``(c, active lobes, need_tint, frame, backend, family)``: the formula's inputs ``c`` (per-pixel
#: values as ``(P, 1, C)``, broadcast over the lights), how to run it (backend None: eager) and
#: the model (``capture_log_residual``'s ``family``).
ResidualInputs = tuple[dict[str, Any], tuple, bool, bool, str | None, str]

#: The fused per-lane kernel family of each model's residual.
_LANE_FAMILY = {"principled": "capture", "svbrdf_ggx": "capture_ggx"}


def residual_inputs(normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor,
                    params: Mapping, log_obs: Tensor, eps: float, x: Tensor | None = None,
                    y: Tensor | None = None, any_size: bool = False, family: str = "principled") -> ResidualInputs:
    """The checked inputs of :func:`~torchbrdf.brdf.formula.capture_log_residual` and its backend.

    Args:
        normal: ``(P, 3)`` unit normals; points ``(P, 3)``; camera ``(3,)``; light_pos and
            light_int ``(L, 3)``; params: ``base_color (P, 3)`` and scalar principled
            parameters ``(P, 1)`` or floats (a ``"normal"`` entry is ignored); log_obs
            ``(P, L, 3)``; eps the log's ε; x, y: the tangent frame ``(P, 3)`` or None.
        any_size: in the automatic mode, the fused kernels at every lane count.
        family: the model, ``"principled"`` or ``"svbrdf_ggx"`` (the recovery's GGX model on
            the same maps).

    Every tensor must share ``log_obs``'s dtype and device (checked).
    """
    _checks.check_same_dtype_device({"log_obs": log_obs, "normal": normal, "points": points, "camera": camera,
                                     "light_pos": light_pos, "light_int": light_int,
                                     **{f"params[{k!r}]": v for k, v in params.items()}})

    def px(t: Any) -> Any:  # a per-pixel value as (P, 1, C): broadcast over the lights
        return t[:, None] if isinstance(t, Tensor) else t

    mat = {**_p.PRINCIPLED_DEFAULTS, **{k: px(v) for k, v in params.items() if k != "normal"}}
    c: dict[str, Any] = {**mat, "pos": points[:, None], "n": normal[:, None], "camera": camera,
                         "light_pos": light_pos[None], "light_int": light_int[None], "log_obs": log_obs,
                         "eps": float(eps), "x": px(x), "y": px(y)}
    active = _p.active_lobes(mat)
    need_tint, frame = _p.needs_tint(c, active), _p.needs_frame(c)
    tensors = [t for t in c.values() if isinstance(t, Tensor)]
    lanes = log_obs.shape[0] * log_obs.shape[1]
    backend = _p.fused_backend(log_obs.device, log_obs.dtype, tensors,
                                lambda: max(lanes, _p.FAST_PATH_MIN_LANES) if any_size else lanes)
    if family not in _LANE_FAMILY:
        raise ValueError(f"family: expected one of {sorted(_LANE_FAMILY)}, got {family!r}")
    return c, active, need_tint, frame, backend, family


def log_residual(inputs: ResidualInputs) -> Tensor:
    """The log residual ``(P, L, 3)`` of :func:`residual_inputs`' result, fused when it says so.

    On the C backend with no derivative taken, from the light-loop kernel (the same bits as the
    per-lane kernel; the result is then a view of its ``(P, 1 + 3 L)`` rows, not contiguous).
    """
    c, active, need_tint, frame, backend, family = inputs
    if backend == "c":
        r = _light_loop_residual(c, frame, family)
        if r is not None:
            return r
    if backend is not None:
        from torchbrdf.kernels.ops import capture_fast

        return capture_fast(c, active, need_tint, frame, backend, _LANE_FAMILY[family])
    ops = formula.TorchOps(c["log_obs"].dtype, c["log_obs"].device)
    return formula.capture_log_residual(ops, c, active, need_tint, frame, family)


def _light_loop_residual(c: dict[str, Any], frame: bool, family: str = "principled") -> Tensor | None:
    """The log residual ``(P, L, 3)`` from the light-loop kernel (C), or None where it does not apply.

    Its pixel-level terms are computed once per pixel, not once per pixel-light as in the
    per-lane kernel: twice the pixel-lights per second at a fit's sizes, with the same bits
    (both print the one traced formula in the same order of operations). It applies to
    per-pixel inputs ``(P, 1, C)``, per-light ones ``(1, L, 3)``, no derivative taken, no
    tangent frame, and the anisotropy and tints at their defaults (the kernel's constants).
    The result is a view of the kernel's rows (each pixel's cost comes first).
    """
    log_obs, camera = c["log_obs"], c["camera"]
    if frame or log_obs.dim() != 3 or log_obs.shape[-1] != 3 or camera.shape != (3,):
        return None
    P, L = log_obs.shape[0], log_obs.shape[1]
    if any(not isinstance(c[k], Tensor) or c[k].shape != (1, L, 3) for k in ("light_pos", "light_int")):
        return None
    params: dict[str, Any] = {}
    for k in ("base_color", *_p.PRINCIPLED_DEFAULTS):
        v = c.get(k, _p.PRINCIPLED_DEFAULTS.get(k))
        if k in ("anisotropic", "specular_tint", "sheen_tint"):
            if isinstance(v, Tensor) or v != _p.PRINCIPLED_DEFAULTS[k]:
                return None
        elif v is not None:
            params[k] = v
    per_pixel = {"pos": c["pos"], "normal": c["n"], **params}
    if not all(isinstance(per_pixel.get(k), Tensor) for k in ("pos", "normal", "base_color")):
        return None
    for k, v in per_pixel.items():
        if isinstance(v, Tensor) and v.shape != (P, 1, 3 if k in ("pos", "normal", "base_color") else 1):
            return None
    if _differentiated([t for t in c.values() if isinstance(t, Tensor)]):
        return None
    from torchbrdf.kernels.normal_eq_ops import normal_equations as fused_normal_equations

    p = {k: v[:, 0] if isinstance(v, Tensor) else v for k, v in per_pixel.items()}
    pos = p.pop("pos")
    *_, r = fused_normal_equations(p, {}, pos, camera, c["light_pos"][0], c["light_int"][0], log_obs,
                                   c["eps"], {}, 0, residuals=True, family=family)
    return r.view(P, L, 3)


def _differentiated(tensors: list[Tensor]) -> bool:
    """Whether a derivative of these tensors is being taken (the light-loop kernel has none):
    an input that needs a gradient, forward-mode dual tensors, ``torch.func`` transforms, or
    ``torch.compile`` tracing (which keeps the per-lane operators it knows)."""
    import torch

    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return True
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return True
    if torch._C._is_fwd_grad_enabled():
        from torch.autograd import forward_ad

        return any(forward_ad.unpack_dual(t).tangent is not None for t in tensors)
    return False


def log_residual_jvp(inputs: ResidualInputs, tangents: Mapping[str, Tensor]) -> tuple[Tensor, Tensor] | None:
    """The residual and its derivatives along ``K`` directions on the fused kernels, or None.

    ``tangents``: ``{name: (K, P, C)}`` for ``"normal"`` and parameter names, ``{name: (K, L, 3)}``
    for ``"light_pos"`` and ``"light_int"``. Returns ``(r (P, L, 3),
    dr (K, P, L, 3))``, or None where the kernels do not apply (no backend, a tangent frame, or
    inputs that need a gradient): the caller then takes ``torch.func``'s ``vmap`` of ``jvp``.
    """
    import torch

    c, active, need_tint, frame, backend, family = inputs
    needs_grad = torch.is_grad_enabled() and any(isinstance(t, Tensor) and t.requires_grad for t in c.values())
    if backend is None or needs_grad or frame:
        return None
    from torchbrdf.kernels.ops import capture_jvp

    # the inputs' layout as residual_inputs gives them: per pixel (P, 1, C), per light (1, L, 3)
    tans = {"n" if k == "normal" else k: t[:, None] if k in ("light_pos", "light_int") else t[:, :, None]
            for k, t in tangents.items()}
    return capture_jvp(c, tans, active, need_tint, frame, backend, _LANE_FAMILY[family])


def normal_equations(normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor,
                     params: Mapping, log_obs: Tensor, eps: float, tangents: Mapping[str, Tensor],
                     pattern: Mapping[str, Any], unknowns: int, family: str = "principled"
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """A Gauss–Newton fit's per-pixel terms of the log residual on the fused kernel, or None.

    One pass of ``torch.ops.torchbrdf.normal_equations`` over every light: ``(r (P, 3 L), cost
    (P,), JᵀJ (P, K, K), Jᵀr (P, K))`` with ``J`` the residuals' derivatives along
    ``K = unknowns`` directions, whose tangents of ``normal`` and of ``params``' entries are
    ``tangents`` (``(S, P, C)`` rows, ``pattern`` their non-zero ``(direction, channel, row)``
    entries, as :func:`torchbrdf.kernels.normal_eq_ops.normal_equations` takes them). ``JᵀJ``
    and ``Jᵀr`` count non-finite Jacobian entries and residuals as 0; ``r`` and the cost are
    as they come (``r`` light-major, ``3 l + c``). ``family``: the residual's BRDF
    (``"svbrdf_ggx"``: the recovery's GGX model on the same maps). The other arguments as for
    :func:`residual_inputs`, in ``log_obs``'s dtype and device. None where the kernel does not
    apply (the fused path off or not available for this dtype or device, inputs that need a
    gradient, or parameters other than the isotropic untinted ones): the caller then
    linearises by ``torch.func``.
    """
    if not _light_loop_applies(params, log_obs, (normal, points, camera, light_pos, light_int, log_obs,
                                                 *params.values(), *tangents.values())):
        return None
    from torchbrdf.kernels.normal_eq_ops import normal_equations as fused_normal_equations
    from torchbrdf.kernels.normal_eq_ops import unpack_jtj

    p = {**params, "normal": normal}
    cost, jtj, jtr, r = fused_normal_equations(p, tangents, points, camera, light_pos, light_int, log_obs, eps,
                                               pattern, unknowns, residuals=True, family=family)
    return r, cost, unpack_jtj(jtj, unknowns), jtr


def data_cost(normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor,
              params: Mapping, log_obs: Tensor, eps: float, family: str = "principled") -> Tensor | None:
    """Each pixel's data cost ``Σ r²`` over every light ``(P, 1)`` on the fused kernel, or None.

    One pass of ``torch.ops.torchbrdf.data_cost`` (the light-loop kernel's cost-only variant):
    the squared log residuals summed in float64 per pixel, a non-finite sum as +inf, in
    ``log_obs``'s dtype and device, without the ``(P, L, 3)`` residuals in memory. ``family``
    as for :func:`normal_equations`, the other arguments as for :func:`residual_inputs`. None where the kernel does not apply (as for
    :func:`normal_equations`): the caller then sums :func:`log_residual`'s squares.
    """
    if not _light_loop_applies(params, log_obs, (normal, points, camera, light_pos, light_int, log_obs,
                                                 *params.values())):
        return None
    from torchbrdf.kernels.normal_eq_ops import data_cost as fused_data_cost

    return fused_data_cost({**params, "normal": normal}, points, camera, light_pos, light_int, log_obs, eps,
                           family)


def _light_loop_applies(params: Mapping, log_obs: Tensor, values: tuple) -> bool:
    """Whether the light-loop kernels (normal equations, data cost) take these inputs: the fused
    path on for ``log_obs``'s dtype and device, no input that needs a gradient, and the
    isotropic untinted parameters (the kernels keep the others' defaults)."""
    import torch

    if any(k in params for k in ("anisotropic", "specular_tint", "sheen_tint")):
        return False
    tensors = [t for t in values if isinstance(t, Tensor)]
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    lanes = log_obs.shape[0] * log_obs.shape[1]
    return _p.fused_backend(log_obs.device, log_obs.dtype, tensors,
                            lambda: max(lanes, _p.FAST_PATH_MIN_LANES)) is not None


def light_schur(r: Tensor, cols: Tensor, prior_g: Tensor, prior_h: Tensor, damping: float, huber: float,
                chunk: int = 1024, base_one: bool = False) -> tuple[Tensor, Tensor] | None:
    """A joint light step's per-pixel elimination in one C pass, or None.

    :func:`torchbrdf.kernels.schur_ops.light_schur` (its arguments and results: the per-light
    ``Σ [Jg | r]ᵀ W [Jg | r]`` ``(L, G+1, G+1)`` and ``Σ [B | gp]ᵀ A⁻¹ [B | gp]`` ``(L G + 1,
    L G + 1)``, float64) where the fused path is on and the C kernel applies (CPU tensors,
    float32 or float64); None elsewhere: the caller then eliminates with PyTorch operations.
    """
    import torch

    if r.device.type != "cpu" or torch.is_grad_enabled() and (r.requires_grad or cols.requires_grad):
        return None
    if _p.fused_backend(r.device, r.dtype, [r, cols], lambda: _p.FAST_PATH_MIN_LANES) != "c":
        return None
    from torchbrdf.kernels import schur_ops

    if not schur_ops.available(r):
        return None
    return schur_ops.light_schur(r, cols, prior_g, prior_h, damping, huber, chunk, base_one)
