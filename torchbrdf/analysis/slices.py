"""Half/difference-angle parametrisation (Rusinkiewicz 1998) and BRDF image slices.

Burley's Figure 3 views an isotropic BRDF as an image over (θh, θd) at fixed φd (90° shows
every feature of the MERL materials): θh runs left to right, θd top to bottom.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from torchbrdf._types import BRDF, Device, Scalar

__all__ = ["half_diff_to_lv", "image_slice"]


def half_diff_to_lv(
    theta_h: Tensor, theta_d: Tensor, phi_d: Scalar, phi_h: Scalar = 0.0
) -> tuple[Tensor, Tensor]:
    """Directions ``(l, v)`` in the local frame (normal +z, tangent +x) from half/difference angles.

    Args:
        theta_h, theta_d: ``(*)`` angles in radians.
        phi_d: ``(*)`` tensor or float, azimuth of ``l`` about the half vector.
        phi_h: ``(*)`` tensor or float, azimuth of the half vector.

    Returns:
        ``(l, v)``, each ``(*, 3)``; ``v`` is ``l`` mirrored about the half vector.
    """
    phi_d = torch.as_tensor(phi_d, dtype=theta_h.dtype, device=theta_h.device)
    phi_h = torch.as_tensor(phi_h, dtype=theta_h.dtype, device=theta_h.device)
    sd, cd = torch.sin(theta_d), torch.cos(theta_d)
    dx, dy, dz = sd * torch.cos(phi_d), sd * torch.sin(phi_d), cd
    sh, ch = torch.sin(theta_h), torch.cos(theta_h)
    # Rotate d by θh about y, then by φh about z.
    rx, ry, rz = ch * dx + sh * dz, dy, -sh * dx + ch * dz
    cph, sph = torch.cos(phi_h), torch.sin(phi_h)
    l = torch.stack([cph * rx - sph * ry, sph * rx + cph * ry, rz], dim=-1)
    h = torch.stack([sh * cph, sh * sph, ch], dim=-1)
    v = 2.0 * (l * h).sum(-1, keepdim=True) * h - l
    return l, v


def image_slice(
    brdf: BRDF,
    resolution: int = 128,
    phi_d: float = math.pi / 2,
    dtype: torch.dtype = torch.float64,
    device: Device = None,
    **params: Any,
) -> Tensor:
    """Evaluate ``brdf`` on a (θh, θd) image slice at fixed ``phi_d``.

    Args:
        brdf: any BRDF callable ``brdf(l, v, n, x, y, **params) -> (*, 3)``.
        resolution: pixels per axis; θh and θd each sample ``[0, π/2)`` at pixel centres.
        phi_d: difference azimuth in radians (Burley's slices use π/2).
        params: material parameters (floats or broadcastable tensors).

    Returns:
        ``(3, resolution, resolution)`` tensor: row = θd (top = 0), column = θh (left = 0).
    """
    t = (torch.arange(resolution, dtype=dtype, device=device) + 0.5) * (math.pi / 2) / resolution
    td, th = torch.meshgrid(t, t, indexing="ij")
    l, v = half_diff_to_lv(th, td, phi_d)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device).expand_as(l)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=dtype, device=device).expand_as(l)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=dtype, device=device).expand_as(l)
    return brdf(l, v, n, x, y, **params).permute(2, 0, 1)
