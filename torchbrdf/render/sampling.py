"""Importance samplers for the environment integral, each paired with its density.

Every sampler turns uniform numbers ``u`` in ``[0, 1)^2`` (shape ``(*, 2)``) into directions
and has a ``pdf_*`` partner that returns the density of the same directions with respect to
solid angle (for half-vector samplers: with respect to the half vector's solid angle, plus a
helper for the reflected direction). Local directions live in a frame whose z axis is the
normal (see :func:`torchbrdf.frames.to_local`).

Samplers and densities:

* :func:`sample_cosine_hemisphere` / :func:`pdf_cosine_hemisphere` — ``cos θ / π`` through
  the concentric (Shirley–Chiu) disk map, which keeps strata compact.
* :func:`sample_ggx_vndf` / :func:`pdf_ggx_vndf` — GGX visible normals, Heitz, "Sampling the
  GGX Distribution of Visible Normals", JCGT 7(4), 2018; reflected-direction density
  :func:`pdf_ggx_reflection` ``= G1(v) D(h) / (4 n·v)``.
* :func:`sample_gtr1` / :func:`pdf_gtr1` — GTR with γ = 1 (the principled clearcoat), Burley
  2012 appendix B eq. (2), (4), (5); ``pdf_h = D(h) cos θ_h``, reflected density
  ``pdf_h / (4 l·h)`` (:func:`pdf_half_to_reflection`).
* :class:`LatLongSampler` — piecewise-constant lat-long map sampled in proportion to texel
  luminance times texel solid angle; uniform in solid angle inside the chosen texel, so
  ``pdf = luminance / Σ luminance · Ω`` exactly (no ``1/sin θ`` spike).

Uniform numbers come from :func:`stratified_samples`: a Hammersley point set shifted per
point by a seeded random offset (Cranley–Patterson rotation). Each point is uniformly
distributed (so estimators stay unbiased) while the set stays stratified in both dimensions.

All functions are device/dtype generic and use no global RNG state.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchbrdf._math import dot, safe_normalize
from torchbrdf._types import Device, Scalar
from torchbrdf.brdf.formula import ALPHA_MIN  # the principled model's floor (Burley 2012 code)

__all__ = [
    "hammersley",
    "rotated_hammersley",
    "stratified_samples",
    "sample_cosine_hemisphere",
    "pdf_cosine_hemisphere",
    "sample_ggx_vndf",
    "pdf_ggx_vndf",
    "pdf_ggx_reflection",
    "ggx_ndf_local",
    "ggx_smith_g1_local",
    "sample_gtr1",
    "pdf_gtr1",
    "gtr1_ndf",
    "reflect",
    "pdf_half_to_reflection",
    "latlong_directions",
    "latlong_row_solid_angles",
    "latlong_texel_index",
    "LatLongSampler",
]

# |α² - 1| below which GTR1 uses its α = 1 limit (uniform in cos² θ_h, D = 1/π); the
# relative error of the general formula there is ~1e-6 in float64 and worse in float32.
_GTR1_LIMIT_EPS = 1e-4


# --------------------------------------------------------------------------------------
# Stratified uniform numbers
# --------------------------------------------------------------------------------------


def _radical_inverse_base2(i: Tensor) -> Tensor:
    """Van der Corput radical inverse of non-negative int64 ``i < 2**32``, as float64 in [0, 1)."""
    b = i & 0xFFFFFFFF
    b = ((b & 0x55555555) << 1) | ((b >> 1) & 0x55555555)
    b = ((b & 0x33333333) << 2) | ((b >> 2) & 0x33333333)
    b = ((b & 0x0F0F0F0F) << 4) | ((b >> 4) & 0x0F0F0F0F)
    b = ((b & 0x00FF00FF) << 8) | ((b >> 8) & 0x00FF00FF)
    b = ((b & 0x0000FFFF) << 16) | ((b >> 16) & 0x0000FFFF)
    return b.to(torch.float64) / 4294967296.0


def hammersley(
    start: int, count: int, total: int, *, dtype: torch.dtype | None = None, device: Device = None
) -> Tensor:
    """Points ``start .. start + count - 1`` of the ``total``-point Hammersley set.

    Point ``i`` is ``(i / total, radical_inverse_2(i))``: exactly one point per stratum
    ``[k / total, (k + 1) / total)`` of the first coordinate, and a (0, m, 2)-net when
    ``total`` is a power of two.

    Args:
        start: first point index.
        count: number of points.
        total: size of the whole set.
        dtype: floating dtype of the result (default: torch's default dtype).
        device: device of the result.

    Returns:
        ``(count, 2)`` points in ``[0, 1)^2``.

    Example:
        >>> hammersley(0, 4, 4)
        tensor([[0.0000, 0.0000],
                [0.2500, 0.5000],
                [0.5000, 0.2500],
                [0.7500, 0.7500]])
    """
    dtype = dtype or torch.get_default_dtype()
    i = torch.arange(start, start + count, device=device, dtype=torch.int64)
    u1 = i.to(torch.float64) / float(total)
    u2 = _radical_inverse_base2(i)
    return torch.stack((u1, u2), dim=-1).to(dtype)


def rotated_hammersley(shift: Tensor, start: int, count: int, total: int) -> Tensor:
    """Hammersley points ``start .. start + count - 1`` of ``total``, rotated per row by ``shift``.

    Args:
        shift: ``(*, 2)`` offsets in ``[0, 1)`` (one per pixel), e.g. from ``torch.rand``.
        start: first point index.
        count: number of points.
        total: size of the whole set (the per-pixel sample count).

    Returns:
        ``(*, count, 2)`` uniform numbers in ``[0, 1)``: ``frac(point + shift)``.
    """
    pts = hammersley(start, count, total, dtype=shift.dtype, device=shift.device)
    u = pts + shift.unsqueeze(-2)
    u = u - torch.floor(u)
    # frac() can round up to exactly 1.0 in low precision; fold that back to 0.
    return torch.where(u >= 1.0, torch.zeros_like(u), u)


def stratified_samples(
    num_points: int,
    num_samples: int,
    *,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype | None = None,
    device: Device = None,
) -> Tensor:
    """Stratified, seeded uniform numbers: ``num_samples`` per point, each in ``[0, 1)^2``.

    Args:
        num_points: number of independent point sets (e.g. pixels).
        num_samples: samples per set.
        generator: the random source of the per-set shifts; built from ``seed`` if omitted.
        seed: seed used when ``generator`` is omitted (default 0).
        dtype: floating dtype (default: torch's default dtype).
        device: device of the result.

    Returns:
        ``(num_points, num_samples, 2)``.

    Example:
        >>> stratified_samples(3, 16, seed=1).shape
        torch.Size([3, 16, 2])
    """
    dtype = dtype or torch.get_default_dtype()
    device = torch.device("cpu") if device is None else torch.device(device)
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(0 if seed is None else int(seed))
    shift = torch.rand((num_points, 2), generator=generator, dtype=dtype, device=device)
    return rotated_hammersley(shift, 0, num_samples, num_samples)


# --------------------------------------------------------------------------------------
# Cosine-weighted hemisphere
# --------------------------------------------------------------------------------------


def sample_cosine_hemisphere(u: Tensor) -> Tensor:
    """Directions with density ``cos θ / π`` about +z (local frame).

    Maps ``u`` to the unit disk with Shirley & Chiu's concentric map and lifts the point to
    the hemisphere (Malley's method).

    Args:
        u: ``(*, 2)`` uniform numbers in ``[0, 1)``.

    Returns:
        ``(*, 3)`` unit local directions with ``z >= 0``.
    """
    a = 2.0 * u[..., 0] - 1.0
    b = 2.0 * u[..., 1] - 1.0
    use_a = a.abs() > b.abs()
    # Sanitise the divisor of the branch not taken so neither branch can produce inf/NaN.
    a_safe = torch.where(a == 0, torch.ones_like(a), a)
    b_safe = torch.where(b == 0, torch.ones_like(b), b)
    r = torch.where(use_a, a, b)
    phi = torch.where(use_a, (math.pi / 4.0) * (b / a_safe), (math.pi / 2.0) - (math.pi / 4.0) * (a / b_safe))
    x = r * torch.cos(phi)
    y = r * torch.sin(phi)
    z = torch.sqrt(torch.clamp(1.0 - x * x - y * y, min=0.0))
    return torch.stack((x, y, z), dim=-1)


def pdf_cosine_hemisphere(w_local: Tensor) -> Tensor:
    """Solid-angle density of :func:`sample_cosine_hemisphere`: ``max(z, 0) / π``, ``(*, 3) -> (*, 1)``."""
    return torch.clamp(w_local[..., 2:3], min=0.0) / math.pi


# --------------------------------------------------------------------------------------
# GGX (GTR2), visible normals
# --------------------------------------------------------------------------------------


def ggx_ndf_local(h: Tensor, alpha_x: Scalar, alpha_y: Scalar) -> Tensor:
    """Anisotropic GGX ``D(h)`` for a local half vector (Burley 2012 eq. 13), ``(*, 3) -> (*, 1)``.

    Zero for ``h_z <= 0``. ``alpha_x``/``alpha_y`` are floats or ``(*, 1)`` tensors.
    """
    hx = h[..., 0:1] / alpha_x
    hy = h[..., 1:2] / alpha_y
    hz = h[..., 2:3]
    den = hx * hx + hy * hy + hz * hz
    d = 1.0 / (math.pi * alpha_x * alpha_y * den * den)
    return torch.where(hz > 0, d, torch.zeros_like(d))


def ggx_smith_g1_local(w: Tensor, alpha_x: Scalar, alpha_y: Scalar) -> Tensor:
    """Smith masking ``G1(w) = 2 w_z / (w_z + sqrt(αx² wx² + αy² wy² + w_z²))``, ``(*, 3) -> (*, 1)``.

    This is the uncorrelated anisotropic form of the principled model (Heitz 2014); zero for
    ``w_z <= 0``.
    """
    wz = w[..., 2:3]
    t2 = (alpha_x * w[..., 0:1]) ** 2 + (alpha_y * w[..., 1:2]) ** 2
    wzc = torch.clamp(wz, min=0.0)
    g = 2.0 * wzc / torch.clamp(wzc + torch.sqrt(t2 + wzc * wzc), min=1e-30)
    return torch.where(wz > 0, g, torch.zeros_like(g))


def sample_ggx_vndf(v_local: Tensor, alpha_x: Scalar, alpha_y: Scalar, u: Tensor) -> Tensor:
    """Half vectors distributed as the GGX visible normals seen from ``v_local``.

    Heitz 2018: stretch the view to the unit-roughness configuration, sample the projected
    hemisphere (a disk warped toward the view), unstretch.

    Args:
        v_local: ``(*, 3)`` unit view direction in the local frame, ``z > 0``.
        alpha_x: NDF width along x, float or ``(*, 1)``.
        alpha_y: NDF width along y, float or ``(*, 1)``.
        u: ``(*, 2)`` uniform numbers.

    Returns:
        ``(*, 3)`` unit local half vectors with ``z >= 0``; density :func:`pdf_ggx_vndf`.
    """
    vh = safe_normalize(
        torch.cat((alpha_x * v_local[..., 0:1], alpha_y * v_local[..., 1:2], v_local[..., 2:3]), dim=-1)
    )
    lensq = vh[..., 0:1] ** 2 + vh[..., 1:2] ** 2
    has_len = lensq > 0
    inv_len = torch.rsqrt(torch.where(has_len, lensq, torch.ones_like(lensq)))
    zero = torch.zeros_like(lensq)
    t1 = torch.where(
        has_len,
        torch.cat((-vh[..., 1:2] * inv_len, vh[..., 0:1] * inv_len, zero), dim=-1),
        torch.cat((torch.ones_like(lensq), zero, zero), dim=-1),
    )
    t2 = torch.linalg.cross(vh, t1, dim=-1)
    r = torch.sqrt(u[..., 0:1])
    phi = (2.0 * math.pi) * u[..., 1:2]
    p1 = r * torch.cos(phi)
    p2 = r * torch.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2:3])
    p2 = (1.0 - s) * torch.sqrt(torch.clamp(1.0 - p1 * p1, min=0.0)) + s * p2
    nh = p1 * t1 + p2 * t2 + torch.sqrt(torch.clamp(1.0 - p1 * p1 - p2 * p2, min=0.0)) * vh
    return safe_normalize(
        torch.cat(
            (alpha_x * nh[..., 0:1], alpha_y * nh[..., 1:2], torch.clamp(nh[..., 2:3], min=0.0)), dim=-1
        )
    )


def pdf_ggx_vndf(v_local: Tensor, h_local: Tensor, alpha_x: Scalar, alpha_y: Scalar) -> Tensor:
    """Density of :func:`sample_ggx_vndf` over half vectors: ``G1(v) max(v·h, 0) D(h) / v_z``, ``(*, 1)``."""
    vz = v_local[..., 2:3]
    num = ggx_smith_g1_local(v_local, alpha_x, alpha_y) * torch.clamp(dot(v_local, h_local), min=0.0)
    num = num * ggx_ndf_local(h_local, alpha_x, alpha_y)
    return torch.where(vz > 0, num / torch.clamp(vz, min=1e-30), torch.zeros_like(num))


def pdf_ggx_reflection(v_local: Tensor, l_local: Tensor, alpha_x: Scalar, alpha_y: Scalar) -> Tensor:
    """Solid-angle density of ``l = reflect(v, h)`` with ``h`` from :func:`sample_ggx_vndf`.

    Equal to ``G1(v) D(h) / (4 v_z)`` with ``h = normalize(v + l)`` (the Jacobian
    ``1 / (4 v·h)`` cancels the ``v·h`` of the visible-normal density), ``(*, 1)``.
    """
    h = safe_normalize(v_local + l_local)
    vz = v_local[..., 2:3]
    num = ggx_smith_g1_local(v_local, alpha_x, alpha_y) * ggx_ndf_local(h, alpha_x, alpha_y)
    ok = (vz > 0) & (dot(v_local, h) > 0)
    return torch.where(ok, num / (4.0 * torch.clamp(vz, min=1e-30)), torch.zeros_like(num))


def reflect(v: Tensor, h: Tensor) -> Tensor:
    """Mirror ``v`` about ``h``: ``2 (v·h) h - v``, ``(*, 3)``."""
    return 2.0 * dot(v, h) * h - v


def pdf_half_to_reflection(pdf_h: Tensor, l_dot_h: Tensor) -> Tensor:
    """Half-vector density to reflected-direction density: ``pdf_h / (4 |l·h|)`` (Burley 2012 B.1).

    ``pdf_h`` and ``l_dot_h`` broadcast together (``(*, 1)``); 0 where ``l·h = 0``.
    """
    lh = l_dot_h.abs()
    return torch.where(lh > 0, pdf_h / (4.0 * torch.clamp(lh, min=1e-30)), torch.zeros_like(pdf_h))


# --------------------------------------------------------------------------------------
# GTR1 (clearcoat)
# --------------------------------------------------------------------------------------


def _as_tensor(x: Scalar, like: Tensor) -> Tensor:
    return x if isinstance(x, Tensor) else torch.as_tensor(float(x), dtype=like.dtype, device=like.device)


def gtr1_ndf(cos_h: Tensor, alpha: Scalar) -> Tensor:
    """GTR with γ = 1 (Burley 2012 eq. 4): ``(α² - 1) / (π ln α² (1 + (α² - 1) cos² θ_h))``.

    ``α = 1`` is handled by its limit ``1/π``. Zero for ``cos_h <= 0``.

    Args:
        cos_h: ``(*, 1)`` cosine of the half vector with the normal.
        alpha: float or ``(*, 1)`` tensor, floored at ``ALPHA_MIN``.

    Returns:
        ``(*, 1)``.
    """
    a = torch.clamp(_as_tensor(alpha, cos_h), min=ALPHA_MIN)
    a2 = a * a
    near_one = (a2 - 1.0).abs() < _GTR1_LIMIT_EPS
    a2s = torch.where(near_one, torch.full_like(a2, 0.5), a2)  # sanitised branch input
    norm = torch.where(near_one, torch.full_like(a2, 1.0 / math.pi), (a2s - 1.0) / (math.pi * torch.log(a2s)))
    d = norm / (1.0 + (a2 - 1.0) * cos_h * cos_h)
    return torch.where(cos_h > 0, d, torch.zeros_like(d))


def sample_gtr1(alpha: Scalar, u: Tensor) -> Tensor:
    """Local half vectors with density ``D_GTR1(θ_h) cos θ_h`` (Burley 2012 eq. 2 and 5).

    Args:
        alpha: float or ``(*, 1)`` tensor (the clearcoat α), floored at ``ALPHA_MIN``.
        u: ``(*, 2)`` uniform numbers; ``u[..., 0]`` drives φ, ``u[..., 1]`` drives θ.

    Returns:
        ``(*, 3)`` unit local half vectors, ``z > 0``.
    """
    u1, u2 = u[..., 0:1], u[..., 1:2]
    a = torch.clamp(_as_tensor(alpha, u), min=ALPHA_MIN)
    a2 = a * a
    near_one = (a2 - 1.0).abs() < _GTR1_LIMIT_EPS
    a2s = torch.where(near_one, torch.full_like(a2, 0.5), a2)
    cos2 = torch.where(near_one, 1.0 - u2, (1.0 - torch.pow(a2s, 1.0 - u2)) / (1.0 - a2s))
    cos2 = torch.clamp(cos2, 0.0, 1.0)
    cos_t = torch.sqrt(cos2)
    sin_t = torch.sqrt(torch.clamp(1.0 - cos2, min=0.0))
    phi = (2.0 * math.pi) * u1
    return torch.cat((sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t), dim=-1)


def pdf_gtr1(h_local: Tensor, alpha: Scalar) -> Tensor:
    """Half-vector density of :func:`sample_gtr1`: ``D_GTR1(h) h_z``, ``(*, 3) -> (*, 1)``."""
    cz = h_local[..., 2:3]
    return gtr1_ndf(cz, alpha) * torch.clamp(cz, min=0.0)


# --------------------------------------------------------------------------------------
# Lat-long environment maps
# --------------------------------------------------------------------------------------


def latlong_directions(
    height: int, width: int, *, dtype: torch.dtype | None = None, device: Device = None
) -> Tensor:
    """Texel-centre directions of a lat-long map, the library's lat-long convention (z up).

    Row ``i`` has polar angle ``θ = (i + 0.5) π / height`` from +z, column ``j`` azimuth
    ``φ = -π + (j + 0.5) 2π / width``; ``d = (sin θ cos φ, sin θ sin φ, cos θ)``.

    Returns:
        ``(height, width, 3)``.
    """
    dtype = dtype or torch.get_default_dtype()
    theta = (torch.arange(height, dtype=torch.float64, device=device) + 0.5) * (math.pi / height)
    phi = -math.pi + (torch.arange(width, dtype=torch.float64, device=device) + 0.5) * (2.0 * math.pi / width)
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    d = torch.stack((st * torch.cos(phi)[None], st * torch.sin(phi)[None], ct.expand(height, width)), dim=-1)
    return d.to(dtype)


def latlong_row_solid_angles(
    height: int, width: int, *, dtype: torch.dtype | None = None, device: Device = None
) -> Tensor:
    """Exact solid angle of one texel per row, ``(2π / width)(cos θ_top - cos θ_bottom)``: ``(height,)``."""
    dtype = dtype or torch.get_default_dtype()
    edges = torch.arange(height + 1, dtype=torch.float64, device=device) * (math.pi / height)
    c = torch.cos(edges)
    return ((c[:-1] - c[1:]) * (2.0 * math.pi / width)).to(dtype)


def latlong_texel_index(d: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Row and column (int64, ``(*)``) of the texel containing direction ``d`` ``(*, 3)``.

    Texel ``(i, j)`` covers ``θ ∈ [iπ/H, (i+1)π/H)`` and ``φ ∈ [-π + 2πj/W, -π + 2π(j+1)/W)``;
    ``d`` need not be normalised.
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    theta = torch.atan2(torch.sqrt(x * x + y * y), z)
    phi = torch.atan2(y, x)
    row = torch.clamp(torch.floor(theta * (height / math.pi)), 0, height - 1).long()
    col = torch.floor((phi + math.pi) * (width / (2.0 * math.pi))).long()
    return row, torch.remainder(col, width)


class LatLongSampler:
    """Samples directions from a lat-long map in proportion to luminance × texel solid angle.

    The map is treated as piecewise constant over texels (the same convention
    :func:`torchbrdf.render.envmap.latlong_lookup` uses). A texel is chosen with probability
    ``p_ij ∝ lum_ij Ω_i`` (marginal over rows, then conditional over columns), and the
    direction is uniform in solid angle inside the texel (uniform ``φ``, uniform ``cos θ``), so
    the density is exactly ``p_ij / Ω_i``. A map with zero luminance everywhere falls back to
    uniform sphere sampling. The sampler holds no autograd history (densities are constants
    for the estimator; see :mod:`torchbrdf.render.envmap`).

    Args:
        radiance: ``(B, 3, H, W)`` or ``(3, H, W)`` linear radiance.

    Example:
        >>> s = LatLongSampler(torch.rand(3, 8, 16))
        >>> d, pdf = s.sample(torch.rand(5, 2))
        >>> d.shape, pdf.shape
        (torch.Size([5, 3]), torch.Size([5, 1]))
    """

    def __init__(self, radiance: Tensor) -> None:
        r = radiance.detach()
        if r.dim() == 3:
            r = r.unsqueeze(0)
        if r.dim() != 4 or r.shape[1] != 3:
            raise ValueError(
                f"radiance: expected shape [B, 3, H, W] or [3, H, W], got {list(radiance.shape)}"
            )
        b, _, h, w = r.shape
        self.batch, self.height, self.width = b, h, w
        dtype = r.dtype
        omega = latlong_row_solid_angles(h, w, dtype=torch.float64, device=r.device)  # (H,)
        c = r.to(torch.float64).abs()
        lum = 0.3 * c[:, 0] + 0.6 * c[:, 1] + 0.1 * c[:, 2]  # (B, H, W)
        weight = lum * omega[None, :, None]
        total = weight.sum(dim=(1, 2), keepdim=True)
        empty = total <= 0
        weight = torch.where(empty, omega[None, :, None].expand_as(weight), weight)
        lum = torch.where(empty, torch.ones_like(lum), lum)
        total = weight.sum(dim=(1, 2), keepdim=True)
        # Densities per texel: p_ij / Ω_i = lum_ij / Σ lum Ω.
        self.texel_pdf = (lum / total).to(dtype)  # (B, H, W)
        rows = weight.sum(dim=2)  # (B, H)
        self.row_cdf = self._cdf(rows)  # (B, H + 1), float64
        self.col_cdf = self._cdf(weight)  # (B, H, W + 1)
        edges = torch.arange(h + 1, dtype=torch.float64, device=r.device) * (math.pi / h)
        self.cos_edges = torch.cos(edges)  # (H + 1,)
        self.dtype = dtype

    @staticmethod
    def _cdf(weight: Tensor) -> Tensor:
        c = torch.cumsum(weight, dim=-1)
        tot = c[..., -1:]
        c = torch.where(tot > 0, c / torch.where(tot > 0, tot, torch.ones_like(tot)), torch.zeros_like(c))
        c[..., -1] = torch.where(tot[..., 0] > 0, 1.0, 0.0)
        return torch.cat((torch.zeros_like(c[..., :1]), c), dim=-1)

    def _batch_ids(self, batch_index, shape, device):
        if self.batch == 1:
            return None
        if batch_index is None:
            raise ValueError(f"batch_index is required for a sampler over {self.batch} maps")
        return torch.as_tensor(batch_index, device=device).long().expand(shape)

    def sample(self, u: Tensor, batch_index: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Directions and their solid-angle densities.

        Args:
            u: ``(*, 2)`` uniform numbers in ``[0, 1)``.
            batch_index: int64 ``(*)`` (broadcastable) map index per sample; required
                when the sampler holds more than one map.

        Returns:
            ``(d, pdf)``: unit world directions ``(*, 3)`` and densities ``(*, 1)``, in
            ``u``'s dtype.
        """
        shape = u.shape[:-1]
        u64 = u.detach().to(torch.float64)
        bid = self._batch_ids(batch_index, shape, u.device)
        if bid is None:
            bid = torch.zeros(shape, dtype=torch.long, device=u.device)
        u1, u2 = u64[..., 0], u64[..., 1]
        row = torch.empty(shape, dtype=torch.long, device=u.device)
        col = torch.empty(shape, dtype=torch.long, device=u.device)
        r1 = torch.empty_like(u1)
        r2 = torch.empty_like(u2)
        for b in range(self.batch):
            sel = bid == b if self.batch > 1 else torch.ones(shape, dtype=torch.bool, device=u.device)
            if self.batch > 1 and not bool(sel.any()):
                continue
            cdf = self.row_cdf[b]
            x1 = u1[sel]
            i = torch.clamp(torch.searchsorted(cdf[1:].contiguous(), x1, right=True), 0, self.height - 1)
            lo, hi = cdf[i], cdf[i + 1]
            r1[sel] = torch.clamp((x1 - lo) / torch.clamp(hi - lo, min=1e-300), 0.0, 1.0)
            ccdf = self.col_cdf[b][i]  # (N, W + 1)
            x2 = u2[sel]
            j = torch.searchsorted(ccdf[:, 1:].contiguous(), x2[:, None], right=True)[:, 0]
            j = torch.clamp(j, 0, self.width - 1)
            lo2 = torch.gather(ccdf, 1, j[:, None])[:, 0]
            hi2 = torch.gather(ccdf, 1, (j + 1)[:, None])[:, 0]
            r2[sel] = torch.clamp((x2 - lo2) / torch.clamp(hi2 - lo2, min=1e-300), 0.0, 1.0)
            row[sel] = i
            col[sel] = j
        ct = self.cos_edges[row] + r1 * (self.cos_edges[row + 1] - self.cos_edges[row])
        st = torch.sqrt(torch.clamp(1.0 - ct * ct, min=0.0))
        phi = -math.pi + (col.to(torch.float64) + r2) * (2.0 * math.pi / self.width)
        d = torch.stack((st * torch.cos(phi), st * torch.sin(phi), ct), dim=-1).to(u.dtype)
        pdf = self.texel_pdf[bid, row, col].to(u.dtype).unsqueeze(-1)
        return d, pdf

    def pdf(self, d: Tensor, batch_index: Tensor | None = None) -> Tensor:
        """Solid-angle density of directions ``d`` ``(*, 3)`` (unit or not), ``(*, 1)``."""
        shape = d.shape[:-1]
        bid = self._batch_ids(batch_index, shape, d.device)
        row, col = latlong_texel_index(d.detach(), self.height, self.width)
        if bid is None:
            p = self.texel_pdf[0][row, col]
        else:
            p = self.texel_pdf[bid, row, col]
        return p.to(d.dtype).unsqueeze(-1)
