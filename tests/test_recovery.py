"""SVBRDF recovery: accuracy on a tiny capture, CLI outputs, demo, resume, NaN recovery."""

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


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap")
    generate_capture(folder, recipe="metal_inlay", seed=2, size=32, lights=8, noise=0.01)
    return folder


@pytest.fixture(scope="module")
def tiny_result(tiny):
    return recover(tiny, RecoveryConfig(seed=0, threads=2), None, gt=tiny / "gt", progress=False)


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
    conf, names = read_exr(out / "confidence.exr", return_names=True)  # issue 13
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


# --------------------------------------------------------------------------------------
# The coupled prior, propagation, normal search and the class choice
# --------------------------------------------------------------------------------------


def _random_edges(size, c=7, seed=0):
    gen = torch.Generator().manual_seed(seed)
    wx = torch.rand(size, size - 1, c, generator=gen, dtype=torch.float64)
    wy = torch.rand(size - 1, size, c, generator=gen, dtype=torch.float64)
    return wx, wy


def test_laplacian_is_the_gradient_of_the_prior_energy():
    size = 5
    wx, wy = _random_edges(size)
    x = torch.randn(size * size, 7, dtype=torch.float64, requires_grad=True)
    energy = 0.5 * smoothness_prior.prior_energy(x, wx, wy, size).sum()  # per-pixel shares sum to 2 E
    (grad,) = torch.autograd.grad(energy, x)
    assert torch.allclose(grad, smoothness_prior.laplacian(x.detach(), wx, wy, size), atol=1e-12)
    # Diagonal: L applied to a unit vector at pixel p, channel c.
    e = torch.zeros(size * size, 7, dtype=torch.float64)
    e[7, 3] = 1.0
    assert math.isclose(float(smoothness_prior.laplacian(e, wx, wy, size)[7, 3]), float(smoothness_prior.laplacian_diag(wx, wy, size)[7, 3]))


def test_metal_base_tie_is_guided_by_base_colour():
    """Two metal pixels' base colours are tied only where they are alike (metal_base_guided).

    A dark red rust island called metal inside a bright metal is cut loose from it, so its F0
    does not pull the bright metal's down through the chain of ties. Unguided (as before
    2026-12-02), the tie is class-only; a dielectric pair has no base-colour tie at all.
    """
    from torchbrdf.recovery.smoothness_prior import edge_weights
    from torchbrdf.recovery.params import encode

    size = 4
    base = torch.tensor([0.95, 0.93, 0.88]).repeat(size, size, 1)
    base[:, 2:] = torch.tensor([0.45, 0.2, 0.1])  # columns 2-3: the island
    n = size * size
    theta = encode({"base_color": base.reshape(n, 3), "specular": torch.full((n, 1), 0.5),
                    "roughness": torch.full((n, 1), 0.3),
                    "normal": torch.tensor([0.0, 0.0, 1.0]).repeat(n, 1)})
    metal = torch.ones(n, 1)
    for guided in (True, False):
        cfg = Settings(metal_base_guided=guided)
        wx, wy = edge_weights(theta, metal, size, cfg)
        w = cfg.prior_metal_base
        assert torch.allclose(wx[:, 0, 0:3], torch.full((size, 3), w))  # alike: tied
        assert torch.allclose(wy[..., 0:3], torch.full((size - 1, size, 3), w))
        across = wx[:, 1, 0:3]  # between columns 1 and 2
        assert torch.allclose(across, torch.full_like(across, w)) != guided
        if guided:
            assert float(across.max()) < 1e-6 * w
    wx, _ = edge_weights(theta, torch.zeros(n, 1), size, Settings())
    assert float(wx[..., 0:3].abs().max()) == 0.0


@pytest.mark.parametrize("joined", [range(7), range(3, 5), range(0, 5), range(0)])
def test_pcg_solves_the_coupled_system(joined):
    """Every pattern of prior-joined channels (all; a dielectric's specular and roughness; with
    a metal's base colour; none), so the per-pixel elimination of the others is exact."""
    size, c = 4, 7
    p = size * size
    wx, wy = _random_edges(size, c, seed=1)
    free = [k for k in range(c) if k not in joined]
    wx[..., free], wy[..., free] = 0.0, 0.0
    a = torch.randn(p, c, c, dtype=torch.float64)
    hess = a @ a.transpose(-1, -2) + 1e-2 * torch.eye(c, dtype=torch.float64)  # SPD blocks
    rhs = torch.randn(p, c, dtype=torch.float64)
    x = smoothness_prior.pcg(hess, wx, wy, rhs, size, iters=300)
    # Dense reference: assemble the (P·C)² matrix column by column.
    cols = []
    for k in range(p * c):
        e = torch.zeros(p * c, dtype=torch.float64)
        e[k] = 1.0
        e = e.reshape(p, c)
        cols.append((torch.einsum("pij,pj->pi", hess, e) + smoothness_prior.laplacian(e, wx, wy, size)).flatten())
    dense = torch.stack(cols, 1)
    ref = torch.linalg.solve(dense, rhs.flatten()).reshape(p, c)
    assert torch.allclose(x, ref, atol=1e-8, rtol=1e-6)


def _flat_level(size=16, lights=8, normal_tilt_deg=0.0):
    """A LevelData of a uniform glossy dielectric (or a tilted normal everywhere)."""
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import light_layout, render_capture

    n = torch.tensor([math.sin(math.radians(normal_tilt_deg)), 0.0, math.cos(math.radians(normal_tilt_deg))])
    maps = {"base_color": torch.tensor([0.5, 0.3, 0.2])[:, None, None].expand(3, size, size),
            "roughness": torch.full((1, size, size), 0.3), "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), 0.5), "normal": n[:, None, None].expand(3, size, size)}
    pos, inten = light_layout(lights)
    imgs = render_capture(maps, (pos, inten), backend="compact")
    cap = Capture(images=imgs, light_positions=pos, light_intensities=inten,
                  camera_position=torch.tensor([0.0, 0.0, 3.0]), width=size, height=size,
                  files=tuple(f"{k}.exr" for k in range(len(pos))))
    data = levels.LevelData(cap, size, list(range(len(pos))), float(0.01 * imgs.mean()))
    p = {k: v.reshape(v.shape[0], -1).T.contiguous() for k, v in maps.items()}
    metal = p.pop("metallic")
    return data, params.encode(p), metal


def test_normal_equations_match_reverse_mode_and_the_fused_kernels():
    # The fit's JᵀJ and Jᵀr come from forward mode vmapped over the 7 unknowns through
    # torchbrdf.principled, block by block. Against them: the full Jacobian by reverse mode
    # (eager), and the same computation through the fused kernels (used at fit sizes).
    import torchbrdf
    from torchbrdf.kernels import fused

    data, theta, metal = _flat_level(size=12, lights=6, normal_tilt_deg=10.0)
    theta = theta + 0.3 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(0))
    metal = metal.clone()
    metal[::3] = 1.0
    idx = data.train_idx
    P = theta.shape[0]
    torchbrdf.set_fast_path(False)
    try:
        r_ref = data.residual(theta, metal, idx)
        # d r[p] / d theta[p]: the residual of pixel p depends only on its own unknowns.
        full = torch.func.jacrev(lambda t: data.residual(t, metal, idx))(theta)  # (P, M, P, 7)
        jac = full[torch.arange(P), :, torch.arange(P)]  # (P, M, 7)
        got = {False: lm.gauss_newton(data, theta, metal, idx, "principled", chunk=50)}
    finally:
        torchbrdf.set_fast_path(None)
    jtj_ref = torch.einsum("pmi,pmj->pij", jac, jac)
    jtr_ref = torch.einsum("pmi,pm->pi", jac, r_ref)
    if fused.available():
        torchbrdf.set_fast_path(True)
        try:
            got[True] = lm.gauss_newton(data, theta, metal, idx, "principled", chunk=50)
        finally:
            torchbrdf.set_fast_path(None)
    for r, jtj, jtr in got.values():
        assert jtj.shape == (P, 7, 7) and jtr.shape == (P, 7) and r.shape == r_ref.shape
        assert torch.allclose(r, r_ref, rtol=1e-5, atol=1e-6)
        scale = float(jtj_ref.abs().max())
        assert torch.allclose(jtj, jtj_ref, rtol=1e-4, atol=1e-5 * scale)
        assert torch.allclose(jtr, jtr_ref, rtol=1e-4, atol=1e-5 * float(jtr_ref.abs().max()))


def test_a_propagation_pass_restricted_to_the_last_changes_equals_a_full_pass():
    # Pass 2 can differ from pass 1 only where a 3x3 neighbourhood changed in pass 1, so the
    # recovery evaluates only those pixels; the result must be exactly the full pass's. A
    # wrong 6x6 block is repaired one ring per pass, so pass 2 has work to do.
    data, theta, metal = _flat_level(size=12, lights=6)
    bad = theta.clone().reshape(12, 12, -1)
    bad[3:9, 3:9, 0:5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])
    bad = bad.reshape(theta.shape)
    t1, m1, changed = search.propagate(data, bad, metal, Settings())
    full = search.propagate(data, t1, m1, Settings())
    part = search.propagate(data, t1, m1, Settings(), active=map_ops.dilate(changed, 12))
    assert bool(changed.any()) and bool(full[2].any())
    assert torch.equal(full[0], part[0]) and torch.equal(full[1], part[1]) and torch.equal(full[2], part[2])
    # Only the changed pixels themselves would miss the next ring.
    only = search.propagate(data, t1, m1, Settings(), active=changed)
    assert not torch.equal(full[0], only[0])


