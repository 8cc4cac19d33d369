"""Fused shading as PyTorch operators: ``torch.ops.torchbrdf.shade_lights_{fwd,bwd}``.

* ``shade_lights_fwd(tensors, floats, uniforms, seg, cfg) -> (P, 3)``: the radiance of ``P``
  surface points summed over the point and directional lights, in one kernel pass
  (:mod:`torchbrdf.kernels.codegen_shade`);
* ``shade_lights_bwd(tensors, floats, uniforms, seg, cfg, grad_out, need)``: the gradients of
  ``tensors[i]`` for ``i`` in ``need`` (``i = len(tensors)``: of ``uniforms``), by
  recomputation (nothing is saved but the inputs).

``tensors`` are the per-pixel inputs named in ``cfg`` (``pos (P, 3)``, ``n (P, 3)``, ``x, y``
when the anisotropic form is evaluated, ``base_color (P, 3)``, scalar maps ``(P, 1)``; each
may also be one value broadcast to all points), ``floats`` the material parameters that are
Python numbers. ``uniforms`` ``(S, 3 + 6 (Lp + Ld))`` holds per segment of points (one per
batch element when lights or camera differ between images) the camera position, then
``(q, I)`` per point light and ``(d, E)`` per directional light; ``seg`` (``S + 1`` offsets)
are the segments' point ranges. Gradients flow to ``tensors`` and to ``uniforms`` (the
camera and the lights, per segment): the kernel sums each uniform's per-pixel gradient over
blocks of pixels, and the blocks' partial sums (float64, one row per block) are added by torch,
so the result is deterministic.

``cfg`` = ``"tensor names|float names|lobes|tint|frame|normalize n|Lp|Ld[|backend[|family]]"``
(normalize n: ``n`` is the raw normal and the kernel normalises it, as the eager shader does;
family: the BRDF, ``principled`` unless given, or ``svbrdf_ggx``, whose maps are
``diffuse_albedo``, ``specular_albedo``, ``roughness`` and whose floor is a float). Autograd is registered on
the forward op (what ``torch.compile`` traces). If a kernel cannot be built, the ops evaluate
the same formula (:mod:`torchbrdf.brdf.formula`) eagerly.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

from torchbrdf._checks import active_transforms
from torchbrdf.kernels.codegen_shade import BLOCK, CAMERA, LIGHT_STRIDE, ShadeSpec, generate_triton
from torchbrdf.kernels.fused import buffer_pool, load
from torchbrdf.kernels.layout import SCALAR_NAMES, dparams, flatten, ptrs, to_shape

__all__ = ["shade_lights", "make_cfg", "TENSOR_ORDER"]

#: The order of the per-pixel inputs (those present): the principled BRDF's, then the SVBRDF GGX's.
TENSOR_ORDER = ("pos", "n", "x", "y", "base_color") + SCALAR_NAMES + (
    "diffuse_albedo", "specular_albedo", "alpha_floor", "roughness_floor")


def make_cfg(tensor_names: Iterable[str], float_names: Iterable[str], active: Iterable[str], need_tint: bool,
             frame: bool, normalize_n: bool, n_point: int, n_dir: int, backend: str = "c",
             family: str = "principled") -> str:
    """The ``cfg`` string of the shading operators (what changes the kernel, as text).

    ``backend``: ``"c"`` (the C kernels, CPU tensors) or ``"triton"`` (CUDA tensors, or CPU
    tensors under ``TRITON_INTERPRET=1``); ``family``: the BRDF (``codegen_shade.FAMILIES``).
    """
    parts = [
        ",".join(tensor_names),
        ",".join(float_names),
        ",".join(active),
        str(int(need_tint)),
        str(int(frame)),
        str(int(normalize_n)),
        str(int(n_point)),
        str(int(n_dir)),
    ]
    tail = [backend, family] if family != "principled" else [backend] if backend != "c" else []
    return "|".join(parts + tail)


class _Plan:
    def __init__(self, cfg: str, tensors, floats):
        tn, fn, act, tint, frame, nrm, lp, ld, *rest = cfg.split("|")
        self.backend = rest[0] if rest else "c"
        self.family = rest[1] if len(rest) > 1 else "principled"
        self.tensor_names = tn.split(",") if tn else []
        self.float_names = fn.split(",") if fn else []
        self.active = tuple(act.split(",")) if act else ()
        self.need_tint, self.frame, self.normalize_n = tint == "1", frame == "1", nrm == "1"
        self.n_point, self.n_dir = int(lp), int(ld)
        self.C = [1 if k in SCALAR_NAMES else 3 for k in self.tensor_names]
        self.N = tensors[0].shape[0]  # pos is always a (P, 3) tensor
        self.dtype = tensors[0].dtype
        self.floats = [float(x) for x in floats]

    def flat(self, tensors):
        out = [flatten(t, C, (self.N,), self.N) for t, C in zip(tensors, self.C)]
        modes = tuple((k, m, C) for k, (_, m), C in zip(self.tensor_names, out, self.C))
        return [f for f, _ in out], modes

    def spec(self, modes, grad_mask=(), go_mode="full", uniform_grad=False) -> ShadeSpec:
        ctype = "float" if self.dtype == torch.float32 else "double"
        lights = (("point",) if self.n_point else ()) + (("directional",) if self.n_dir else ())
        return ShadeSpec(
            ctype,
            modes,
            self.float_names,
            self.active,
            self.need_tint,
            self.frame,
            lights,
            grad_mask,
            self.normalize_n,
            go_mode,
            uniform_grad,
            self.family,
        )

    def params(self):
        return dparams(self.floats + [float(self.n_point), float(self.n_dir)])

    def triton_params(self, device) -> Tensor:
        # float64 (the formula folds Python numbers in double); at least one element
        return torch.tensor(self.floats + [0.0], dtype=torch.float64, device=device)


def _segments(seg):
    return [(r, s, e) for r, (s, e) in enumerate(zip(seg[:-1], seg[1:])) if e > s]


def _formula_eager(plan: _Plan, tensors, floats, uniforms: Tensor, seg) -> Tensor:
    """The shared formula on torch tensors: the fallback and the double backward."""
    from torchbrdf.brdf import formula

    ops = formula.TorchOps(plan.dtype, tensors[0].device)
    pieces = []
    for r, s, e in _segments(seg):
        c = dict(zip(plan.float_names, floats))
        for k, t in zip(plan.tensor_names, tensors):
            c[k] = t[s:e] if t.dim() == 2 and t.shape[0] == plan.N and plan.N > 1 else t
        c.setdefault("x", None)
        c.setdefault("y", None)
        u = uniforms[r]
        pos = c.pop("pos")
        if plan.normalize_n:
            c["n"] = formula.normalize(ops, c["n"])
        n = c["n"]
        c["v"] = formula.view_direction(ops, u[:CAMERA], pos)

        def brdf(l, c=c, family=getattr(formula, plan.family)):
            return family(ops, {**c, "l": l}, plan.active, plan.need_tint, plan.frame)

        acc = torch.zeros(e - s, 3, dtype=plan.dtype, device=pos.device)
        for j in range(plan.n_point + plan.n_dir):
            lu = u[CAMERA + LIGHT_STRIDE * j : CAMERA + LIGHT_STRIDE * (j + 1)]
            if j < plan.n_point:
                acc = acc + formula.point_light(ops, pos, n, lu[:3], lu[3:], brdf)
            else:
                acc = acc + formula.directional_light(ops, n, lu[:3], lu[3:], brdf)
        pieces.append(acc)
    if not pieces:
        return torch.zeros(plan.N, 3, dtype=plan.dtype, device=tensors[0].device)
    return torch.cat(pieces) if len(pieces) > 1 else pieces[0]


def _run_fwd(plan: _Plan, tensors, uniforms: Tensor, seg) -> Tensor:
    N = plan.N
    if N == 0:
        return torch.zeros(0, 3, dtype=plan.dtype, device=tensors[0].device)
    flat, modes = plan.flat(tensors)
    if plan.backend == "triton":
        res = _run_triton(plan, plan.spec(modes), "fwd", flat, modes, uniforms, seg)
        if res is not None:
            return res[0][0]
        with torch.no_grad():
            return _formula_eager(plan, tensors, plan.floats, uniforms, seg)
    lib = load(plan.spec(modes), backward=False)
    if lib is None:
        with torch.no_grad():
            return _formula_eager(plan, tensors, plan.floats, uniforms, seg)
    uniforms = uniforms.contiguous()
    out = buffer_pool.empty((N, 3), plan.dtype)
    item = out.element_size()
    P = plan.params()
    nt = torch.get_num_threads()
    for r, s, e in _segments(seg):
        ins = [f.data_ptr() + (s * C * item if mode == "full" else 0) for f, (_, mode, C) in zip(flat, modes)]
        ins.append(uniforms[r].data_ptr())
        lib[1](e - s, ptrs(ins), P, out.data_ptr() + s * 3 * item, nt)
    return out


def _zeros(t: Tensor) -> Tensor:
    # Gradients are always contiguous (what the fake implementation promises torch.compile).
    return t.new_zeros(t.shape)


def _run_bwd(plan: _Plan, tensors, uniforms: Tensor, seg, grad_out: Tensor, need) -> list:
    """Gradients of ``tensors[i]`` for ``i`` in ``need``; index ``len(tensors)``: of ``uniforms``."""
    N = plan.N
    inputs = [*tensors, uniforms]
    if N == 0 or not need:
        return [_zeros(inputs[i]) for i in need]
    T = len(tensors)
    flat, modes = plan.flat(tensors)
    # The output gradient as lanes too: the gradient of a sum is one value for all pixels ('b0'),
    # read in place instead of being materialised.
    go, go_mode = flatten(grad_out.to(plan.dtype), 3, (N,), N)
    want_u = T in need
    spec = plan.spec(modes, grad_mask=tuple(i for i in need if i < T), go_mode=go_mode, uniform_grad=want_u)
    lib = None
    if plan.backend == "triton":
        res = _run_triton(plan, spec, "bwd", flat, modes, uniforms, seg, go, go_mode)
        if res is not None:
            full = dict(zip(res[1], res[0]))
            return _assemble(inputs, need, full, res[2])
    else:
        lib = load(spec, backward=True)
    if lib is None:
        # torch.func: autograd does not record inside a custom operator's implementation
        def image(*wrt):
            full = list(inputs)
            for i, t in zip(need, wrt):
                full[i] = t
            return _formula_eager(plan, full[:T], plan.floats, full[T], seg)

        pullback = torch.func.vjp(image, *[inputs[i].detach() for i in need])[1]
        gs = pullback(grad_out.to(plan.dtype))
        return [g.contiguous() if g is not None else _zeros(inputs[i]) for i, g in zip(need, gs)]
    written = lib[2]
    uniforms = uniforms.contiguous()
    item = go.element_size()
    full = {i: buffer_pool.empty((N, plan.C[i]), plan.dtype) for i in need if i in written}
    P = plan.params()
    nt = torch.get_num_threads()
    partials = []
    for r, s, e in _segments(seg):
        ins = [f.data_ptr() + (s * C * item if mode == "full" else 0) for f, (_, mode, C) in zip(flat, modes)]
        ins.append(uniforms[r].data_ptr())
        gouts = [full[i].data_ptr() + s * plan.C[i] * item if i in full else None for i in range(T)]
        if want_u:
            part = uniforms.new_zeros(((e - s + BLOCK - 1) // BLOCK, uniforms.shape[1]), dtype=torch.float64)
            partials.append((r, part))
            gouts.append(part.data_ptr())
        go_ptr = go.data_ptr() + (s * 3 * item if go_mode == "full" else 0)
        lib[1](e - s, ptrs(ins), P, go_ptr, ptrs(gouts), nt)
    return _assemble(inputs, need, full, partials)


def _assemble(inputs: list[Tensor], need, full: dict[int, Tensor], partials: list[tuple[int, Tensor]]
              ) -> list[Tensor]:
    """The gradients in ``need``'s order: the kernels' per-pixel gradients ``full`` (zeros where
    an input has no path to the output) and the uniforms' gradient, each segment's row the sum
    of its blocks' partial sums."""
    T = len(inputs) - 1
    grads = []
    for i in need:
        if i == T:
            gu = torch.zeros(inputs[T].shape, dtype=torch.float64, device=inputs[T].device)
            for r, part in partials:
                gu[r] = part.sum(0)
            grads.append(gu.to(inputs[T].dtype))
        else:
            grads.append(to_shape(full[i], inputs[i]).contiguous() if i in full else _zeros(inputs[i]))
    return grads


