"""The recovery run: accuracy on a tiny capture, CLI outputs, demo, resume, stages, NaN recovery, the non-local F0 fusion."""

import json
import math
import time

import pytest
import torch

from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.recovery import (calibration, classes, engine, levels, lm, map_ops, params, priors, search,
                                smoothness_prior, soft_metal)
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.svbrdf import CHECKPOINT, RecoveryConfig, main, recover

CONTRACT_FILES = ["base_color.exr", "roughness.exr", "metallic.exr", "specular.exr", "normal.exr", "report.json"]


def test_tiny_capture_recovers_known_maps(tiny_result):
    e = tiny_result["errors"]
    assert e["base_color_rmse"] < 0.05
    assert e["roughness_rmse"] < 0.08
    assert e["metallic_rmse"] < 0.2
    assert e["normal_mean_deg"] < 1.5
    assert tiny_result["held_out_light"]["psnr"] > 35
    assert min(tiny_result["per_image_psnr"].values()) > 30


def test_cli_writes_every_contract_file(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["--capture", str(tiny), "--out", str(out), "--iters", "8", "--gt", str(tiny / "gt"), "--quiet"])
    assert rc == 0
    for f in CONTRACT_FILES + ["comparison.png", "loss.png", "base_color.png", "normal.png", "roughness.png"]:
        assert (out / f).is_file(), f
    rep = json.loads((out / "report.json").read_text())
    assert isinstance(rep["iterations"], int) and rep["iterations"] > 0
    assert rep["seconds"] > 0 and math.isfinite(rep["final_loss"])
    assert len(rep["per_image_psnr"]) == 9 and "errors" in rep
    for name, ch in [("base_color", 3), ("roughness", 1), ("metallic", 1), ("specular", 1), ("normal", 3)]:
        m, names = read_exr(out / f"{name}.exr", return_names=True)
        assert m.shape == (ch, 32, 32) and torch.isfinite(m).all()
        assert names == (["R", "G", "B"] if ch == 3 else ["Y"])
    n = read_exr(out / "normal.exr")
    assert (n[2] > 0).all() and torch.allclose(n.norm(dim=0), torch.ones(32, 32), atol=1e-4)
    conf, names = read_exr(out / "confidence.exr", return_names=True)
    assert names == ["Y"] and conf.shape == (1, 32, 32) and bool(((conf >= 0) & (conf <= 1)).all())
    assert (out / "confidence.png").is_file() and len(rep["light_intensity_scale"]) == 9


@pytest.mark.parametrize("flag", ["--no-light-calibration", "--no-light-position"])
def test_cli_light_calibration_switches(tiny, tmp_path, flag):
    """The CLI's light-calibration switches reach the recovery.

    ``--no-light-calibration`` keeps every light as capture.json states it (scales 1, offsets
    0 in report.json); ``--no-light-position`` estimates the scales only.
    """
    out = tmp_path / "out"
    assert main(["--capture", str(tiny), "--out", str(out), "--iters", "6", "--quiet", flag]) == 0
    rep = json.loads((out / "report.json").read_text())
    scales = list(rep["light_intensity_scale"].values())
    offsets = [c for v in rep["light_position_offset"].values() for c in v]
    assert all(o == 0.0 for o in offsets)
    if flag == "--no-light-calibration":
        assert all(s == 1.0 for s in scales)
    else:
        assert any(s != 1.0 for s in scales)


def test_cli_bad_capture_is_a_clear_error(tmp_path, capsys):
    rc = main(["--capture", str(tmp_path / "missing"), "--out", str(tmp_path / "o"), "--quiet"])
    assert rc == 2
    assert "missing" in capsys.readouterr().err


def test_demo_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "demo"
    assert main(["--demo", "--demo-size", "24", "--iters", "6", "--out", str(out), "--quiet"]) == 0
    for f in CONTRACT_FILES:
        assert (out / f).is_file()
    assert "errors" in json.loads((out / "report.json").read_text())


