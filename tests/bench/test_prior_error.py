"""bench.prior_error: the estimator's per-map error on panel materials, and the card it writes."""

import math

import pytest
import torch

from torchbrdf.bench import prior_error
from torchbrdf.bench.prior_error import map_errors, panel_errors
from torchbrdf.recovery.prior import MapEstimator, Prior


def _maps(base: float, rough: float) -> dict:
    n = torch.zeros(3, 4, 4)
    n[2] = 1.0
    return {"base_color": torch.full((3, 4, 4), base), "roughness": torch.full((1, 4, 4), rough),
            "metallic": torch.zeros(1, 4, 4), "specular": torch.full((1, 4, 4), 0.5), "normal": n}


def test_map_errors_sums_squares_and_the_mean_error():
    truth = _maps(0.5, 0.4)
    pred = _maps(0.6, 0.4)
    pred["roughness"][0, :2] = 0.6  # half the pixels off by +0.2, half exact: mean 0.1, RMS 0.141
    tilt = torch.tensor([math.sin(0.1), 0.0, math.cos(0.1)])
    pred["normal"] = tilt[:, None, None].expand(3, 4, 4).clone()
    e = map_errors(pred, truth)
    assert e["base_color_sse"] == pytest.approx(48 * 0.01, rel=1e-5) and e["base_color_bias"] == pytest.approx(0.1)
    assert e["roughness_sse"] == pytest.approx(8 * 0.04, rel=1e-5) and e["roughness_bias"] == pytest.approx(0.1)
    assert e["metallic_sse"] == 0 and e["roughness_n"] == 16
    assert e["normal_deg_sum"] / e["normal_n"] == pytest.approx(math.degrees(0.1), rel=1e-5)


def _constant_prior() -> Prior:
    model = MapEstimator(lights=1, width=8, depth=1)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.copy_(torch.logit(torch.tensor([0.5, 0.5, 0.5, 0.5, 0.05, 0.5, 0.5, 0.5])))
        model.head.bias[6:] = 0.0
    return Prior(model, {"heldout": {"roughness_rmse": 0.1}})


def test_panel_errors_pool_the_split_and_split_bias_from_spread():
    res = panel_errors(_constant_prior(), "tuning", lights=2, size=16)
    assert res["materials"] == len(res["cases"]) == 20
    assert {c["case"].split("/")[1] for c in res["cases"]} == {"0", "1"}  # tuning seeds only
    for m in ("base_color", "roughness", "metallic", "specular"):
        pooled = math.sqrt(sum(c[f"{m}_rmse"] ** 2 for c in res["cases"]) / 20)  # equal pixel counts
        assert res[f"{m}_rmse"] == pytest.approx(pooled, rel=1e-6)
        assert 0.0 <= res[f"{m}_bias_share"] <= 1.0 + 1e-9
    with pytest.raises(ValueError, match="split"):
        panel_errors(_constant_prior(), "all")


def test_card_gets_the_tuning_measurement_and_refuses_the_report_split(tmp_path, monkeypatch, capsys):
    path = tmp_path / "w.pt"
    _constant_prior().save(path)
    fake = {"split": "tuning", "lights": 4, "size": 16, "materials": 20, "normal_mean_deg": 2.0, "cases": [{}],
            **{f"{m}_rmse": 0.1 for m in prior_error.SCALAR_MAPS},
            **{f"{m}_bias_share": 0.5 for m in prior_error.SCALAR_MAPS}}
    monkeypatch.setattr(prior_error, "panel_errors", lambda *a, **k: fake)
    assert prior_error.main(["--prior", str(path), "--card", str(path)]) == 0
    card = Prior.from_file(path).card
    assert card["heldout"] == {"roughness_rmse": 0.1}  # the rest of the card is kept
    assert card["panel"]["roughness_rmse"] == 0.1 and "cases" not in card["panel"]
    assert card["panel"]["command"].startswith("python -m torchbrdf.bench.prior_error --prior")
    with pytest.raises(SystemExit):
        prior_error.main(["--split", "report", "--card", str(path)])
    assert "tuning split only" in capsys.readouterr().err


def test_card_measures_its_own_weights_not_the_default_for_the_light_count(tmp_path, monkeypatch, capsys):
    path, other = tmp_path / "w.pt", tmp_path / "other.pt"
    _constant_prior().save(path)
    _constant_prior().save(other)
    measured = []

    def fake(prior, *a, **k):
        measured.append(prior)
        return {"split": "tuning", "lights": 4, "size": 16, "materials": 20, "normal_mean_deg": 2.0, "cases": [{}],
                **{f"{m}_rmse": 0.1 for m in prior_error.SCALAR_MAPS},
                **{f"{m}_bias_share": 0.5 for m in prior_error.SCALAR_MAPS}}

    monkeypatch.setattr(prior_error, "panel_errors", fake)
    monkeypatch.setattr(prior_error.Prior, "default", lambda *a, **k: pytest.fail("--card measured Prior.default"))
    assert prior_error.main(["--lights", "4", "--card", str(path)]) == 0
    assert len(measured) == 1
    with pytest.raises(SystemExit):
        prior_error.main(["--prior", str(other), "--card", str(path)])
    assert "another file" in capsys.readouterr().err