_triton_lock = threading.Lock()
_triton_kernels: dict = {}
_triton_failed: set = set()


def _triton_kernel(spec: ShadeSpec, kind: str, wide: bool):
    """The ``@triton.jit`` shading kernel of ``spec`` (``kind`` ``"fwd"``/``"bwd"``) and the
    inputs whose gradient it writes, or None when it cannot be built (one warning)."""
    from torchbrdf.kernels import codegen_triton

    key = (spec.key(kind == "bwd"), kind, wide, codegen_triton.interpret_mode())
    hit = _triton_kernels.get(key)
    if hit is not None:
        return hit
    with _triton_lock:
        hit = _triton_kernels.get(key)
        if hit is not None or key in _triton_failed:
            return hit
        if not codegen_triton.available():
            _triton_failed.add(key)
            return None
        try:
            src = generate_triton(spec, kind, wide)
            hit = (codegen_triton.compile_source(src, f"tb_{kind}"), spec.written)
        except Exception as e:  # noqa: BLE001 - any failure: the shading runs eagerly
            _triton_failed.add(key)
            warnings.warn(f"torchbrdf: building the Triton shading kernel failed; using eager.\n{e!r}"[:2000],
                          RuntimeWarning, stacklevel=3)
            return None
        _triton_kernels[key] = hit
        return hit


