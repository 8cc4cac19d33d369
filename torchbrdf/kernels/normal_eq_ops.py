"""The recovery's per-pixel normal equations as a PyTorch operator: ``torch.ops.torchbrdf.normal_equations``.

``normal_equations(tensors, tangents, floats, uniforms, log_obs, cfg) -> (N, W)``: per pixel
the data cost ``Σ r²``, ``JᵀJ`` (upper triangle) and ``Jᵀr`` of the capture's log residuals
over every light (optionally the residuals too, ``(N, W + 3 L)``), in one kernel pass (:mod:`torchbrdf.kernels.codegen_normal_eq`; C for CPU
tensors, Triton for CUDA tensors and under ``TRITON_INTERPRET=1``). A fake implementation lets
``torch.compile`` trace it; it has no autograd (its outputs are already derivatives). Where no
kernel can be built it evaluates the same formula eagerly (``torch.func.jvp`` per direction).

``data_cost(tensors, floats, uniforms, log_obs, cfg) -> (N, 1)``
(``torch.ops.torchbrdf.data_cost``): the same kernel family's cost-only variant, each pixel's
``Σ r²`` summed in float64 and non-finite as +inf (a search's candidate costs); eagerly, the
residuals' sum of squares.

:func:`normal_equations` and :func:`data_cost` are the entry points on the recovery's decoded maps.
"""

from __future__ import annotations

import ctypes
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal, overload

import torch
from torch import Tensor

from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import PRINCIPLED_DEFAULTS, SCALAR_PARAMS, active_lobes
from torchbrdf.kernels import build
from torchbrdf.kernels.codegen_normal_eq import CAMERA, NormalEqSpec, generate, generate_triton, width

__all__ = ["normal_equations", "normal_equations_op", "data_cost", "data_cost_op", "make_cfg", "unpack_jtj",
           "tangent_pattern"]

#: The per-pixel inputs in kernel order (those present).
TENSOR_ORDER = ("pos", "n", "base_color") + SCALAR_PARAMS

_lock = threading.Lock()
_kernels: dict = {}
_failed: set = set()


def make_cfg(tensor_names: Sequence[str], float_names: Sequence[str], active: Sequence[str], need_tint: bool,
             K: int, pattern: Sequence[Sequence[tuple[int, ...]]], backend: str = "c",
             residuals: bool = False, cost_only: bool = False, family: str = "principled") -> str:
    """The ``cfg`` string of the operators; ``pattern[k]``: input ``k``'s non-zero ``(direction,
    channel[, slot])`` tangents (:class:`~.codegen_normal_eq.NormalEqSpec`); ``backend`` ``"c"``
    or ``"triton"``; ``residuals``: the rows hold the residuals too; ``cost_only``: the
    cost-only variant (``K`` 0, no pattern); ``family``: the residual's BRDF (a tenth field
    when not ``"principled"``)."""
    pat = ";".join(",".join(".".join(str(int(x)) for x in e) for e in p) for p in pattern)
    return "|".join([",".join(tensor_names), ",".join(float_names), ",".join(active), str(int(need_tint)),
                     str(int(K)), pat, backend, str(int(residuals)), str(int(cost_only))]
                    + ([family] if family != "principled" else []))


def _parse(cfg: str, dtype: torch.dtype) -> tuple[NormalEqSpec, str]:
    tn, fn, act, tint, K, pat, backend, res, cost_only, *family = cfg.split("|")
    names = tn.split(",") if tn else []
    C = [3 if k in ("pos", "n", "base_color") else 1 for k in names]
    pattern = [[tuple(int(x) for x in e.split(".")) for e in p.split(",") if e] for p in pat.split(";")]
    pattern += [[] for _ in range(len(names) - len(pattern))]
    ctype = "float" if dtype == torch.float32 else "double"
    spec = NormalEqSpec(ctype, list(zip(names, C)), fn.split(",") if fn else [],
                        act.split(",") if act else [], tint == "1", int(K), pattern, res == "1", cost_only == "1",
                        family[0] if family else "principled")
    return spec, backend


