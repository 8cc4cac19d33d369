"""The split-sum environment integrator (Karis 2013), with the map's peaks taken out first.

:class:`SplitSumEnvironment` holds a map's peaks, prefiltered levels and irradiance;
:func:`split_sum_table` the pre-integrated (n·v, roughness) table of the principled lobes;
:func:`integrate_environment_split_sum` combines them. The method and its error behaviour
are described in :mod:`torchbrdf.render.envmap`.
"""

from __future__ import annotations

import math
from typing import cast

import torch
from torch import Tensor

from torchbrdf._math import dot, lerp, luminance, safe_normalize
from torchbrdf._types import BRDF, Device, Scalar
from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS, PrincipledBRDF
from torchbrdf.render.env.latlong import (
    as_bhwc,
    direction_angles,
    directions_sum,
    latlong_bilinear,
    lookup_cl,
)
from torchbrdf.render.env.params import as_rgb, as_tensor_like, brdf_kind, with_sample_axes
from torchbrdf.render.env.peaks import (
    PEAK_CONTRAST,
    PEAK_DIRECTIONS,
    PEAK_ELEMENTS_PER_PASS,
    PEAK_FINE_DIRECTIONS,
    peak_cells,
    peak_subdivisions,
    select_peaks,
)
from torchbrdf.render.env.prefilter import (
    PREFILTER_ROUGHNESS,
    UNIFORM,
    irradiance_environment,
    kernel_mean_cosine,
    prefilter_environment,
)
from torchbrdf.render.sampling import (
    ALPHA_MIN,
    hammersley,
    pdf_ggx_reflection,
    pdf_gtr1,
    reflect,
    sample_cosine_hemisphere,
    sample_ggx_vndf,
    sample_gtr1,
)

__all__ = [
    "SPLIT_SUM_RESOLUTION",
    "SPLIT_SUM_SAMPLES",
    "SPLIT_SUM_TABLE_CHANNELS",
    "split_sum_table",
    "SplitSumEnvironment",
    "integrate_environment_split_sum",
]


#: (n·v, roughness) table: resolution per axis and quasi-random samples per cell.
SPLIT_SUM_RESOLUTION = 32
SPLIT_SUM_SAMPLES = 1024
SPLIT_SUM_TABLE_CHANNELS = (
    "specular_scale",
    "specular_bias",
    "diffuse",
    "subsurface",
    "sheen",
    "clearcoat",
    "diffuse_tilt",
    "diffuse_spread",
    "specular_scale_bend",
    "specular_scale_spread",
    "specular_bias_bend",
    "specular_bias_spread",
)


_TABLE_CACHE: dict = {}