def test_resume_equals_uninterrupted(tiny, tmp_path):
    cfg = dict(seed=1, iters=12, checkpoint_every=3, threads=2)
    full = recover(tiny, RecoveryConfig(**cfg), tmp_path / "full", progress=False)
    part = recover(tiny, Settings(**cfg, signal_at=3), tmp_path / "part", progress=False)
    assert not part["completed"] and part["iterations"] == 3
    assert (tmp_path / "part" / CHECKPOINT).is_file()
    for f in CONTRACT_FILES:  # partial outputs are valid files
        assert (tmp_path / "part" / f).is_file()
    assert torch.isfinite(read_exr(tmp_path / "part" / "roughness.exr")).all()
    resumed = recover(tiny, RecoveryConfig(**cfg), tmp_path / "part", resume=True, progress=False)
    assert resumed["completed"] and resumed["iterations"] == full["iterations"]
    for k in full["maps"]:
        torch.testing.assert_close(resumed["maps"][k], full["maps"][k], rtol=1e-5, atol=1e-6)
    assert abs(resumed["final_loss"] - full["final_loss"]) <= 1e-6 * max(1.0, abs(full["final_loss"]))


def test_full_resolution_stages_end_once_converged(tiny):
    """A stage at full resolution ends after ``converge_min_iters`` once its fit loss stops moving
    (a tolerance of 99 %: at once); the coarse stages and ``converge_tol=0`` run every planned one."""
    loose = recover(tiny, RecoveryConfig(seed=0, threads=2, converge_tol=0.99), None, progress=False)
    exact = recover(tiny, RecoveryConfig(seed=0, threads=2, converge_tol=0.0), None, progress=False)
    plan = exact["schedule"]
    full = plan[-1]["size"]
    assert exact["iterations"] == sum(p["iterations"] for p in plan) == len(exact["loss_history"])
    assert not any("skipped" in h for h in exact["loss_history"])
    for k, p in enumerate(plan):
        ran = [h for h in loose["loss_history"] if (h["size"], h["stage"]) == (p["size"], p["stage"])]
        if k > 0 and plan[k - 1]["size"] == p["size"] and plan[k - 1]["stage"] == p["stage"]:
            continue  # (two stages alike: not in the default plan)
        if p["size"] < full:
            assert len(ran) == p["iterations"]
        else:
            assert len(ran) == min(2, p["iterations"])
            assert ran[-1].get("skipped", 0) == p["iterations"] - len(ran)
    assert loose["iterations"] == len(loose["loss_history"]) < exact["iterations"]


def test_report_says_where_the_time_went(tiny_result):
    """Each iteration has its own seconds, and ``stage_seconds`` sums them per stage run, in order.

    Together they are part of the run's ``seconds``.
    """
    hist, stages = tiny_result["loss_history"], tiny_result["stage_seconds"]
    assert all(h["seconds"] > 0 for h in hist)
    plan = tiny_result["schedule"]
    assert [(e["size"], e["stage"]) for e in stages] == [(p["size"], p["stage"]) for p in plan]
    assert sum(e["iterations"] for e in stages) == len(hist) == tiny_result["iterations"]
    for e in stages:
        mine = [h["seconds"] for h in hist if (h["size"], h["stage"]) == (e["size"], e["stage"])]
        assert e["seconds"] == pytest.approx(sum(mine)) and len(mine) == e["iterations"]
    assert sum(e["seconds"] for e in stages) <= tiny_result["seconds"]


def test_stage_seconds_group_runs_of_one_stage():
    """Consecutive iterations of one (size, stage) form an entry; a time missing anywhere makes it None."""
    from torchbrdf.recovery.svbrdf import stage_seconds

    h = [{"size": 4, "stage": "dual", "seconds": 1.0}, {"size": 4, "stage": "dual", "seconds": 2.0},
         {"size": 8, "stage": "dual", "seconds": 0.5}, {"size": 8, "stage": "polish"},
         {"size": 8, "stage": "polish", "seconds": 1.0}]
    assert stage_seconds(h) == [{"size": 4, "stage": "dual", "iterations": 2, "seconds": 3.0},
                                {"size": 8, "stage": "dual", "iterations": 1, "seconds": 0.5},
                                {"size": 8, "stage": "polish", "iterations": 2, "seconds": None}]
    assert stage_seconds([]) == []
    # a stage met again after another is a new entry
    again = stage_seconds([{"size": 4, "stage": "dual", "seconds": 1.0},
                           {"size": 8, "stage": "dual", "seconds": 1.0},
                           {"size": 4, "stage": "dual", "seconds": 2.0}])
    assert [(e["size"], e["seconds"]) for e in again] == [(4, 1.0), (8, 1.0), (4, 2.0)]


