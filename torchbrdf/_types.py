"""Type aliases shared by the annotations of the public API.

These are for readers and for mypy; nothing checks them at run time. They are real
objects (not strings), so ``typing.get_type_hints`` resolves annotations that use them.

* :data:`Scalar` — a material parameter or width that may be a Python number or a tensor
  (``(*, 1)`` or 0-d), as the API allows "a Python float or a 0-d tensor wherever a
  tensor is".
* :data:`Color` — a colour ``(*, C)`` (usually ``C = 3``), or a float / 0-d tensor for grey.
* :data:`BRDF` — a BRDF callable with the principled signature
  ``f(l, v, n, x=None, y=None, **params) -> (*, C)``.
* :data:`Angles` — one angle or several, in radians: a float, a sequence of floats or a
  ``(T,)`` tensor.
* :data:`PathLike` — a file system path: ``str`` or :class:`os.PathLike`.
* :data:`Device` — what ``torch`` accepts as a device: a ``torch.device``, a string such as
  ``"cuda:0"``, an index, or ``None`` for the default.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import TypeAlias

import torch
from torch import Tensor

__all__ = ["Scalar", "Color", "BRDF", "Angles", "PathLike", "Device"]

Scalar: TypeAlias = float | Tensor
Color: TypeAlias = float | Tensor
BRDF: TypeAlias = Callable[..., Tensor]
Angles: TypeAlias = float | Sequence[float] | Tensor
PathLike: TypeAlias = str | os.PathLike[str]
Device: TypeAlias = torch.device | str | int | None
