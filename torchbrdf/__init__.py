"""torchbrdf: physically based reflectance for neural and inverse rendering, in PyTorch.

Conventions (fixed, see the README): direction vectors are channel-last ``(*, 3)``,
unit length, pointing away from the surface (``l`` to the light, ``v`` to the viewer, ``n``
the normal, ``x``/``y`` tangent and bitangent); material parameters are channel-last
(colours ``(*, 3)`` linear RGB, scalars ``(*, 1)``, floats allowed); images and maps are
``(B, C, H, W)`` linear values. Every function keeps the dtype and device it is given.
"""

# Architecture (each layer imports only from the ones above it):
#   _math, _checks, io   plumbing: gradient-safe helpers, argument checks, EXR/PNG
#   brdf/                the reflectance models and their microfacet pieces
#   kernels/             fused kernels generated from the brdf formulas (CPU C, Triton)
#   render/              g-buffers, lights, screen-space shading, environment integration
#   analysis/            albedo, furnace, reciprocity, slices, plots, the explore report
#   capture/             the multi-light capture format and the synthetic capture generator
#   recovery/            SVBRDF recovery and measured-BRDF fitting
#   bench/               benchmarks (python -m torchbrdf.bench)
import os as _os
import sys as _sys

# The recovery commands own their process, so they choose how OpenMP threads wait: a short
# poll, then sleep (docs/fast_path.md, "Threads"). libgomp reads this once, when torch loads it,
# which the first import below does; a console script or a script of the checkout's training/
# folder (run as a file or with python -m) gets here before anything else imports torch. A
# value the user set is kept, and an import in any other process leaves the environment alone.
_argv0 = getattr(_sys, "argv", [""])[0] or ""
_script = _os.path.basename(_argv0)
if ((_script.startswith("torchbrdf-recover")
     or (_os.path.basename(_os.path.dirname(_os.path.abspath(_argv0))) == "training"
         and _script in ("recover_svbrdf.py", "recover_many.py")))
        and "OMP_WAIT_POLICY" not in _os.environ and "GOMP_SPINCOUNT" not in _os.environ):
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    _os.environ["GOMP_SPINCOUNT"] = "2000"
del _argv0, _script

from torchbrdf import analysis, io
from torchbrdf.analysis import plots
from torchbrdf.brdf import diffuse, distributions, fresnel, masking, measured
from torchbrdf.render import envmap, sampling
from torchbrdf.analysis import (
    Estimate,
    albedo_curve,
    bind_brdf,
    directional_albedo,
    polar_lobe,
    reciprocity_error,
    render_sphere,
    retro_reflection_curve,
    specular_peak_curve,
    weak_white_furnace,
    white_furnace,
)
from torchbrdf._checks import set_validation, validation, validation_enabled
from torchbrdf.brdf.diffuse import diffuse_burley, diffuse_lambert, diffuse_oren_nayar, diffuse_subsurface
from torchbrdf.brdf.distributions import (
    ndf_abc,
    ndf_beckmann,
    ndf_beckmann_aniso,
    ndf_blinn_phong,
    ndf_ggx,
    ndf_ggx_aniso,
    ndf_gtr,
    ndf_gtr1,
    roughness_to_alpha,
)
from torchbrdf.brdf.frames import frame_from_normal, gram_schmidt
from torchbrdf.brdf.fresnel import (
    f0_from_ior,
    f0_from_specular,
    fresnel_conductor,
    fresnel_dielectric,
    fresnel_schlick,
    ior_from_f0,
    specular_from_f0,
)
from torchbrdf.brdf.masking import (
    g_cook_torrance,
    g_implicit,
    g_kelemen,
    smith_g1_beckmann,
    smith_g1_beckmann_walter,
    smith_g1_ggx,
    smith_g1_ggx_aniso,
    smith_g2_ggx_correlated,
    smith_g2_height_correlated,
    smith_g2_separable,
    smith_lambda_beckmann,
    smith_lambda_ggx,
)
from torchbrdf.io import read_exr, to_display, write_exr, write_png
from torchbrdf.brdf.measured import MERLBRDF, merl_coordinates, read_merl, write_merl
from torchbrdf.brdf.microfacet import MicrofacetBRDF, microfacet
from torchbrdf.brdf.svbrdf_ggx import SVBRDFGGX, svbrdf_ggx
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.geometry import pinhole_rays, plane_gbuffer, sphere_gbuffer
from torchbrdf.brdf.lambert import LambertBRDF, lambert
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, PointLight
from torchbrdf.render.shading import Shader, ShadingPlan, plan, shade
from torchbrdf.kernels.backend import get_backend, set_backend
from torchbrdf.brdf.principled import LOBES, PRINCIPLED_DEFAULTS, PrincipledBRDF, fast_path_enabled, principled, set_fast_path
from torchbrdf import data, losses
from torchbrdf.brdf.smits import SMITS_LOBES, SmitsBRDF, SmitsLayeredBRDF, smits, smits_composite, smits_layered, smits_lobes

__version__ = "0.1.0"

__all__ = [
    "principled",
    "PrincipledBRDF",
    "GBuffer",
    "shade",
    "plan",
    "Shader",
    "ShadingPlan",
    "PointLight",
    "DirectionalLight",
    "EnvironmentLight",
    "lambert",
    "LambertBRDF",
    "sphere_gbuffer",
    "plane_gbuffer",
    "pinhole_rays",
    "sampling",
    "envmap",
    "PRINCIPLED_DEFAULTS",
    "LOBES",
    "set_fast_path",
    "set_backend",
    "get_backend",
    "fast_path_enabled",
    "microfacet",
    "MicrofacetBRDF",
    "smits",
    "SmitsBRDF",
    "SMITS_LOBES",
    "smits_lobes",
    "smits_composite",
    "smits_layered",
    "SmitsLayeredBRDF",
    "svbrdf_ggx",
    "SVBRDFGGX",
    "set_validation",
    "validation",
    "validation_enabled",
    "frame_from_normal",
    "gram_schmidt",
    "fresnel_schlick",
    "fresnel_dielectric",
    "fresnel_conductor",
    "f0_from_ior",
    "ior_from_f0",
    "f0_from_specular",
    "specular_from_f0",
    "roughness_to_alpha",
    "ndf_ggx",
    "ndf_ggx_aniso",
    "ndf_gtr",
    "ndf_gtr1",
    "ndf_beckmann",
    "ndf_beckmann_aniso",
    "ndf_blinn_phong",
    "ndf_abc",
    "smith_g1_ggx",
    "smith_g1_ggx_aniso",
    "smith_lambda_ggx",
    "smith_g1_beckmann",
    "smith_g1_beckmann_walter",
    "smith_lambda_beckmann",
    "smith_g2_separable",
    "smith_g2_height_correlated",
    "smith_g2_ggx_correlated",
    "g_cook_torrance",
    "g_kelemen",
    "g_implicit",
    "diffuse_lambert",
    "diffuse_burley",
    "diffuse_subsurface",
    "diffuse_oren_nayar",
    "read_exr",
    "write_exr",
    "write_png",
    "to_display",
    "MERLBRDF",
    "read_merl",
    "write_merl",
    "merl_coordinates",
    "io",
    "measured",
    "analysis",
    "plots",
    "Estimate",
    "albedo_curve",
    "bind_brdf",
    "directional_albedo",
    "polar_lobe",
    "reciprocity_error",
    "render_sphere",
    "retro_reflection_curve",
    "specular_peak_curve",
    "weak_white_furnace",
    "white_furnace",
    "diffuse",
    "distributions",
    "fresnel",
    "masking",
]