def _cached(key: tuple, make: Callable[[], Any]) -> Any:
    """The kernel under ``key``, made once by ``make()`` (None: it cannot be made; not retried)."""
    hit = _kernels.get(key)
    if hit is not None or key in _failed:
        return hit
    with _lock:
        hit = _kernels.get(key)
        if hit is not None or key in _failed:
            return hit
        hit = make()
        if hit is None:
            _failed.add(key)
        else:
            _kernels[key] = hit
        return hit


def _c_kernel(spec: NormalEqSpec):
    def make():
        args = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
        lib = build.load_kernel(generate(spec), "normal_eq", {"tb_ne": (args, None)})
        return None if lib is None else (lib, lib.tb_ne)  # the library stays alive with its function

    return _cached(("c", spec.key()), make)


def _triton_kernel(spec: NormalEqSpec, wide: bool):
    from torchbrdf.kernels import codegen_triton

    def make():
        try:
            if not codegen_triton.available():
                raise ImportError("triton does not import")
            return codegen_triton.compile_source(generate_triton(spec, wide), "tb_ne")
        except Exception as e:  # noqa: BLE001 - any failure: evaluated eagerly
            msg = f"torchbrdf: building the Triton normal-equations kernel failed; using eager.\n{e!r}"
            warnings.warn(msg[:2000], RuntimeWarning, stacklevel=4)
            return None

    return _cached(("triton", spec.key(), wide, codegen_triton.interpret_mode()), make)


def _eager(spec: NormalEqSpec, tensors, tangents, floats, uniforms, log_obs) -> Tensor:
    """The same sums from the formula on torch tensors (the fallback): one ``jvp`` per direction
    (non-finite entries as the kernel takes them, :mod:`.codegen_normal_eq`)."""
    N, L = log_obs.shape[0], log_obs.shape[1]
    ops = formula.TorchOps(log_obs.dtype, log_obs.device)
    names = [k for k, _ in spec.tensors]
    K = spec.K

    def res(*ts):
        c: dict[str, Any] = dict(zip(spec.floats, floats[:-1]))
        c.update({k: t[:, None] for k, t in zip(names, ts)})
        c.setdefault("x", None)
        c.setdefault("y", None)
        c.update({"camera": uniforms[:CAMERA], "light_pos": uniforms[CAMERA:].reshape(L, 6)[None, :, :3],
                  "light_int": uniforms[CAMERA:].reshape(L, 6)[None, :, 3:], "log_obs": log_obs,
                  "eps": floats[-1]})
        return formula.capture_log_residual(ops, c, spec.active, spec.need_tint, False, spec.family).reshape(N, -1)

    tan_of = dict(zip(spec.tan_inputs, tangents))
    r = res(*tensors)
    if spec.cost_only:
        inf = float("inf")
        return torch.nan_to_num((r * r).sum(-1, keepdim=True), nan=inf, posinf=inf)
    J = []
    for a in range(K):
        dirs = []
        for k, t in enumerate(tensors):
            d = torch.zeros_like(t)
            for j, c, slot in spec.pattern[k]:
                if j == a:
                    d[:, c] = tan_of[k][slot][:, c]
            dirs.append(d)
        J.append(torch.func.jvp(res, tuple(tensors), tuple(dirs))[1])
    Jm = torch.stack(J, -1).nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)  # (N, M, K)
    rf = r.nan_to_num(nan=0.0, posinf=0.0, neginf=0.0)
    iu = torch.triu_indices(K, K, device=log_obs.device)
    jtj = torch.einsum("nma,nmb->nab", Jm, Jm)[:, iu[0], iu[1]]
    out = [(r * r).sum(-1, keepdim=True), jtj, torch.einsum("nma,nm->na", Jm, rf)]
    return torch.cat(out + [r] if spec.residuals else out, -1)