def _compute_split_sum_table(res: int, samples: int) -> Tensor:
    """The (n·v, roughness) table in float64 on the CPU, ``(12, res, res)``; see :func:`split_sum_table`."""
    from torchbrdf.brdf.principled import principled

    dt = torch.float64
    nodes = torch.linspace(0.0, 1.0, res, dtype=dt)
    # The Hammersley points moved to the centres of their strata: left in the corners (i / N)
    # they integrate with an O(1/N) error, 0.2-0.4 % of the albedos at 256 samples, which a
    # white furnace showed as the split sum's bias.
    u = hammersley(0, samples, samples, dtype=dt) + 0.5 / samples  # (S, 2)
    table = torch.zeros(len(SPLIT_SUM_TABLE_CHANNELS), res, res, dtype=dt)
    rows = 8  # n·v nodes per batched evaluation: (rows, res, samples) points per call
    for i0 in range(0, res, rows):
        # Grazing floor: n·v = 0 is degenerate; the ceiling keeps the mirror angle non-zero.
        nv = torch.clamp(nodes[i0 : i0 + rows], min=1e-4, max=1.0 - 1e-4)
        m = nv.shape[0]
        shape = (m, res, samples)
        v = torch.stack((torch.sqrt(1.0 - nv * nv), torch.zeros_like(nv), nv), dim=-1)[
            :, None, None, :
        ].expand(*shape, 3)
        n = torch.tensor([0.0, 0.0, 1.0], dtype=dt).expand(*shape, 3)
        col = nodes[None, :, None, None].expand(*shape, 1)  # roughness (or gloss) per column
        uu = u.expand(*shape, 2)

        def f(l, **kw):
            kw.setdefault("base_color", 0.0)
            kw.setdefault("specular", 0.0)
            return principled(l, v, n, **kw)[..., 0:1]

        def mean(x):
            return x.mean(dim=(2, 3))

        # Specular: GGX visible-normal sampling, weight cos / pdf.
        alpha = torch.clamp(col * col, min=ALPHA_MIN)
        l = reflect(v, sample_ggx_vndf(v, alpha, alpha, uu))
        pdf = pdf_ggx_reflection(v, l, alpha, alpha)
        ok = pdf > 0
        wgt = torch.where(
            ok,
            torch.clamp(l[..., 2:3], min=0.0) / torch.where(ok, pdf, torch.ones_like(pdf)),
            torch.zeros_like(pdf),
        )
        f_bias = f(l, roughness=col)
        f_full = f(l, roughness=col, base_color=1.0, metallic=1.0)
        table[0, i0 : i0 + m] = mean((f_full - f_bias) * wgt)
        table[1, i0 : i0 + m] = mean(f_bias * wgt)
        # Each part's centroid (its angle from n, on the mirror side, -x) and spread (mean
        # cosine about the centroid): where and how wide the prefiltered map is read. The
        # Fresnel part leans further toward the mirror at grazing view. The angle is stored as a
        # fraction of the mirror direction's, smooth in n·v where the angle itself,
        # ∝ sqrt(1 - n·v), is not (interpolated linearly it would lag near n·v = 1).
        for c, part in ((8, f_full - f_bias), (10, f_bias)):
            fs = part * wgt
            mx, mz = mean(fs * l[..., 0:1]), mean(fs * l[..., 2:3])
            table[c, i0 : i0 + m] = torch.atan2(-mx, mz) / torch.acos(nv)[:, None]
            table[c + 1, i0 : i0 + m] = torch.hypot(mx, mz) / mean(fs)
        # Diffuse-like lobes: cosine sampling, weight π.
        l = sample_cosine_hemisphere(uu)
        f0 = f(l, roughness=col)
        fd = math.pi * (f(l, roughness=col, base_color=1.0) - f0)  # Burley's diffuse × cos / pdf
        table[2, i0 : i0 + m] = mean(fd)
        # Its lobe's centroid (x toward v, z along n): Burley's retro-reflection leans toward v.
        table[6, i0 : i0 + m] = mean(fd * l[..., 0:1]) / mean(fd * l[..., 2:3])
        # ... and its spread: the length of its first moment over its albedo, |∫ Fd cos l| / ∫ Fd cos.
        moment = torch.hypot(mean(fd * l[..., 0:1]), mean(fd * l[..., 2:3]))
        table[7, i0 : i0 + m] = moment / table[2, i0 : i0 + m]
        table[3, i0 : i0 + m] = mean(math.pi * (f(l, roughness=col, base_color=1.0, subsurface=1.0) - f0))
        table[4, i0 : i0 + m] = mean(math.pi * (f(l, roughness=col, sheen=1.0, sheen_tint=0.0) - f0))
        # Clearcoat over (n·v, gloss): GTR1 sampling.
        ac = torch.clamp(lerp(0.1, 0.001, col), min=ALPHA_MIN)
        h = sample_gtr1(ac, uu)
        l = reflect(v, h)
        lh = dot(l, h)
        pdf = torch.where(lh > 0, pdf_gtr1(h, ac) / (4.0 * torch.clamp(lh, min=1e-30)), torch.zeros_like(lh))
        ok = pdf > 0
        wgt = torch.where(
            ok,
            torch.clamp(l[..., 2:3], min=0.0) / torch.where(ok, pdf, torch.ones_like(pdf)),
            torch.zeros_like(pdf),
        )
        fc = f(l, roughness=0.5, clearcoat=1.0, clearcoat_gloss=col) - f(l, roughness=0.5)
        table[5, i0 : i0 + m] = mean(fc * wgt)
    return table


