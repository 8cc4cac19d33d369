"""Datasets for torchbrdf: multi-light captures on disk (contract §3) and their loaders."""

from .capture import CAPTURE_JSON, Capture, load_capture, pixel_points, write_capture

from .synthetic import RECIPES, default_capture, generate_capture, light_layout, make_material, random_lights, render_capture

__all__ = [
    "CAPTURE_JSON", "Capture", "load_capture", "pixel_points", "write_capture",
    "RECIPES", "default_capture", "generate_capture", "light_layout", "make_material", "random_lights", "render_capture",
]
