"""The Lambertian BRDF ``f = base_color / π`` with the principled call signature.

It ships beside :func:`torchbrdf.principled` so that any model with the principled
signature renders through the same shader (:func:`torchbrdf.shade`); it is also the BRDF of
the white-furnace checks (a white Lambert surface under a white constant environment
reflects radiance exactly 1).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import dot
from torchbrdf._types import Color

__all__ = ["lambert", "LambertBRDF"]

INV_PI = 1.0 / math.pi


def lambert(
    l: Tensor,
    v: Tensor,
    n: Tensor,
    x: Tensor | None = None,
    y: Tensor | None = None,
    *,
    base_color: Color,
    **ignored: Any,
) -> Tensor:
    """Lambertian BRDF value ``base_color / π`` (without the ``n·l`` cosine).

    Args:
        l: ``(*, 3)`` unit direction toward the light.
        v: ``(*, 3)`` unit direction toward the viewer.
        n: ``(*, 3)`` unit shading normal.
        x: unused (accepted for the principled signature).
        y: unused.
        base_color: linear RGB albedo ``(*, 3)``, or a float / 0-d tensor for grey.
        **ignored: any other material parameter (roughness, metallic, ...) is ignored, so a
            principled material dict can be passed unchanged.

    Returns:
        ``(*, 3)`` in ``l``'s dtype; exactly 0 (zero gradient) where ``n·l <= 0`` or
        ``n·v <= 0``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> lambert(n, n, n, base_color=torch.tensor([[math.pi, 0.0, 1.0]]))
        tensor([[1.0000, 0.0000, 0.3183]])
    """
    if _checks.validation_enabled():
        _checks.check_finite({"l": l, "v": v, "n": n, "x": x, "y": y, "base_color": base_color})
    valid = (dot(n, l) > 0) & (dot(n, v) > 0)
    if not isinstance(base_color, Tensor) or base_color.dim() == 0:
        base_color = torch.as_tensor(base_color, dtype=l.dtype, device=l.device).expand(3)
    f = base_color.to(l.dtype) * INV_PI
    f = torch.broadcast_to(f, torch.broadcast_shapes(f.shape, valid.shape[:-1] + (3,)))
    return torch.where(valid, f, torch.zeros_like(f))


# Tells the shader which importance sampler fits this BRDF (see torchbrdf.render.envmap).
# (mypy does not model attributes set on functions.)
lambert.sampling_lobes = ("diffuse",)  # type: ignore[attr-defined]


class LambertBRDF(nn.Module):
    """Lambertian BRDF as a module: ``forward(l, v, n, x=None, y=None, **params)``.

    Shape:
        - l, v, n: ``(*, 3)``; base_color ``(*, 3)`` or scalar.
        - Output: ``(*, 3)``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> LambertBRDF()(n, n, n, base_color=torch.ones(1, 3)).shape
        torch.Size([1, 3])
    """

    sampling_lobes = ("diffuse",)

    def forward(
        self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None, **params: Any
    ) -> Tensor:
        """Evaluate :func:`lambert`."""
        return lambert(l, v, n, x, y, **params)