def _check_operands(op: str, spec: NormalEqSpec, tensors, tangents, uniforms, log_obs) -> None:
    """Raise ValueError unless the operands have the layout the kernels index without bounds checks.

    The kernels read ``(N, C)`` rows of each input, ``(S, N, C)`` tangents, ``3 + 6 L`` uniforms
    and write ``log_obs``'s dtype as float or double: another layout would read or write
    outside the tensors' memory, so it is refused here, for direct operator calls too.
    """
    if log_obs.dtype not in (torch.float32, torch.float64) or log_obs.dim() != 3 or log_obs.shape[-1] != 3:
        raise ValueError(f"{op}: log_obs must be (N, L, 3) float32 or float64, got {tuple(log_obs.shape)} "
                         f"{log_obs.dtype}")
    N, L = log_obs.shape[0], log_obs.shape[1]
    dtype, dev = log_obs.dtype, log_obs.device

    def check(what: str, t: Tensor, shape: tuple) -> None:
        if t.dtype != dtype or t.device != dev or tuple(t.shape) != shape:
            raise ValueError(f"{op}: {what} must be {shape} {dtype} on {dev}, got {tuple(t.shape)} {t.dtype} "
                             f"on {t.device}")

    check("uniforms (camera, then each light's position and intensity)", uniforms, (3 + 6 * L,))
    if len(tensors) != len(spec.tensors) or len(tangents) != len(spec.tan_inputs):
        raise ValueError(f"{op}: cfg names {len(spec.tensors)} tensors with {len(spec.tan_inputs)} tangents, "
                         f"got {len(tensors)} and {len(tangents)}")
    for (name, C), t in zip(spec.tensors, tensors):
        check(f"tensor {name!r}", t, (N, C))
    for k, t in zip(spec.tan_inputs, tangents):
        name, C = spec.tensors[k]
        rows = max(e[2] for e in spec.pattern[k]) + 1  # the slots cfg's pattern reads
        check(f"the tangents of {name!r}", t, (max(rows, t.shape[0] if t.dim() else 0), N, C))


def _run(spec: NormalEqSpec, backend: str, tensors, tangents, floats, uniforms, log_obs) -> Tensor:
    N, L = log_obs.shape[0], log_obs.shape[1]
    W = width(spec.K) + (3 * L if spec.residuals else 0)
    dtype, dev = log_obs.dtype, log_obs.device
    if N == 0:
        return torch.zeros(N, W, dtype=dtype, device=dev)
    tensors = [t.contiguous() for t in tensors]
    tangents = [t.contiguous() for t in tangents]
    log_obs, uniforms = log_obs.contiguous(), uniforms.contiguous()
    out = torch.empty(N, W, dtype=dtype, device=dev)
    if backend == "triton":
        from torchbrdf.kernels import codegen_triton

        wide = N * max(W, 3 * L, 3 * spec.K) >= 2**31
        kernel = _triton_kernel(spec, wide)
        if kernel is not None:
            P = torch.tensor(list(floats) + [0.0], dtype=torch.float64, device=dev)
            codegen_triton.launch(kernel, "fwd", N, P, [uniforms, *tensors, *tangents, log_obs, out, L])
            return out
    else:
        hit = _c_kernel(spec)
        if hit is not None:
            ptrs = [t.data_ptr() for t in (*tensors, *tangents, log_obs, uniforms)]
            params = list(floats) + [float(L)]
            hit[1](N, (ctypes.c_void_p * len(ptrs))(*ptrs), (ctypes.c_double * len(params))(*params),
                   out.data_ptr(), torch.get_num_threads())
            return out
    with torch.no_grad():
        return _eager(spec, tensors, tangents, floats, uniforms, log_obs)


@torch.library.custom_op("torchbrdf::normal_equations", mutates_args=())
def normal_equations_op(tensors: list[Tensor], tangents: list[Tensor], floats: list[float], uniforms: Tensor,
                        log_obs: Tensor, cfg: str) -> Tensor:
    """Per pixel ``[cost, JᵀJ upper triangle, Jᵀr]`` ``(N, W)`` (see the module docstring).

    ``tensors``: the per-pixel inputs ``(N, C)`` named in ``cfg``; ``tangents``: ``(K, N, C)``
    per input with a tangent; ``floats``: the material floats then ``eps``; ``uniforms``
    ``(3 + 6 L,)``: camera, then position and intensity per light; ``log_obs`` ``(N, L, 3)``.
    With the residuals (``cfg``), ``(N, W + 3 L)``.
    """
    spec, backend = _parse(cfg, log_obs.dtype)
    _check_operands("normal_equations_op", spec, tensors, tangents, uniforms, log_obs)
    return _run(spec, backend, tensors, tangents, floats, uniforms, log_obs)