def test_propagation_repairs_a_pixel_from_its_neighbours():
    data, theta, metal = _flat_level()
    bad = theta.clone()
    bad[40, 0:5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])  # a wrong local optimum
    fixed, new_metal, changed = search.propagate(data, bad, metal, Settings())
    assert int(changed.sum()) >= 1 and torch.allclose(fixed[40], theta[40], atol=1e-5)
    assert torch.equal(new_metal, metal)
    # Across classes: a pixel wrongly called metal returns to dielectric by the margin rule.
    m2 = metal.clone()
    m2[40] = 1.0
    fixed, new_metal, _ = search.propagate(data, bad, m2, Settings(), margin=0.5)
    assert float(new_metal[40]) == 0.0 and torch.allclose(fixed[40], theta[40], atol=1e-5)


def test_normal_search_finds_a_steep_normal():
    data, theta, metal = _flat_level(normal_tilt_deg=24.0)
    rows = torch.arange(100, 110)
    flat = theta.clone()
    flat[rows, 5:7] = 0.0  # these normals started flat, 24° off: a glossy local optimum
    flat[rows - 16, 5:7] = 0.0  # ... and so did the rows above and below: only the grid
    flat[rows + 16, 5:7] = 0.0  # of normals can help the middle ones
    cost = lambda t: (data.residual(t, metal, data.train_idx) ** 2).sum(-1)  # noqa: E731
    found, changed = search.normal_search(data, flat, metal, "principled")
    assert changed >= len(rows)
    assert bool((cost(found)[rows] < 0.1 * cost(flat)[rows]).all())
    nz = 1 / torch.sqrt(1 + (found[rows, 5:7] ** 2).sum(-1))
    # The best candidate is the true normal of a neighbour or a grid normal within 4° of it.
    assert torch.allclose(torch.rad2deg(torch.acos(nz)), torch.full_like(nz, 24.0), atol=4.0)


def test_ambiguous_pixels_take_their_neighbours_class():

    size = 6
    diel = torch.ones(size * size, 1)
    met = torch.full((size * size, 1), 10.0)  # decisively dielectric everywhere ...
    met.view(size, size)[:, :3] = 0.01  # ... except the left half, decisively metal
    met.view(size, size)[2, 2] = 1.0  # ambiguous, among metals
    met.view(size, size)[3, 4] = 1.0  # ambiguous, among dielectrics
    label = classes.choose_class(diel, met, 0.5, size).view(size, size)
    assert float(label[2, 2]) == 1.0 and float(label[3, 4]) == 0.0
    assert torch.equal(label[:, :2], torch.ones(size, 2)) and torch.equal(label[:, 4:], torch.zeros(size, 2))


def test_a_metal_win_over_an_unconverged_dielectric_is_refitted_first():
    """A metal win over a dielectric stuck well above the noise is no evidence: refit first.

    Here 7× the median, as the README example's bottom-edge grout; not when the metal fits at
    the noise level, nor for a dielectric near it.
    """

    diel = torch.ones(100, 1)
    metal = torch.full((100, 1), 5.0)  # dielectric clearly better everywhere ...
    diel[0], metal[0] = 7.0, 2.5  # stuck dielectric, metal fits only at 2.5x the noise: refit
    diel[1], metal[1] = 7.0, 1.5  # ... a metal at the noise level: a metal
    diel[2], metal[2] = 3.0, 1.0  # ... a dielectric near the noise level: no refit needed
    diel[3], metal[3] = 20.0, 4.0  # stuck far above the noise: refit
    rows = classes.unconverged_dielectric_rows(diel, metal, 0.5)
    assert rows.tolist() == [0, 3]


def test_edge_pixels_vote_with_the_neighbours_they_have():
    """Issue 13: an edge pixel has 5 neighbours (a corner 3), not copies of itself (replicate
    padding let an edge row outvote the rows inside and kept a frame of the wrong class)."""

    size = 6
    diel = torch.ones(size * size, 1)
    met = torch.full((size * size, 1), 0.01)  # decisively metal everywhere ...
    met.view(size, size)[0, :] = 1.0  # ... except the top edge row: ambiguous
    label = classes.choose_class(diel, met, 0.5, size).view(size, size)
    assert torch.equal(label, torch.ones(size, size))  # the edge row joins the metal inside it
    # A corner pixel with 2 of its 3 neighbours decisively metal takes their class.
    met = torch.full((size * size, 1), 10.0)
    met.view(size, size)[0, 0] = 1.0
    met.view(size, size)[0, 1] = met.view(size, size)[1, 0] = 0.01
    assert float(classes.choose_class(diel, met, 0.5, size).view(size, size)[0, 0]) == 1.0
    # An isolated metal pixel in a corner or on an edge is a speckle like any other ...
    speck = torch.zeros(size, size)
    speck[0, 0] = speck[0, 3] = speck[3, 3] = 1.0
    assert float(classes.despeckle(speck.reshape(-1, 1), size).sum()) == 0.0
    # ... while a one-pixel line along the edge is kept, and the majority vote keeps an edge row
    # of metal that has metal inside it.
    line = torch.zeros(size, size)
    line[0, 1:5] = 1.0
    assert torch.equal(classes.despeckle(line.reshape(-1, 1), size).view(size, size), line)
    block = torch.zeros(size, size)
    block[:2] = 1.0
    assert torch.equal(classes.majority_vote(block.reshape(-1, 1), size).view(size, size), block)
    # The NaN fill averages the neighbours that exist.
    x = torch.arange(size * size, dtype=torch.float32).reshape(-1, 1)
    assert float(map_ops.neighbour_mean(x, size)[0]) == (1.0 + size) / 2


def test_light_scale_step_recovers_per_light_calibration_error():
    """Issue 13: images taken with intensities off by a few percent per light; the per-light
    scale step finds the factors (up to the fixed overall scale) from the residuals at the
    true maps, and a capture without error gives scales of exactly-ish 1."""
    data, theta, metal = _flat_level()
    n_l = data.pos.shape[0]
    true = 0.03 * torch.randn(n_l, generator=torch.Generator().manual_seed(3))
    true = true - true.mean()
    data.log_obs = data.log_obs + true[:, None, None] * data.obs / (data.obs + data.eps)  # images × e^true (bright pixels)
    data._light = {}
    idx = list(range(n_l))
    est = torch.zeros(n_l)
    for _ in range(3):
        data.set_light_scale(est)
        est = calibration.light_scale_step(data.residual(theta, metal, idx), idx, est, idx)
    assert torch.allclose(est, true, atol=2e-3)
    clean, _, _ = _flat_level()
    r = clean.residual(theta, metal, idx)
    assert float(calibration.light_scale_step(r, idx, torch.zeros(n_l), idx).abs().max()) < 1e-4


def test_nonlocal_fill_takes_the_measured_value_of_the_same_material(monkeypatch):
    """Issue 13: glossy pixels no highlight constrains (low information) get a unary prior toward
    the reliable pixels of the same base colour; another material is not mixed in."""
    data, theta, metal = _flat_level()
    p = theta.shape[0]
    theta = theta.clone()
    half = torch.arange(p) < p // 2
    theta[~half, 0:3] = params.logit(torch.tensor([0.1, 0.1, 0.1]))  # a second, dark material
    theta[~half, 4] = 2.0
    info = torch.full((p, 7), 1e3)
    blind = torch.zeros(p, dtype=torch.bool)
    blind[10:30] = True  # material 1, no highlight: roughness drifted
    theta[blind, 4] = -2.5
    info[blind, 3:5] = 1e-6
    monkeypatch.setattr(priors, "marginal_information", lambda *a: info)
    tgt, prec = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
    good = half & ~blind
    assert torch.allclose(tgt[blind, 4], theta[good, 4].mean().expand(int(blind.sum())), atol=1e-4)
    assert bool((prec[blind, 4] > 1e3 * info[blind, 4]).all())  # the prior dominates where data are silent
    assert bool((prec[good, 4] < 1e-2 * info[good, 4]).all())  # ... and not where they speak
    assert torch.allclose(tgt[~half, 4], torch.full((int((~half).sum()),), 2.0), atol=1e-4)


def test_light_position_step_finds_a_moved_light():
    """Issue 13: a light 1.5 cm from where capture.json says; the position step finds the offset."""
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = _flat_level(size=24)
    n_l = data.pos.shape[0]
    true = torch.zeros(n_l, 3)
    true[2] = torch.tensor([0.015, -0.01, 0.005])
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true, data.inten_stated), backend="compact")
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    data._light = {}
    off = torch.zeros(n_l, 3)
    for _ in range(4):
        data.set_light_offset(off)
        off = calibration.light_position_step(data, theta, metal, off, "principled", stride=1)
    assert torch.allclose(off, true, atol=2e-3)