def split_sum_table(
    *,
    dtype: torch.dtype = torch.float32,
    device: Device = None,
    resolution: int = SPLIT_SUM_RESOLUTION,
    samples: int = SPLIT_SUM_SAMPLES,
) -> Tensor:
    """Pre-integrated directional albedos of the principled lobes, computed once and cached.

    Channels (:data:`SPLIT_SUM_TABLE_CHANNELS`), each over a ``resolution²`` grid of
    ``n·v ∈ [0, 1]`` (axis 1) × roughness ``∈ [0, 1]`` (axis 2; clearcoat_gloss for the
    clearcoat channel), with ``∫ · max(n·l, 0) dω`` of:

    0. ``specular_scale``: ``Ds Gs (1 - FH)`` (multiplies ``Cspec0``);
    1. ``specular_bias``: ``Ds Gs FH``;
    2. ``diffuse``: Burley's diffuse ``Fd / π``;
    3. ``subsurface``: the subsurface term ``ss / π``;
    4. ``sheen``: ``FH``;
    5. ``clearcoat``: ``0.25 Gr Fr Dr``;
    6. ``diffuse_tilt``: not an albedo but the direction of Burley's diffuse lobe,
       ``∫ Fd (l·t) cos dω / ∫ Fd (l·n) cos dω`` with ``t`` the tangent toward ``v`` (0 for a
       Lambertian lobe; > 0 where the retro-reflection leans the lobe toward the viewer). The
       split sum reads the irradiance along ``normalize(n + tilt · t)``, the lobe's centroid.
    7. ``diffuse_spread``: the mean cosine of Burley's diffuse lobe about that centroid,
       ``|∫ Fd cos l dω| / ∫ Fd cos dω`` (2/3 for a Lambertian lobe; more where the lobe is
       narrower than the cosine, as at roughness 0). See :meth:`SplitSumEnvironment.diffuse`.
    8. ``specular_scale_bend``: the angle between ``n`` and the centroid of the lobe of
       channel 0, ``Ds Gs (1 - FH) cos``, as a fraction of the mirror direction's angle
       ``acos(n·v)``: the centroid is ``n cos a - t sin a`` with ``a = bend · acos(n·v)``.
       Below 1: a rough lobe leans toward the normal, and at grazing view it is lifted above
       the horizon.
    9. ``specular_scale_spread``: that lobe's mean cosine about its centroid (1 for a mirror).
    10. ``specular_bias_bend``, 11. ``specular_bias_spread``: the same for the lobe of channel
        1, ``Ds Gs FH cos`` (closer to the mirror at grazing view). See
        :meth:`SplitSumEnvironment.specular_lobe`.

    Computed with :func:`torchbrdf.principled` itself (so the table follows the model
    exactly) using ``samples`` Hammersley samples per cell, centred in their strata, with the
    matching importance sampler (VNDF, cosine, GTR1) in float64, then cast: the albedos are
    the model's to about 1e-3 (tested against a brute-force quadrature).

    Returns:
        ``(12, resolution, resolution)`` in ``dtype`` on ``device``.
    """
    device = torch.device("cpu") if device is None else torch.device(device)
    key64 = (resolution, samples)
    if key64 not in _TABLE_CACHE:
        _TABLE_CACHE[key64] = _compute_split_sum_table(resolution, samples)
    key = (resolution, samples, dtype, str(device))
    if key not in _TABLE_CACHE:
        _TABLE_CACHE[key] = _TABLE_CACHE[key64].to(device=device, dtype=dtype)
    return _TABLE_CACHE[key]


def _table_lookup(table: Tensor, nv: Tensor, r: Tensor) -> Tensor:
    """Bilinear lookup of ``(C, N, N)`` at ``nv``, ``r`` (each ``(P, 1)``, clamped) -> ``(P, C)``."""
    c, res, _ = table.shape
    fy = torch.clamp(nv, 0.0, 1.0) * (res - 1)
    fx = torch.clamp(r, 0.0, 1.0) * (res - 1)
    y0 = torch.clamp(torch.floor(fy.detach()), 0, res - 2)
    x0 = torch.clamp(torch.floor(fx.detach()), 0, res - 2)
    ty, tx = fy - y0, fx - x0
    y0, x0 = y0.long()[..., 0], x0.long()[..., 0]
    flat = table.permute(1, 2, 0).reshape(res * res, c)
    v00 = flat[y0 * res + x0]
    v01 = flat[y0 * res + x0 + 1]
    v10 = flat[(y0 + 1) * res + x0]
    v11 = flat[(y0 + 1) * res + x0 + 1]
    top = v00 + (v01 - v00) * tx
    bot = v10 + (v11 - v10) * tx
    return top + (bot - top) * ty


