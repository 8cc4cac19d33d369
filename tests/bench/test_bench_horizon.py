"""``python -m torchbrdf.bench.horizon``: the sky with a soft horizon and the split sum's error on it."""

import math

import pytest
import torch

from torchbrdf.bench import horizon


def test_horizon_sky_blends_sky_over_ground_across_the_band():
    sky = horizon.horizon_sky(90, sun=None)  # rows of 2° of polar angle
    assert sky.shape == (3, 90, 180)
    elevation = 90.0 - (torch.arange(90, dtype=torch.float64) + 0.5) * 2.0
    top, bottom = sky[:, elevation > 5.0], sky[:, elevation < -5.0]
    assert torch.allclose(top, top[:, :1].expand_as(top)) and torch.allclose(bottom, bottom[:, :1].expand_as(bottom))
    assert torch.allclose(top[:, 0, 0], torch.tensor([0.6, 0.75, 1.0], dtype=torch.float64))
    assert torch.allclose(bottom[:, 0, 0], torch.tensor([0.12, 0.1, 0.08], dtype=torch.float64))
    band = sky[2, (elevation.abs() < 5.0)][:, 0]  # inside the band: strictly between, rising with elevation
    assert len(band) == 4 and (band > 0.08).all() and (band < 1.0).all() and (band.diff() < 0).all()


def test_horizon_sky_sun_is_where_asked():
    sky = horizon.horizon_sky(90, sun=(35.0, 0.6), sun_radius=3.0)
    row, col = divmod(int(sky[0].argmax()), 180)
    theta = (row + 0.5) * 2.0
    phi = math.degrees(-math.pi + (col + 0.5) * 2 * math.pi / 180)
    assert abs((90 - theta) - 35.0) < 3.0 and abs(phi - math.degrees(0.6)) < 4.0
    assert float(sky.max()) > 1000.0


def test_horizon_errors_rows():
    rows = horizon.horizon_errors(lambda s: None, side=6, height=16, samples=64, roughness=(0.5,))
    assert len(rows) == len(horizon.SUNS)
    for r in rows:
        assert r["rel_l1"] >= abs(r["bias"]) and r["reference_l1"] > 0
    assert horizon.horizon_table(rows).count("\n") == len(rows) + 1


@pytest.mark.parametrize("argv", [["--side", "0"], ["--samples", "x"]])
def test_main_refuses_bad_arguments(argv):
    with pytest.raises(SystemExit):
        horizon.main(argv)
