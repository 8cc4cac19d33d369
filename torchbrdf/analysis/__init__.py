"""BRDF-Explorer-style analysis: albedo, furnace tests, reciprocity, slices, plots, reports.

``measures`` (directional albedo by quadrature or Monte Carlo, white and weak white furnace,
reciprocity, retro-reflection / peak / albedo curves, lit spheres), ``slices`` (Burley's
(θh, θd) image slices), ``plots`` (matplotlib figures with labelled axes) and ``explore``
(``python -m torchbrdf.analysis.explore`` / ``torchbrdf-explore``: a side-by-side HTML
report of several BRDFs).

May import: ``torchbrdf.brdf``, ``torchbrdf.render``, ``torchbrdf.io`` and the plumbing.
Never ``capture`` or ``recovery``.
"""

from torchbrdf.analysis.measures import *  # noqa: F401,F403  (the analysis API lives in measures)
from torchbrdf.analysis.measures import __all__  # noqa: F401
