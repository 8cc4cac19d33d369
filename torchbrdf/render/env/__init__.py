"""Environment lighting over lat-long maps, one concept per module.

``latlong`` (map lookups and texel cells), ``params`` (material values and BRDF kinds for the
integrators), ``mc`` (Monte Carlo and the reference quadrature), ``prefilter`` (power-conserving
prefiltered levels and irradiance), ``peaks`` (concentrated sources as directional lights) and
``split_sum`` (the split-sum integrator). :mod:`torchbrdf.render.envmap` re-exports the public
names and documents the methods' error behaviour.

Imports run ``latlong``/``params`` -> ``mc``, ``prefilter``, ``peaks`` -> ``split_sum``.
"""

from torchbrdf.render.env.latlong import as_bhwc, latlong_bilinear, latlong_lookup
from torchbrdf.render.env.mc import (
    ENV_SAMPLINGS,
    MCSetup,
    check_env_sampling,
    integrate_environment_mc,
    integrate_environment_quadrature,
    mc_pass,
    sampling_lobes_for,
)
from torchbrdf.render.env.params import brdf_kind
from torchbrdf.render.env.peaks import extract_peaks
from torchbrdf.render.env.prefilter import PREFILTER_ROUGHNESS, irradiance_environment, prefilter_environment
from torchbrdf.render.env.split_sum import (
    SplitSumEnvironment,
    integrate_environment_split_sum,
    split_sum_table,
)

__all__ = [
    "as_bhwc",
    "latlong_bilinear",
    "latlong_lookup",
    "ENV_SAMPLINGS",
    "MCSetup",
    "check_env_sampling",
    "integrate_environment_mc",
    "integrate_environment_quadrature",
    "mc_pass",
    "sampling_lobes_for",
    "brdf_kind",
    "extract_peaks",
    "PREFILTER_ROUGHNESS",
    "irradiance_environment",
    "prefilter_environment",
    "SplitSumEnvironment",
    "integrate_environment_split_sum",
    "split_sum_table",
]