def test_light_beside_the_camera_keeps_its_stated_position():
    """With ``at_camera=False`` the flash's position is held as capture.json states it.

    It is the lights' least determined position and took up what the two-hypothesis maps had
    not yet fitted (docs/recovery.md, issue 18: the recovery holds it in that stage); by
    default both steps move it toward where it is.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = _flat_level(size=24)
    n_l = data.pos.shape[0]
    true = torch.zeros(n_l, 3)
    true[-1] = torch.tensor([0.01, -0.01, -0.02])  # the flash (last light of light_layout)
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true, data.inten_stated), backend="compact")
    data.log_obs = torch.log(torch.clamp(img.permute(0, 2, 3, 1).reshape(n_l, -1, 3) + data.eps,
                                         min=0.5 * data.eps))
    data._light = {}
    zero, idx = torch.zeros(n_l, 3), list(range(n_l))
    held = calibration.light_position_step(data, theta, metal, zero, "principled", stride=1, at_camera=False)
    moved = calibration.light_position_step(data, theta, metal, zero, "principled", stride=1)
    assert torch.equal(held[-1], torch.zeros(3))
    assert float(torch.nn.functional.cosine_similarity(moved[-1], true[-1], dim=0)) > 0.5
    _, held = calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), zero, idx, "principled",
                                 at_camera=False)
    _, moved = calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), zero, idx, "principled")
    assert torch.equal(held[-1], torch.zeros(3)) and float(moved[-1].norm()) > 2e-3


def test_light_position_step_is_not_moved_by_pixels_the_maps_do_not_fit():
    """Lights where capture.json says, 1 % noise, and 4 % of the pixels rendered from another
    material (a front the maps have not fitted yet): the offsets stay within 5 mm (the noise
    alone moves them ~2 mm on these 576 pixels).

    Least squares let those pixels' residuals pull the lights to the 5 cm clamp.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = _flat_level(size=24)
    n_l = data.pos.shape[0]
    g = torch.Generator().manual_seed(3)
    other = theta.clone()
    wrong = torch.rand(theta.shape[0], generator=g) < 0.04
    other[wrong, 0:3] += 2.0  # a much brighter base colour there
    other[wrong, 4] -= 2.0  # and glossier
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(other, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated, data.inten_stated), backend="compact")
    img = img * (1 + 0.01 * torch.randn(img.shape, generator=g, dtype=img.dtype))
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    data._light = {}
    off = torch.zeros(n_l, 3)
    for _ in range(4):
        data.set_light_offset(off)
        off = calibration.light_position_step(data, theta, metal, off, "principled", stride=1)
    assert float(off.abs().max()) < 5e-3, off


def test_light_joint_step_finds_light_errors_the_maps_absorb():
    """A moved and a brightened light are found although the maps are fitted alongside.

    One light 1.9 cm from where capture.json says and another 6 % brighter: six rounds of (map
    LM step, joint light step) find both within 4 mm (up to a move of the whole rig) and
    0.2 %. The joint step eliminates each pixel's unknowns (the maps would follow a light's
    move); stepping the lights with the maps held fixed sees only what the maps have not
    already absorbed, and after the same six rounds is still ~1.2 cm and 0.7 % off here.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = _flat_level(size=24)
    n_l = data.pos.shape[0]
    true_off = torch.zeros(n_l, 3)
    true_off[2] = torch.tensor([0.015, -0.01, 0.005])
    true_s = torch.zeros(n_l)
    true_s[4] = 0.06
    true_s = true_s - true_s.mean()  # the overall scale is the stated one
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true_off, data.inten_stated * true_s.exp()[:, None]),
                             backend="compact")
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    data._light = {}
    idx = list(range(n_l))
    lam = torch.full((theta.shape[0], 1), 1e-3)
    th, s, off = theta.clone(), torch.zeros(n_l), torch.zeros(n_l, 3)
    for _ in range(6):
        th, lam, _, _ = lm.lm_step(data, th, metal, lam, Settings(), 1.0)
        s, off = calibration.light_joint_step(data, th, metal, s, off, idx, "principled")
        data.set_light_scale(s)
        data.set_light_offset(off)
    # What the images tell apart from a move of the whole rig (which the maps absorb: the
    # rig's placement is the stated one) is found; the rig's own moves are not made.
    free = calibration.rig_free_directions(data.pos_stated, data.points.mean(0))
    seen = (free @ (free.T @ true_off.reshape(-1))).reshape(n_l, 3)
    assert float((off - seen).norm(dim=1).max()) < 4e-3, off
    assert float((free @ (free.T @ off.reshape(-1)) - off.reshape(-1)).abs().max()) < 1e-6
    assert float((s - true_s).abs().max()) < 2e-3, s
    # Scales only: the offsets are left as they are.
    s2, off2 = calibration.light_joint_step(data, th, metal, s, off, idx, "principled", position=False)
    assert torch.equal(off2, off)


def test_light_joint_step_is_the_dense_joint_gauss_newton_step():
    """The Schur-complement step is the light part of one dense joint Gauss–Newton step.

    The dense step takes all the unknowns at once (every pixel's 7 and the lights'), from the
    full Jacobian (``jacfwd``), with the same weights, priors, damping and constraints; a map
    prior's gradient and curvature enter as the pixels' own do. In float64, so the two agree
    closely.
    """
    from torchbrdf.capture.synthetic import log_residual_points

    f64 = torch.float64
    data, theta, metal = _flat_level(size=8, lights=8, normal_tilt_deg=10.0)
    g = torch.Generator().manual_seed(1)
    data.points, data.camera, data.pos_stated, data.inten_stated = (
        data.points.to(f64), data.camera.to(f64), data.pos_stated.to(f64), data.inten_stated.to(f64))
    data.log_obs = data.log_obs.to(f64) + 0.01 * torch.randn(data.log_obs.shape, generator=g, dtype=f64)
    theta, metal = theta.to(f64), metal.to(f64)
    n_px, n_l = theta.shape[0], data.pos_stated.shape[0]
    idx = list(range(n_l))
    ref = idx[:-1]  # the last light is not a reference (as a held-out light that joined)
    s0 = 0.02 * torch.randn(n_l, generator=g, dtype=f64)
    s0[ref] -= s0[ref].mean()
    off0 = torch.zeros(n_l, 3, dtype=f64)
    grad = 1e-3 * torch.randn(theta.shape, generator=g, dtype=f64)
    curv = 0.5 * torch.rand(theta.shape, generator=g, dtype=f64)
    s1, off1 = calibration.light_joint_step(data, theta, metal, s0, off0, ref, "principled", map_prior=(grad, curv),
                                  scale_sigma=0.05, position_sigma=0.02, damping=1e-3, at_camera=False)

    def residual(x):  # all unknowns -> (P * L * 3,)
        t = x[: n_px * 7].reshape(n_px, 7)
        pos = data.pos_stated + x[n_px * 7: n_px * 7 + 3 * n_l].reshape(n_l, 3)
        inten = data.inten_stated * x[n_px * 7 + 3 * n_l:].exp()[:, None]
        p = params.decode(t, metal)
        return log_residual_points(p["normal"], data.points, data.camera, pos, inten, p,
                                   data.log_obs.permute(1, 0, 2), data.eps).reshape(-1)

    n_p = n_px * 7
    x0 = torch.cat((theta.reshape(-1), off0.reshape(-1), s0))
    r = residual(x0)
    j = torch.func.jacfwd(residual)(x0)
    sigma2 = float(r.pow(2).median())
    w = (3 * sigma2**0.5 / r.abs()).clamp(max=1.0)  # Huber weights
    hess = j.T @ (w[:, None] * j)
    grad_all = j.T @ (w * r)
    grad_all[:n_p] += grad.reshape(-1)
    pix = torch.arange(n_p)
    hess[pix, pix] += 1e-3 * hess[pix, pix] + 1e-9 + curv.reshape(-1)  # damping, the prior's curvature
    prior = torch.cat((torch.full((3 * n_l,), 1 / 0.02**2), torch.full((n_l,), 1 / 0.05**2))).to(f64) * sigma2
    hess[n_p:, n_p:] += torch.diag(prior)
    grad_all[n_p:] += prior * x0[n_p:]
    # Constraints: no move of the whole rig nor (at_camera=False) of the light beside the
    # camera, the reference lights' mean log scale kept.
    flash = calibration.camera_lights(data.pos_stated, data.camera, data.points.mean(0))
    assert flash.tolist() == [False] * (n_l - 1) + [True]
    free = calibration.rig_free_directions(data.pos_stated, data.points.mean(0), flash)
    is_ref = torch.tensor([float(i in ref) for i in idx], dtype=f64)
    keep_mean = torch.linalg.qr(is_ref[:, None], mode="complete")[0][:, 1:]
    t = torch.block_diag(torch.eye(n_p, dtype=f64), free, keep_mean)
    step = t @ torch.linalg.solve(t.T @ hess @ t, -(t.T @ grad_all))
    ref_off = step[n_p: n_p + 3 * n_l].reshape(n_l, 3)
    ref_s = s0 + step[n_p + 3 * n_l:]
    assert 2e-3 < float(ref_off.abs().max()) < 0.05 and float((ref_s - s0).abs().max()) > 1e-3  # it moves
    assert torch.allclose(off1, ref_off, atol=1e-7, rtol=1e-5), (off1, ref_off)
    assert torch.allclose(s1, ref_s, atol=1e-7, rtol=1e-5), (s1, ref_s)


def test_rig_free_directions_exclude_every_move_of_the_whole_rig():
    """``3L − 7`` orthonormal directions that exclude every move of all the lights together.

    Orthogonal to every translation, turn (about any axis through the centre) and dilation;
    one light alone moves freely.
    """
    from torchbrdf.capture.synthetic import light_layout

    f64 = torch.float64
    pos, _ = light_layout(8)
    centre = torch.tensor([0.1, -0.2, 0.0], dtype=f64)
    free = calibration.rig_free_directions(pos.to(f64), centre)
    n = pos.shape[0]
    assert free.shape == (3 * n, 3 * n - 7)
    assert torch.allclose(free.T @ free, torch.eye(3 * n - 7, dtype=f64), atol=1e-12)
    rel = pos.to(f64) - centre
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=f64)
    moves = [torch.tensor([0.3, -0.1, 0.2], dtype=f64).expand_as(rel),  # a translation
             0.05 * rel,  # a dilation about the centre
             torch.linalg.cross(axis.expand_as(rel), rel)]  # a turn about an axis through it
    for d in moves:
        assert float((free.T @ d.reshape(-1)).abs().max()) < 1e-12
    one = torch.zeros_like(rel)
    one[3, 0] = 1.0
    assert float((free.T @ one.reshape(-1)).norm()) > 0.8
    # Held lights: no component on their coordinates, three directions fewer each, still
    # orthonormal and free of every rig move; the others still move.
    held = torch.zeros(n, dtype=torch.bool)
    held[[1, 5]] = True
    part = calibration.rig_free_directions(pos.to(f64), centre, held)
    assert part.shape == (3 * n, 3 * n - 13)
    assert torch.allclose(part.T @ part, torch.eye(3 * n - 13, dtype=f64), atol=1e-12)
    assert float(part.reshape(n, 3, -1)[held].abs().max()) < 1e-12
    for d in moves:
        assert float((part.T @ d.reshape(-1)).abs().max()) < 1e-12
    assert float((part.T @ one.reshape(-1)).norm()) > 0.8


@pytest.mark.parametrize("at_camera", [True, False])
def test_flash_position_in_the_dual_stage_is_a_choice(tiny, at_camera):
    """``dual_calibration_at_camera=False`` holds the flash through the two-hypothesis stage.

    The light beside the camera keeps its stated position through the full-resolution
    two-hypothesis stage (the ring lights move already) and is estimated from the single-class
    stages on; by default it moves there too.
    """
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery
    from torchbrdf.recovery.calibration import camera_lights

    cap = load_capture(tiny)
    rec = Recovery(cap, Settings(seed=0, soft_metal=False, dual_calibration_at_camera=at_camera),
                   log=lambda m: None)
    full = rec.plan[-1][0]
    dual_end = max(i for i, (s, k, _) in enumerate(rec.plan) if s == full and k == "dual") + 1
    flash = camera_lights(cap.light_positions, cap.camera_position, rec.data(full).points.mean(0))
    assert int(flash.sum()) == 1
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < dual_end:
            rec.tick()
        assert float(rec.light_offset()[~flash].abs().max()) > 0
        assert bool((rec.light_offset()[flash] != 0).any()) == at_camera
        while rec.state["stage"] < len(rec.plan):
            rec.tick()
    assert bool((rec.light_offset()[flash] != 0).any())


def _recovery_at_polish(capture, cfg):
    """A :class:`Recovery` of ``capture`` run up to the start of its polish stage, and that stage's index."""
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery

    rec = Recovery(load_capture(capture), cfg, log=lambda m: None)
    polish = next(i for i, (_, k, _) in enumerate(rec.plan) if k == "polish")
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < polish:
            rec.tick()
    return rec, polish


