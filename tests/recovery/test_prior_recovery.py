"""recover(..., prior=...): the learned prior as the fit's start and as a Gaussian unary term.

The fits run on 16 px captures with a stand-in estimator whose maps are known constants (the
shipped network's maps depend on its training; the mechanism does not).
"""

import math

import pytest
import torch
from torch import Tensor

from torchbrdf.capture.format import load_capture
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery.checks import RecoveryError
from torchbrdf.recovery.engine import Recovery
from torchbrdf.recovery.params import R_MAX, R_MIN, decode
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.classes import choose_class, evidence_threshold
from torchbrdf.recovery.prior import (LearnedPrior, MapEstimator, Prior, class_costs_with_prior, class_prior_cost,
                                      estimator_errors,
                                      measured_map_errors, measured_metallic_error, prior_maps_at, prior_unary)
from torchbrdf.recovery.svbrdf import main

from tests.recovery.recovery_fixtures import cap, copy_out, one_line_error, stopped  # noqa: F401  (fixtures)

CFG = RecoveryConfig(seed=0, threads=1)
#: The stand-in estimator's maps: a wrong grey base colour and a wrong rough, plastic surface.
CONSTANT = {"base_color": 0.5, "roughness": 0.9, "metallic": 0.05, "specular": 0.3}
CARD = {"heldout": {"base_color_rmse": 0.15, "roughness_rmse": 0.06, "metallic_rmse": 0.2,
                    "specular_rmse": 0.06, "normal_mean_deg": 2.0}}


def constant_prior(lights: int = 1, card=CARD, **maps: float) -> Prior:
    """A Prior whose network outputs :data:`CONSTANT` maps (``maps`` replacing some) and flat normals
    at every pixel."""
    model = MapEstimator(lights=lights, width=8, depth=1)
    const = CONSTANT | maps
    with torch.no_grad():
        model.head.weight.zero_()
        values = [const["base_color"]] * 3 + [const[k] for k in ("roughness", "metallic", "specular")]
        model.head.bias.copy_(torch.logit(torch.tensor(values + [0.5, 0.5])))
        model.head.bias[6:] = 0.0  # no tilt: flat normals
    return Prior(model, card)


@pytest.fixture(scope="module")
def painted(tmp_path_factory):
    """A dielectric under four ring lights and the flash: its roughness is silent where no highlight falls."""
    folder = tmp_path_factory.mktemp("painted16")
    generate_capture(folder, recipe="painted", seed=1, size=16, lights=4, noise=0.01)
    return folder


@pytest.fixture(scope="module")
def without_prior(painted):
    return recover(painted, CFG, progress=False)


#: Without the spatial ties and the roughness basin tie, a pixel no highlight reaches is silent
#: (with them its neighbours fill it in).
# The spatial priors and the fill off: they would hand silent pixels the measured neighbours' values first.
UNTIED = CFG.settings(prior_roughness=0.0, prior_specular=0.0, rough_tie=0.0, soft_metal=False, fill=False)


@pytest.fixture(scope="module")
def untied(painted):
    return recover(painted, UNTIED, progress=False), recover(painted, UNTIED, progress=False, prior=constant_prior())


def test_no_prior_is_the_plain_fit_bit_for_bit(painted, without_prior):
    again = recover(painted, CFG, progress=False, prior=None)
    for k, v in without_prior.maps.items():
        assert torch.equal(again.maps[k], v), k
    assert again.report["final_loss"] == without_prior.report["final_loss"]
    assert "learned_prior" not in again.report
    # ... and its start is the photometric-stereo one, not a network's
    rec = Recovery(load_capture(painted), CFG)
    rec.init_state()
    assert not torch.equal(rec.state["theta"][0], rec.state["theta"][1])


