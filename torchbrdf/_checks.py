"""Argument checks with messages that name the argument, its shape/dtype and what was expected.

Metadata checks (shape, dtype, device) are always on: they cost nothing next to the math.
Value checks (NaN/inf, negative intensities) read tensor data, which synchronises a GPU, so
they run only when validation is enabled with :func:`set_validation` or ``validate=True``.
With validation off nothing reads the data: what a non-finite input gives then is described
in ``docs/numerics.md`` ("Non-finite inputs").

Messages show a short excerpt of a bad value (:func:`excerpt`), never a whole list or array.
:func:`active_transforms` and :func:`forward_mode_active` tell dispatch which ``torch.func``
transforms (or forward-mode AD) wrap a call, and
:func:`constant_while_tracing` marks a function Dynamo should run once rather than trace.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import reprlib
from collections.abc import Iterator, Sequence
from typing import TypeVar

import torch
from torch import Tensor

_VALIDATE = False

_F = TypeVar("_F")


def constant_while_tracing(fn: _F) -> _F:
    """Mark ``fn`` as ``torch.compiler.assume_constant_result`` does: under torch.compile it is
    run once while tracing and its result taken as a constant.

    Sets the same mark without importing ``torch._dynamo`` (half of ``import torchbrdf``'s time,
    for users who never compile); tests/test_api_surface.py checks that torch still marks
    functions this way.
    """
    setattr(fn, "_dynamo_marked_constant", True)
    return fn

# check_tensor returns its argument unchanged, so callers keep their own (narrower) type.
_T = TypeVar("_T")


def _switch(enabled: object) -> bool:
    """``enabled`` as a bool; a string or None is refused (``bool("no")`` is True)."""
    if enabled not in (True, False):
        raise ValueError(f"set_validation: enabled must be True or False, got {enabled!r}")
    return bool(enabled)


def set_validation(enabled: bool) -> None:
    """Turn value checks (NaN/inf in inputs, negative intensities) on or off globally.

    Raises:
        ValueError: ``enabled`` is not True or False.
    """
    global _VALIDATE
    _VALIDATE = _switch(enabled)


def validation_enabled() -> bool:
    """Whether value checks are on (see :func:`set_validation`)."""
    return _VALIDATE


@contextlib.contextmanager
def validation(enabled: bool = True) -> Iterator[None]:
    """Context manager form of :func:`set_validation`."""
    global _VALIDATE
    old, new = _VALIDATE, _switch(enabled)
    _VALIDATE = new
    try:
        yield
    finally:
        _VALIDATE = old


# Short reprs for error messages: a 4096-element list must not become a 40 kB message.
_REPR = reprlib.Repr()
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = _REPR.maxfrozenset = _REPR.maxdeque = 6
_REPR.maxdict = 4
_REPR.maxlevel = 3
_REPR.maxstring = 60
_REPR.maxother = 60  # numpy arrays and other objects: their repr, cut to 60 characters


def excerpt(value: object) -> str:
    """A repr of ``value`` short enough for an error message (at most a few dozen characters
    per level; long sequences end in ``...``)."""
    return _REPR.repr(value)


def _describe(t) -> str:
    if isinstance(t, Tensor):
        return f"tensor of shape {tuple(t.shape)}, dtype {t.dtype}, device {t.device}"
    size = f" of length {len(t)}" if isinstance(t, (list, tuple)) else ""
    return f"{type(t).__name__}{size} {excerpt(t)}"


def check_tensor(name: str, t: _T, last: int | None = None, allow_scalar: bool = False) -> _T:
    """Check a tensor argument's type, floating dtype and trailing dimension.

    Args:
        name: argument name used in messages.
        t: the value.
        last: required size of the last axis (``None`` = any). 0-d tensors pass when
            ``allow_scalar``; so do Python numbers, which are returned unchanged.
        allow_scalar: accept Python numbers and 0-d tensors.

    Returns:
        ``t`` unchanged.
    """
    if isinstance(t, numbers.Real) and not isinstance(t, bool):
        if allow_scalar:
            return t
        raise TypeError(f"{name}: expected a tensor with last dimension {last}, got {_describe(t)}")
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor or float, got {_describe(t)}")
    if not t.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {_describe(t)}")
    if t.dim() == 0:
        if allow_scalar:
            return t
        raise ValueError(f"{name}: expected shape (..., {last}), got a 0-d tensor")
    if last is not None and t.shape[-1] != last:
        raise ValueError(f"{name}: expected shape (..., {last}), got {_describe(t)}")
    return t


def check_same_dtype_device(named: dict) -> tuple[torch.dtype, torch.device]:
    """All tensors in ``named`` must share one floating dtype and one device.

    Returns:
        The common ``(dtype, device)``.
    """
    ref_name, ref = None, None
    for name, t in named.items():
        if not isinstance(t, Tensor):
            continue
        if ref is None:
            ref_name, ref = name, t
            continue
        if t.dtype != ref.dtype:
            raise TypeError(
                f"{name}: dtype {t.dtype} differs from {ref_name}'s {ref.dtype}; "
                "pass all tensors in one floating dtype"
            )
        if t.device != ref.device:
            raise ValueError(
                f"{name}: on device {t.device} but {ref_name} is on {ref.device}; "
                "move all tensors to one device"
            )
    if ref is None:
        raise TypeError("expected at least one tensor argument")
    return ref.dtype, ref.device


def active_transforms() -> list[tuple[str, int]]:
    """The active ``torch.func`` transforms, innermost first, as ``(kind, batch size)``: kind
    ``"Vmap"``, ``"Grad"``, ``"Jvp"`` or ``"Functionalize"``; the size is 1 but for vmap."""
    from torch._C._functorch import peek_interpreter_stack
    from torch._functorch.pyfunctorch import VmapInterpreter, coerce_cinterpreter

    if not torch._C._are_functorch_transforms_active():
        return []
    interpreter = coerce_cinterpreter(peek_interpreter_stack())
    size = interpreter.batch_size() if isinstance(interpreter, VmapInterpreter) else 1
    with interpreter.lower():  # the transforms below this one
        return [(interpreter.key().name, size)] + active_transforms()


def forward_mode_active() -> bool:
    """Whether forward-mode AD is active: a ``torch.autograd.forward_ad`` dual level, or a
    ``torch.func`` forward transform (``jvp``, ``jacfwd``) at any depth of the transform stack.
    Traceable by Dynamo without a graph break."""
    from torch._C._functorch import TransformType, peek_interpreter_stack
    from torch._functorch.pyfunctorch import coerce_cinterpreter

    if getattr(torch.autograd.forward_ad, "_current_level", -1) >= 0:
        return True
    if not torch._C._are_functorch_transforms_active():
        return False
    interpreter = coerce_cinterpreter(peek_interpreter_stack())
    if interpreter.key() == TransformType.Jvp:
        return True
    with interpreter.lower():  # the transforms below this one
        return forward_mode_active()


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """:func:`torch.broadcast_shapes` (same result, same ``RuntimeError``), fast for concrete shapes.

    For sequences of ints. Torch's handles symbolic sizes and costs 0.1–0.9 ms a call; a
    fused call builds a few, so a recovery spent 0.15 s in it. Under ``torch.compile``, or
    with a symbolic size, torch's.
    """
    if torch.compiler.is_compiling() or not all(type(d) is int for s in shapes for d in s):
        return torch.broadcast_shapes(*shapes)
    nd = max((len(s) for s in shapes), default=0)
    out = [1] * nd
    for s in shapes:
        for i, d in enumerate(s, nd - len(s)):
            if d != 1 and out[i] != d:
                if out[i] != 1:
                    raise RuntimeError(f"Shape mismatch: objects cannot be broadcast to a single shape "
                                       f"({', '.join(str(tuple(x)) for x in shapes)})")
                out[i] = d
    return torch.Size(out)


def check_broadcast(named: dict) -> torch.Size:
    """Batch shapes (all but the last axis) must broadcast; returns the broadcast batch shape."""
    shapes = {k: t.shape[:-1] for k, t in named.items() if isinstance(t, Tensor) and t.dim() > 0}
    try:
        return broadcast_shapes(*shapes.values())
    except RuntimeError:
        desc = ", ".join(f"{k} {tuple(s)}" for k, s in shapes.items())
        raise ValueError(f"batch shapes do not broadcast: {desc} (the last axis is the channel axis)") from None


def check_finite(named: dict) -> None:
    """Raise if any tensor holds NaN or inf, or any Python number is NaN or inf.

    Reads tensor data (a GPU sync), so callers run it only under validation. ``None`` and
    other non-numeric values are skipped. The message names the argument and shows the
    first bad value and its index.
    """
    for name, t in named.items():
        if isinstance(t, Tensor):
            finite = torch.isfinite(t)
            if not bool(finite.all()):
                bad = ~finite
                first = tuple(int(i) for i in bad.nonzero()[0]) if t.dim() else ()
                value = float(t.detach()[first])
                where = f" at index {first}" if t.dim() else ""
                raise ValueError(
                    f"{name}: contains {int(bad.sum())} non-finite value(s), first {value}{where} "
                    f"({_describe(t)}); pass finite values"
                )
        elif isinstance(t, numbers.Real) and not isinstance(t, bool) and not math.isfinite(t):
            raise ValueError(f"{name}: expected a finite number, got {float(t)}")


def sample_counts(name: str, value: object, default: tuple[int, int], least: tuple[int, int] = (1, 1),
                  pair: bool = True) -> tuple[int, int]:
    """A sample-count argument as a pair of ints, each at least ``least``.

    ``None`` gives ``default``, an int ``k`` gives ``(k, default[1])``, a pair (when ``pair``)
    is taken as is.
    """
    if value is None:
        counts: object = default
    elif isinstance(value, numbers.Integral):
        counts = (value, default[1])
    else:
        counts = value if pair else None
    if (
        not isinstance(counts, Sequence)
        or len(counts) != 2
        or not all(isinstance(k, numbers.Integral) and not isinstance(k, bool) and int(k) >= lo
                   for k, lo in zip(counts, least))
    ):
        what = f"an int or a pair of ints, at least {least}" if pair else f"an int of at least {least[0]}"
        raise ValueError(f"{name}: expected {what}, got {excerpt(value)}")
    return int(counts[0]), int(counts[1])


def check_nonnegative(name: str, t: Tensor | float) -> None:
    """Raise if ``t`` has a negative entry (reads data)."""
    if isinstance(t, Tensor):
        if bool((t < 0).any()):
            raise ValueError(f"{name}: expected non-negative values, got min {float(t.min())}")
    elif t < 0:
        raise ValueError(f"{name}: expected a non-negative value, got {excerpt(t)}")