def _run_triton(plan: _Plan, spec: ShadeSpec, kind: str, flat, modes, uniforms: Tensor, seg, go=None,
                go_mode="full") -> tuple[list[Tensor], tuple[int, ...], list[tuple[int, Tensor]]] | None:
    """One Triton launch per segment: ``([out (N, 3)], (), [])`` (``"fwd"``) or the gradients
    ``(N, C_k)`` of the inputs ``written``, ``written`` and, with ``spec.uniform_grad``, each
    segment's row and its blocks' partial uniform gradients (``"bwd"``); None when the kernel
    cannot be built."""
    from torchbrdf.kernels import codegen_triton

    N = plan.N
    wide = N * max([3] + plan.C) >= 2**31
    hit = _triton_kernel(spec, kind, wide)
    if hit is None:
        return None
    kernel, written = hit
    dev = flat[0].device
    outs = ([torch.empty((N, 3), dtype=plan.dtype, device=dev)] if kind == "fwd"
            else [torch.empty((N, plan.C[k]), dtype=plan.dtype, device=dev) for k in written])
    P = plan.triton_params(dev)
    uniforms = uniforms.to(device=dev).contiguous()
    partials = []
    for r, s, e in _segments(seg):
        ins = [f[s:e] if mode == "full" else f for f, (_, mode, _) in zip(flat, modes)]
        if kind == "fwd":
            tail = [outs[0][s:e]]
        else:
            tail = [go[s:e] if go_mode == "full" else go] + [o[s:e] for o in outs]
            if spec.uniform_grad:
                blocks = -(-(e - s) // codegen_triton.block_size(kind))
                part = torch.zeros((blocks, uniforms.shape[1]), dtype=torch.float64, device=dev)
                partials.append((r, part))
                tail.append(part)
        args = [uniforms[r], *ins, *tail, plan.n_point, plan.n_dir]
        try:
            codegen_triton.launch(kernel, kind, e - s, P, args)
        except Exception as exc:  # noqa: BLE001 - a launch failure: this family runs eagerly
            with _triton_lock:
                _triton_failed.add((spec.key(kind == "bwd"), kind, wide, codegen_triton.interpret_mode()))
                _triton_kernels.clear()
            warnings.warn(f"torchbrdf: the Triton shading kernel failed; using eager.\n{exc!r}"[:2000],
                          RuntimeWarning, stacklevel=3)
            return None
    return outs, written, partials


@torch.library.custom_op("torchbrdf::shade_lights_fwd", mutates_args=())
def shade_lights_fwd(
    tensors: list[Tensor], floats: list[float], uniforms: Tensor, seg: list[int], cfg: str
) -> Tensor:
    """The fused shading forward: ``(P, 3)`` radiance summed over the lights."""
    return _run_fwd(_Plan(cfg, tensors, floats), tensors, uniforms, list(seg))


@shade_lights_fwd.register_fake
def _(tensors, floats, uniforms, seg, cfg):
    return tensors[0].new_empty((tensors[0].shape[0], 3))


@torch.library.custom_op("torchbrdf::shade_lights_bwd", mutates_args=())
def shade_lights_bwd(
    tensors: list[Tensor],
    floats: list[float],
    uniforms: Tensor,
    seg: list[int],
    cfg: str,
    grad_out: Tensor,
    need: list[int],
) -> list[Tensor]:
    """The fused recompute-backward: gradients of ``tensors[i]`` for ``i`` in ``need``
    (``i = len(tensors)``: of ``uniforms``)."""
    return _run_bwd(_Plan(cfg, tensors, floats), tensors, uniforms, list(seg), grad_out, list(need))


@shade_lights_bwd.register_fake
def _(tensors, floats, uniforms, seg, cfg, grad_out, need):
    inputs = [*tensors, uniforms]
    return [inputs[i].new_empty(inputs[i].shape) for i in need]


def _setup_context(ctx, inputs, output):
    tensors, floats, uniforms, seg, cfg = inputs
    ctx.save_for_backward(*tensors, uniforms)
    ctx.need = [i for i, t in enumerate([*tensors, uniforms]) if t.requires_grad]
    ctx.floats, ctx.seg, ctx.cfg = floats, seg, cfg


def _no_grad(floats):
    # torch.library matches the gradient structure to the inputs: an empty list stays a list.
    return [] if len(floats) == 0 else None


def _gradients(tensors, floats, uniforms, seg, cfg, grad_out, need) -> list[Tensor | None]:
    """Gradients of ``tensors[i]`` for ``i`` in ``need`` and of ``uniforms`` (last; index
    ``len(tensors)`` in ``need``), ``None`` elsewhere."""
    inputs = [*tensors, uniforms]
    grads: list[Tensor | None] = [None] * len(inputs)
    if not need:
        return grads
    if torch.is_grad_enabled() and any(inputs[i].requires_grad for i in need):
        # create_graph=True: a differentiable backward, eagerly from the same formula.
        plan = _Plan(cfg, tensors, floats)
        with torch.enable_grad():
            out = _formula_eager(plan, tensors, floats, uniforms, seg)
            gs = torch.autograd.grad(
                out, [inputs[i] for i in need], grad_out, create_graph=True, allow_unused=True
            )
        for i, g in zip(need, gs):
            grads[i] = g
        return grads
    for i, g in zip(need, shade_lights_bwd(list(tensors), list(floats), uniforms, list(seg), cfg, grad_out, need)):
        grads[i] = g
    return grads


def _backward(ctx, grad_out):
    *tensors, uniforms = ctx.saved_tensors
    *grads, grad_uniforms = _gradients(tensors, ctx.floats, uniforms, ctx.seg, ctx.cfg, grad_out, ctx.need)
    return grads, _no_grad(ctx.floats), grad_uniforms, None, None


shade_lights_fwd.register_autograd(_backward, setup_context=_setup_context)


class _ShadeLightsFunction(torch.autograd.Function):
    """``shade_lights_fwd`` with its backward in the form ``torch.func.grad``/``vjp`` accept (a
    custom operator's registered autograd is not visible to them); used under those transforms."""

    @staticmethod
    def forward(uniforms, seg, cfg, floats, *tensors):
        return shade_lights_fwd(list(tensors), floats, uniforms, seg, cfg)

    @staticmethod
    def setup_context(ctx, inputs, output):
        uniforms, seg, cfg, floats, *tensors = inputs
        ctx.save_for_backward(*tensors, uniforms)
        ctx.floats, ctx.seg, ctx.cfg = floats, seg, cfg

    @staticmethod
    def backward(ctx, grad_out):
        *tensors, uniforms = ctx.saved_tensors
        need = [i for i, wanted in enumerate(ctx.needs_input_grad[4:]) if wanted]
        need += [len(tensors)] if ctx.needs_input_grad[0] else []
        # torch.func.grad records every backward with grad mode on; only when something will
        # differentiate it again does it need the eager formula's differentiable gradient.
        with torch.set_grad_enabled(_differentiated_again([*tensors, uniforms, grad_out])):
            *grads, grad_uniforms = _gradients(tensors, ctx.floats, uniforms, ctx.seg, ctx.cfg, grad_out,
                                               need)
        return (grad_uniforms, None, None, None, *grads)


def _differentiated_again(tensors: list[Tensor]) -> bool:
    """Whether a gradient computed now can be differentiated again: a second ``torch.func.grad``
    level, or plain autograd tracking the tensors beneath the transforms."""
    if sum(kind == "Grad" for kind, _ in active_transforms()) > 1:
        return True
    for t in tensors:
        while torch._C._functorch.is_functorch_wrapped_tensor(t):
            t = torch._C._functorch.get_unwrapped(t)
        if t.requires_grad:
            return True
    return False


def shade_lights(
    c: dict[str, Any],
    uniforms: Tensor,
    seg: list[int] | Tensor,
    active: Iterable[str],
    need_tint: bool,
    frame: bool,
    normalize_n: bool,
    n_point: int,
    n_dir: int,
    backend: str = "c",
    family: str = "principled",
) -> Tensor:
    """Fused shading of ``P`` points on compute-dtype inputs.

    Args:
        c: ``pos``, ``n`` ``(P, 3)``; ``x, y`` ``(P, 3)`` when ``frame``; the BRDF's material:
            principled, ``base_color`` and the ten scalar parameters; ``svbrdf_ggx``,
            ``diffuse_albedo``, ``specular_albedo``, ``roughness`` and one floor (tensors
            ``(P, C)`` / 0-d, or Python numbers; a floor is a number).
        uniforms: ``(S, 3 + 6 (n_point + n_dir))`` (see the module docstring); ``seg``: ``S + 1``
            point offsets.
        backend: ``"c"`` (CPU tensors) or ``"triton"`` (CUDA tensors; CPU tensors under
            ``TRITON_INTERPRET=1``).
        family: the BRDF, ``"principled"`` or ``"svbrdf_ggx"``.

    Returns:
        ``(P, 3)`` radiance summed over the lights, on the inputs' device.
    """
    names = [k for k in TENSOR_ORDER if k in c and (k not in ("x", "y") or frame)]
    tensor_names = [k for k in names if isinstance(c[k], Tensor)]
    float_names = [k for k in names if k not in tensor_names]
    tensors = [c[k] if c[k].dim() > 0 else c[k].reshape(1) for k in tensor_names]
    floats = [float(c[k]) for k in float_names]
    cfg = make_cfg(tensor_names, float_names, active, need_tint, frame, normalize_n, n_point, n_dir, backend,
                   family)
    seg = [int(s) for s in seg]
    if not torch.compiler.is_compiling() and torch._C._are_functorch_transforms_active():
        return _ShadeLightsFunction.apply(uniforms, seg, cfg, floats, *tensors)
    return shade_lights_fwd(tensors, floats, uniforms, seg, cfg)
