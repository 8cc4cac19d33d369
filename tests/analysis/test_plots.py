"""Figures of torchbrdf.analysis.plots say what a reader cannot see: coinciding curves, pixels with no value."""

import math

import numpy as np
import pytest

import torchbrdf
from torchbrdf.analysis import bind_brdf
from torchbrdf.analysis import plots as P

pytest.importorskip("matplotlib")


def test_coincidence_note_names_pairs_and_their_range():
    x = np.linspace(0.0, 90.0, 91)
    a, b, c = np.ones_like(x), np.ones_like(x) * 1.01, np.ones_like(x) * 2.0
    d = np.where(x < 60, 1.0, 1.5)
    assert P._coincidence_note([("a", x, a), ("b", x, b)]) == "'a' and 'b' coincide within 3% everywhere"
    assert P._coincidence_note([("a", x, a), ("c", x, c)]) == ""
    assert P._coincidence_note([("a", x, a), ("d", x, d)]) == "'a' and 'd' coincide within 3% from 0° to 59°"
    short = np.where(x < 20, 1.0, 1.5)  # agreeing over less than half the range: no note
    assert P._coincidence_note([("a", x, a), ("s", x, short)]) == ""


def test_log_curves_legend_says_which_curves_coincide():
    f = bind_brdf(torchbrdf.principled, base_color=0.5, roughness=0.3)
    g = bind_brdf(torchbrdf.principled, base_color=0.9, roughness=0.8)
    fig = P.plot_specular_peaks([("one", f), ("same", f), ("other", g)])
    title = fig.axes[0].get_legend().get_title().get_text()
    assert "'one' and 'same' coincide" in title and "other" not in title


@pytest.mark.parametrize("phi_d, greyed", [(math.radians(45), True), (math.pi / 2, False)])
def test_image_slices_mark_directions_below_the_surface(phi_d, greyed):
    f = bind_brdf(torchbrdf.principled, base_color=0.0, roughness=0.5)  # black: no pixel is grey by value
    fig = P.plot_image_slices([("black", f)], 32, phi_d)
    img = fig.axes[0].get_images()[0].get_array()
    grey = np.all(np.isclose(np.asarray(img)[..., :3], P._HORIZON_GREY), axis=-1)
    below = P._below_horizon(32, phi_d)
    assert below.any() == greyed
    assert np.array_equal(grey, below)
    assert ("below the surface" in fig._suptitle.get_text()) == greyed
