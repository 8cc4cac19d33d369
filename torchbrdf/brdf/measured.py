"""Measured isotropic BRDFs in the MERL binary format (Matusik et al. 2003).

File layout (little-endian), exactly as the published MERL 100 database stores it:

* a header of three ``int32``: the table dimensions ``(90, 90, 180)``;
* ``3 * 90 * 90 * 180`` ``float64`` samples: all of red, then all of green, then all of blue.
  Within a channel the index is ``(i_h * 90 + i_d) * 180 + i_p`` (φd varies fastest);
* the stored numbers are scaled: the reflectance is ``stored * scale`` with
  ``scale = (1/1500, 1.15/1500, 1.66/1500)`` for R, G, B. Negative stored values (the
  database uses -1) mark samples that were not measured; they evaluate as 0.

Coordinates are Rusinkiewicz's half/difference angles in the shading frame (z = normal):

* ``h = normalize(l + v)``, ``θh = angle(h, n)``, ``φh = azimuth(h)``;
* ``d`` is ``l`` rotated by ``-φh`` about the normal and then by ``-θh`` about the bitangent
  (which brings ``h`` to the pole); ``θd = angle(d, n)``, ``φd = azimuth(d)``.

Sample ``(i_h, i_d, i_p)`` sits at ``θh = (i_h / 90)^2 · π/2`` (the square-root warp puts
more samples near the specular peak), ``θd = i_d · π/180`` and ``φd = i_p · π/180``:
the lower edge of the bin that the reference reader's truncating lookup maps to that sample.
φd covers ``[0, π)`` only: swapping ``l`` and ``v`` (reciprocity) turns φd into ``φd + π``,
so a negative φd is folded by adding π, and φd is periodic with period π between the last
and first sample. This module interpolates trilinearly in the index coordinates
``(sqrt(θh / (π/2)) · 90, θd / (π/2) · 90, φd / π · 180)``, clamping at the θ edges and
wrapping in φd, so the value and its gradient with respect to the directions are defined
everywhere.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Any
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, compute_dtype, dot, safe_normalize, safe_sqrt
from torchbrdf._types import Scalar
from torchbrdf.brdf.frames import frame_from_normal, to_local
from torchbrdf.io import atomic_path, check_readable_file

__all__ = [
    "MERL_RES",
    "MERL_SCALE",
    "MERLBRDF",
    "merl_coordinates",
    "merl_directions",
    "merl_grid",
    "merl_interpolate",
    "read_merl",
    "write_merl",
]

#: Table dimensions ``(θh, θd, φd)`` as stored in the header.
MERL_RES = (90, 90, 180)
#: Per-channel factors from stored numbers to reflectance (R, G, B).
MERL_SCALE = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)

_N_SAMPLES = MERL_RES[0] * MERL_RES[1] * MERL_RES[2]
_HEADER_BYTES = 3 * 4
_FILE_BYTES = _HEADER_BYTES + 3 * _N_SAMPLES * 8

# Below this squared length a vector's azimuth is undefined; atan2 there would have an
# infinite gradient, so a fixed fallback is used (gradient bounded by 1 / sqrt(eps) = 1e6).
_AZIMUTH_EPS = 1e-12


# --------------------------------------------------------------------------------------
# Coordinates
# --------------------------------------------------------------------------------------


def _length(a: Tensor) -> Tensor:
    """Euclidean length over the last axis, kept: ``(*, k) -> (*, 1)``."""
    return torch.linalg.vector_norm(a, dim=-1, keepdim=True)


def merl_coordinates(
    l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Rusinkiewicz half/difference angles ``(θh, θd, φd)`` with φd folded into ``[0, π]``.

    Args:
        l: unit directions toward the light ``(*, 3)``.
        v: unit directions toward the viewer ``(*, 3)``.
        n: unit normals ``(*, 3)``.
        x: tangents ``(*, 3)``; with ``y``, only used to fix φd where ``h = n`` (where the
            angle is undefined and the MERL convention takes φh = 0). Built from ``n``
            when omitted.
        y: bitangents ``(*, 3)``, ``x × y = n``.

    Returns:
        ``(theta_h, theta_d, phi_d)``, each ``(*, 1)`` in radians: ``θh ∈ [0, π]``
        (``> π/2`` only for invalid configurations), ``θd ∈ [0, π]``, ``φd ∈ [0, π]``.
        Finite with finite gradients everywhere, including ``l = v``, ``h = n`` and
        ``l = -v``.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> th, td, pd = merl_coordinates(n, n, n)
        >>> float(th), float(td)
        (0.0, 0.0)
    """
    if x is None or y is None:
        l, v, n = torch.broadcast_tensors(l, v, n)
        x, y = frame_from_normal(n)
    else:
        l, v, n, x, y = torch.broadcast_tensors(l, v, n, x, y)
    ll = to_local(l, x, y, n)
    h = safe_normalize(to_local(l + v, x, y, n))
    hx, hy, hz = h[..., 0:1], h[..., 1:2], h[..., 2:3]
    lx, ly, lz = ll[..., 0:1], ll[..., 1:2], ll[..., 2:3]

    # Polar angles as atan2(|sin|, cos): accurate at both ends, unlike acos near 1. The sines
    # come from vector_norm, whose value is exact at 0 and whose gradient stays bounded (it is
    # defined as 0 at the zero vector), where sqrt of a floored square would shift θ by 1e-6.
    s2 = hx * hx + hy * hy  # sin²θh
    theta_h = torch.atan2(_length(h[..., :2]), hz)
    theta_d = torch.atan2(_length(torch.linalg.cross(ll, h, dim=-1)), dot(ll, h))

    # d = R l with R taking h to the pole. Its x, y components times sin θh are
    #   d_x s = hz (lx hx + ly hy) - lz s²,   d_y s = ly hx - lx hy,
    # which avoids dividing by s. At h = n (s = 0) MERL takes φh = 0, so d = l.
    tilted = s2 > _AZIMUTH_EPS
    num = torch.where(tilted, ly * hx - lx * hy, ly)
    den = torch.where(tilted, hz * (lx * hx + ly * hy) - lz * s2, lx)
    # At θd = 0 the azimuth is undefined too: sanitise before atan2 so its gradient stays finite.
    flat = num * num + den * den <= _AZIMUTH_EPS
    num = torch.where(flat, torch.zeros_like(num), num)
    den = torch.where(flat, torch.ones_like(den), den)
    phi_d = torch.atan2(num, den)
    phi_d = torch.where(phi_d < 0, phi_d + math.pi, phi_d)  # reciprocity fold into [0, π]
    return theta_h, theta_d, phi_d


