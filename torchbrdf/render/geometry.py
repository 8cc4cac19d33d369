"""Analytic g-buffers for tests and examples: a sphere and a flat sample with a normal map.

Both use a pinhole camera. Image convention: pixel ``(i, j)`` has its centre at
``((j + 0.5) / W, (i + 0.5) / H)`` of the image; row 0 is the top (+y, camera up).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import TypeAlias

import torch
from torch import Tensor

from torchbrdf._math import dot, safe_normalize
from torchbrdf._types import Device
from torchbrdf.render.gbuffer import GBuffer

# A 3-vector argument: a (3,) tensor or three numbers.
Vec3: TypeAlias = Tensor | Sequence[float]

__all__ = ["pinhole_rays", "sphere_gbuffer", "plane_gbuffer"]


def _vec(x, dtype, device) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(device=device, dtype=dtype)
    return torch.as_tensor(x, dtype=dtype, device=device)


def pinhole_rays(
    height: int,
    width: int,
    camera_position: Vec3,
    look_at: Vec3 = (0.0, 0.0, 0.0),
    up: Vec3 = (0.0, 1.0, 0.0),
    fov_degrees: float = 40.0,
    *,
    dtype: torch.dtype | None = None,
    device: Device = None,
) -> Tensor:
    """Unit ray directions through pixel centres of a pinhole camera, ``(H, W, 3)``.

    Args:
        height: image height ``H``.
        width: image width ``W``.
        camera_position: ``(3,)`` camera centre.
        look_at: ``(3,)`` point the optical axis passes through.
        up: ``(3,)`` approximate up direction (row 0 of the image is on this side).
        fov_degrees: vertical field of view; pixels are square.
        dtype: floating dtype (default: torch's default dtype).
        device: device.

    Returns:
        ``(H, W, 3)`` unit directions in world space.

    Raises:
        ValueError: if ``height`` or ``width`` is not a positive integer.
    """
    _check_size("pinhole_rays", height=height, width=width)
    dtype = dtype or torch.get_default_dtype()
    c = _vec(camera_position, dtype, device)
    fwd = safe_normalize(_vec(look_at, dtype, device) - c)
    right = safe_normalize(torch.linalg.cross(fwd, _vec(up, dtype, device), dim=-1))
    true_up = torch.linalg.cross(right, fwd, dim=-1)
    t = math.tan(math.radians(fov_degrees) / 2.0)
    ys = (1.0 - 2.0 * (torch.arange(height, dtype=dtype, device=device) + 0.5) / height) * t
    xs = (2.0 * (torch.arange(width, dtype=dtype, device=device) + 0.5) / width - 1.0) * t * (width / height)
    d = fwd + xs[None, :, None] * right + ys[:, None, None] * true_up
    return safe_normalize(d)


def _check_size(who: str, **sizes) -> None:
    """Image sizes and batch sizes must be positive integers (they divide the pixel grid)."""
    for name, value in sizes.items():
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
            raise ValueError(f"{who}: `{name}` must be a positive integer, got {value!r}")


def _material_maps(material, b, h, w, dtype, device) -> dict:
    if material is None:
        return {"base_color": torch.full((b, 3, h, w), 0.8, dtype=dtype, device=device)}
    return dict(material)


def sphere_gbuffer(
    height: int,
    width: int,
    *,
    radius: float = 1.0,
    center: Vec3 = (0.0, 0.0, 0.0),
    camera_position: Vec3 = (0.0, 0.0, 4.0),
    fov_degrees: float | None = None,
    up: Vec3 = (0.0, 1.0, 0.0),
    material: dict | None = None,
    batch_size: int = 1,
    dtype: torch.dtype | None = None,
    device: Device = None,
) -> GBuffer:
    """G-buffer of a sphere seen by a pinhole camera aimed at its centre.

    Pixels whose ray misses the sphere are masked out (their position is the ray's point
    nearest the centre and their normal faces the camera, both harmless). The tangent map is
    ``normalize(up × n)`` (the direction of increasing longitude about the up axis).

    Args:
        height: image height ``H``.
        width: image width ``W``.
        radius: sphere radius.
        center: ``(3,)`` sphere centre.
        camera_position: ``(3,)`` camera centre (outside the sphere).
        fov_degrees: vertical field of view; default fits the sphere with a 10 % margin.
        up: camera up direction.
        material: material dict for the :class:`~torchbrdf.GBuffer`; default a grey
            ``base_color`` map of 0.8.
        batch_size: ``B`` (copies of the same geometry).
        dtype: floating dtype (default: torch's default dtype).
        device: device.

    Returns:
        A :class:`~torchbrdf.GBuffer` with ``(B, ·, H, W)`` maps, a tangent map and a mask.

    Note:
        Under ``torch.compile(fullgraph=True)`` pass ``center`` and ``camera_position`` as
        numbers: the distance between them (the inside-the-sphere check, the default field of
        view) is then computed on the host, in double precision; from tensors it is a
        data-dependent value.

    Raises:
        ValueError: if ``height``, ``width`` or ``batch_size`` is not a positive integer,
            ``radius`` is not positive, or the camera is inside the sphere; the message
            names the argument.

    Example:
        >>> g = sphere_gbuffer(16, 16)
        >>> g.position.shape, int(g.mask.sum()) > 100
        (torch.Size([1, 3, 16, 16]), True)
    """
    _check_size("sphere_gbuffer", height=height, width=width, batch_size=batch_size)
    if not radius > 0 or not math.isfinite(radius):
        raise ValueError(f"sphere_gbuffer: `radius` must be a positive finite number, got {radius!r}")
    dtype = dtype or torch.get_default_dtype()
    c = _vec(camera_position, dtype, device)
    ctr = _vec(center, dtype, device)
    host_numbers = not isinstance(camera_position, Tensor) and not isinstance(center, Tensor)
    if torch.compiler.is_compiling() and host_numbers:
        # Numbers known on the host: no data-dependent branch (and fov) in the traced graph.
        dist = math.dist(camera_position, center)
    else:
        dist = float(torch.linalg.norm(c - ctr))
    if dist <= radius:
        raise ValueError(
            "sphere_gbuffer: `camera_position` must be outside the sphere "
            f"(distance {dist:g} <= radius {radius:g})"
        )
    if fov_degrees is None:
        fov_degrees = 2.0 * math.degrees(math.asin(radius / dist)) * 1.1
    d = pinhole_rays(height, width, c, ctr, up, fov_degrees, dtype=dtype, device=device)  # (H, W, 3)
    oc = c - ctr
    bq = dot(d, oc.expand_as(d))  # (H, W, 1)
    cq = dot(oc, oc) - radius * radius
    disc = bq * bq - cq
    hit = disc[..., 0] > 0
    t_hit = -bq - torch.sqrt(torch.clamp(disc, min=0.0))
    t_near = -bq  # closest approach to the centre, for missed rays
    t = torch.where(hit[..., None], t_hit, t_near)
    p = c + t * d
    n = torch.where(hit[..., None], (p - ctr) / radius, -d)
    n = safe_normalize(n)
    upv = _vec(up, dtype, device).expand_as(n)
    tangent = safe_normalize(torch.linalg.cross(upv, n, dim=-1))

    def img(x):
        return x.permute(2, 0, 1).unsqueeze(0).expand(batch_size, -1, -1, -1).contiguous()

    mask = hit[None, None].expand(batch_size, 1, height, width).contiguous()
    return GBuffer(
        position=img(p),
        normal=img(n),
        camera_position=c,
        material=_material_maps(material, batch_size, height, width, dtype, device),
        tangent=img(tangent),
        mask=mask,
    )


def plane_gbuffer(
    height: int,
    width: int,
    *,
    normal_map: Tensor | None = None,
    camera_position: Vec3 = (0.0, 0.0, 3.0),
    material: dict | None = None,
    batch_size: int | None = None,
    dtype: torch.dtype | None = None,
    device: Device = None,
) -> GBuffer:
    """G-buffer of the flat sample ``[-1, 1]²`` at ``z = 0`` (+z up), optionally normal-mapped.

    Pixel ``(i, j)`` sees ``p = (-1 + (j + 0.5) 2 / W, 1 - (i + 0.5) 2 / H, 0)`` — exactly the
    capture layout (docs/capture_format.md): the view of a pinhole camera at ``(0, 0, d)`` looking
    down ``-z`` with vertical field of view ``2 atan(1 / d)``; for other camera positions the
    mapping is kept and the camera only sets each pixel's view vector. The frame is
    ``x = +X, y = +Y, n = +Z``; a tangent-space normal map gives ``n = normalize(normal_map)``
    and the shader builds the tangent frame by Gram–Schmidt from +X (the tangent map).

    Args:
        height: image height ``H``.
        width: image width ``W``.
        normal_map: optional ``(B, 3, H, W)`` tangent-space normals (``z > 0``).
        camera_position: ``(3,)`` or ``(B, 3)``.
        material: material dict; default a grey ``base_color`` map of 0.8.
        batch_size: ``B`` (default: the normal map's, else 1).
        dtype: floating dtype (default: the normal map's, else torch's default).
        device: device (default: the normal map's).

    Returns:
        A :class:`~torchbrdf.GBuffer` with a tangent map and no mask.

    Raises:
        ValueError: if ``height``, ``width`` or ``batch_size`` is not a positive integer, or
            ``normal_map`` does not have shape ``[B, 3, H, W]``; the message names the argument.

    Example:
        >>> plane_gbuffer(4, 4).normal[0, :, 0, 0]
        tensor([0., 0., 1.])
    """
    _check_size("plane_gbuffer", height=height, width=width)
    if batch_size is not None:
        _check_size("plane_gbuffer", batch_size=batch_size)
    if normal_map is not None:
        if (
            not isinstance(normal_map, Tensor)
            or normal_map.dim() != 4
            or normal_map.shape[1] != 3
            or tuple(normal_map.shape[2:]) != (height, width)
        ):
            shape = list(normal_map.shape) if isinstance(normal_map, Tensor) else type(normal_map).__name__
            raise ValueError(
                f"plane_gbuffer: `normal_map` must have shape [B, 3, {height}, {width}], got {shape}"
            )
        dtype = dtype or normal_map.dtype
        device = device if device is not None else normal_map.device
        batch_size = batch_size or normal_map.shape[0]
    dtype = dtype or torch.get_default_dtype()
    b = batch_size or 1
    xs = -1.0 + (torch.arange(width, dtype=dtype, device=device) + 0.5) * (2.0 / width)
    ys = 1.0 - (torch.arange(height, dtype=dtype, device=device) + 0.5) * (2.0 / height)
    pos = torch.stack(
        (
            xs[None, :].expand(height, width),
            ys[:, None].expand(height, width),
            torch.zeros(height, width, dtype=dtype, device=device),
        )
    )
    pos = pos.unsqueeze(0).expand(b, 3, height, width).contiguous()
    if normal_map is None:
        normal = torch.zeros(b, 3, height, width, dtype=dtype, device=device)
        normal[:, 2] = 1.0
    else:
        nm = normal_map.to(dtype=dtype, device=device).expand(b, 3, height, width)
        normal = nm * torch.rsqrt(torch.clamp((nm * nm).sum(1, keepdim=True), min=1e-12))
    tangent = torch.zeros(b, 3, height, width, dtype=dtype, device=device)
    tangent[:, 0] = 1.0
    cam = _vec(camera_position, dtype, device)
    return GBuffer(
        position=pos,
        normal=normal,
        camera_position=cam,
        material=_material_maps(material, b, height, width, dtype, device),
        tangent=tangent,
    )
