"""Local shading frames: tangent ``x``, bitangent ``y`` and normal ``n``, channel-last ``(*, 3)``."""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf._math import dot, safe_normalize


def frame_from_normal(n: Tensor) -> tuple[Tensor, Tensor]:
    """Orthonormal tangent and bitangent for unit normals, branch-free.

    Duff et al., "Building an Orthonormal Basis, Revisited" (JCGT 2017): continuous
    everywhere except across ``n_z = 0``, finite gradients everywhere.

    Args:
        n: unit normals ``(*, 3)``.

    Returns:
        ``(x, y)``, each ``(*, 3)``, with ``x × y = n``.
    """
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    sign = torch.where(nz >= 0, 1.0, -1.0).to(n.dtype)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    x = torch.stack((1.0 + sign * nx * nx * a, sign * b, -sign * nx), dim=-1)
    y = torch.stack((b, sign + ny * ny * a, -ny), dim=-1)
    return x, y


def gram_schmidt(n: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """Tangent frame from a normal and a (not necessarily orthogonal) tangent guess.

    Args:
        n: unit normals ``(*, 3)``.
        t: tangent guesses ``(*, 3)``; the part along ``n`` is removed.

    Returns:
        ``(x, y)`` with ``x = normalize(t - (n·t) n)`` and ``y = n × x``, each ``(*, 3)``.
    """
    x = safe_normalize(t - dot(n, t) * n)
    y = torch.linalg.cross(n, x, dim=-1)
    return x, y


def to_local(w: Tensor, x: Tensor, y: Tensor, n: Tensor) -> Tensor:
    """Express world vectors ``(*, 3)`` in the frame ``(x, y, n)`` (z along the normal)."""
    return torch.cat((dot(w, x), dot(w, y), dot(w, n)), dim=-1)


def to_world(w: Tensor, x: Tensor, y: Tensor, n: Tensor) -> Tensor:
    """Inverse of :func:`to_local`: local ``(*, 3)`` to world ``(*, 3)``."""
    return w[..., 0:1] * x + w[..., 1:2] * y + w[..., 2:3] * n
