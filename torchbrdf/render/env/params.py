"""What the environment integrators need to know about a BRDF and its material values.

Material values come as Python floats, 0-d tensors or per-pixel ``(P, C)`` maps alike; these
helpers read them with the principled defaults and shape them against the pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf._types import BRDF, Color, Scalar
from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS, PrincipledBRDF

__all__ = ["param_value", "as_tensor_like", "as_rgb", "with_sample_axes", "brdf_kind"]


def param_value(material: dict, name: str) -> Scalar:
    """``material[name]``, else the principled default, else 0."""
    return material.get(name, PRINCIPLED_DEFAULTS.get(name, 0.0))


def as_tensor_like(p: Scalar, like: Tensor) -> Tensor:
    """A material value as a tensor broadcastable against ``like`` ``(P, ...)``."""
    if isinstance(p, Tensor):
        return p.to(like.dtype)
    return torch.as_tensor(float(p), dtype=like.dtype, device=like.device)


def as_rgb(p: Color, like: Tensor) -> Tensor:
    """A colour value (float, 0-d, ``(..., 1)`` or ``(..., 3)``) as a tensor with last axis 3."""
    t = as_tensor_like(p, like)
    if t.dim() == 0:
        return t.expand(3)
    return t.expand(*t.shape[:-1], 3)


def with_sample_axes(p: Scalar, dims: int) -> Scalar:
    """Insert ``dims`` sample axes before the channel axis of a ``(P, C)`` material value."""
    if isinstance(p, Tensor) and p.dim() >= 2:
        return p.reshape(p.shape[:-1] + (1,) * dims + p.shape[-1:])
    return p


def brdf_kind(brdf: BRDF) -> str:
    """``"lambert"``, ``"principled"`` or ``"custom"`` — what the split sum knows how to handle."""
    if getattr(brdf, "sampling_lobes", None) == ("diffuse",):
        return "lambert"
    from torchbrdf.brdf.principled import principled

    if brdf is principled or isinstance(brdf, PrincipledBRDF):
        return "principled"
    return "custom"