def merl_directions(theta_h: Tensor, theta_d: Tensor, phi_d: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`merl_coordinates` in the local frame (n = +z), with φh = 0.

    Args:
        theta_h: half-vector polar angles ``(*)``.
        theta_d: difference polar angles ``(*)``.
        phi_d: difference azimuths ``(*)``.

    Returns:
        ``(l, v)``, unit vectors ``(*, 3)`` in the frame x = +X, y = +Y, n = +Z. They may
        point below the horizon (the MERL grid covers such configurations).

    Example:
        >>> l, v = merl_directions(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(0.0))
        >>> l.tolist(), v.tolist()
        ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    """
    theta_h, theta_d, phi_d = torch.broadcast_tensors(theta_h, theta_d, phi_d)
    sd, cd = torch.sin(theta_d), torch.cos(theta_d)
    d = torch.stack((sd * torch.cos(phi_d), sd * torch.sin(phi_d), cd), dim=-1)
    sh, ch = torch.sin(theta_h), torch.cos(theta_h)
    # Undo the -θh rotation about the bitangent (y): rotate d by +θh about y.
    l = torch.stack((d[..., 0] * ch + d[..., 2] * sh, d[..., 1], d[..., 2] * ch - d[..., 0] * sh), dim=-1)
    h = torch.stack((sh, torch.zeros_like(sh), ch), dim=-1)
    v = 2.0 * dot(l, h) * h - l  # mirror l about h
    return l, v


def merl_grid(
    dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Angles of the MERL samples: ``θh [90]``, ``θd [90]``, ``φd [180]`` (radians).

    Example:
        >>> th, td, pd = merl_grid()
        >>> th.shape, td.shape, pd.shape
        (torch.Size([90]), torch.Size([90]), torch.Size([180]))
    """
    ih = torch.arange(MERL_RES[0], dtype=dtype, device=device)
    i_d = torch.arange(MERL_RES[1], dtype=dtype, device=device)
    ip = torch.arange(MERL_RES[2], dtype=dtype, device=device)
    theta_h = (ih / MERL_RES[0]) ** 2 * (math.pi / 2)
    theta_d = i_d * (math.pi / 2) / MERL_RES[1]
    phi_d = ip * math.pi / MERL_RES[2]
    return theta_h, theta_d, phi_d


# --------------------------------------------------------------------------------------
# Interpolation
# --------------------------------------------------------------------------------------


def _corners(u: Tensor, size: int, wrap: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Lower/upper sample index and fractional weight for continuous index ``u``."""
    # A non-finite direction (validation off) must not become an out-of-range index; its
    # lane reads sample 0 and is zeroed by the caller's n.l > 0 and n.v > 0 test.
    u = torch.nan_to_num(u, nan=0.0, posinf=0.0, neginf=0.0)
    if wrap:
        i0 = torch.floor(u).clamp(0, size - 1)
        t = u - i0
        i0 = i0.long()
        i1 = (i0 + 1) % size
    else:
        u = u.clamp(0, size - 1)  # beyond the last sample: hold its value
        i0 = torch.floor(u).clamp(max=size - 2)
        t = u - i0
        i0 = i0.long()
        i1 = i0 + 1
    return i0, i1, t


def merl_interpolate(
    table: Tensor, theta_h: Tensor, theta_d: Tensor, phi_d: Tensor, scale: Tensor | None = None
) -> Tensor:
    """Trilinear lookup in a MERL-layout table; negative (missing) samples count as 0.

    Args:
        table: ``(3, 90, 90, 180)`` samples indexed ``[channel, θh, θd, φd]``.
        theta_h: half angles ``(*, 1)`` (or ``(*)``), radians.
        theta_d: difference polar angles, same shape.
        phi_d: difference azimuths in ``[0, π]``, same shape.
        scale: optional per-channel factor ``(3,)`` applied after the lookup (e.g.
            :data:`MERL_SCALE` when ``table`` holds the file's stored numbers).

    Returns:
        ``(*, 3)`` values in the dtype of ``theta_h``; differentiable w.r.t. the angles
        (piecewise linear in the warped index coordinates).

    Example:
        >>> table = torch.ones(3, 90, 90, 180)
        >>> z = torch.zeros(5, 1)
        >>> merl_interpolate(table, z, z, z).shape
        torch.Size([5, 3])
    """
    if tuple(table.shape) != (3, *MERL_RES):
        raise ValueError(f"MERL table must have shape (3, 90, 90, 180), got {tuple(table.shape)}")
    rh, rd, rp = MERL_RES
    uh = rh * safe_sqrt(theta_h / (math.pi / 2))
    ud = theta_d * (rd / (math.pi / 2))
    up = phi_d * (rp / math.pi)
    batch = uh.shape[:-1] if uh.dim() > 0 and uh.shape[-1] == 1 else uh.shape
    uh, ud, up = (u.reshape(-1) for u in torch.broadcast_tensors(uh, ud, up))

    h0, h1, th = _corners(uh, rh, wrap=False)
    d0, d1, td = _corners(ud, rd, wrap=False)
    p0, p1, tp = _corners(up, rp, wrap=True)
    flat = table.reshape(3, -1)
    dtype = theta_h.dtype
    if scale is not None:
        scale = torch.as_tensor(scale, dtype=table.dtype, device=table.device)

    def sample(ih, i_d, ip):
        vals = flat[:, (ih * rd + i_d) * rp + ip].clamp(min=0)  # -1 marks a missing sample
        if scale is not None:
            vals = vals * scale[:, None]
        return vals.t().to(dtype)

    th, td, tp = th[:, None], td[:, None], tp[:, None]
    c00 = sample(h0, d0, p0) * (1 - tp) + sample(h0, d0, p1) * tp
    c01 = sample(h0, d1, p0) * (1 - tp) + sample(h0, d1, p1) * tp
    c10 = sample(h1, d0, p0) * (1 - tp) + sample(h1, d0, p1) * tp
    c11 = sample(h1, d1, p0) * (1 - tp) + sample(h1, d1, p1) * tp
    c0 = c00 * (1 - td) + c01 * td
    c1 = c10 * (1 - td) + c11 * td
    out = c0 * (1 - th) + c1 * th
    return out.reshape(*batch, 3)


# --------------------------------------------------------------------------------------
# File format
# --------------------------------------------------------------------------------------


def _read_stored(path: str | os.PathLike, allow_nonfinite: bool = False) -> np.ndarray:
    path = Path(path)
    check_readable_file(path, "MERL file")
    data = path.read_bytes()
    if len(data) < _HEADER_BYTES:
        raise ValueError(f"MERL file '{path}' is {len(data)} bytes, too short for the 12-byte header")
    dims = tuple(int(d) for d in np.frombuffer(data, dtype="<i4", count=3))
    if dims != MERL_RES:
        raise ValueError(f"MERL file '{path}': header dimensions {dims}, expected {MERL_RES}")
    if len(data) != _FILE_BYTES:
        raise ValueError(
            f"MERL file '{path}' is {len(data)} bytes, expected {_FILE_BYTES} "
            f"(12-byte header + 3 x {_N_SAMPLES} float64 samples)"
        )
    stored = np.frombuffer(data, dtype="<f8", offset=_HEADER_BYTES).reshape(3, *MERL_RES).copy()
    if not allow_nonfinite:
        bad = ~np.isfinite(stored)
        if bad.any():
            c, ih, i_d, ip = (int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"MERL file '{path}': {int(bad.sum())} non-finite sample(s) (NaN or inf), first in "
                f"channel {'RGB'[c]} at (θh, θd, φd) index ({ih}, {i_d}, {ip}); a corrupt file? "
                "Pass allow_nonfinite=True to load it anyway"
            )
    return stored


def read_merl(path: str | os.PathLike, raw: bool = False, *, allow_nonfinite: bool = False) -> Tensor:
    """Read a MERL ``.binary`` file.

    Args:
        path: the file.
        raw: return the stored numbers as they are in the file (before the per-channel
            scale, with -1 for missing samples) instead of reflectance values.
        allow_nonfinite: load a file holding NaN or inf samples instead of refusing it. Such
            samples then give NaN/inf wherever an evaluation interpolates them, and
            :func:`write_merl` refuses to write the table back.

    Returns:
        ``(3, 90, 90, 180)`` float64 CPU tensor indexed ``[channel, θh, θd, φd]``:
        reflectance ``stored * MERL_SCALE`` per channel (missing samples stay negative).

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        IsADirectoryError: if ``path`` is a folder.
        ValueError: if the header or the file size is not the MERL layout, or (unless
            ``allow_nonfinite``) a sample is NaN or inf.
    """
    stored = torch.from_numpy(_read_stored(path, allow_nonfinite))
    if raw:
        return stored
    return stored * torch.tensor(MERL_SCALE, dtype=torch.float64)[:, None, None, None]


def write_merl(path: str | os.PathLike, brdf_or_table: MERLBRDF | Tensor | np.ndarray | Callable[..., Tensor],
               **params: Any) -> None:  # Any: forwarded to from_brdf (materials and its options)
    """Write a BRDF to the MERL binary format (atomically).

    Args:
        path: destination file (conventionally ``*.binary``); its folder must exist.
        brdf_or_table: one of

            * a :class:`MERLBRDF` — its stored numbers are written unchanged, so a file read
              with :meth:`MERLBRDF.from_file` is written back byte for byte;
            * a ``(3, 90, 90, 180)`` tensor or array of reflectance values (as returned by
              :func:`read_merl`), divided by :data:`MERL_SCALE` for storage;
            * any BRDF callable ``brdf(l, v, n, x=None, y=None, **params) -> (*, 3)``,
              tabulated with :meth:`MERLBRDF.from_brdf`.
        **params: material parameters passed to a BRDF callable.

    Raises:
        TypeError: if ``brdf_or_table`` is none of the above.
        ValueError: on a wrong table shape or non-finite values.
    """
    path = Path(path)
    if isinstance(brdf_or_table, MERLBRDF):
        stored = brdf_or_table.stored.detach().to("cpu", torch.float64)
    elif isinstance(brdf_or_table, (Tensor, np.ndarray)):
        values = torch.as_tensor(brdf_or_table).detach().to("cpu", torch.float64)
        if tuple(values.shape) != (3, *MERL_RES):
            raise ValueError(
                f"cannot write MERL '{path}': table must have shape (3, 90, 90, 180), "
                f"got {tuple(values.shape)}"
            )
        stored = values / torch.tensor(MERL_SCALE, dtype=torch.float64)[:, None, None, None]
    elif callable(brdf_or_table):
        stored = MERLBRDF.from_brdf(brdf_or_table, **params).stored.to("cpu", torch.float64)
    else:
        raise TypeError(
            f"cannot write MERL '{path}': expected a MERLBRDF, a (3, 90, 90, 180) table or a BRDF callable, "
            f"got {type(brdf_or_table).__name__}"
        )
    if not torch.isfinite(stored).all():
        raise ValueError(f"cannot write MERL '{path}': table has non-finite values")
    header = np.asarray(MERL_RES, dtype="<i4").tobytes()
    body = stored.numpy().astype("<f8", copy=False).tobytes(order="C")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(body)


# --------------------------------------------------------------------------------------
# Module
# --------------------------------------------------------------------------------------


class MERLBRDF(nn.Module):
    """A measured isotropic BRDF on the MERL grid, evaluated like :func:`torchbrdf.principled`.

    The module keeps the file's stored numbers in the buffer ``stored``
    ``(3, 90, 90, 180)`` (float64 unless the module is cast), so reading and writing a file
    is lossless; :attr:`table` gives the reflectance values. Evaluation interpolates
    trilinearly (see the module docstring) and is differentiable w.r.t. the directions.

    Args:
        stored: ``(3, 90, 90, 180)`` numbers as stored in a MERL file (reflectance divided by
            :data:`MERL_SCALE`; negative for missing samples).
        name: optional label shown in ``repr`` (e.g. the material name).

    Shape:
        - forward inputs ``l``, ``v``, ``n`` (and optional ``x``, ``y``): ``(*, 3)``,
          broadcast against each other.
        - output: ``(*, 3)`` BRDF value (without the ``n·l`` cosine), in the inputs' dtype.

    Example:
        >>> brdf = MERLBRDF.from_table(torch.full((3, 90, 90, 180), 0.2))
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> brdf(n, n, n)
        tensor([0.2000, 0.2000, 0.2000])
    """

    stored: Tensor
    scale: Tensor

    def __init__(self, stored: Tensor, name: str | None = None) -> None:
        super().__init__()
        stored = torch.as_tensor(stored)
        if tuple(stored.shape) != (3, *MERL_RES):
            raise ValueError(f"MERLBRDF needs a (3, 90, 90, 180) table, got {tuple(stored.shape)}")
        if not stored.is_floating_point():
            stored = stored.to(torch.float64)
        self.register_buffer("stored", stored)
        self.register_buffer(
            "scale", torch.tensor(MERL_SCALE, dtype=stored.dtype, device=stored.device), persistent=False
        )
        self.name = name

    @classmethod
    def from_file(cls, path: str | os.PathLike, *, allow_nonfinite: bool = False) -> MERLBRDF:
        """Load a MERL ``.binary`` file (see :func:`read_merl` for ``allow_nonfinite`` and the
        errors raised)."""
        return cls(torch.from_numpy(_read_stored(path, allow_nonfinite)), name=Path(path).stem)

    @classmethod
    def from_table(cls, values: Tensor, name: str | None = None, *, allow_nonfinite: bool = False) -> MERLBRDF:
        """Build from reflectance values ``(3, 90, 90, 180)`` (as :func:`read_merl` returns).

        A table holding NaN or inf is refused, as :func:`read_merl` refuses such a file, unless
        ``allow_nonfinite`` is set.
        """
        values = torch.as_tensor(values)
        if tuple(values.shape) != (3, *MERL_RES):
            raise ValueError(f"values: expected a (3, 90, 90, 180) table, got {tuple(values.shape)}")
        if not allow_nonfinite:
            _checks.check_finite({"values": values})
        scale = torch.tensor(MERL_SCALE, dtype=torch.float64, device=values.device)[:, None, None, None]
        return cls(values.to(torch.float64) / scale, name=name)

    @classmethod
    @torch.no_grad()
    def from_brdf(
        cls,
        brdf: Callable[..., Tensor],
        *,
        batch_size: int = 1 << 16,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
        name: str | None = None,
        **params: Scalar,
    ) -> MERLBRDF:
        """Tabulate any BRDF callable at the MERL sample positions.

        Configurations where the light or the view is at or below the horizon are stored as
        0 (the library's value there), whatever the callable returns.

        Args:
            brdf: ``brdf(l, v, n, x, y, **params) -> (*, 3)`` (or ``(*, 1)`` for a grey BRDF),
                e.g. :func:`torchbrdf.principled`.
            batch_size: samples evaluated per call (the grid has 1,458,000): bounds memory.
            device: device to evaluate on (the table is kept there).
            dtype: dtype of the directions handed to ``brdf``; the table is stored in float64.
            name: optional label.
            **params: material parameters forwarded to ``brdf`` (tensors must broadcast
                against ``(batch, 3)`` / ``(batch, 1)``, i.e. be per-material constants;
                floating ones are cast to ``dtype``, so float32 parameters tabulate as given).

        Returns:
            A :class:`MERLBRDF` on ``device``.

        Raises:
            ValueError: if ``brdf`` returns the wrong shape or non-finite values.
        """
        params = {k: p.to(dtype) if isinstance(p, Tensor) and p.is_floating_point() else p
                  for k, p in params.items()}
        theta_h, theta_d, phi_d = merl_grid(dtype=dtype, device=device)
        th, td, tp = torch.meshgrid(theta_h, theta_d, phi_d, indexing="ij")
        th, td, tp = th.reshape(-1), td.reshape(-1), tp.reshape(-1)
        frame = torch.eye(3, dtype=dtype, device=device)
        out = torch.empty(_N_SAMPLES, 3, dtype=torch.float64, device=device)
        for start in range(0, _N_SAMPLES, batch_size):
            sl = slice(start, start + batch_size)
            l, v = merl_directions(th[sl], td[sl], tp[sl])
            m = l.shape[0]
            x, y, n = (frame[i].expand(m, 3) for i in range(3))
            f = brdf(l, v, n, x, y, **params)
            if tuple(f.shape) == (m, 1):
                f = f.expand(m, 3)  # a grey BRDF
            if tuple(f.shape) != (m, 3):
                raise ValueError(
                    f"from_brdf: the BRDF returned shape {tuple(f.shape)} for {m} directions, "
                    f"expected ({m}, 3)"
                )
            if not torch.isfinite(f).all():
                raise ValueError("from_brdf: the BRDF returned non-finite values")
            visible = (l[:, 2:3] > 0) & (v[:, 2:3] > 0)
            out[sl] = torch.where(visible, f.to(torch.float64), 0.0)
        scale = torch.tensor(MERL_SCALE, dtype=torch.float64, device=device)[:, None, None, None]
        return cls(out.t().reshape(3, *MERL_RES) / scale, name=name)

    @property
    def table(self) -> Tensor:
        """Reflectance values ``(3, 90, 90, 180)``: ``stored * MERL_SCALE`` (missing stay negative)."""
        return self.stored * self.scale[:, None, None, None]

    def forward(
        self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None
    ) -> Tensor:
        """Evaluate ``f(l, v)``; see the class docstring for shapes.

        Returns 0 (with zero, finite gradients) where ``n·l <= 0`` or ``n·v <= 0``.
        ``x``/``y`` only matter at ``h = n`` (MERL data are isotropic); when omitted the
        frame is built from ``n``.
        """
        if _checks.validation_enabled():
            _checks.check_finite({"l": l, "v": v, "n": n, "x": x, "y": y})
        dtype = l.dtype
        work = compute_dtype(dtype)
        l, v, n = (t.to(work) for t in torch.broadcast_tensors(l, v, n))
        if x is not None and y is not None:
            x, y = x.to(work), y.to(work)
        theta_h, theta_d, phi_d = merl_coordinates(l, v, n, x, y)
        value = merl_interpolate(self.stored, theta_h, theta_d, phi_d, scale=self.scale)
        visible = (dot(n, l) > 0) & (dot(n, v) > 0)
        value = torch.where(visible, value, torch.zeros((), dtype=work, device=value.device))
        return cast_back(value, dtype)

    def extra_repr(self) -> str:
        return f"name={self.name!r}" if self.name else ""