def test_the_start_is_the_datas_own_with_or_without_the_prior(painted):
    # A network wrong about a material would trap the fit in its basin (a glossy lacquer it calls
    # rough stayed rough): the prior enters as a Gaussian term only, so both hypotheses start
    # where they start without it, at every light count.
    cap = load_capture(painted)
    prior = Prior.default()
    learned = LearnedPrior(prior_maps_at(prior.predict(cap), 16), estimator_errors(prior.card))
    for train in (None, 2):
        guided, plain = Recovery(cap, CFG, prior=learned), Recovery(cap, CFG)
        for rec in (guided, plain):
            if train:
                rec.train_idx = rec.train_idx[:train]
            rec.init_state()
        for a, b in zip(guided.state["theta"], plain.state["theta"]):
            assert torch.equal(a, b)
    assert guided.plan[0][1] == "dual" and guided.state["prior_noise"] > 0
    assert guided.state["prior_information"] is None  # the maps' term waits for the class choice


def test_the_dual_stages_fit_as_without_the_prior_and_the_class_stages_follow_it(painted):
    # While each pixel's class is open, the network's maps pull neither hypothesis (a pull
    # weighted by its class probability made the two fits unequal and biased the class test);
    # once the class is chosen they enter, weighed against the data's information.
    cap = load_capture(painted)
    guided, plain = Recovery(cap, CFG, prior=LearnedPrior(prior_maps_at(constant_prior().predict(cap), 16),
                                                          estimator_errors(CARD))), Recovery(cap, CFG)
    for rec in (guided, plain):
        rec.init_state()
        for _ in range(rec.plan[0][2] - 1):  # the first stage, short of its end (the class choice)
            rec.step()
    assert guided.state["stage"] == plain.state["stage"] == 0
    for a, b in zip(guided.state["theta"], plain.state["theta"]):
        assert torch.equal(a, b)
    while guided.plan[guided.state["stage"]][1] == "dual":
        guided.step()
    size = guided.plan[guided.state["stage"]][0]
    info = guided.state["prior_information"]
    assert len(info) == 1 and info[0].shape == (size * size, 7) and bool((info[0] >= 0).all())


def test_silent_pixels_stay_at_the_prior_and_measured_ones_follow_the_data(painted, untied):
    plain, guided = untied
    truth = read_exr(painted / "gt" / "base_color.exr")
    conf = plain.confidence[0]
    silent, measured = conf < 0.05, conf > 0.8
    assert silent.sum() >= 8 and measured.sum() >= 8, "the capture must hold both kinds of pixel"
    rough0, rough1 = plain.maps["roughness"][0], guided.maps["roughness"][0]
    # Where the images do not determine the roughness, the prior's value (0.9) draws it toward
    # itself from where the plain fit leaves it; weakly, as the measured pixels show the constant
    # wrong by far more than the card's 0.06 (measured_map_errors) ...
    far = (rough0[silent] - CONSTANT["roughness"]).abs().median()
    assert far > 0.4 and (rough1[silent] - CONSTANT["roughness"]).abs().median() < far - 0.04
    # ... where they do, the fit follows them as without the prior, within the prior's stated
    # error (0.06), on the pixels both fits call dielectric: this capture's 4-light plain fit
    # calls some of them metal, where a roughness means another lobe.
    both = measured & (plain.maps["metallic"][0] < 0.5) & (guided.maps["metallic"][0] < 0.5)
    assert both.sum() >= 8
    assert (rough1[both] - rough0[both]).abs().median() < 0.06
    # The base colour is measured everywhere (the diffuse): the wrong grey prior moves it by no
    # more than the fit's own run-to-run spread (±0.005 over solver changes), far from the grey.
    rmse = [(r.maps["base_color"] - truth).square().mean().sqrt() for r in (plain, guided)]
    grey = (torch.full_like(truth, CONSTANT["base_color"]) - truth).square().mean().sqrt()
    assert rmse[1] <= rmse[0] + 0.005 and rmse[1] < grey / 3
    assert guided.report["learned_prior"]["map_errors"]["roughness"] == pytest.approx(0.06)
    # its measured pixels show the constant 0.9 wrong by more than the card's 0.06
    assert guided.report["learned_prior"]["measured_map_errors"]["roughness"] > 0.1


