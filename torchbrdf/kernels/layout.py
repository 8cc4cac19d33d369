"""Memory layout of one fused-kernel call: configuration, lanes, input modes, gradient shapes.

:class:`KernelConfig` is a kernel family's structure (the operators carry it encoded as their
``cfg`` string); :class:`Plan` is one call's layout from it and the tensors' shapes;
:func:`flatten` views each input as lanes (``'full'``, a broadcast ``'b1'``/``'b0'``, or the
two-level ``'s2'``). Shared by the C and Triton runners (:mod:`.c_runner`,
:mod:`.triton_runner`) and by the fused shader's operator (:mod:`.shade_ops`).
"""

from __future__ import annotations

import ctypes
import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchbrdf._checks import broadcast_shapes
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels import graphs
from torchbrdf.kernels.fused import KernelSpec

__all__ = ["KernelConfig", "Plan", "flatten", "merges", "ptrs", "dparams", "formula_eager", "written_inputs",
           "grad_mode", "to_shape", "grad_out_lanes", "directions_per_tangent", "nonzero_tangents", "SCALAR_NAMES",
           "ONE_CHANNEL"]

#: The principled scalar parameters, in the kernels' slot order.
SCALAR_NAMES = SCALAR_PARAMS


def merges(t: Tensor, dims: int) -> bool:
    """Whether ``t``'s first ``dims`` dimensions merge into one without a copy (``view`` works).

    They do when each one that is not 1 long steps over the next such one whole. Asked
    instead of trying ``view``: a failed view raises, and a recovery asks thousands of times,
    so building those errors would cost more than the question.
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


def flatten(t: Tensor, C: int, batch: tuple, N: int, s2: bool = False) -> tuple[Tensor, str]:
    """View ``t`` as ``(N, C)`` lanes: mode 'full' (lane-dense), 'b1'/'b0' (same for all lanes).

    With ``s2`` (kernels that support it), a value broadcast over one of two batch dims — a
    per-pixel value under every light, or a per-light value at every pixel — is not copied
    out to all lanes: mode 's2' returns the ``(N / B, B, C)`` strided view (``B = batch[-1]``),
    and lane ``(q, r)`` reads row ``q·sA + r·sB`` (:meth:`Plan.params` passes the strides).
    """
    e = t.expand(*batch, C) if t.dim() > 0 else t.reshape(1).expand(*batch, C)
    f = e.view(N, C) if merges(e, len(batch)) else None
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
        return flatten(t.contiguous(), C, batch, N, s2)
    if s2 and len(batch) >= 2 and batch[-1] > 1 and N > batch[-1] and (C == 1 or e.stride(-1) == 1) \
            and merges(e, len(batch) - 1):  # (else the leading batch dims do not collapse: copy)
        return e.view(N // batch[-1], batch[-1], C), "s2"
    return (f if f is not None else e).reshape(N, C).contiguous(), "full"


@dataclass(frozen=True)
class KernelConfig:
    """The structure of one kernel family's call: what the operators' ``cfg`` string encodes.

    ``tensor_names``: the tensor inputs in slot order; ``float_names``: the runtime Python
    floats; ``active``: the lobes; ``need_tint``/``frame``: the tint and tangent-frame terms;
    ``backend``: ``"c"`` (CPU kernels) or ``"triton"``; ``family``: the formula
    (:data:`torchbrdf.brdf.formula.FAMILIES`). The custom operators take it as a string
    (:meth:`encode`; their schema has no structured types), decoded once per distinct string.
    """

    tensor_names: tuple[str, ...]
    float_names: tuple[str, ...]
    active: tuple[str, ...]
    need_tint: bool
    frame: bool
    backend: str = "c"
    family: str = "principled"

    def encode(self) -> str:
        """The operators' ``cfg`` string."""
        parts = [",".join(self.tensor_names), ",".join(self.float_names), ",".join(self.active),
                 str(int(self.need_tint)), str(int(self.frame)), self.backend]
        return "|".join(parts + ([self.family] if self.family != "principled" else []))

    @staticmethod
    @functools.lru_cache(maxsize=1024)
    def decode(cfg: str) -> KernelConfig:
        """The configuration of an operator's ``cfg`` string."""
        tn, fn, act, tint, frame, backend, *rest = cfg.split("|")
        return KernelConfig(tuple(tn.split(",")) if tn else (), tuple(fn.split(",")) if fn else (),
                            tuple(act.split(",")) if act else (), tint == "1", frame == "1", backend,
                            rest[0] if rest else "principled")


#: Channels of each tensor input that is not a scalar principled parameter (all others: 3).
ONE_CHANNEL = frozenset(SCALAR_PARAMS)