def test_a_stages_end_work_counts_in_its_last_iteration(tiny, monkeypatch):
    """The work at a stage's end (here a 0.2 s sleep added to it) is in its last iteration's seconds."""
    from torchbrdf.recovery.engine import Recovery

    plain = Recovery.end_stage

    def slow_end(self):
        time.sleep(0.2)
        plain(self)

    monkeypatch.setattr(Recovery, "end_stage", slow_end)
    rep = recover(tiny, RecoveryConfig(seed=0, threads=2, iters=6), None, progress=False).report
    hist = rep["loss_history"]
    key = [(h["size"], h["stage"]) for h in hist]
    last = {len(hist) - 1} | {k for k in range(len(hist) - 1) if key[k] != key[k + 1]}
    assert len(last) == len(rep["stage_seconds"])
    assert all(hist[k]["seconds"] >= 0.2 for k in last)


def test_resume_after_a_converged_stage_equals_uninterrupted(tiny, tmp_path):
    """Stopped just before the iteration that ends a stage early, a resumed run ends it there too."""
    cfg = dict(seed=1, checkpoint_every=1, threads=2, converge_tol=0.05)
    full = recover(tiny, RecoveryConfig(**cfg), tmp_path / "full", progress=False)
    first = next(h["iteration"] for h in full["loss_history"] if "skipped" in h)
    part = recover(tiny, Settings(**cfg, signal_at=first), tmp_path / "part", progress=False)
    assert not part["completed"] and part["iterations"] == first
    resumed = recover(tiny, RecoveryConfig(**cfg), tmp_path / "part", resume=True, progress=False)
    assert resumed["iterations"] == full["iterations"]
    assert [h.get("skipped") for h in resumed["loss_history"]] == [h.get("skipped") for h in full["loss_history"]]
    # the iterations before the stop keep their times through the checkpoint
    counts = [e["iterations"] for e in full["stage_seconds"]]
    assert [e["iterations"] for e in resumed["stage_seconds"]] == counts
    assert all(e["seconds"] > 0 for e in resumed["stage_seconds"])
    for k in full["maps"]:
        torch.testing.assert_close(resumed["maps"][k], full["maps"][k], rtol=1e-5, atol=1e-6)


def test_the_fit_loss_is_the_training_lights_data_cost(tiny):
    """The fit loss taken from each LM step equals a render of the state on the training lights,
    in every stage (the "all" stage also fits the held-out light, which it leaves out)."""
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery
    from torchbrdf.recovery.svbrdf import _fit_losses

    cfg = RecoveryConfig(seed=0, light_scale=False, light_position=False, soft_metal=False)
    rec = Recovery(load_capture(tiny), cfg, log=lambda m: None)
    kinds = set()
    with torch.no_grad():
        rec.init_state()
        while not rec.finished():
            stage = rec.state["stage"]
            rec.tick()
            if rec.state["stage"] != stage:  # end_stage changed the state after the LM step
                continue
            kinds.add(rec.plan[stage][1])
            from_lm = _fit_losses(rec)
            rec.fit_cost = {}
            rendered = _fit_losses(rec)
            assert from_lm.keys() == rendered.keys()
            for key in from_lm:
                assert math.isclose(from_lm[key], rendered[key], rel_tol=1e-4), (rec.plan[stage], key)
    assert kinds == {"dual", "polish", "all"}


def test_a_resumed_progress_bar_starts_where_the_stages_left_off():
    from torchbrdf.recovery.svbrdf import _Progress

    plan = [(8, "dual", 2), (16, "polish", 3), (16, "all", 2)]
    bar = _Progress(plan, 2, 1, False, lambda m: None)  # polish ended early after 1 of its 3
    assert bar.done == 8 * 8 * 2 * 2 + 16 * 16 * 3 + 16 * 16


def test_nan_is_detected_recovered_and_never_written(tiny, tmp_path):
    rep = recover(tiny, Settings(seed=0, iters=10, fault_at=3, threads=2), tmp_path / "nan", progress=False)
    assert rep["completed"]
    assert any(e["event"].startswith("non-finite") for e in rep["events"])
    for f in ("base_color", "roughness", "metallic", "specular", "normal"):
        assert torch.isfinite(read_exr(tmp_path / "nan" / f"{f}.exr")).all()
    assert math.isfinite(rep["final_loss"])
    assert min(rep["per_image_psnr"].values()) > 25