def test_prior_unary_is_the_maps_gaussian_linearised_at_the_unknowns():
    maps = {"base_color": torch.tensor([0.2, 0.5, 0.9]).reshape(3, 1, 1), "roughness": torch.full((1, 1, 1), 0.4),
            "specular": torch.full((1, 1, 1), 0.5), "normal": torch.tensor([0.3, -0.2, 1.0]).reshape(3, 1, 1)}
    maps["normal"] = maps["normal"] / maps["normal"].norm()
    errors = estimator_errors(CARD)
    theta = torch.tensor([[0.3, -1.0, 2.0, 0.5, -0.4, 0.0, 0.1]], dtype=torch.float64)
    target, prec = prior_unary(theta, maps, 1e-4, errors, class_weight=0.5)
    # The unary's gradient and curvature equal those of σ² Σ (g(θ) − m_p)² / σ_m² (its Gauss–Newton
    # form) on the logits; the slopes are pulled toward the network's normal's.
    want = torch.tensor([0.2, 0.5, 0.9, 0.5, 0.4], dtype=torch.float64)
    sig = torch.tensor([0.15] * 3 + [0.06, CARD["heldout"]["roughness_rmse"]], dtype=torch.float64)

    def energy(t):
        v = torch.sigmoid(t)
        v = torch.cat((v[:4], R_MIN + (R_MAX - R_MIN) * v[4:]))
        return 0.5 * 1e-4 * (((v - want) / sig) ** 2).sum()

    t5 = theta[0, :5].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(energy(t5), t5)
    torch.testing.assert_close(prec[0, :5] * (theta[0, :5] - target[0, :5]), 0.5 * grad)  # (class weight ½)
    jac = torch.autograd.functional.jacobian(lambda t: torch.cat((torch.sigmoid(t[:4]), (R_MAX - R_MIN)
                                                                    * torch.sigmoid(t[4:]))), theta[0, :5])
    torch.testing.assert_close(prec[0, :5], 0.5 * 1e-4 * (torch.diagonal(jac) / sig) ** 2)
    torch.testing.assert_close(target[0, 5:], torch.tensor([0.3, -0.2], dtype=torch.float64))
    torch.testing.assert_close(prec[0, 5:], torch.full((2,), 0.5e-4 / errors["normal"] ** 2, dtype=torch.float64))
    assert errors["normal"] == pytest.approx(math.radians(2.0) / math.sqrt(math.pi / 2))



def test_the_class_prior_is_the_networks_bounded_log_odds():
    # −2 σ² log q per class: the evidence it adds is 2 logit(q) noise variances, at most 2 ln 999.
    diel, metal = class_prior_cost(torch.tensor([[0.25], [1.0], [0.0]], dtype=torch.float64), 1e-4)
    assert float(diel[0]) == pytest.approx(-2e-4 * math.log(0.75)) and float(metal[0]) == pytest.approx(-2e-4 * math.log(0.25))
    assert float((diel - metal)[1] / 1e-4) == pytest.approx(2 * math.log(999))
    assert float((diel - metal)[2] / 1e-4) == pytest.approx(-2 * math.log(999))


def test_a_prior_wrong_about_the_class_does_not_make_a_dielectric_metal(painted, without_prior):
    # A network calling the whole dielectric metal (0.95 everywhere): its metallic is worth its
    # odds, 2 logit(0.95) ≈ 5.9 noise variances, and nothing where the data reject metal, so a
    # metal class needs the data's evidence as without the prior.
    guided = recover(painted, CFG, progress=False, prior=constant_prior(metallic=0.95))
    plain_fraction = float(without_prior.maps["metallic"].mean())
    assert float(guided.maps["metallic"].mean()) <= plain_fraction + 0.02