class SplitSumEnvironment:
    """A map prepared for the split-sum approximation: irradiance + prefiltered levels.

    The map's peaks (texels brighter than ``peak_contrast`` × its mean radiance, e.g. a sun)
    are taken out first and summed exactly as directional lights (:func:`extract_peaks`);
    the irradiance and the prefiltered levels hold the rest.

    Args:
        radiance: ``(3, H, W)`` or ``(B, 3, H, W)`` lat-long map (gradients flow through).
        dtype: compute dtype (default the map's).
        peak_contrast: see :func:`extract_peaks`.
        peak_directions: most directional lights the peaks become; ``0`` prefilters the whole
            map (the plain split sum).
    """

    def __init__(
        self,
        radiance: Tensor,
        dtype: torch.dtype | None = None,
        *,
        peak_contrast: float = PEAK_CONTRAST,
        peak_directions: int = PEAK_DIRECTIONS,
    ) -> None:
        dtype = dtype or radiance.dtype
        img = radiance.to(dtype)
        img = img.unsqueeze(0) if img.dim() == 3 else img
        h = img.shape[-2]
        found = select_peaks(img, peak_contrast, peak_directions)
        s_coarse = peak_subdivisions(h)
        # The peaks' cells (radians: their rows' height), and the same texels in finer cells for
        # sharp lobes: up to 8× finer, at most PEAK_FINE_DIRECTIONS cells, and as a map (zero
        # elsewhere) for lobes sharper still.
        self.peak_cell = math.pi / (h * s_coarse)
        self.fine_cell = self.peak_cell
        self.peak_map: Tensor | None = None
        if found is None:
            rest = img
            self.peak_directions = self.peak_irradiance = img.new_zeros(img.shape[0], 0, 3)
            self.fine_directions = self.fine_irradiance = self.peak_directions
        else:
            rest, idx, valid = found
            self.peak_directions, self.peak_irradiance = peak_cells(img, idx, valid, s_coarse)
            s_fine = max(s_coarse, min(8 * s_coarse, math.isqrt(PEAK_FINE_DIRECTIONS // idx.shape[1])))
            self.fine_directions, self.fine_irradiance = peak_cells(img, idx, valid, s_fine)
            self.fine_cell = math.pi / (h * s_fine)
            self.peak_map = as_bhwc(img - rest)
        self.irradiance = as_bhwc(irradiance_environment(rest))
        self.levels = [as_bhwc(m) for m in prefilter_environment(rest)]
        # Broader than every level: the hemisphere's mean (32 rows: its kernel is smooth).
        self.broad = as_bhwc(irradiance_environment(rest, 32, UNIFORM))
        self.roughness = PREFILTER_ROUGHNESS
        self.batch = self.irradiance.shape[0]
        # The roughest level below 1: the lobe a diffuse lobe narrower than the cosine blends in.
        sharp = max(i for i, r in enumerate(self.roughness) if 0 < r < 1)
        self._sharp = self.levels[sharp]
        alpha_sharp = max(self.roughness[sharp] ** 2, ALPHA_MIN)
        # Mean cosine of each level's kernel (level 0, the map itself: 1), decreasing, then the
        # broad map's (1/2); and of the maps a diffuse lobe blends (that level, the cosine, broad).
        k_broad = kernel_mean_cosine(UNIFORM)
        self._level_kappa = [
            1.0 if r <= 0 else kernel_mean_cosine(max(r * r, ALPHA_MIN)) for r in self.roughness
        ] + [k_broad]
        self._diffuse_kappa = [kernel_mean_cosine(alpha_sharp), kernel_mean_cosine(None), k_broad]

    def specular(self, r_dir: Tensor, roughness: Scalar, batch_index: Tensor | None = None) -> Tensor:
        """Prefiltered radiance along ``r_dir`` ``(P, 3)`` at ``roughness`` (float or ``(P, 1)``)."""
        k = len(self.roughness) - 1
        if isinstance(roughness, Tensor):
            t = torch.clamp(roughness, 0.0, 1.0) * k
            acc: Tensor | float = 0.0
            for i, level in enumerate(self.levels):
                wi = torch.clamp(1.0 - (t - i).abs(), min=0.0)
                acc = acc + wi * latlong_bilinear(level, r_dir, batch_index)
            return cast(Tensor, acc)  # a tensor: there is always at least one level
        tf = min(max(float(roughness), 0.0), 1.0) * k
        i0 = min(int(math.floor(tf)), k - 1)
        a = tf - i0
        out = latlong_bilinear(self.levels[i0], r_dir, batch_index) * (1.0 - a)
        if a > 0:
            out = out + latlong_bilinear(self.levels[i0 + 1], r_dir, batch_index) * a
        return out

    def specular_lobe(self, direction: Tensor, spread: Tensor, batch_index: Tensor | None = None) -> Tensor:
        """Prefiltered radiance ``(P, 3)`` along ``direction`` ``(P, 3)``, at a lobe width.

        ``spread`` ``(P, 1)`` is the lobe's mean cosine about ``direction``.

        The two levels whose kernels' mean cosines bracket ``spread`` are blended linearly in
        the mean cosine (level 0, the map itself, counts as 1), so the blend has the lobe's
        mean cosine; read along the lobe's centroid, it has the lobe's first moment and is
        exact for a map linear in ``l``. Past the roughest level (the cosine lobe, 2/3) the blend
        continues toward the hemisphere's mean (:attr:`broad`, 1/2).
        """
        return _blend_by_mean_cosine(self.levels + [self.broad], self._level_kappa, spread, direction, batch_index)

    def sharpness(self, width: Tensor | float) -> tuple[Tensor | float, Tensor | float]:
        """How a lobe of angular width ``width`` (radians) sees the peaks: ``(w_fine, w_map)``.

        A cell is one direction, so a lobe not much wider than the cells falls between them.
        ``w_fine``: the share summed over the finer cells instead (1 for lobes narrower than
        4 cells, 0 for lobes wider than 6, linear between); ``w_map``: the share read from
        :attr:`peak_map` along the lobe instead (1 for lobes narrower than 2 fine cells, 0 for
        lobes wider than 4; exact as the lobe narrows to a mirror, where a texel is
        constant across it). ``w_map ≤ w_fine``.
        """
        if self.peak_map is None:
            return 0.0, 0.0

        def ramp(w):
            return torch.clamp(w, 0.0, 1.0) if isinstance(w, Tensor) else min(max(w, 0.0), 1.0)

        c, f = self.peak_cell, self.fine_cell
        return ramp((6.0 * c - width) / (2.0 * c)), ramp((4.0 * f - width) / (2.0 * f))

    def peaks(
        self,
        brdf: BRDF,
        n: Tensor,
        v: Tensor,
        material: dict,
        x: Tensor | None = None,
        y: Tensor | None = None,
        batch_index: Tensor | None = None,
        fine: bool = False,
    ) -> Tensor | float:
        """The peaks' exact contribution ``Σ f(l_k, v) E_k max(n·l_k, 0)``, ``(P, 3)``.

        ``0.0`` when the map has none. Arguments as in :func:`integrate_environment_split_sum`;
        ``fine``: over the finer cells.
        """
        if fine:
            dirs, irr = self.fine_directions, self.fine_irradiance
        else:
            dirs, irr = self.peak_directions, self.peak_irradiance
        count = dirs.shape[1]
        if count == 0:
            return 0.0
        n1, v1 = n.unsqueeze(1), v.unsqueeze(1)
        x1 = None if x is None else x.unsqueeze(1)
        y1 = None if y is None else y.unsqueeze(1)
        mat = {k: with_sample_axes(val, 1) for k, val in material.items()}
        per_pass = max(1, PEAK_ELEMENTS_PER_PASS // max(n.shape[0], 1))
        out: Tensor | float = 0.0
        for start in range(0, count, per_pass):
            d, e = dirs[:, start : start + per_pass], irr[:, start : start + per_pass]
            if batch_index is not None and self.batch > 1:
                d, e = d[batch_index], e[batch_index]
            ll = d.expand(n.shape[0], -1, -1)
            out = out + directions_sum(brdf, n1, v1, x1, y1, mat, ll, e)
        return out

    def diffuse(self, n: Tensor, batch_index: Tensor | None = None, spread: Tensor | None = None) -> Tensor:
        """Normalised irradiance ``∫ L max(n·l, 0) dω / π`` at normals ``(P, 3)`` -> ``(P, 3)``.

        With ``spread`` ``(P, 1)`` (a lobe's mean cosine about ``n``, 2/3 for the cosine lobe):
        for a lobe narrower than the cosine (``spread > 2/3``) the irradiance is blended with
        the roughest prefiltered level below 1 (mean cosine ``κ_s ≈ 0.73``), weight
        ``(spread - 2/3) / (κ_s - 2/3)`` clamped to [0, 1], so the blend has the lobe's mean
        cosine. A lobe centred on ``n`` with the right albedo and mean cosine has the right
        first moment: the split sum is then exact for a map linear in ``l`` (a sky gradient, or
        the far field of a small source), where the cosine lobe alone is off by the spread's
        difference. A lobe broader than the cosine (``spread < 2/3``) is blended toward the
        hemisphere's mean (:attr:`broad`, mean cosine 1/2) the same way.
        """
        if spread is None:
            return latlong_bilinear(self.irradiance, n, batch_index)
        maps = [self._sharp, self.irradiance, self.broad]
        return _blend_by_mean_cosine(maps, self._diffuse_kappa, spread, n, batch_index)


def _blend_by_mean_cosine(maps: list[Tensor], kappa: list[float], spread: Tensor, direction: Tensor,
                          batch_index: Tensor | None) -> Tensor:
    """Maps ``(B, h, w, 3)`` blended linearly in their kernels' mean cosines ``kappa``
    (decreasing) to a lobe's mean cosine ``spread`` ``(P, 1)``, read along ``direction``
    ``(P, 3)``: ``(P, 3)``. A spread outside ``kappa``'s range reads the nearest end's map."""
    s = torch.clamp(spread, min=kappa[-1], max=kappa[0])
    angles = direction_angles(direction)
    acc = torch.zeros_like(direction)
    for i, m in enumerate(maps):
        # Hat function in κ: 1 at κ_i, 0 at the neighbouring maps' κ (flat past either end).
        up = (s - kappa[i + 1]) / (kappa[i] - kappa[i + 1]) if i + 1 < len(kappa) else None
        down = (kappa[i - 1] - s) / (kappa[i - 1] - kappa[i]) if i > 0 else None
        hat = down if up is None else up if down is None else torch.minimum(up, down)
        wi = torch.clamp(cast(Tensor, hat), 0.0, 1.0)
        if _may_be_nonzero(wi):  # (a material's roughness range reads two or three maps)
            acc = acc + wi * latlong_bilinear(m, direction, batch_index, angles=angles)
    return acc


def _dominant_direction(n: Tensor, r_dir: Tensor, alpha) -> Tensor:
    """Lookup direction of the prefiltered map: the mirror direction bent toward ``n``.

    A rough lobe's energy is centred between the mirror direction and the normal, the more
    so the rougher it is (the ``n = v = r`` prefilter ignores this). The blend factor
    ``s (sqrt(s) + α)`` with ``s = 1 - α`` is the fit of Lagarde & de Rousiers, "Moving
    Frostbite to PBR" (2014), §4.9.3; on a sphere under smooth and noisy maps it cuts the
    split sum's median error against quadrature by 2–7× for roughness ≥ 0.5.
    """
    s = 1.0 - alpha
    if isinstance(s, Tensor):
        s = torch.clamp(s, min=0.0)
        f = s * (torch.sqrt(s) + alpha)
    else:
        s = max(s, 0.0)
        f = s * (math.sqrt(s) + alpha)
    return safe_normalize(n + (r_dir - n) * f)


def integrate_environment_split_sum(
    brdf: BRDF,
    n: Tensor,
    v: Tensor,
    env: SplitSumEnvironment,
    material: dict,
    *,
    x: Tensor | None = None,
    y: Tensor | None = None,
    batch_index: Tensor | None = None,
) -> Tensor:
    """Split-sum approximation of the environment integral at ``P`` points.

    Supports :func:`torchbrdf.principled` / :class:`~torchbrdf.PrincipledBRDF` (respecting
    its ``lobes``) and the Lambert BRDF; anisotropy is approximated by the isotropic lobe
    of the same mean width ``roughness²``. The map's peaks (:func:`extract_peaks`) are added
    exactly, with ``brdf`` itself (anisotropy included).

    Args:
        brdf: the BRDF (its kind selects the formula; see :func:`brdf_kind`).
        n: ``(P, 3)`` unit normals.
        v: ``(P, 3)`` unit view directions.
        env: a :class:`SplitSumEnvironment`.
        material: name -> float, 0-d tensor or ``(P, C)`` tensor.
        x: optional ``(P, 3)`` tangents (for the peaks of an anisotropic material).
        y: optional ``(P, 3)`` bitangents.
        batch_index: int64 ``(P,)`` when the map is batched.

    Returns:
        ``(P, 3)``.
    """
    kind = brdf_kind(brdf)
    base = as_rgb(material.get("base_color", 1.0), n)
    if kind not in ("principled", "lambert"):
        raise ValueError(
            f"env_strategy='split_sum' supports the principled and Lambert BRDFs, not {brdf!r}; "
            "use env_strategy='mc'"
        )
    peaks = env.peaks(brdf, n, v, material, x, y, batch_index)
    if kind == "lambert":
        return env.diffuse(n, batch_index) * base + peaks
    from torchbrdf.brdf.principled import active_lobes

    lobes = active_lobes(material, getattr(brdf, "lobes", None))
    p = {k: material.get(k, d) for k, d in PRINCIPLED_DEFAULTS.items()}
    metal, rough = p["metallic"], p["roughness"]
    nv = torch.clamp(dot(n, v), 0.0, 1.0)
    r_t = as_tensor_like(rough, n) * torch.ones_like(nv)
    table = split_sum_table(dtype=n.dtype, device=n.device)
    tab = _table_lookup(table, nv, r_t)
    lum = luminance(base)
    positive = lum > 0
    ctint = torch.where(
        positive, base / torch.where(positive, lum, torch.ones_like(lum)), torch.ones_like(base)
    )
    out = torch.zeros_like(n) + peaks
    dielectric = 1.0 - metal
    if "diffuse" in lobes:
        # Irradiance along the centroid of Burley's lobe, which leans toward v at grazing view
        # (irradiance along n alone misses the retro-reflection there).
        t_dir = safe_normalize(v - nv * n)
        d_dir = safe_normalize(n + tab[:, 6:7] * t_dir)
        w_d = dielectric * (1.0 - p["subsurface"]) * tab[:, 2:3]
        # ... and blended toward a sharper level where the lobe is narrower than the cosine.
        out = out + env.diffuse(d_dir, batch_index, spread=tab[:, 7:8]) * base * w_d
    if "subsurface" in lobes:
        out = out + env.diffuse(n, batch_index) * base * (dielectric * p["subsurface"] * tab[:, 3:4])
    if "sheen" in lobes:
        csheen = lerp(1.0, ctint, p["sheen_tint"])
        out = out + env.diffuse(n, batch_index) * csheen * (dielectric * p["sheen"] * tab[:, 4:5])
    r_dir = reflect(v, n)
    if "specular" in lobes:
        cspec0 = lerp(0.08 * p["specular"] * lerp(1.0, ctint, p["specular_tint"]), base, metal)
        # Each part of the lobe (scale on Cspec0, Fresnel bias) read along its centroid, at its
        # width: its first moment is then right (exact for a map linear in l). The centroid is
        # at a = bend·θ from n toward the mirror side (θ = acos(n·v), kept below 1 - 1e-6 in
        # n·v: acos' is infinite at 1); v - (n·v) n has length sin θ.
        theta = torch.acos(torch.clamp(nv, max=1.0 - 1e-6))
        off_n = (v - nv * n) / torch.sin(theta)
        # A lobe too sharp for the peaks' cells sees them through finer cells, and sharper
        # still through the peak map (SplitSumEnvironment.sharpness).
        w_fine, w_map = env.sharpness(torch.sqrt(2.0 * torch.clamp(1.0 - tab[:, 9:10], min=0.0)))
        for c, weight in ((8, cspec0 * tab[:, 0:1]), (10, tab[:, 1:2])):
            angle = tab[:, c : c + 1] * theta
            look = safe_normalize(n * torch.cos(angle) - off_n * torch.sin(angle))
            out = out + env.specular_lobe(look, tab[:, c + 1 : c + 2], batch_index) * weight
            if _may_be_nonzero(w_map):  # (texel-constant: a mirror sees one texel)
                out = out + w_map * lookup_cl(cast(Tensor, env.peak_map), look, batch_index) * weight
        if _may_be_nonzero(w_fine):
            out = out + _sharp_peaks(env, w_fine, w_map, n, v, material, x, y, batch_index)
    if "clearcoat" in lobes:
        gloss = p["clearcoat_gloss"]
        g_t = as_tensor_like(gloss, n) * torch.ones_like(nv)
        e_cc = _table_lookup(table[5:6], nv, g_t)
        ac = lerp(0.1, 0.001, gloss)
        ac = torch.clamp(ac, min=ALPHA_MIN) if isinstance(ac, Tensor) else max(ac, ALPHA_MIN)
        r_cc = torch.sqrt(ac) if isinstance(ac, Tensor) else math.sqrt(ac)
        look = _dominant_direction(n, r_dir, ac)
        # (No swap for the peaks here: GTR1's tails hold most of its energy, and the cells
        # resolve them; at gloss 1 the cells are −4 % off over a sphere, the peak map −17 %.)
        out = out + env.specular(look, r_cc, batch_index) * (p["clearcoat"] * e_cc)
    return out


#: The principled specular lobe on its own (the peaks it cannot resolve are swapped).
_SPECULAR_ONLY = PrincipledBRDF(lobes=("specular",))


def _sharp_peaks(env: SplitSumEnvironment, w_fine: Tensor | float, w_map: Tensor | float, n: Tensor,
                 v: Tensor, material: dict, x: Tensor | None, y: Tensor | None,
                 batch_index: Tensor | None) -> Tensor:
    """The specular lobe's response to the peaks moved between cells, ``(P, 3)``.

    From the cells to the fine cells (share ``w_fine``) and from those to the peak map (share
    ``w_map``, added by the caller): ``(w_fine - w_map) F - w_fine C`` with ``F`` / ``C`` the
    sums over the fine / coarse cells. On the CPU only at the points where ``w_fine``
    ``(P, 1)`` is non-zero (roughness ≲ 0.2); elsewhere at every point (no host sync).
    """

    def shift(n, v, mat, x, y, bi, wf, wm):
        fine = env.peaks(_SPECULAR_ONLY, n, v, mat, x, y, bi, fine=True)
        coarse = env.peaks(_SPECULAR_ONLY, n, v, mat, x, y, bi)
        return (wf - wm) * fine - wf * coarse + torch.zeros_like(n)

    if (not isinstance(w_fine, Tensor) or w_fine.device.type != "cpu" or n.shape[0] < 2
            or torch.compiler.is_compiling()):
        return shift(n, v, material, x, y, batch_index, w_fine, w_map)
    idx = w_fine[:, 0].nonzero()[:, 0]
    count = n.shape[0]

    def sub(t):
        return t[idx] if isinstance(t, Tensor) and t.dim() >= 1 and t.shape[0] == count else t

    part = shift(n[idx], v[idx], {k: sub(t) for k, t in material.items()}, sub(x), sub(y), sub(batch_index),
                 w_fine[idx], sub(w_map))
    return torch.zeros_like(n).index_add(0, idx, part)


def _may_be_nonzero(w: Tensor | float) -> bool:
    """Whether a weight may be non-zero anywhere.

    True without looking on an accelerator (a host sync) and under ``torch.compile`` (a graph
    break).
    """
    if isinstance(w, Tensor):
        return w.device.type != "cpu" or torch.compiler.is_compiling() or bool((w != 0).any())
    return w != 0