@pytest.mark.parametrize("tie", [True, False])
def test_the_nonlocal_f0_tie_is_a_prior_of_the_fit(tiny, tie):
    """From the polish stage on, the metals' non-local F0 average is a unary prior of the fit.

    Set at the stage's start: precision ``prior_nonlocal_base`` on exactly the metal pixels'
    base colour, zero elsewhere, the target :func:`nonlocal_prior`'s average at that state; the
    stage's LM steps are given it. Without ``fit_nonlocal_tie`` there is none.
    """

    cfg = Settings(seed=0, soft_metal=False, fit_nonlocal_tie=tie)
    rec, polish = _recovery_at_polish(tiny, cfg)
    if not tie:
        assert "tie" not in rec.state
        return
    target, prec = rec.state["tie"]
    ism = rec.state["metal"][:, 0] > 0.5
    assert bool(ism.any()) and bool((~ism).any())
    assert torch.all(prec[ism, :3] == cfg.prior_nonlocal_base) and torch.all(prec[~ism] == 0)
    assert torch.all(prec[:, 3:] == 0)
    d = rec.data(rec.plan[polish][0])
    th, mt = rec.state["theta"][0], rec.state["metal"]
    r0, jtj, jtr = lm.gauss_newton(d, th, mt, d.train_idx, cfg.model)
    avg = priors.nonlocal_prior(d, th, mt, cfg, jtj, lm.pixel_cost(r0), jtr)[1]
    assert torch.allclose(target[ism, :3], avg[ism, :3], atol=1e-5)
    assert float((target[ism, :3] - th[ism, :3]).abs().max()) > 1e-3  # not the pixel's own value
    seen = []
    step = engine.lm_step

    def spy(*args, **kwargs):
        seen.append(kwargs.get("unary", args[7] if len(args) > 7 else None))
        return step(*args, **kwargs)

    engine.lm_step = spy
    try:
        with torch.no_grad():
            rec.tick()
    finally:
        engine.lm_step = step
    assert seen and seen[0] is not None and torch.equal(seen[0][1], prec)


def test_a_tie_pass_on_the_metal_pixels_alone_gives_the_full_passs_average(tiny):
    """The stage-start tie's pass on the metal pixels alone (``nonlocal_prior(rows=...)``).

    Without the roughness average only the metal pixels' normal equations enter the F0
    average, so the pass nobody takes up (the last stage's) is made on them alone: the same
    precisions and targets on every pixel as the full pass, the metal pixels' information, 0
    elsewhere. Fails if the rows are mixed up (a pixel given another's normal equations); rows
    without every metal pixel, or with the roughness average (which needs every pixel), are
    refused.
    """

    cfg = Settings(seed=0, soft_metal=False)
    rec, polish = _recovery_at_polish(tiny, cfg)
    d = rec.data(rec.plan[polish][0])
    th, mt = rec.state["theta"][0], rec.state["metal"]
    ism = mt[:, 0] > 0.5
    assert bool(ism.any()) and bool((~ism).any())
    r0, jtj, jtr = lm.gauss_newton(d, th, mt, d.train_idx, cfg.model)
    w, m, info = priors.nonlocal_prior(d, th, mt, cfg, jtj, lm.pixel_cost(r0), jtr)
    rows = torch.nonzero(ism)[:, 0]
    r_m, jtj_m, jtr_m = lm.gauss_newton(d.subset(rows), th[rows], mt[rows], d.train_idx, cfg.model)
    w_m, m_m, info_m = priors.nonlocal_prior(d, th, mt, cfg, jtj_m, lm.pixel_cost(r_m), jtr_m, rows=rows)
    assert torch.equal(w_m, w)
    assert torch.allclose(m_m, m, atol=1e-5, rtol=0)
    assert torch.allclose(info_m[ism], info[ism], rtol=1e-4) and torch.all(info_m[~ism] == 0)
    with pytest.raises(ValueError, match="prior_nonlocal"):
        priors.nonlocal_prior(d, th, mt, Settings(prior_nonlocal=1.0), jtj_m, lm.pixel_cost(r_m), jtr_m,
                         rows=rows)
    with pytest.raises(ValueError, match="every metal pixel"):  # a metal pixel left out
        priors.nonlocal_prior(d, th, mt, cfg, jtj_m[1:], lm.pixel_cost(r_m[1:]), jtr_m[1:], rows=rows[1:])


def test_a_pixel_subset_gathers_its_levels_targets(tiny):
    """``LevelData.subset``: a pixel list whose observations, log targets and residuals are the level's.

    Rows may repeat, come as a mask, or index a subset again; the targets are gathered from
    the level's when first used, and new targets set on the level reach the subsets made after;
    a subset given targets of its own is its subsets' level. A mask must cover every pixel.
    """
    import dataclasses

    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.levels import LevelData
    from torchbrdf.recovery.params import encode

    cap = load_capture(tiny)
    data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(0)
    p = data.points.shape[0]
    theta = encode({"base_color": torch.rand(p, 3, generator=g), "specular": torch.full((p, 1), 0.5),
                    "roughness": torch.rand(p, 1, generator=g) * 0.8 + 0.1,
                    "normal": torch.nn.functional.normalize(torch.randn(p, 3, generator=g) * 0.1
                                                            + torch.tensor([0.0, 0.0, 1.0]), dim=-1)})
    metal = (torch.rand(p, 1, generator=g) > 0.5).to(theta.dtype)
    idx = data.train_idx[:5]
    full = data.residual(theta, metal, idx)
    rows = torch.tensor([7, 3, 3, 900, 0])
    mask = torch.zeros(p, dtype=torch.bool)
    mask[[5, 40, 41]] = True
    for sub, at in ((data.subset(rows), rows), (data.subset(mask), mask.nonzero()[:, 0]),
                    (data.subset(rows).subset(torch.tensor([4, 1])), rows[[4, 1]])):
        assert torch.equal(sub.residual(theta[at], metal[at], idx), full[at])
        assert torch.equal(sub.obs, data.obs[:, at]) and torch.equal(sub.log_obs, data.log_obs[:, at])
        assert torch.equal(sub.points, data.points[at]) and sub.size == 0 and sub.images is None
    # a subset made before its level's first residual on a light set gathers them as well
    fresh = LevelData(dataclasses.replace(cap), 32, data.train_idx, data.eps).subset(rows)
    assert torch.equal(fresh.residual(theta[rows], metal[rows], idx), full[rows])
    # a subset with targets of its own is the level of its subsets
    own = data.subset(rows)
    own.log_obs = own.log_obs - 2.0
    at = rows[[4, 1]]
    nested = own.subset(torch.tensor([4, 1]))
    assert torch.allclose(nested.residual(theta[at], metal[at], idx), full[at] + 2.0)
    with pytest.raises(IndexError, match="mask"):
        data.subset(mask[:-1])
    # new targets on the level: the cached ones go
    data.log_obs = data.log_obs + 1.0
    assert torch.allclose(data.subset(rows).residual(theta[rows], metal[rows], idx), full[rows] - 1.0)