@pytest.fixture(scope="module")
def many_lights(tmp_path_factory):
    """The painted dielectric under sixteen ring lights and the flash: most of it is measured."""
    folder = tmp_path_factory.mktemp("painted16_17")
    generate_capture(folder, recipe="painted", seed=1, size=16, lights=16, noise=0.01)
    return folder


def test_at_many_lights_a_wrong_prior_moves_the_maps_less_than_the_fits_own_error(many_lights):
    plain = recover(many_lights, CFG, progress=False)
    guided = recover(many_lights, CFG, progress=False, prior=constant_prior())
    for name in ("base_color", "roughness", "specular"):
        truth = read_exr(many_lights / "gt" / f"{name}.exr")
        moved = (guided.maps[name] - plain.maps[name]).abs().median()
        own_error = (plain.maps[name] - truth).abs().median()
        assert moved < own_error, name


def test_the_prior_precision_is_weighed_by_its_share_against_the_data():
    maps = {"base_color": torch.full((3, 1, 1), 0.5), "roughness": torch.full((1, 1, 1), 0.4),
            "specular": torch.full((1, 1, 1), 0.5), "normal": torch.tensor([0.0, 0.0, 1.0]).reshape(3, 1, 1)}
    theta = torch.tensor([[0.3, -1.0, 2.0, 0.5, -0.4, 0.0, 0.1]], dtype=torch.float64)
    errors = estimator_errors(CARD)
    target, prec = prior_unary(theta, maps, 1e-4, errors)
    info = torch.tensor([[0.0, 1.0, 1e6, 0.0, 3.0, 1e-3, 1e3]], dtype=torch.float64) * prec
    target2, prec2 = prior_unary(theta, maps, 1e-4, errors, information=info)
    torch.testing.assert_close(target2, target)
    # π / (π + info): whole where the data say nothing, half at equal information, ~π / info beyond
    torch.testing.assert_close(prec2 / prec, 1 / (1 + info / prec))
    assert float(prec2[0, 2] / prec[0, 2]) < 1e-5


def test_the_metallic_error_is_measured_where_the_data_decide_the_class():
    card = 0.2
    decided = torch.tensor([[-1.0], [-1.0], [-1.0], [0.0]])  # three clear dielectrics, one tie
    wrong = measured_metallic_error(torch.zeros(4, 1), -decided, 1e-3, torch.full((4, 1), 0.95), card)
    assert wrong == pytest.approx(0.95, abs=1e-3)  # the tie counts for nothing
    right = measured_metallic_error(torch.zeros(4, 1), -decided, 1e-3, torch.full((4, 1), 0.05), card)
    assert right == card  # never better than the card
    assert measured_metallic_error(torch.zeros(2, 1), torch.zeros(2, 1), 1e-3, torch.ones(2, 1), card) == card


def test_the_map_errors_are_measured_where_the_data_decide_the_map():
    # Four pixels; the network says roughness 0.5, specular 0.5 and the base colour the fit has.
    net = {"base_color": torch.full((3, 2, 2), 0.4), "roughness": torch.full((1, 2, 2), 0.5),
           "specular": torch.full((1, 2, 2), 0.5), "normal": torch.tensor([0.0, 0.0, 1.0]).reshape(3, 1, 1).expand(3, 2, 2)}
    rough = torch.tensor([0.8, 0.8, 0.1, 0.1])  # measured 0.3 off twice; silent and 0.4 off twice
    theta = torch.cat((torch.logit(torch.full((4, 3), 0.4)), torch.logit(torch.full((4, 1), 0.5)),
                       torch.logit((rough[:, None] - R_MIN) / (R_MAX - R_MIN)), torch.zeros(4, 2)), -1).double()
    errors = estimator_errors(CARD)
    info = torch.zeros(4, 7, dtype=torch.float64)
    info[:2] = 1e9  # the data determine every unknown of the first two pixels, nothing of the others
    got = measured_map_errors(theta, net, 1e-4, errors, info)
    assert got["roughness"] == pytest.approx(0.3, abs=1e-4)  # the silent pixels count for nothing
    assert got["base_color"] == errors["base_color"] and got["specular"] == errors["specular"]  # never below the card
    assert got["normal"] == errors["normal"] and got["metallic"] == errors["metallic"]
    assert measured_map_errors(theta, net, 1e-4, errors, torch.zeros_like(info)) == errors  # nothing measured
    # Equal information and prior precision: each pixel counts half, the RMS is unchanged.
    _, prec = prior_unary(theta, net, 1e-4, errors)
    half = measured_map_errors(theta, net, 1e-4, errors, torch.cat((prec[:2], torch.zeros(2, 7, dtype=prec.dtype))))
    assert half["roughness"] == pytest.approx(0.3, abs=1e-4)