@normal_equations_op.register_fake
def _(tensors, tangents, floats, uniforms, log_obs, cfg):
    fields = cfg.split("|")
    extra = 3 * log_obs.shape[1] if fields[7] == "1" else 0
    return log_obs.new_empty((log_obs.shape[0], width(int(fields[4])) + extra))


def tangent_pattern(tangents: Mapping[str, Tensor]) -> dict[str, list[tuple[int, ...]]]:
    """The ``(direction, channel)`` pairs of each ``(K, N, C)`` tangent that are not zero at
    every pixel (one reduction and a host read: pass a known pattern to avoid it)."""
    out: dict[str, list[tuple[int, ...]]] = {}
    for k, t in tangents.items():
        nz = (t != 0).any(dim=1).cpu()  # (K, C)
        out[k] = [(int(j), int(c)) for j, c in nz.nonzero().tolist()]
    return out


@overload
def normal_equations(params: Mapping[str, Any], tangents: Mapping[str, Tensor], points: Tensor,
                     camera: Tensor, light_pos: Tensor, light_int: Tensor, log_obs: Tensor, eps: float,
                     pattern: Mapping[str, Sequence[tuple[int, ...]]] | None = None,
                     unknowns: int | None = None, residuals: Literal[False] = False,
                     family: str = "principled") -> tuple[Tensor, Tensor, Tensor]:
    ...