def test_two_unary_priors_sum_to_one():
    """``sum_unary``: the target and precision whose quadratic is the two priors' sum (up to a constant)."""
    from torchbrdf.recovery.lm import sum_unary, unary_cost

    g = torch.Generator().manual_seed(0)
    a = (torch.randn(5, 7, generator=g), torch.rand(5, 7, generator=g))
    b = (torch.randn(5, 7, generator=g), torch.rand(5, 7, generator=g))
    b[1][0] = 0.0  # absent on one pixel
    s = sum_unary(a, b)
    x, y = torch.randn(5, 7, generator=g), torch.randn(5, 7, generator=g)
    both = lambda t: unary_cost(t, a) + unary_cost(t, b)  # noqa: E731
    assert torch.allclose(both(x) - both(y), unary_cost(x, s) - unary_cost(y, s), atol=1e-5)
    assert sum_unary(a, None) is a and sum_unary(None, b) is b


def _recovery_with_a_brighter_light(tiny, **settings):
    """A :class:`Recovery` of ``tiny`` whose training light 3 is 6 % brighter than capture.json states."""
    import dataclasses as dc

    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery

    cap = load_capture(tiny)
    images = cap.images.clone()
    images[3] *= 1.06
    return Recovery(dc.replace(cap, images=images), Settings(seed=0, soft_metal=False, **settings),
                    log=lambda m: None)


@pytest.mark.parametrize("dual_calibration", [True, False])
def test_lights_are_estimated_from_the_dual_stages_on(tiny, dual_calibration):
    """A training light 6 % brighter than stated is found by the end of the full-resolution dual stage.

    Each pixel's better hypothesis gives the residuals, before the single-class stages; without
    ``dual_calibration`` the scale is still as stated there (the maps absorb it first). By
    default the intensity scales start at the coarsest level (the positions at full
    resolution); ``dual_calibration_coarse=False`` waits for the full-resolution level for
    both. By the end of the fit every light's scale is found to 1 % (0.3 % here; the
    alternating steps of ``light_joint=False`` end 1.2 % off on this capture, and move its
    correctly stated lights by 0.9–1.8 cm, against 0.2–0.7 cm).
    """
    rec = _recovery_with_a_brighter_light(tiny, dual_calibration=dual_calibration)
    full = rec.plan[-1][0]
    dual_end = max(i for i, (s, k, _) in enumerate(rec.plan) if s == full and k == "dual") + 1
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < dual_end:
            rec.tick()
    scale = rec.light_log_scale()
    rel = scale[3] - scale[rec.train_idx].mean()  # the overall scale is fixed by the stated ones
    if dual_calibration:  # most of it already (the single-class stages continue the estimate)
        assert 0.6 * math.log(1.06) < float(rel) < 1.2 * math.log(1.06), scale
        others = [k for k in rec.train_idx if k != 3]
        assert float((scale[others] - scale[rec.train_idx].mean()).abs().max()) < 0.03, scale
        # ... and by the end of the fit every training light's scale is within 1 % of the truth
        # (relative to the training lights' mean, which the stated intensities fix).
        with torch.no_grad():
            while rec.state["stage"] < len(rec.plan):
                rec.tick()
        scale = rec.light_log_scale()[rec.train_idx]
        true = torch.tensor([math.log(1.06) * (k == 3) for k in rec.train_idx])
        assert float(((scale - scale.mean()) - (true - true.mean())).abs().max()) < 0.01, scale
    else:
        assert float(scale.abs().max()) == 0.0


@pytest.mark.parametrize("light_joint", [True, False])
def test_coarse_dual_levels_estimate_the_intensity_scales_not_the_positions(tiny, light_joint):
    """The coarsest two-hypothesis level moves a light 6 % brighter than stated, and no light's position.

    Both light steps (the joint one and the alternating ``light_joint=False``): a coarse level's
    blended pixels would move the positions, which start at full resolution.
    """
    rec = _recovery_with_a_brighter_light(tiny, light_joint=light_joint)
    assert rec.plan[0][0] < rec.plan[-1][0] and rec.plan[0][1] == "dual"  # a coarse dual level
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < 1:
            rec.tick()
    coarse = float(rec.light_log_scale()[3] - rec.light_log_scale()[rec.train_idx].mean())
    assert coarse > 0.3 * math.log(1.06), rec.light_log_scale()
    assert float(rec.light_offset().abs().max()) == 0.0


def test_coarse_dual_calibration_can_be_left_to_full_resolution(tiny):
    """``dual_calibration_coarse=False``: the coarse two-hypothesis levels keep the stated lights.

    The full-resolution one estimates the intensity scales and positions from its first iteration.
    """
    rec = _recovery_with_a_brighter_light(tiny, dual_calibration_coarse=False)
    full = rec.plan[-1][0]
    first_full = min(i for i, (s, _, _) in enumerate(rec.plan) if s == full)
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < first_full:
            rec.tick()
        assert float(rec.light_log_scale().abs().max()) == 0.0
        assert float(rec.light_offset().abs().max()) == 0.0
        rec.tick()  # the full-resolution dual stage's first iteration estimates them
    assert float(rec.light_log_scale()[3] - rec.light_log_scale()[rec.train_idx].mean()) > 0.01
    assert float(rec.light_offset().abs().max()) > 0.0


def test_soft_lm_judges_each_candidate_by_its_linearisation():
    """One residual evaluation per LM iteration: a candidate's cost comes with its Jacobian.

    The start and each iteration's candidates but the last are linearised (the accepted ones'
    normal equations are the next iteration's; a rejected pixel keeps its own), the last
    iteration's candidates are only costed; the returned cost is ``cost`` at the returned
    unknowns, the priors' residuals included, and a candidate with non-finite residuals costs
    +inf. Fails if a candidate were costed and then linearised anew, if the cost left out the
    prior, or if it were taken from the cleaned residuals.
    """

    gen = torch.Generator().manual_seed(4)
    n, m = 6, 15
    a = torch.randn(n, m, 8, generator=gen, dtype=torch.float64)
    a[..., :3] *= (torch.arange(m)[:, None] % 3 == torch.arange(3)).to(a.dtype)
    b = torch.randn(n, m, generator=gen, dtype=torch.float64)
    at = lambda v, r: v if r is None else v[r]  # noqa: E731
    fn = lambda x, r=None: torch.einsum("nmk,nk->nm", at(a, r), x) - at(b, r)  # noqa: E731

    def prior(x, r=None):  # 2 (m - 0.3): metallic pulled toward 0.3
        row = torch.zeros(x.shape[0], 1, 8, dtype=x.dtype)
        row[:, 0, 7] = 2.0
        return 2.0 * (x[:, 7:8] - 0.3), row

    counts = {"jvp": 0, "cost": 0}

    def cost(x, r=None):
        counts["cost"] += 1
        return (torch.cat((fn(x, r), prior(x, r)[0]), -1) ** 2).sum(-1, keepdim=True)

    def jvp(v, tg, r):
        counts["jvp"] += 1
        return levels.vmapped_jvp(lambda u: fn(u, r))(v, tg)

    x0 = torch.zeros(n, 8, dtype=torch.float64)
    x, c = lm.soft_lm(jvp, cost, x0, 4, prior=prior, tol=0.0)
    assert counts == {"jvp": 4, "cost": 1}
    counts["cost"] = 0
    assert torch.allclose(c, cost(x), rtol=1e-12)
    assert float(c.sum()) < float(cost(x0).sum())
    # a candidate whose residuals are not finite costs +inf and is refused: pixel 0's optimum
    # lies at x[3] = 2, behind a wall at 0.5
    b[0] = a[0] @ torch.tensor([0.0, 0, 0, 2, 0, 0, 0, 0], dtype=torch.float64)

    def walled(x, r=None):
        out = fn(x, r)
        first = (torch.arange(n) if r is None else r) == 0
        return torch.where((first & (x[:, 3] > 0.5))[:, None], float("nan"), out)

    x, c = lm.soft_lm(lambda v, tg, r: levels.vmapped_jvp(lambda u: walled(u, r))(v, tg),
                      lambda v, r=None: lm.pixel_cost(walled(v, r)), x0, 6, tol=0.0)
    assert bool(torch.isfinite(c).all()) and float(x[0, 3]) <= 0.5
    assert torch.equal(c, lm.pixel_cost(walled(x)))