def _class_choice_with_prior(evidence: float, metallic: float, size: int = 8) -> Tensor:
    """The class test's labels ``(P, 1)`` on ``size²`` pixels whose data give ``evidence`` for metal
    (noise variances) with a network saying ``metallic`` everywhere (the prior's σ² ten times the
    class test's, as where a stage starts unconverged)."""
    sigma2, n_res, rate = 1e-4, 51, 1e-4
    metal = torch.full((size * size, 1), sigma2 * n_res, dtype=torch.float64)
    diel = metal + evidence * sigma2
    prior_cost = class_prior_cost(torch.full_like(metal, metallic), 1e-3)
    costs = class_costs_with_prior(diel, metal, prior_cost, sigma2, n_res, rate)
    return choose_class(costs[0], costs[1], size, sigma2, n_res, rate)


def test_a_confidently_wrong_network_does_not_outweigh_data_that_decide_dielectric():
    # Data rejecting metal at 3 τ (a glossy dielectric under 17 lights) against a network calling
    # it metal at 0.999 (worth 2 ln 999 × 10 ≈ 138 σ² of the test's at the prior's σ²): the data decide.
    tau = evidence_threshold(7, 1e-4)
    assert float(_class_choice_with_prior(-3 * tau, 0.999).sum()) == 0
    # Where the data leave the class open, the network's metal decides; its dielectric outweighs
    # even data deciding metal (the test's null hypothesis: it can only lower the false-metal rate).
    assert bool((_class_choice_with_prior(-0.5 * tau, 0.999) == 1).all())
    assert float(_class_choice_with_prior(2 * tau, 0.01).sum()) == 0


def test_a_prior_for_more_lights_than_the_capture_is_refused(painted):
    with pytest.raises(RecoveryError, match=r"prior: the estimator takes 6 images per capture.*has 5.*trained on 5 or fewer images"):
        recover(painted, CFG, progress=False, prior=constant_prior(lights=6))


def test_cli_prior_option(painted, tmp_path, capsys):
    rc = main(["--capture", str(painted), "--out", str(tmp_path / "o"), "--prior", str(tmp_path / "none.pt"),
               "--quiet", "--threads", "1"])
    assert rc == 2
    assert "prior" in one_line_error(capsys) and not (tmp_path / "o").exists()


def test_a_checkpoint_made_without_the_prior_is_not_resumed_with_it(cap, stopped, tmp_path):
    out = copy_out(stopped, tmp_path)
    with pytest.raises(RecoveryError, match="other settings.*learned_prior"):
        recover(cap, Settings(iters=4, threads=1), out, resume=True, progress=False, prior=constant_prior())


def test_the_default_prior_is_the_shipped_estimator_for_the_captures_lights(painted, monkeypatch):
    asked = []
    shipped = Prior.default.__func__

    def spy(cls, lights=None):
        asked.append(lights)
        return shipped(cls, lights)

    monkeypatch.setattr(Prior, "default", classmethod(spy))
    recover(painted, CFG.settings(iters=2), progress=False, prior="default")
    assert asked == [5]  # the flash and four ring lights: the ring-trained estimator (Prior.default(5).lights == 4)
