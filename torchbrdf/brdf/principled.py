"""The Disney principled BRDF (Burley 2012, with the 2014 addendum).

Exactly the published model: Burley's diffuse with retro-reflection, the
Hanrahan–Krueger-like subsurface blend, an anisotropic GGX primary lobe with the
un-remapped anisotropic Smith G of the 2014 addendum, Schlick Fresnel toward a tinted or
metallic F0, a Schlick-shaped sheen, and a GTR1 clearcoat with its fixed α = 0.25 Smith G.

Numerics (each pinned by ``tests/brdf/test_principled.py`` and ``tests/brdf/test_hard_cases.py``):

* ``f = 0`` exactly, with zero gradients, where ``n·l <= 0`` or ``n·v <= 0``: the math runs
  on cosines clamped to ``COS_EPS`` so the masked lanes stay finite, then is masked.
* ``1 - (n·h)²`` is computed as ``|n × h|²`` (no cancellation at narrow peaks); the
  anisotropic GGX form ``(h·x/αx)² + (h·y/αy)² + (h·n)²`` has none to begin with.
* ``1 - 0.9 anisotropic`` is floored at 0.1 (anisotropic > 1 behaves as 1) and the clearcoat
  α at 0.001 (clearcoat_gloss > 1 behaves as 1), so pushing parameters past [0, 1] never
  produces NaN.
* float16 / bfloat16 inputs are evaluated in float32 and the result saturates at the dtype's
  largest finite value (a roughness-0 mirror peak reaches ~3e5, beyond float16's 65504).
* Input vectors are used as given (not renormalised): pass unit vectors.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Callable, Iterator
import numbers
import os
from collections.abc import Iterable

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, cast_in, compute_dtype
from torchbrdf._types import Color, Scalar
from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import ASPECT2_MIN, COS_EPS, INV_PI  # noqa: F401  (re-exported constants)
from torchbrdf.brdf.formula import LOBES, PRINCIPLED_DEFAULTS, SCALAR_PARAMS  # noqa: F401  (defined with the formula)
from torchbrdf.brdf.formula import active_lobes, is_const
from torchbrdf.brdf.frames import frame_from_normal

__all__ = ["principled", "PrincipledBRDF", "PRINCIPLED_DEFAULTS", "LOBES", "set_fast_path", "fast_path_enabled",
           "FAST_PATH_MIN_LANES", "fused_at_every_size"]



def _prepare(l, v, n, x, y, params, base_color):
    """Check arguments and cast everything to the compute dtype. Returns the cast values."""
    for name, t in (("l", l), ("v", v), ("n", n)):
        _checks.check_tensor(name, t, last=3)
    if x is not None:
        _checks.check_tensor("x", x, last=3)
    if y is not None:
        _checks.check_tensor("y", y, last=3)
    _checks.check_tensor("base_color", base_color, last=3, allow_scalar=True)
    if isinstance(base_color, Tensor) and base_color.dim() > 0 and base_color.shape[-1] != 3:
        raise ValueError(f"base_color: expected shape (..., 3), got {tuple(base_color.shape)}")
    for k, p in params.items():
        _checks.check_tensor(k, p, last=1, allow_scalar=True)
    named = {"l": l, "v": v, "n": n, "x": x, "y": y, "base_color": base_color, **params}
    dtype, device = _checks.check_same_dtype_device(named)
    _checks.check_broadcast(named)
    if _checks.validation_enabled():
        _checks.check_finite(named)
    cd = compute_dtype(dtype)
    cast = {k: cast_in(t, cd) for k, t in named.items()}
    return dtype, cast


def principled(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    base_color: Color,
    metallic: Scalar = 0.0,
    subsurface: Scalar = 0.0,
    specular: Scalar = 0.5,
    roughness: Scalar = 0.5,
    specular_tint: Scalar = 0.0,
    anisotropic: Scalar = 0.0,
    sheen: Scalar = 0.0,
    sheen_tint: Scalar = 0.5,
    clearcoat: Scalar = 0.0,
    clearcoat_gloss: Scalar = 1.0,
    lobes: Iterable[str] | None = None,
) -> Tensor:
    """Evaluate the Disney principled BRDF ``f(l, v)`` (without the ``n·l`` cosine).

    Args:
        l: unit direction toward the light, ``(*, 3)``.
        v: unit direction toward the viewer, ``(*, 3)``.
        n: unit shading normal, ``(*, 3)``.
        x: unit tangent ``(*, 3)``; needed only when ``anisotropic`` is non-zero. When
            omitted, a frame is built from ``n`` (Duff et al. 2017) if anisotropy is a tensor.
        y: unit bitangent ``(*, 3)``; defaults to ``n × x``.
        base_color: linear RGB ``(*, 3)`` (or a float for grey).
        metallic, subsurface, specular, roughness, specular_tint, anisotropic, sheen,
            sheen_tint, clearcoat, clearcoat_gloss: ``(*, 1)`` tensors or floats,
            nominally in ``[0, 1]``; values beyond are allowed (Burley's principle 4).
        lobes: optional subset of :data:`LOBES` to evaluate; by default every lobe whose
            weight is not a Python 0 (skipping those changes nothing).

    Returns:
        ``(*, 3)`` BRDF values in the inputs' dtype and on their device; exactly 0 (with
        zero gradient) where ``n·l <= 0`` or ``n·v <= 0``.

    Reference:
        Burley, "Physically Based Shading at Disney", 2012 (appendix B, eq. 13; 2014
        addendum for the un-remapped anisotropic Smith G).

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> principled(n, n, n, base_color=torch.tensor([[0.5, 0.5, 0.5]])).shape
        torch.Size([1, 3])
    """
    params = {
        "metallic": metallic,
        "subsurface": subsurface,
        "specular": specular,
        "roughness": roughness,
        "specular_tint": specular_tint,
        "anisotropic": anisotropic,
        "sheen": sheen,
        "sheen_tint": sheen_tint,
        "clearcoat": clearcoat,
        "clearcoat_gloss": clearcoat_gloss,
    }
    if x is None and y is None and isinstance(anisotropic, numbers.Real) and anisotropic != 0:
        raise ValueError(f"anisotropic={anisotropic} needs a tangent frame: pass x (and optionally y)")
    dtype, c = _prepare(l, v, n, x, y, params, base_color)
    active = active_lobes(params, lobes)
    backend = fast_backend(c)
    f = _principled_fast_or_none(c, active, backend) if backend is not None else None
    if f is None:
        f = principled_eager(c, active)
    return cast_back(f, dtype)


# ---------------------------------------------------------------------------------------------
# Dispatch between the eager path and the fused kernels (torchbrdf/kernels/, same formula).
# ---------------------------------------------------------------------------------------------

#: Lanes (broadcast batch size) from which ``principled`` uses the fused kernels by default.
#: Below it the eager path is kept: a call is then cheap anyway and the first use of a new
#: kernel family costs a one-off compile (~1-3 s, cached on disk afterwards).
FAST_PATH_MIN_LANES = 8192

_fast_mode: dict = {"enabled": None}


def set_fast_path(enabled: bool | None) -> None:
    """Choose how :func:`principled` (and :func:`torchbrdf.svbrdf_ggx`) evaluates.

    Args:
        enabled: ``True`` uses the fused kernels (of the backend in force, see
            :func:`torchbrdf.set_backend`) for every batch size where they apply; ``False``
            always uses the eager reference path, whatever the backend; ``None`` (default)
            decides automatically (fused from :data:`FAST_PATH_MIN_LANES` lanes in the
            ``"auto"`` backend, at any size for an explicitly named one; float32/float64;
            ``TORCHBRDF_EAGER`` not set to ``1``).

    :func:`torchbrdf.set_backend` chooses *which* fused kernels (C on CPU, Triton on CUDA);
    this switch chooses *whether* they are used.
    """
    if enabled not in (True, False, None):
        raise ValueError(f"enabled: expected True, False or None, got {enabled!r}")
    _fast_mode["enabled"] = enabled


def fast_path_enabled() -> bool | None:
    """The current :func:`set_fast_path` setting (``None`` = automatic)."""
    return _fast_mode["enabled"]


# Per thread and per asyncio task, unlike the process-wide set_fast_path switch.
_every_size: contextvars.ContextVar[bool] = contextvars.ContextVar("torchbrdf_fused_at_every_size", default=False)


@contextlib.contextmanager
def fused_at_every_size() -> Iterator[None]:
    """Within the block, the automatic mode uses the fused kernels below :data:`FAST_PATH_MIN_LANES` too.

    For a caller that repeats one kind of small call many times (a dataset rendering each
    sample, one of two halves of a batch): the threshold spares a one-off call the kernel's
    first compile (once per machine: the kernel is cached on disk), which such a caller
    repays after a few thousand calls (a 4096-lane forward is about 3× faster fused:
    docs/fast_path.md). It changes only the automatic mode: ``set_fast_path(False)``,
    ``TORCHBRDF_EAGER``, the backend and the dtype/device rules still apply. Scoped to the
    current thread (a ``contextvars`` variable); not traced by ``torch.compile``, which
    always picks the fused operator.
    """
    token = _every_size.set(True)
    try:
        yield
    finally:
        _every_size.reset(token)


def fast_backend(c: dict) -> str | None:
    """``"c"`` or ``"triton"`` when fused kernels evaluate this BRDF call, else None.

    ``c``: the call's checked, compute-dtype inputs by name (``l`` among them); its tensors'
    broadcast batch is the lane count (``principled`` and ``svbrdf_ggx`` share the rule).
    """
    tensors = [t for t in c.values() if isinstance(t, Tensor)]

    def lanes() -> int | None:
        shapes = [t.shape[:-1] if t.dim() > 0 else () for t in tensors]
        try:
            # under torch.func.vmap a tensor shows one sample's shape; the operator's vmap
            # rule folds the vmapped dims into the lanes, so they count toward the threshold
            return math.prod(_checks.broadcast_shapes(*shapes)) * vmap_batch_size()
        except RuntimeError:
            return None

    return fused_backend(c["l"].device, c["l"].dtype, tensors, lanes)


def fused_backend(device: torch.device, dtype: torch.dtype, tensors: list[Tensor],
                   lanes: Callable[[], int | None]) -> str | None:
    """The one dispatch rule of the fused kernels (``principled`` and the shader's light pass).

    Returns ``"c"`` or ``"triton"`` when fused kernels evaluate a call on ``device`` in
    ``dtype`` with these input ``tensors``, else ``None`` (eager). The backend comes from
    :func:`torchbrdf.set_backend` / ``TORCHBRDF_BACKEND`` (see :mod:`torchbrdf.kernels.backend`);
    :func:`set_fast_path` says whether a fused one is used; in automatic mode with the
    ``"auto"`` backend, ``lanes()`` (the batch's lane count, None if it does not broadcast)
    must reach :data:`FAST_PATH_MIN_LANES` (any count inside :func:`fused_at_every_size`).
    """
    mode = _fast_mode["enabled"]
    if mode is False or os.environ.get("TORCHBRDF_EAGER", "") not in ("", "0"):
        return None
    if dtype not in (torch.float32, torch.float64):
        return None
    backend = _resolve_backend(device.type)
    if backend == "eager":
        return None
    if torch.compiler.is_compiling():
        # torch.compile traces the fused operator (torch.ops.torchbrdf.*) at any size, so the
        # compiled graph never depends on the batch size or recompile history.
        # The traced operator has a backward rule but no forward-mode one (custom ops cannot
        # carry one): under forward mode the compiled graph would get a zero tangent, so it
        # traces the eager formula instead.
        if _checks.forward_mode_active():
            return None
        return backend
    if torch.jit.is_tracing() or torch.jit.is_scripting():
        return None
    for t in tensors:
        # tensor subclasses (e.g. __torch_function__ wrappers) stay on eager ATen ops; torch.func
        # transforms (vmap, grad, jvp) and forward-mode AD go through the operator's rules.
        if type(t) not in (Tensor, nn.Parameter):
            return None
    if mode is None and _backend_setting() == "auto" and not _every_size.get():
        n = lanes()
        if n is None or n < FAST_PATH_MIN_LANES:
            return None
    return backend


@_checks.constant_while_tracing
def _resolve_backend(device_type: str) -> str:
    from torchbrdf.kernels import backend as _backend

    return _backend.resolve(torch.device(device_type))


def vmap_batch_size() -> int:
    """The product of the batch sizes of the active ``torch.func.vmap`` levels (1 outside vmap)."""
    return math.prod(size for _, size in _checks.active_transforms())


def _backend_setting() -> str:
    from torchbrdf.kernels import backend as _backend

    return _backend.get_backend()


def _principled_fast_or_none(c: dict, active: tuple[str, ...], backend: str = "c"):
    from torchbrdf.kernels import ops as _ops

    c = _fill_frame(c)
    return _ops.principled_fast(c, active, needs_tint(c, active), needs_frame(c), backend=backend)


def _fill_frame(c: dict) -> dict:
    """``c`` with the tangent frame filled in when the anisotropic form needs one."""
    if not needs_frame(c) or (c["x"] is not None and c["y"] is not None):
        return c
    c = dict(c)
    if c["x"] is None:
        c["x"], c["y"] = frame_from_normal(c["n"])
    else:
        c["y"] = torch.linalg.cross(c["n"], c["x"], dim=-1)
    return c


def principled_eager(c: dict, active: tuple[str, ...]) -> Tensor:
    """The principled BRDF on already-checked, compute-dtype inputs ``c`` (see ``_prepare``).

    This is :func:`torchbrdf.brdf.formula.principled` evaluated with torch operations.
    """
    c = _fill_frame(c)
    ops = formula.TorchOps(c["l"].dtype, c["l"].device)
    return formula.principled(ops, c, active, needs_tint(c, active), needs_frame(c))


def needs_tint(c: dict, active: tuple[str, ...]) -> bool:
    """Whether the tint colour is needed: ``specular_tint`` or (with sheen active) ``sheen_tint``
    is not the constant 0. ``c`` maps parameter names to checked values (``_prepare``'s)."""
    tinted_sheen = "sheen" in active and not is_const(c["sheen_tint"], 0.0)
    return not is_const(c["specular_tint"], 0.0) or tinted_sheen


def needs_frame(c: dict) -> bool:
    """Whether the anisotropic form (and so a tangent frame ``x``, ``y``) is needed for ``c``."""
    return not (c["x"] is None and c["y"] is None and is_const(c["anisotropic"], 0.0))


def half_vector_terms(l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None,
                      need_frame: bool = False) -> dict:
    """Half-vector cosines ``nh``, ``lh``, ``one_minus_lh``, ``sin2_h = |n × h|²``, each ``(*, 1)``.

    Also ``hx``, ``hy`` and the frame ``x``, ``y`` when ``need_frame``; in the inputs' dtype.

    See :func:`torchbrdf.brdf.formula.half_vector_terms` (float64 projections for float32).
    """
    if need_frame:
        if x is None:
            x, y = frame_from_normal(n)
        elif y is None:
            y = torch.linalg.cross(n, x, dim=-1)
    ops = formula.TorchOps(l.dtype, l.device)
    out = formula.half_vector_terms(ops, l, v, n, x if need_frame else None, y)
    if need_frame:
        out["x"], out["y"] = x, y
    return out


class PrincipledBRDF(nn.Module):
    """The Disney principled BRDF as a module: ``forward(l, v, n, x=None, y=None, **params)``.

    Args:
        lobes: optional subset of ``("diffuse", "subsurface", "specular", "sheen",
            "clearcoat")`` to evaluate; default all (each still skipped when its weight is a
            Python 0).

    Shape:
        - l, v, n, x, y: ``(*, 3)``; base_color ``(*, 3)``; scalar parameters ``(*, 1)``.
        - Output: ``(*, 3)``.

    Example:
        >>> brdf = PrincipledBRDF(lobes=("diffuse", "specular"))
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> brdf(n, n, n, base_color=torch.ones(1, 3), roughness=0.3).shape
        torch.Size([1, 3])
    """

    def __init__(self, lobes: Iterable[str] | None = None) -> None:
        super().__init__()
        if lobes is not None:
            active_lobes({}, lobes)  # validates the names
        self.lobes = None if lobes is None else tuple(lobes)

    def forward(self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None,
                **params: Scalar) -> Tensor:
        """Evaluate the BRDF; see :func:`principled` for arguments and shapes."""
        return principled(l, v, n, x, y, lobes=self.lobes, **params)

    def extra_repr(self) -> str:
        return f"lobes={self.lobes}"