def test_soft_lm_solves_a_linear_least_squares_problem_with_metallic_free_or_held():
    """The soft-metal stage's per-pixel LM reaches each pixel's least-squares solution.

    Residuals linear in the 8 unknowns (each base-colour unknown acting on its own channel's
    residuals, every third: :func:`fit_jacobian`'s premise); with ``fix_metal`` the last
    unknown keeps its value (no tangent) and the other 7 solve the reduced problem. With
    ``tol`` a pixel whose accepted step gained less than that fraction of its cost stops (the
    others go on, evaluated on their rows alone); on these linear problems its cost is then
    within about that fraction of the optimum's.
    A pixel whose cost starts infinite does not stop on its first finite one. Per-pixel
    ``held`` unknowns keep their start and the others solve the reduced problem.
    """

    gen = torch.Generator().manual_seed(3)
    n, m = 5, 21
    a = torch.randn(n, m, 8, generator=gen, dtype=torch.float64)
    a[..., :3] *= (torch.arange(m)[:, None] % 3 == torch.arange(3)).to(a.dtype)  # channel c: base c only
    b = torch.randn(n, m, generator=gen, dtype=torch.float64)
    at = lambda v, r: v if r is None else v[r]  # noqa: E731
    fn = lambda x, r=None: torch.einsum("nmk,nk->nm", at(a, r), x) - at(b, r)  # noqa: E731

    def cost(x, r=None):
        return (fn(x, r) ** 2).sum(-1, keepdim=True)

    def jvp(f):  # the residuals and their derivatives along K directions, as LevelData.residual_jvp
        return lambda v, tg, r: levels.vmapped_jvp(lambda u: f(u, r))(v, tg)

    x0 = torch.zeros(n, 8, dtype=torch.float64)
    x0[:, 7] = 0.5
    x, c = lm.soft_lm(jvp(fn), cost, x0, 30, fix_metal=True, tol=0.0)
    want = torch.linalg.lstsq(a[..., :7], (b - a[..., 7] * 0.5)[..., None]).solution[..., 0]
    assert torch.equal(x[:, 7], x0[:, 7])
    assert torch.allclose(x[:, :7], want, atol=1e-6)
    assert torch.allclose(c, cost(x))
    # metallic free: the full solution, its last unknown clamped to [0, 1] by the projected steps
    x, _ = lm.soft_lm(jvp(fn), cost, x0, 60, tol=0.0)
    full = torch.linalg.lstsq(a, b[..., None]).solution[..., 0]
    inside = (full[:, 7] > 0) & (full[:, 7] < 1)
    assert torch.allclose(x[inside], full[inside], atol=1e-5)
    assert bool(((x[:, 7] >= 0) & (x[:, 7] <= 1)).all())
    # converged pixels leave: each pixel's cost within 1 % of its optimum, and the calls on a
    # subset of the rows (some pixels stop before others) give each pixel its own data
    # (two pixels start near their optimum, three far: the clamped steps take those longer)
    calls: list = []
    near = torch.tensor([0.01, 0.01, 20.0, 20.0, 20.0], dtype=torch.float64)[:, None]
    start = torch.cat((want + near, x0[:, 7:]), -1)
    logged = lambda v, r=None: calls.append(r) or fn(v, r)  # noqa: E731
    x, c = lm.soft_lm(jvp(logged), cost, start, 60, fix_metal=True, tol=1e-2)
    best = cost(torch.cat((want, x0[:, 7:]), -1))
    assert bool((c <= best * 1.02 + 1e-9).all()) and torch.allclose(c, cost(x))
    assert any(r is not None and 0 < len(r) < n for r in calls)
    # priors given with their Jacobian (not part of fn): the augmented problem's solution, more
    # rows per pixel — one on metallic alone, sqrt(s) (m - t), and one coupling an unknown to
    # metallic, sqrt(s) (x0 - 0.3 - 0.5 m) (as the blend line couples base colour and metallic)
    s, t = 4.0, torch.full((n, 1), 0.4, dtype=torch.float64)
    row = torch.zeros(n, 2, 8, dtype=torch.float64)
    row[:, 0, 7] = math.sqrt(s)
    row[:, 1, 0], row[:, 1, 7] = math.sqrt(s), -0.5 * math.sqrt(s)
    rhs = torch.cat((b, math.sqrt(s) * t, torch.full_like(t, 0.3 * math.sqrt(s))), 1)

    def prior(v, r=None):
        return torch.einsum("nkj,nj->nk", at(row, r), v) - at(rhs[:, m:], r), at(row, r)

    def cost_p(v, r=None):
        return cost(v, r) + (prior(v, r)[0] ** 2).sum(-1, keepdim=True)

    x, _ = lm.soft_lm(jvp(fn), cost_p, x0, 60, prior=prior, tol=0.0)
    aug = torch.linalg.lstsq(torch.cat((a, row), 1), rhs[..., None]).solution[..., 0]
    inside = (aug[:, 7] > 0) & (aug[:, 7] < 1)
    assert bool(inside.any()) and not torch.allclose(aug[inside], full[inside], atol=1e-3)
    assert torch.allclose(x[inside], aug[inside], atol=1e-5)
    # ... also when the converged pixels leave (the prior evaluated on row subsets)
    calls.clear()
    logged_p = lambda v, r=None: calls.append(r) or prior(v, r)  # noqa: E731
    x, c = lm.soft_lm(jvp(fn), cost_p, torch.cat((aug[:, :7] + near, x0[:, 7:]), -1), 60, prior=logged_p,
                      tol=1e-2)
    assert any(r is not None and 0 < len(r) < n for r in calls)
    # (where the optimum's metallic is in [0, 1]: elsewhere the clamped fit cannot reach it)
    assert bool((c[inside] <= cost_p(aug)[inside] * 1.02 + 1e-9).all()) and torch.allclose(c, cost_p(x))
    # a cost that starts infinite (a residual undefined at the start, NaN): its first finite
    # step is not convergence
    def fn_inf(v, r=None):  # its first residual undefined while the first unknown is below -5
        f = fn(v, r)
        return torch.cat((torch.where(v[:, :1] < -5.0, float("nan"), f[:, :1]), f[:, 1:]), -1)

    cost_inf = lambda v, r=None: lm.pixel_cost(fn_inf(v, r))  # noqa: E731
    start_inf = torch.cat((want, x0[:, 7:]), -1)
    start_inf[:, 0] = -6.0
    x, c = lm.soft_lm(jvp(fn_inf), cost_inf, start_inf, 60, fix_metal=True, tol=1e-2)
    assert bool((c <= best * 1.02 + 1e-9).all()), (c, best)
    # ... and with metallic held, the prior's other columns still act (the coupled row)
    x, _ = lm.soft_lm(jvp(fn), cost_p, x0, 30, fix_metal=True, prior=prior, tol=0.0)
    rhs_h = rhs - torch.cat((a, row), 1)[..., 7] * 0.5
    held = torch.linalg.lstsq(torch.cat((a, row), 1)[..., :7], rhs_h[..., None]).solution[..., 0]
    assert torch.allclose(x[:, :7], held, atol=1e-6)
    # per-pixel held unknowns (``held``, as the glossy/rough tie holds roughness): a held entry
    # keeps its start exactly and the others solve the reduced problem, also when converged
    # pixels leave and the mask is taken on their rows
    hold = torch.zeros(n, 8, dtype=torch.bool)
    for i in range(n - 1):  # the last pixel holds nothing
        hold[i, 3 + i % 4] = True
    calls.clear()
    x, _ = lm.soft_lm(jvp(logged), cost, start, 60, fix_metal=True, tol=1e-2, held=hold)
    assert any(r is not None and 0 < len(r) < n for r in calls)
    assert torch.equal(x[hold], start[hold])
    x, _ = lm.soft_lm(jvp(fn), cost, start, 60, fix_metal=True, tol=0.0, held=hold)
    assert torch.equal(x[hold], start[hold])
    for i in range(n):
        f = (~hold[i, :7]).nonzero()[:, 0]
        rhs_i = b[i] - a[i, :, 7] * 0.5 - a[i][:, hold[i]] @ start[i][hold[i]]
        want_i = torch.linalg.lstsq(a[i][:, f], rhs_i[:, None]).solution[:, 0]
        assert torch.allclose(x[i, f], want_i, atol=1e-6), i