class Plan:
    """One call's layout, from its :class:`KernelConfig` and the tensors' shapes."""

    def __init__(self, config: KernelConfig, tensors: Sequence[Tensor], floats: Sequence[float]) -> None:
        self.config = config
        self.backend = config.backend  # which kernels: "c" or "triton"
        self.family = config.family  # which formula
        self.tensor_names = list(config.tensor_names)
        self.float_names = list(config.float_names)
        self.active = config.active
        self.need_tint, self.frame = config.need_tint, config.frame
        self.C = [1 if k in ONE_CHANNEL else 3 for k in self.tensor_names]
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

    def params(self, *flats: Iterable[tuple[Tensor, str]]) -> list[float]:
        """The kernel's runtime parameter row.

        The Python floats, then, when some input of ``flats`` (iterables of ``(flat, mode)``, in
        the kernel's slot order) is 's2', the inner batch size and each such input's two lane
        strides (see :func:`flatten`).
        """
        s2 = [f for fl in flats for f, m in fl if m == "s2"]
        if not s2:
            return self.floats
        return self.floats + [float(self.batch[-1])] + [float(x) for f in s2 for x in f.stride()[:2]]

    def flat(self, tensors: Sequence[Tensor], s2: bool = False
             ) -> tuple[list[Tensor], tuple[tuple[str, str, int], ...]]:
        """Each input as lanes (:func:`flatten`) and its ``(name, mode, channels)``."""
        out = [flatten(t, C, self.batch, self.N, s2) for t, C in zip(tensors, self.C)]
        modes = tuple((k, m, C) for k, (_, m), C in zip(self.tensor_names, out, self.C))
        return [f for f, _ in out], modes

    def spec(self, modes: tuple[tuple[str, str, int], ...], **kw: Any) -> KernelSpec:
        """The kernel spec of this call with input ``modes`` (and the spec's other fields ``kw``)."""
        ctype = "float" if self.dtype == torch.float32 else "double"
        kw["family"] = self.family
        return KernelSpec(ctype, modes, self.float_names, self.active, self.need_tint, self.frame, **kw)


def ptrs(ptrs: Sequence[int | None]) -> ctypes.Array:
    """A C ``void *[]`` of the addresses (at least one slot)."""
    return (ctypes.c_void_p * max(1, len(ptrs)))(*ptrs)


def dparams(vals: Sequence[float]) -> ctypes.Array:
    """A C ``double[]`` of the runtime parameters (at least one slot)."""
    return (ctypes.c_double * max(1, len(vals)))(*vals)


def formula_eager(plan: Plan, tensors: Sequence[Tensor], floats: Sequence[float]) -> Tensor:
    """The shared formula on torch tensors (the eager path), for fallbacks and double backward."""
    from torchbrdf.brdf import formula

    c: dict[str, Any] = dict(zip(plan.float_names, floats))
    c.update(zip(plan.tensor_names, tensors))
    c.setdefault("x", None)
    c.setdefault("y", None)
    ops = formula.TorchOps(plan.dtype, tensors[0].device)
    return formula.FAMILIES[plan.family](ops, c, plan.active, plan.need_tint, plan.frame)


@functools.lru_cache(maxsize=None)
def written_inputs(spec_args: tuple, family: str = "principled") -> tuple:
    """Inputs (indices) whose gradient the backward kernel writes (those with a path to the output)."""
    ctype, tensors, floats, active, tint, frame, go_strides, grad_mask = spec_args
    spec = KernelSpec(ctype, tensors, floats, active, tint, frame, go_strides, grad_mask, family=family)
    return graphs.build(spec, "bwd").written


def grad_mode(t: Tensor, C: int, N: int) -> str:
    """How an input's gradient is formed: ``'red'`` or ``'full'``.

    ``'red'``: the input is one value for all lanes, its gradient is the sum over the lanes
    (reduced chunk by chunk); ``'full'``: a lane-dense gradient, then summed to the input's
    shape (an input that is an expanded view of one value still needs its per-lane gradient).
    """
    lanes = math.prod(t.shape[:-1]) if t.dim() > 0 else 1
    return "red" if lanes == 1 and N > 1 else "full"


def to_shape(g: Tensor, t: Tensor) -> Tensor:
    """Sum a gradient ``(*batch, C)`` or ``(C,)`` (summed over lanes) down to ``t``'s shape."""
    if t.dim() == 0:
        return g.sum().reshape(())
    if g.dim() == 1:
        g = g.reshape((1,) * (t.dim() - 1) + (g.shape[0],))
    return g.sum_to_size(t.shape) if tuple(g.shape) != tuple(t.shape) else g


def grad_out_lanes(plan: Plan, grad_out: Tensor) -> tuple[Tensor, tuple[int, int]]:
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


def directions_per_tangent(tangents: list[Tensor], ntan: int, K: int) -> list[list[bool]]:
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


def nonzero_tangents(tangents: list[Tensor], tidx: list[int], ntan: int
                     ) -> tuple[list[int], list[Tensor], list[list[bool]]]:
    """The JVP's tangents without those that are zero in every direction.

    Returns the kept ``(tidx, tangents)`` and ``nz[j][k]`` (:func:`directions_per_tangent`) for them.
    """
    nz = directions_per_tangent(tangents, ntan, max(1, ntan))  # (K, T)
    used = [k for k in range(len(tangents)) if any(row[k] for row in nz)]
    return [tidx[k] for k in used], [tangents[k] for k in used], [[row[k] for k in used] for row in nz]
