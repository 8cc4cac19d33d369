"""Datasets for torchbrdf: multi-light captures on disk (contract §3) and their loaders."""

from .capture import CAPTURE_JSON, Capture, load_capture, pixel_points, write_capture

__all__ = ["CAPTURE_JSON", "Capture", "load_capture", "pixel_points", "write_capture"]