def test_soft_prior_residuals_and_jacobian():
    """The soft-metal priors' residuals, and their Jacobian against ``torch.func.jacrev``.

    The double well is 0 at metallic 0 and 1; the pull is 0 at its target; the blend line is 0
    where the base colour is the blend of its two ends at the pixel's own metallic, and moves by
    −√w (metal − dielectric) per unit of metallic. Per-pixel weights too.
    """

    gen = torch.Generator().manual_seed(4)
    n = 6
    x = torch.randn(n, 8, generator=gen, dtype=torch.float64)
    x[:, 7] = torch.rand(n, generator=gen, dtype=torch.float64)
    d = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.5
    e = 0.5 + torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.5
    target = torch.rand(n, 1, generator=gen, dtype=torch.float64)
    smooth = torch.rand(n, 1, generator=gen, dtype=torch.float64) + 0.5
    lw = torch.rand(n, 1, generator=gen, dtype=torch.float64) + 1.0
    res, jac = soft_metal.soft_prior(x, 3.0, target, smooth, (d, e), lw)
    assert res.shape == (n, 5) and jac.shape == (n, 5, 8)
    want = torch.func.vmap(torch.func.jacrev(
        lambda xi, ti, si, di, ei, wi: soft_metal.soft_prior(xi[None], 3.0, ti[None], si[None], (di[None], ei[None]),
                                                     wi[None])[0][0]))(x, target, smooth, d, e, lw)
    assert torch.allclose(jac, want, atol=1e-12)
    m = x[:, 7:8]
    assert torch.allclose(res[:, 0:1], math.sqrt(3.0) * m * (1 - m))
    assert torch.allclose(res[:, 1:2], smooth.sqrt() * (m - target))
    on_line = x.clone()
    on_line[:, 0:3] = torch.logit(d + m * (e - d))
    r_on = soft_metal.soft_prior(on_line, 3.0, None, 0.0, (d, e), lw)[0]
    assert r_on.shape == (n, 4) and float(r_on[:, 1:].abs().max()) < 1e-12
    moved = on_line.clone()
    moved[:, 7] += 0.01
    r_mv = soft_metal.soft_prior(moved, 3.0, None, 0.0, (d, e), lw)[0]
    assert torch.allclose(r_mv[:, 1:], -lw.sqrt() * (e - d) * 0.01, atol=1e-12)
    # a float weight is the same as a constant per-pixel one; no line, no line rows
    r_f = soft_metal.soft_prior(x, 3.0, target, 2.0, (d, e), 1.5)[0]
    r_t = soft_metal.soft_prior(x, 3.0, target, torch.full_like(m, 2.0), (d, e), torch.full_like(m, 1.5))[0]
    assert torch.allclose(r_f, r_t) and soft_metal.soft_prior(x, 3.0)[0].shape == (n, 1)


def _silver_capture(size=8, lights=8):
    """A noise-free flat silver metal (F0 0.9 / 0.85 / 0.8, roughness 0.25), float64."""
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import light_layout, render_capture

    maps = _silver_maps(size)
    pos, inten = light_layout(lights)
    imgs = render_capture(maps, (pos, inten), backend="compact").double()
    camera = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    return Capture(images=imgs, light_positions=pos.double(), light_intensities=inten.double(),
                   camera_position=camera, width=size, height=size,
                   files=tuple(f"{k}.exr" for k in range(len(pos))))


def _silver_maps(size):
    return {"base_color": torch.tensor([0.9, 0.85, 0.8])[:, None, None].expand(3, size, size),
            "roughness": torch.full((1, size, size), 0.25), "metallic": torch.ones(1, size, size),
            "specular": torch.full((1, size, size), 0.5),
            "normal": torch.tensor([0.0, 0.0, 1.0])[:, None, None].expand(3, size, size)}


def _silver_level(size=8, lights=8):
    """:func:`_silver_capture` at one level: ``(LevelData, theta (P, 7) at the truth, metal (P, 1))``."""

    cap = _silver_capture(size, lights)
    data = levels.LevelData(cap, size, list(range(len(cap))), float(0.01 * cap.images.mean()))
    p = {k: v.reshape(v.shape[0], -1).T.contiguous().double() for k, v in _silver_maps(size).items()}
    metal = p.pop("metallic")
    return data, params.encode(p), metal


def test_conditional_shift_keeps_a_metal_on_its_f0_roughness_valley():
    """After the non-local fusion moves a metal's F0, its other unknowns follow it.

    Without ``conditional_shift`` the pixel leaves the F0–roughness valley of the GGX tail and
    no longer fits its images (dusty_metal 3: 8645 such pixels at 10–100× the noise). The shift
    is the linear least-squares response of the free unknowns, checked against a dense solve,
    and it takes back most of the cost the F0 move alone adds.
    """

    size = 8
    data, theta, metal = _silver_level(size)
    idx = data.train_idx
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    delta = torch.zeros_like(theta)
    delta[:, 0:3] = 0.4  # F0 0.9 -> 0.93: what the fusion does to a dark tail pixel
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    moved[5] = False  # a pixel the fusion leaves alone: no shift at all
    moved[9, 0:3] = False  # one whose roughness was moved instead
    moved[9, 4] = True
    delta[9] = 0.0
    delta[9, 4] = 0.05  # small: the F0 response is ~16x (the valley), inside the ±3 clamp
    shift = lm.conditional_shift(jtj, delta, moved)
    assert torch.equal(lm.conditional_shift(jtj, delta, moved, chunk=7), shift)  # blocks change nothing
    assert torch.equal(shift[moved], torch.zeros_like(shift[moved]))
    assert torch.equal(shift[5], torch.zeros_like(shift[5]))
    # Against a dense least-squares solve of the linearised residuals, pixel by pixel.
    for k in (0, 9, 27, 63):
        fn = lambda t: data.residual(t, metal[k:k + 1], idx, "principled", rows=slice(k, k + 1))[0]  # noqa: E731
        j = torch.func.jacfwd(fn)(theta[k:k + 1])[:, 0]  # (M, 7)
        free = ~moved[k]
        jo = j[:, free]
        rhs = -(j[:, ~free] @ delta[k, ~free])
        keep = jo.abs().sum(0) > 0  # a metal's specular does not reach the image
        sol = torch.linalg.lstsq(jo[:, keep], rhs[:, None]).solution[:, 0]
        assert torch.allclose(shift[k, free][keep], sol, rtol=1e-4, atol=1e-6), (k, shift[k], sol)

    def cost(t):
        r = data.residual(t, metal, idx, "principled")
        return float((r * r).sum())

    alone = cost(theta + delta)
    followed = cost(theta + delta + shift)
    assert float(shift[9, 0:3].abs().max()) > 0  # F0 follows a moved roughness
    assert cost(theta) < 1e-8 and followed < 0.2 * alone, (alone, followed)


def test_a_held_refit_takes_the_free_unknowns_to_their_conditional_optimum():
    """``refit_pixels(held=...)`` takes the free unknowns to the data optimum given the held.

    The held unknowns keep their start exactly; the others go further than the linear
    response where the valley bends.

    This is how a fused metal's roughness and normal follow its fused F0 when
    ``conditional_shift`` falls short (rusted_metal 68's corners: 10³–10⁴ noise variances).
    """

    data, theta, metal = _silver_level()
    idx, n = data.train_idx, theta.shape[0]
    rows = torch.arange(n)
    held = torch.zeros(n, 7, dtype=torch.bool)
    held[:, 0:3] = True
    # F0 0.9 -> 0.96 (held), roughness left at the truth: off the valley of the moved F0
    start = theta.clone()
    start[:, 0:3] += 1.0

    def cost(t):
        return lm.pixel_cost(data.residual(t, metal, idx, "principled"))[:, 0]

    out, c = lm.refit_pixels(data, theta, metal, rows, [start], idx, "principled", iters=10, held=held)
    assert torch.equal(out[:, 0:3], start[:, 0:3])  # held exactly
    assert torch.allclose(c[:, 0], cost(out))
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    linear = start + lm.conditional_shift(jtj, start - theta, held)
    # the F0 rise is paid back by a smoother lobe; the refit fits better than the linear
    # response from the truth, and far better than the move alone
    assert float((out[:, 4] - theta[:, 4]).mean()) < -0.02
    assert float(cost(out).sum()) < 0.5 * float(cost(linear).sum()) < 0.5 * float(cost(start).sum())
    free = lm.refit_pixels(data, theta, metal, rows, [start], idx, "principled", iters=10)[0]
    assert float((free[:, 0:3] - start[:, 0:3]).abs().max()) > 0.1  # without held, F0 moves


