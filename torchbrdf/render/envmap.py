"""Environment lighting: ``∫ f(l, v) L(l) max(n·l, 0) dω`` over a lat-long map.

The names of :mod:`torchbrdf.render.env` (one module per concept: ``latlong``, ``mc``,
``prefilter``, ``peaks``, ``split_sum``) under the one name they have always had.

The map follows the library's lat-long convention (z up; row ``i`` at ``θ = (i + 0.5) π / H``,
column ``j`` at ``φ = -π + (j + 0.5) 2π / W``) and is read as **piecewise constant over
texels**: ``L(l)`` is the texel containing ``l`` (:func:`latlong_lookup`). That defines the
integral exactly; :func:`integrate_environment_quadrature` evaluates it by brute force.

Two strategies, both differentiable:

**Monte Carlo** (:func:`integrate_environment_mc`, unbiased). Half of the samples come from
the BRDF — a per-pixel mixture of cosine sampling (diffuse, subsurface, sheen), GGX
visible-normal sampling (Heitz 2018; primary specular, anisotropic when the material is)
and GTR1 sampling (Burley 2012 appendix B; clearcoat), weighted by rough lobe albedos —
and half from the map (luminance × solid angle, :class:`~torchbrdf.render.sampling.LatLongSampler`);
they are combined with the power heuristic (Veach 1995). A constant map is not sampled (all
samples go to the BRDF), so a white furnace is exact for Lambert. Numbers are a stratified
Hammersley set rotated per pixel by a seeded offset. The sample directions, densities and
MIS weights are treated as constants by autograd ("detached sampling"): the gradient is then
an unbiased estimate of the gradient of the integral for every input (material, normal,
position, map). Error: zero mean, standard deviation falling as ``1/sqrt(samples)`` (about
1–3 % per pixel at 256 samples for a smooth map and a glossy principled material; see
``docs/shading.md``); highly peaked lobes (roughness < 0.1) under a high-frequency map are
the hardest case.

The ``sampling`` switch (:data:`ENV_SAMPLINGS`) picks the proposal; every choice is unbiased,
stratified and seeded the same way, only the variance differs:

* ``"mis"`` (default) — the BRDF + map mixture above;
* ``"brdf"`` — every sample from the BRDF mixture (weight ``1 / pdf``); noisy when a small
  bright source (a sun) sits inside a rough lobe;
* ``"map"`` — every sample from the map's luminance (over the whole sphere, so samples below
  the surface are wasted; a constant map is then sampled uniformly); noisy for glossy lobes;
* ``"uniform"`` — uniform over the hemisphere about ``n`` (``pdf = 1 / 2π``), no importance
  sampling at all: the baseline the others are measured against.

**Split sum** (:func:`integrate_environment_split_sum`, fast, biased). Karis 2013, with the
map's concentrated sources taken out first: texels brighter than :data:`PEAK_CONTRAST` × the
map's mean radiance (a sun, a lamp; at most :data:`PEAK_DIRECTIONS` cells of them) are summed
exactly as directional lights through the BRDF itself (:func:`extract_peaks`; a specular lobe
too sharp for those cells sums them over finer cells, and a mirror reads them texel by texel),
and only the smooth rest is prefiltered. The specular integral of the rest is split into a prefiltered map
(the map convolved with the GGX lobe under the ``n = v = r`` assumption, at
``len(PREFILTER_ROUGHNESS)`` levels), read along the lobe's centroid and blended between the
two levels whose kernels have the lobe's mean cosine (down to the hemisphere's mean, for lobes
broader than the cosine) — so the lobe's first moment is right,
and a map linear in ``l`` is exact — times a pre-integrated (n·v, roughness) table of the lobe
with Schlick Fresnel split into a scale on ``Cspec0`` and a bias. Diffuse, subsurface and
sheen use the cosine-convolved irradiance times their own tabulated directional albedo;
Burley's diffuse reads the irradiance along its lobe's centroid, tabulated beside its albedo
(the retro-reflection leans the lobe toward ``v`` at grazing view), blended toward a sharper
prefiltered level where its lobe is narrower than the cosine (its tabulated mean cosine, so
its first moment is right too); clearcoat uses a (n·v, clearcoat_gloss) table and the
prefiltered map at the matching width along the mirror direction bent toward ``n``. The table
is computed from :func:`torchbrdf.principled` itself at first use and cached. Every
prefiltered level and the irradiance map conserve the map's power exactly (area resampling
with solid-angle overlaps, then a symmetrically normalised convolution), for any map size.
Error: exact for a constant map (white furnace) and, up to the levels' discretisation, for a
map linear in ``l``; under a sky with a sun within about 0.1 % over a sphere for every lobe
(0.2–0.5 % L1); a bias of a few percent remains for large, moderately bright regions with
sharp edges (a window, a 20× patch: too wide to be a peak, too sharp for one symmetric
kernel), at grazing view, and for anisotropic materials (treated as isotropic with the same
mean width, except at the peaks) — see ``docs/shading.md``.
"""

from __future__ import annotations

# Every name below stays importable from here; __all__ lists the documented ones.
# ruff: noqa: F401

from torchbrdf.render.env.latlong import latlong_bilinear, latlong_lookup
from torchbrdf.render.env.mc import (
    ENV_SAMPLINGS,
    SAMPLING_LOBES,
    check_env_sampling,
    integrate_environment_mc,
    integrate_environment_quadrature,
    sampling_lobes_for,
)
from torchbrdf.render.env.params import brdf_kind
from torchbrdf.render.env.peaks import (
    PEAK_CELL_ROWS,
    PEAK_CONTRAST,
    PEAK_DIRECTIONS,
    PEAK_FINE_DIRECTIONS,
    extract_peaks,
)
from torchbrdf.render.env.prefilter import (
    IRRADIANCE_HEIGHT,
    PREFILTER_MAX_HEIGHT,
    PREFILTER_ROUGHNESS,
    UNIFORM,
    irradiance_environment,
    prefilter_environment,
)
from torchbrdf.render.env.split_sum import (
    SPLIT_SUM_RESOLUTION,
    SPLIT_SUM_SAMPLES,
    SPLIT_SUM_TABLE_CHANNELS,
    SplitSumEnvironment,
    integrate_environment_split_sum,
    split_sum_table,
)

__all__ = [
    "latlong_lookup",
    "latlong_bilinear",
    "integrate_environment_mc",
    "integrate_environment_quadrature",
    "integrate_environment_split_sum",
    "prefilter_environment",
    "irradiance_environment",
    "extract_peaks",
    "UNIFORM",
    "split_sum_table",
    "SplitSumEnvironment",
    "PREFILTER_ROUGHNESS",
    "SPLIT_SUM_TABLE_CHANNELS",
    "ENV_SAMPLINGS",
]
