"""Evidence decides the class: a likelihood-ratio threshold at the measured noise, an MRF over
the neighbours, and the false-metal rate under noise alone."""

import pytest
import torch

from torchbrdf.bench.false_metal import false_metal_rate
from torchbrdf.recovery import classes
from torchbrdf.recovery.params import N_PARAMS

RATE = 1e-4
N_RES = 36


def test_the_threshold_is_the_chi2_quantile_of_the_extra_unknowns():
    # Reference values: scipy.stats.chi2.ppf(1 - 1e-4, 7) and (1 - 1e-4, 1).
    assert classes.evidence_threshold(7, RATE) == pytest.approx(29.8775, rel=1e-4)
    assert classes.evidence_threshold(1, RATE) == pytest.approx(15.1367, rel=1e-4)
    # A rarer false positive asks for more evidence.
    assert classes.evidence_threshold(7, 1e-6) > classes.evidence_threshold(7, RATE)


def test_a_threshold_is_computed_once_per_unknowns_and_rate(monkeypatch):
    """Each propagation pass asks for the class test's threshold: a ``(dof, p)`` quantile is
    bisected once and then remembered (the same float), and bad arguments still raise."""
    calls = []
    gammainc = torch.special.gammainc

    def counted(*args):
        calls.append(1)
        return gammainc(*args)

    monkeypatch.setattr(torch.special, "gammainc", counted)
    classes.chi2_quantile.cache_clear()
    first = classes.evidence_threshold(7, 3e-3)
    bisected = len(calls)
    assert bisected > 10 and classes.evidence_threshold(7, 3e-3) == first and len(calls) == bisected
    with pytest.raises(ValueError, match="dof > 0"):
        classes.chi2_quantile(0, 0.5)


def test_double_the_noise_deviation_needs_four_times_the_cost_drop():
    """A pixel whose metal fit is better by a drop between τσ² and 4τσ² is metal at σ and
    not at 2σ: the richer class needs four times the cost drop at twice the noise."""
    tau = classes.evidence_threshold(N_PARAMS, RATE)
    size, sigma2, n_res = 5, 1e-4, 100
    diel = torch.full((size * size, 1), n_res * sigma2)  # every pixel at the noise level ...
    drop = 1.5 * tau * sigma2  # ... one pixel's metal fits better by 1.5τσ²
    metal = diel.clone()
    metal[12] -= drop
    at_sigma = classes.choose_class(diel, metal, size, sigma2, n_res, RATE)
    metal2 = 4 * diel
    metal2[12] -= drop
    at_2sigma = classes.choose_class(4 * diel, metal2, size, 4 * sigma2, n_res, RATE)
    assert float(at_sigma[12]) == 1.0 and float(at_2sigma[12]) == 0.0
    # At 2σ, four times the drop buys the metal again.
    metal2[12] = 4 * diel[12] - 4 * drop
    assert float(classes.choose_class(4 * diel, metal2, size, 4 * sigma2, n_res, RATE)[12]) == 1.0


def test_a_misfit_larger_than_the_noise_scales_the_evidence():
    """Where both fits are far above the noise (a model the capture does not follow), a cost
    difference of the same size is no evidence: the pixel's own residual sets its variance."""
    size, sigma2 = 5, 1e-4
    diel = torch.full((size * size, 1), N_RES * sigma2)
    metal = diel * 2
    diel[12], metal[12] = 1000 * N_RES * sigma2, 900 * N_RES * sigma2  # 10 % better, 900× the noise
    assert float(classes.choose_class(diel, metal, size, sigma2, N_RES, RATE)[12]) == 0.0


def test_the_mrf_keeps_a_coherent_region_and_judges_an_isolated_flip_by_its_evidence():
    tau = classes.evidence_threshold(N_PARAMS, RATE)
    size, sigma2 = 9, 1e-4
    base = N_RES * sigma2
    diel = torch.full((size, size), base)
    metal = torch.full((size, size), base + 3 * tau * sigma2)  # decisively dielectric ...
    metal[:, :4] = base - 3 * tau * sigma2  # ... the left part decisively metal
    metal[2:7, 1:3] = base + 0.2 * tau * sigma2  # a coherent metal region's weak interior
    metal[4, 6] = base - 0.8 * tau * sigma2  # an isolated flip without enough evidence
    metal[1, 7] = base - 1.5 * tau * sigma2  # an isolated flip with strong evidence
    label = classes.choose_class(diel.reshape(-1, 1), metal.reshape(-1, 1), size, sigma2, N_RES, RATE)
    label = label.view(size, size)
    assert torch.equal(label[:, :4], torch.ones(size, 4))  # the region is kept whole
    assert float(label[4, 6]) == 0.0  # the weak flip follows its neighbours
    assert float(label[1, 7]) == 1.0  # the strong one stands
    assert float(label.sum()) == size * 4 + 1


def test_a_weak_pixel_follows_a_half_metal_neighbourhood_but_not_a_dielectric_one():
    """The Potts term weighs the neighbours: evidence 0.3τ wins beside 5 metal neighbours of 8,
    not beside none."""
    tau = classes.evidence_threshold(N_PARAMS, RATE)
    size, sigma2 = 7, 1e-4
    base = N_RES * sigma2
    diel = torch.full((size, size), base)
    metal = torch.full((size, size), base + 3 * tau * sigma2)
    metal[3, 3] = metal[0, 5] = base - 0.3 * tau * sigma2
    metal[2:5, 2] = metal[2, 3] = metal[4, 3] = base - 3 * tau * sigma2  # 5 decisive metal beside (3, 3)
    label = classes.choose_class(diel.reshape(-1, 1), metal.reshape(-1, 1), size, sigma2, N_RES, RATE)
    label = label.view(size, size)
    assert float(label[3, 3]) == 1.0 and float(label[0, 5]) == 0.0


def test_noise_alone_calls_no_dielectric_pixel_metal():
    """Rendered dielectric captures (two families, 1 % noise, both forward models) recovered
    with the defaults: at most the stated rate, 1e-4 of the pixels (here none of 2 × 24²)."""
    out = false_metal_rate(("cloth", "plaster"), seeds=(10,), size=24, lights=12)
    assert out["pixels"] == 2 * 24 * 24
    assert out["false_metal"] <= RATE * out["pixels"]
    assert out["upper95"] == pytest.approx(3.0 / out["pixels"], rel=0.01)  # the rule of three at 0 found