def test_fusion_averages_each_metals_own_data_optimum_not_where_its_fit_stopped():
    """With the data gradients, the non-local F0 average takes each pixel at its own optimum.

    ``nonlocal_prior(jtr=...)``: where one Gauss–Newton step predicts it.

    A metal fit left part-way along the F0–roughness valley (its F0 dark, its roughness
    compensating, as from the dark metal start) otherwise drags the average toward where it
    stopped: rusted_metal's bright silver came out 1–2 % dark.
    """
    import types


    size = 8
    data, theta, metal = _silver_level(size)
    idx = data.train_idx
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    # Half the pixels stopped along the valley: F0 darker by 0.3 logit, the others following.
    stopped = (torch.arange(theta.shape[0]) % 2 == 0)[:, None]
    delta = torch.zeros_like(theta)
    delta[:, 0:3] = -0.3
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    off = theta + delta + lm.conditional_shift(jtj, delta, moved)
    off = torch.where(stopped, off, theta)
    _, jtj_off, jtr_off = lm.gauss_newton(data, off, metal, idx, "principled")
    cfg = Settings(nonlocal_sigma=1000.0)  # one flat window
    lvl = types.SimpleNamespace(size=size, train_idx=idx)
    # (no fit weights: noise-free, the stopped pixels would weigh ~0 against the exact ones)
    _, m_stop, _ = priors.nonlocal_prior(lvl, off, metal, cfg, jtj_off)
    _, m_opt, _ = priors.nonlocal_prior(lvl, off, metal, cfg, jtj_off, jtr=jtr_off)
    err_stop = float((m_stop[:, 0:3] - theta[:, 0:3]).abs().mean())
    err_opt = float((m_opt[:, 0:3] - theta[:, 0:3]).abs().mean())
    assert err_stop > 0.05  # the stopped pixels' share of the weights × 0.3
    assert err_opt < 0.2 * err_stop, (err_stop, err_opt)
    # the Newton step itself: zero at the truth, and it leaves held unknowns alone
    assert float(lm.newton_step(jtj, torch.zeros_like(theta)).abs().max()) == 0.0
    g = torch.randn(theta.shape, generator=torch.Generator().manual_seed(0), dtype=theta.dtype)
    held = torch.zeros_like(moved)
    held[:, 4] = True
    assert float(lm.newton_step(jtj, g, held)[:, 4].abs().max()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_newton_step_solves_the_damped_normal_equations_on_the_free_unknowns(dtype):
    """``newton_step`` is ``−(H_ff + diag(1e-6 diag(H_ff) + 1e-9))⁻¹ g_f``, 0 on the held unknowns.

    An independent float64 solve per pixel, with and without held unknowns (a singular ``H``
    whose held direction is the null one included); neither input is written to (the float64
    algebra works in place on copies, and a float64 input is no copy by ``.double()``).
    """

    gen = torch.Generator().manual_seed(3)
    P = 40
    j = torch.randn(P, 7, 12, generator=gen, dtype=torch.float64)
    jtj = (j @ j.transpose(1, 2)).to(dtype)
    jtj[:5, 4, :] = 0.0  # singular along roughness: held below, so the free block is regular
    jtj[:5, :, 4] = 0.0
    g = (0.1 * torch.randn(P, 7, generator=gen, dtype=torch.float64)).to(dtype)
    held = torch.zeros(P, 7, dtype=torch.bool)
    held[:5, 4] = True
    held[10:20, 0:3] = True
    jtj0, g0 = jtj.clone(), g.clone()

    def reference(h_all, g_all, hd):
        out = torch.zeros(P, 7, dtype=torch.float64)
        for p in range(P):
            f = ~hd[p]
            h = h_all[p].double()[f][:, f]
            h = h + torch.diag(1e-6 * torch.diagonal(h) + 1e-9)
            out[p, f] = torch.linalg.solve(h, -g_all[p].double()[f]).clamp(-3, 3)
        return out

    tol = 1e-9 if dtype == torch.float64 else 1e-5
    no_held = torch.zeros_like(held)
    for hd, arg in ((no_held, None), (held, held)):
        step = lm.newton_step(jtj[5:] if arg is None else jtj, g[5:] if arg is None else g,
                             None if arg is None else arg)
        want = reference(jtj, g, hd)[5:] if arg is None else reference(jtj, g, hd)
        assert step.dtype == dtype
        torch.testing.assert_close(step.double(), want, rtol=tol, atol=tol)
    assert torch.equal(jtj, jtj0) and torch.equal(g, g0)  # the inputs are the caller's, unchanged


def test_fusion_rounds_refine_the_average_without_compounding_the_pull():
    """``fuse_rounds``: every round combines the same own value with its round's average.

    A pixel's pull toward the average stays ``κ / (info + κ)`` however many rounds. A first
    version fused each round from the last one's fused value: three rounds pulled a pixel
    ``1 − (1 − s)³`` of the way, a hidden multiplier on ``prior_nonlocal_base``.
    """

    cap = _silver_capture()
    data, theta, metal = _silver_level()
    _, jtj, _ = lm.gauss_newton(data, theta, metal, data.train_idx, "principled")
    delta = torch.zeros_like(theta)
    gen = torch.Generator().manual_seed(1)
    delta[:, 0:3] = 0.3 * torch.randn(theta.shape[0], 1, generator=gen, dtype=theta.dtype)  # F0 spread
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    start = theta + delta + lm.conditional_shift(jtj, delta, moved)  # each on its own valley
    info = lm.marginal_information(data, start, metal, "principled")[:, 0]
    well = info > info.median()  # pulled only part of the way (info ≫ κ)
    pull = {}
    for rounds in (1, 3):
        cfg = Settings(soft_metal=False, fuse_rounds=rounds, nonlocal_sigma=1000.0)
        rec = engine.Recovery(cap, cfg, log=lambda *a: None)
        rec.init_state()
        st = rec.state
        st["stage"], st["theta"], st["metal"] = len(rec.plan) - 1, [start.clone()], metal
        st["lam"] = [torch.full_like(metal, 1e-2)]
        rec.end_stage()
        pull[rounds] = float((st["theta"][0][well, 0:3] - start[well, 0:3]).abs().mean())
    assert pull[1] > 1e-3  # the fusion does move them
    assert pull[3] < 1.3 * pull[1], pull  # compounding: about 2.5x here


@pytest.mark.parametrize("model", ["principled", "svbrdf_ggx"])
@pytest.mark.parametrize("n_t", [7, 8])
def test_fit_jacobian_is_the_per_unknown_forward_mode_jacobian(tiny, n_t, model):
    """``fit_jacobian`` equals one forward-mode pass per unknown, column by column.

    The base colour's three columns come from one pass; checked for the seven map unknowns and
    with metallic as an eighth (the soft-metal fit's). Fails if a base-colour column took
    another channel's residuals, or if a channel leaked into another (a tint would couple them);
    for both of the fit's models.
    """
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.levels import LevelData, vmapped_jvp
    from torchbrdf.recovery.lm import fit_jacobian

    cap = load_capture(tiny)
    data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(3)
    x = torch.randn(32 * 32, 8, generator=g) * 0.4
    x[:, 7] = torch.rand(32 * 32, generator=g)  # a fractional metallic

    def fn(v):
        return data.residual(v[:, :7], v[:, 7:8] if n_t == 8 else x[:, 7:8], data.train_idx, model)

    xs = x if n_t == 8 else x[:, :7]
    for jvp in (lambda v, tg: data.residual_jvp(v, x[:, 7:8], data.train_idx, model, tg), vmapped_jvp(fn)):
        r, jac = fit_jacobian(jvp, xs, n_t)
        assert jac.shape == (32 * 32, n_t, 3 * len(data.train_idx))
        assert torch.allclose(r, fn(xs), rtol=1e-6, atol=1e-6)
        for k in range(n_t):
            col = torch.func.jvp(fn, (xs,), (torch.eye(xs.shape[1])[k].expand_as(xs),))[1]
            assert torch.allclose(jac[:, k], col, rtol=1e-5, atol=1e-6), k


def test_fit_jacobian_benchmark_times_both_ways(tiny):
    """``python -m torchbrdf.bench.jvp --fit``: the direct and the vmapped Jacobian, side by side."""
    from torchbrdf.bench.jvp import fit_jacobian_times

    threads = torch.get_num_threads()
    res = fit_jacobian_times(sizes=(16, 64), threads=1, reps=1, capture=str(tiny))
    assert set(res) == {(16, "direct"), (16, "vmap"), (64, "direct"), (64, "vmap")}
    assert all(t > 0 for t in res.values())
    assert torch.get_num_threads() == threads  # restored


def test_blur_is_the_truncated_normalised_gaussian():
    """``blur`` is the truncated, normalised Gaussian, against a direct double sum.

    Σ over the pixels within 3σ (and the map) of g(dx) g(dy) x, g the Gaussian normalised over
    its 2r + 1 taps, zero outside the map.
    """
    from torchbrdf.recovery.map_ops import blur

    size = 9
    g = torch.Generator().manual_seed(0)
    x = torch.rand(size * size, 2, generator=g, dtype=torch.float64)
    img = x.T.reshape(2, size, size)
    for sigma in (0.8, 2.0, 5.0):  # r = 2, 6 and (capped at the map) 8
        r = int(min(3 * sigma, size - 1))
        taps = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma) ** 2)
        k = lambda d: math.exp(-0.5 * (d / sigma) ** 2) / float(taps.sum()) if abs(d) <= r else 0.0  # noqa: E731
        want = torch.zeros(2, size, size, dtype=torch.float64)
        for i in range(size):
            for j in range(size):
                for a in range(size):
                    for b in range(size):
                        want[:, i, j] += k(a - i) * k(b - j) * img[:, a, b]
        got = blur(x, size, sigma).T.reshape(2, size, size)
        assert torch.allclose(got, want, atol=1e-12), sigma


def test_the_polish_stage_first_step_reuses_the_ties_linearisation(tiny):
    """The polish stage's first LM step is handed the Gauss–Newton pass of its F0 tie.

    Made at the stage's start and re-linearised where propagation and the normal search moved
    pixels since: equal to the step's own pass (so the step is the same), handed on once only.
    """

    rec, _ = _recovery_at_polish(tiny, RecoveryConfig(seed=0, soft_metal=False))
    assert rec._stage_gn is not None
    th0 = rec._stage_gn[0]
    seen = []
    step = engine.lm_step

    def spy(data, theta, metal, lam, cfg_, lr, extra=None, unary=None, gn=None):
        own = lm.gauss_newton(data, theta, metal, data.train_idx, cfg_.model)
        seen.append((gn, own, bool((theta != th0).any())))
        return step(data, theta, metal, lam, cfg_, lr, extra, unary, gn)

    engine.lm_step = spy
    try:
        with torch.no_grad():
            rec.tick()
            rec.tick()
    finally:
        engine.lm_step = step
    (gn, own, moved), (gn2, _, _) = seen
    assert moved  # propagation / normal search moved some pixels: they were re-linearised
    assert gn is not None and gn2 is None and rec._stage_gn is None
    for a, b in zip(gn, own):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
