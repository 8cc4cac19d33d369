"""Multi-light captures: the on-disk format and the synthetic capture generator.

``format`` loads and writes a capture folder (``capture.json`` + one linear EXR per light;
see ``docs/capture_format.md``) with clear errors for bad input; ``synthetic`` makes
procedural materials and renders them into captures with ground-truth maps; ``families``
adds ten material families (cloth, plaster, ... patinated copper) in the same layout.

May import: ``torchbrdf.brdf``, ``torchbrdf.render``, ``torchbrdf.io`` and the plumbing.
Never ``recovery``.
"""

from torchbrdf.capture.format import CAPTURE_JSON, Capture, load_capture, pixel_points, write_capture
from torchbrdf.capture.synthetic import (
    RECIPES,
    SOFT_RECIPES,
    default_capture,
    generate_capture,
    light_layout,
    make_material,
    random_lights,
    render_capture,
)

__all__ = [
    "CAPTURE_JSON", "Capture", "load_capture", "pixel_points", "write_capture",
    "RECIPES", "SOFT_RECIPES", "default_capture", "generate_capture", "light_layout", "make_material", "random_lights",
    "render_capture",
]