def test_nonlocal_metal_base_fills_low_information_pixels(monkeypatch):
    """Metal pixels the data barely sees take the information-weighted F0 of their metal
    neighbours; well-observed metal pixels and dielectric pixels keep their own values."""
    import types


    size = 16
    p = size * size
    theta = torch.zeros(p, 7)
    theta[:, 0:3] = 1.0  # well-observed metal F0 (logit 1)
    metal = torch.ones(p, 1)
    metal[: size * 4] = 0.0  # top rows dielectric
    info = torch.full((p, 7), 10.0)
    corner = torch.zeros(size, size, dtype=torch.bool)
    corner[-3:, -3:] = True
    corner = corner.flatten()
    theta[corner, 0:3] = -1.0  # the under-determined corner came out dark
    info[corner, 0:3] = 1e-6
    theta[: size * 4, 0:3] = -2.0  # a dark dielectric must not leak into the metal average
    monkeypatch.setattr(priors, "marginal_information", lambda *a: info)
    cfg = Settings()
    w, m, inf = priors.nonlocal_prior(types.SimpleNamespace(size=size), theta, metal, cfg)
    fused = torch.where(w > 0, (inf * theta + w * m) / (inf + w).clamp(min=1e-12), theta)
    assert torch.allclose(fused[corner, 0:3], torch.ones(int(corner.sum()), 3), atol=0.05)
    keep = ~corner & (metal[:, 0] > 0.5)
    assert torch.allclose(fused[keep, 0:3], theta[keep, 0:3], atol=1e-2)
    assert torch.equal(fused[: size * 4], theta[: size * 4])


def test_nonlocal_metal_base_discounts_pixels_the_model_does_not_fit(monkeypatch):
    """A metal pixel fitted k x above w x the median metal pixel counts 1/k in the F0 average.

    So a dark, badly fitted patch (a rust front called metal) does not pull its neighbours'
    F0 down; pixels fitted better than that count 1 (not more), the median is over the metal
    pixels only, and a non-finite cost counts 0.
    """
    import types


    size = 16
    p = size * size
    grid = torch.arange(p).reshape(size, size)
    diel = (grid < 8 * size).flatten()  # rows 0-7: dielectric, fitted far better than the metal
    bad = torch.zeros(size, size, dtype=torch.bool)
    bad[8:12, :4] = True  # a dark metal patch fitted at 100x the median
    bad = bad.flatten()
    good = torch.zeros(size, size, dtype=torch.bool)
    good[12:, 12:] = True  # metal fitted at a quarter of the median, a brighter F0
    good = good.flatten()
    nan_px = torch.zeros(size, size, dtype=torch.bool)
    nan_px[8, 8] = True
    nan_px = nan_px.flatten()
    theta = torch.zeros(p, 7, dtype=torch.float64)
    theta[:, 0:3] = 1.0
    theta[bad, 0:3], theta[good, 0:3], theta[diel, 0:3] = -3.0, 1.5, 5.0
    metal = (~diel).to(torch.float64)[:, None]
    info = torch.full((p, 7), 10.0, dtype=torch.float64)
    cost = torch.ones(p, 1, dtype=torch.float64)
    cost[bad], cost[good], cost[diel], cost[nan_px] = 100.0, 0.25, 0.01, float("nan")
    monkeypatch.setattr(priors, "marginal_information", lambda *a: info)
    rest = ~diel & ~bad & ~good & ~nan_px

    def expected(w_fit):  # the median metal pixel costs 1
        wt = torch.zeros(p, dtype=torch.float64)
        wt[rest], wt[good], wt[bad] = min(1.0, w_fit), min(1.0, w_fit / 0.25), w_fit / 100.0
        return float((wt * theta[:, 0]).sum() / wt.sum())

    for w_fit in (1.0, 0.5):
        cfg = Settings(nonlocal_sigma=1000.0, nonlocal_fit_weight=w_fit)  # a flat window
        _, m, _ = priors.nonlocal_prior(types.SimpleNamespace(size=size), theta, metal, cfg, cost=cost)
        want = expected(w_fit)
        assert torch.allclose(m[rest, 0:3], torch.full_like(m[rest, 0:3], want), atol=1e-4), (w_fit, want)
        assert torch.equal(m[diel], theta[diel])  # dielectrics keep their own values
    assert abs(expected(1.0) - expected(0.5)) > 0.05  # the setting matters here
    # without the fit weight the dark patch drags the average by most of a logit unit
    _, m0, _ = priors.nonlocal_prior(types.SimpleNamespace(size=size), theta, metal,
                                Settings(nonlocal_sigma=1000.0, nonlocal_fit_weight=0.0), cost=cost)
    assert float(m0[rest, 0].mean()) < expected(1.0) - 0.4
