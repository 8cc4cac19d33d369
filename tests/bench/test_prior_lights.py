"""bench.prior_lights: its captures are the panel's materials under 1 to N lights (the flash last)."""

import pytest
import torch

from torchbrdf.bench.prior_lights import case_model, render_lights_case
from torchbrdf.bench.recovery_panel import panel_cases
from torchbrdf.capture.format import load_capture
from torchbrdf.capture.synthetic import DEFAULT_CAMERA


def test_cases_take_the_panels_model_and_calibration():
    for c in panel_cases("all"):
        assert case_model(c.family, c.seed) == (c.model, c.calibration_error)


@pytest.mark.parametrize("lights", [1, 4])
def test_capture_has_the_light_count_with_the_flash(tmp_path, lights):
    truth = render_lights_case("rubber", 2, lights, tmp_path, size=16)
    cap = load_capture(tmp_path)
    assert len(cap) == lights and truth["base_color"].shape == (3, 16, 16)
    near = (cap.light_positions[-1] - torch.tensor(DEFAULT_CAMERA)).norm()
    assert near < 0.2  # the last light is the flash beside the camera
    with pytest.raises(ValueError, match="lights"):
        render_lights_case("rubber", 2, 0, tmp_path / "none", size=16)
