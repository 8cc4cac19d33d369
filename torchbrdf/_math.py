"""Gradient-safe elementwise helpers shared by every BRDF term.

All vectors are channel-last ``(*, 3)``. Every helper here keeps both the value and the
gradient finite at the singular points of the naive formula (``sqrt`` at 0, division by 0,
normalising a zero vector), which is what lets an optimiser survive grazing angles.

Epsilons (each is the smallest value whose backward stays far from overflow in float32):

* ``SQRT_EPS = 1e-12`` — floor under a ``sqrt`` argument: d sqrt / dx <= 0.5e6.
* ``NORM_EPS = 1e-12`` — floor under a squared length before ``rsqrt``.
* ``DIV_EPS = 1e-12`` — floor under the magnitude of a denominator.

Half-precision inputs are evaluated in float32 by the BRDFs (see :func:`compute_dtype`), so
these floors never underflow.
"""

from __future__ import annotations

import functools
import numbers
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar, cast, overload

import torch
from torch import Tensor

from torchbrdf._types import Scalar

_P = ParamSpec("_P")
_R = TypeVar("_R")

SQRT_EPS = 1e-12
NORM_EPS = 1e-12
DIV_EPS = 1e-12


def is_zero(x: object) -> bool:
    """True only for a Python number equal to 0; a tensor is never inspected (no host sync,
    no guard under ``torch.compile``), so a lobe weighted by it is always evaluated."""
    return isinstance(x, numbers.Real) and float(x) == 0.0


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last axis, keeping it: ``(*, 3), (*, 3) -> (*, 1)``."""
    return (a * b).sum(dim=-1, keepdim=True)


def cross_norm2(a: Tensor, b: Tensor) -> Tensor:
    """``|a x b|^2`` over the last axis, ``(*, 3) -> (*, 1)``.

    For unit vectors this is ``1 - (a.b)^2`` computed *without* cancellation near
    ``a = b``, which is what keeps narrow specular peaks accurate in float32.
    """
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b, dim=-1).square().sum(dim=-1, keepdim=True)


def safe_sqrt(x: Tensor, eps: float = SQRT_EPS) -> Tensor:
    """``sqrt(max(x, eps))``: finite value and gradient everywhere (zero gradient below eps)."""
    return torch.sqrt(torch.clamp(x, min=eps))


def safe_normalize(v: Tensor, eps: float = NORM_EPS) -> Tensor:
    """Normalise ``(*, 3)`` vectors; a zero vector maps to zero with finite gradient."""
    return v * torch.rsqrt(torch.clamp(dot(v, v), min=eps))


def safe_div(a: Tensor, b: Tensor, eps: float = DIV_EPS) -> Tensor:
    """``a / b`` with ``|b|`` floored at ``eps`` (sign kept; ``b = 0`` counts as positive)."""
    sign = torch.where(b < 0, -1.0, 1.0).to(b.dtype)
    return a / (sign * torch.clamp(b.abs(), min=eps))


@overload
def lerp(a: float, b: float, t: float) -> float: ...  # type: ignore[overload-overlap]  # floats in, float out
@overload
def lerp(a: Scalar, b: Scalar, t: Scalar) -> Tensor: ...
def lerp(a: Scalar, b: Scalar, t: Scalar) -> Scalar:
    """``a + (b - a) t`` with full broadcasting and Python scalars allowed anywhere."""
    return a + (b - a) * t


def schlick_weight(u: Tensor) -> Tensor:
    """``(1 - u)^5`` with ``u`` clamped to ``[0, 1]``, as repeated products (no ``pow``)."""
    m = torch.clamp(1.0 - u, 0.0, 1.0)
    m2 = m * m
    return m2 * m2 * m


def luminance(rgb: Tensor) -> Tensor:
    """Burley's approximate luminance ``0.3 R + 0.6 G + 0.1 B``, ``(*, 3) -> (*, 1)``."""
    return 0.3 * rgb[..., 0:1] + 0.6 * rgb[..., 1:2] + 0.1 * rgb[..., 2:3]


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """Dtype the BRDF math runs in: float32 for half types, the input dtype otherwise.

    float16 overflows at 65504 and bfloat16 carries 8 mantissa bits, so ``alpha^2`` at the
    0.001 floor, ``1 / (NL + NV)`` near grazing and the peak of a narrow lobe are evaluated
    in float32 and the result is cast back (saturating at the dtype's largest finite value).
    """
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def cast_back(x: Tensor, dtype: torch.dtype) -> Tensor:
    """Cast a float32 result to ``dtype``, saturating instead of overflowing to inf."""
    if x.dtype == dtype:
        return x
    big = torch.finfo(dtype).max
    return torch.clamp(x, -big, big).to(dtype)


class _SaturatingCast(torch.autograd.Function):
    """Cast to a wider dtype whose backward saturates the gradient at the narrow dtype's range.

    In the ``setup_context`` form with a vmap rule, so that ``torch.func.grad``/``vjp``/``vmap``
    accept it; forward mode takes a plain cast instead (:func:`cast_in`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: Tensor, dtype: torch.dtype) -> Tensor:
        return x.to(dtype)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.in_dtype = inputs[0].dtype

    @staticmethod
    def backward(ctx, grad: Tensor):
        big = torch.finfo(ctx.in_dtype).max
        return torch.clamp(grad, -big, big).to(ctx.in_dtype), None


@overload
def cast_in(x: Tensor, dtype: torch.dtype) -> Tensor: ...
@overload
def cast_in(x: _R, dtype: torch.dtype) -> _R: ...
def cast_in(x: Any, dtype: torch.dtype) -> Any:
    """Cast an input to the compute ``dtype``; for half inputs the gradient coming back
    saturates at the half type's largest finite value instead of overflowing to inf (at
    n·l = n·v = 1e-7 the true gradient is ~1e13)."""
    if not isinstance(x, Tensor) or x.dtype == dtype:
        return x
    # Inside a forward-mode dual level a plain cast: an autograd.Function needs a custom jvp
    # there, which torch.compile refuses to trace.
    if (x.dtype in (torch.float16, torch.bfloat16) and x.requires_grad
            and getattr(torch.autograd.forward_ad, "_current_level", -1) < 0):
        return _SaturatingCast.apply(x, dtype)
    return x.to(dtype)


_HALF = (torch.float16, torch.bfloat16)


def half_safe(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: evaluate ``fn`` in float32 when any tensor argument is float16/bfloat16.

    Inputs are promoted with :func:`cast_in` (gradients saturate on the way back) and tensor
    results are cast back with :func:`cast_back` (values saturate instead of becoming inf).
    """

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        half = next((a.dtype for a in (*args, *kwargs.values()) if isinstance(a, Tensor) and a.dtype in _HALF), None)
        if half is None:
            return fn(*args, **kwargs)
        up = lambda a: cast_in(a, torch.float32) if isinstance(a, Tensor) and a.is_floating_point() else a  # noqa: E731
        out = cast(Callable[..., _R], fn)(*[up(a) for a in args], **{k: up(a) for k, a in kwargs.items()})
        if isinstance(out, tuple):
            return cast(_R, tuple(cast_back(o, half) if isinstance(o, Tensor) else o for o in out))
        return cast(_R, cast_back(cast(Tensor, out), half))

    return wrapper