@overload
def normal_equations(params: Mapping[str, Any], tangents: Mapping[str, Tensor], points: Tensor,
                     camera: Tensor, light_pos: Tensor, light_int: Tensor, log_obs: Tensor, eps: float,
                     pattern: Mapping[str, Sequence[tuple[int, ...]]] | None = None,
                     unknowns: int | None = None, *, residuals: Literal[True], family: str = "principled"
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    ...


def normal_equations(params: Mapping[str, Any], tangents: Mapping[str, Tensor], points: Tensor,
                     camera: Tensor, light_pos: Tensor, light_int: Tensor, log_obs: Tensor, eps: float,
                     pattern: Mapping[str, Sequence[tuple[int, ...]]] | None = None,
                     unknowns: int | None = None, residuals: bool = False,
                     family: str = "principled") -> tuple[Tensor, ...]:
    """Per-pixel Gauss–Newton terms of the capture's log residuals, in one fused pass.

    The residuals are :func:`torchbrdf.capture.synthetic.log_residual_points`'s
    (``log(max(L + ε, ε/2)) − log_obs`` over every light and channel, ``M = 3 L`` rows per
    pixel), their Jacobian ``J (N, M, K)`` is along ``K`` directions of the unknowns.

    Args:
        params: the decoded maps: ``normal (N, 3)``, ``base_color (N, 3)`` and scalar
            principled parameters ``(N, 1)`` (tensors, or Python floats held fixed); the others
            keep their defaults.
        tangents: ``{name: (K, N, C)}``: each direction's tangent of an entry of ``params``
            (``∂p/∂x_j``, e.g. from ``torch.func.jvp`` of the decode); absent entries are held.
            With slots in ``pattern``, ``(S, N, C)``: row ``slot`` holds the tangents of the
            directions mapped to it (directions moving disjoint channels share a row).
        points ``(N, 3)``, camera ``(3,)``, light_pos, light_int ``(L, 3)``, log_obs
        ``(N, L, 3)``, eps: as for ``log_residual_points``; one floating dtype and device.
        pattern: ``{name: [(direction, channel[, slot]), ...]}``, the tangents' non-zero
            entries (default :func:`tangent_pattern`, which reads the tangents; a known pattern
            keeps the call free of host synchronisation).
        unknowns: ``K`` (default: the tangents' leading size; needed with slots).
        residuals: also return the residuals.
        family: the residual's BRDF, ``"principled"`` or ``"svbrdf_ggx"`` (the recovery's GGX
            model on the same maps, :func:`torchbrdf.brdf.formula.ggx_albedos`).

    Returns:
        ``(cost (N,), jtj (N, K (K + 1) / 2), jtr (N, K))``: ``Σ r²``, the upper triangle of
        ``JᵀJ`` row by row (:func:`unpack_jtj`) and ``Jᵀr``, in ``log_obs``'s dtype and device;
        with ``residuals``, then ``r (N, 3 L)`` (light-major, a view of the kernel's rows).
        ``JᵀJ`` and ``Jᵀr`` count a non-finite Jacobian entry or residual as 0; the cost and
        the residuals are as they come.
    """
    unknown = set(tangents) - set(params)
    if unknown:
        raise ValueError(f"normal_equations: tangents for {sorted(unknown)}, which params does not hold")
    Ks = {t.shape[0] for t in tangents.values()}
    if unknowns is None and len(Ks) != 1:
        raise ValueError(f"normal_equations: every tangent needs the same number of directions, got "
                         f"{sorted(Ks)}")
    K = int(unknowns) if unknowns is not None else Ks.pop()
    names, tensors, floats, uniforms, head = _operator_inputs("normal_equations", params, points, camera,
                                                              light_pos, light_int, log_obs, eps)
    tan = {("n" if k == "normal" else k): v for k, v in tangents.items()}
    if pattern is None:
        pattern = tangent_pattern(tangents)
    pat_by = {("n" if k == "normal" else k): v for k, v in pattern.items()}
    pats = [sorted(pat_by.get(k, [])) if k in tan else [] for k in names]
    tans = [tan[k].to(log_obs.dtype) for k, p in zip(names, pats) if p]
    cfg = make_cfg(*head, K, pats, _backend(log_obs), residuals, family=family)
    out = normal_equations_op(tensors, tans, floats, uniforms, log_obs, cfg)
    nt = K * (K + 1) // 2
    sums = (out[:, 0], out[:, 1:1 + nt], out[:, 1 + nt:1 + nt + K])
    return (*sums, out[:, width(K):]) if residuals else sums


@torch.library.custom_op("torchbrdf::data_cost", mutates_args=())
def data_cost_op(tensors: list[Tensor], floats: list[float], uniforms: Tensor, log_obs: Tensor,
                 cfg: str) -> Tensor:
    """Per pixel ``Σ r²`` over every light and channel ``(N, 1)``, non-finite as +inf.

    The arguments as for :func:`normal_equations_op` without tangents; ``cfg`` a cost-only
    one (:func:`make_cfg` with ``cost_only``). The C and Triton kernels sum in float64; the
    eager fallback in ``log_obs``'s dtype.
    """
    spec, backend = _parse(cfg, log_obs.dtype)
    if not spec.cost_only:
        raise ValueError("data_cost_op: cfg is not a cost-only configuration (make_cfg(..., cost_only=True))")
    _check_operands("data_cost_op", spec, tensors, [], uniforms, log_obs)
    return _run(spec, backend, tensors, [], floats, uniforms, log_obs)


@data_cost_op.register_fake
def _(tensors, floats, uniforms, log_obs, cfg):
    return log_obs.new_empty((log_obs.shape[0], 1))


def data_cost(params: Mapping[str, Any], points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor,
              log_obs: Tensor, eps: float, family: str = "principled") -> Tensor:
    """Each pixel's data cost ``Σ r²`` over every light and channel of the capture's log residuals, in one fused pass.

    The residuals are :func:`torchbrdf.capture.synthetic.log_residual_points`'s; the
    arguments as for :func:`normal_equations` (no tangents; ``family`` too). Returns ``(N, 1)`` in
    ``log_obs``'s dtype, on its device: the squares summed in float64 in the kernels (so
    float32 sums round less than ``(r * r).sum(-1)``), a non-finite sum as +inf — as
    ``torch.nan_to_num((r * r).sum(-1, keepdim=True), nan=inf, posinf=inf)`` of the residuals,
    without writing them.
    """
    names, tensors, floats, uniforms, head = _operator_inputs("data_cost", params, points, camera, light_pos,
                                                              light_int, log_obs, eps)
    cfg = make_cfg(*head, 0, [], _backend(log_obs), cost_only=True, family=family)
    return data_cost_op(tensors, floats, uniforms, log_obs, cfg)


def _operator_inputs(caller: str, params: Mapping[str, Any], points: Tensor, camera: Tensor, light_pos: Tensor,
                     light_int: Tensor, log_obs: Tensor, eps: float
                     ) -> tuple[list[str], list[Tensor], list[float], Tensor, tuple[list[str], list[str], list[str], bool]]:
    """Checked operator inputs: ``(tensor names, tensors, floats, uniforms, (tensor names, float
    names, active lobes, need_tint))`` (the last :func:`make_cfg`'s leading arguments)."""
    if log_obs.dim() != 3 or log_obs.shape[-1] != 3:
        raise ValueError(f"{caller}: log_obs must be (N, L, 3), got {tuple(log_obs.shape)}")
    if log_obs.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{caller}: log_obs must be float32 or float64 (the kernels' types), "
                         f"got {log_obs.dtype}")
    L = log_obs.shape[1]
    for name, t, shape in (("light_pos", light_pos, (L, 3)), ("light_int", light_int, (L, 3))):
        if tuple(t.shape) != shape:
            raise ValueError(f"{caller}: {name} must be {shape} (log_obs has {L} lights), "
                             f"got {tuple(t.shape)}")
    if params.get("anisotropic", 0.0) != 0.0 or "specular_tint" in params or "sheen_tint" in params:
        raise ValueError(f"{caller}: anisotropic, specular_tint and sheen_tint must keep their defaults")
    N = log_obs.shape[0]
    dtype, dev = log_obs.dtype, log_obs.device
    c = {"pos": points, "n": params["normal"], **{k: v for k, v in params.items() if k != "normal"}}
    mat = {**PRINCIPLED_DEFAULTS, **{k: v for k, v in c.items() if k in SCALAR_PARAMS}}
    active = active_lobes(mat)
    for k, v in c.items():
        shape = (N, 3 if k in ("pos", "n", "base_color") else 1)
        if isinstance(v, Tensor) and (v.dtype != dtype or v.device != dev or tuple(v.shape) != shape):
            raise ValueError(f"{caller}: {k!r} must be {shape} {dtype} on {dev}, got "
                             f"{tuple(v.shape)} {v.dtype} on {v.device}")
    names = [k for k in TENSOR_ORDER if isinstance(c.get(k), Tensor)]
    float_names = [k for k in SCALAR_PARAMS if k not in names]
    floats = [float(mat[k]) for k in float_names] + [float(eps)]
    uniforms = torch.cat((camera.reshape(3), torch.cat((light_pos, light_int), -1).reshape(-1))).to(dtype)
    # (specular_tint is 0: the tint is needed only by a tinted sheen, sheen_tint's default being 0.5)
    return names, [c[k] for k in names], floats, uniforms, (names, float_names, list(active), "sheen" in active)


def _backend(log_obs: Tensor) -> str:
    return "c" if log_obs.device.type == "cpu" and not _interpreted() else "triton"


def _interpreted() -> bool:
    from torchbrdf.kernels import backend

    return backend.resolve(torch.device("cpu")) == "triton"


def unpack_jtj(packed: Tensor, K: int) -> Tensor:
    """The symmetric ``(N, K, K)`` matrices of packed upper triangles ``(N, K (K + 1) / 2)``.

    One gather of each entry's triangle position (a sixth of the time of two scatters into a
    zeroed buffer at 16k pixels); ``packed``'s dtype and device.
    """
    iu = torch.triu_indices(K, K)
    at = torch.empty(K, K, dtype=torch.long)
    at[iu[0], iu[1]] = at[iu[1], iu[0]] = torch.arange(iu.shape[1])
    return packed.index_select(1, at.reshape(-1).to(packed.device)).reshape(-1, K, K)
