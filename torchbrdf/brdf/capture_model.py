"""Deprecated name of :mod:`torchbrdf.brdf.svbrdf_ggx` (the SVBRDF-capture GGX model).

Importing it warns once with a ``DeprecationWarning``; the names are the same objects.
"""

import warnings

from torchbrdf.brdf.svbrdf_ggx import ALPHA_MIN, ROUGHNESS_FLOOR_DESCHAINTRE, SVBRDFGGX, svbrdf_ggx

__all__ = ["SVBRDFGGX", "svbrdf_ggx", "ALPHA_MIN", "ROUGHNESS_FLOOR_DESCHAINTRE"]

warnings.warn("torchbrdf.brdf.capture_model is renamed torchbrdf.brdf.svbrdf_ggx", DeprecationWarning,
              stacklevel=2)
