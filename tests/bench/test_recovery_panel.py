"""The recovery panel's plumbing: its grid, the second forward model, scoring and --compare.

No recovery runs here (a capture takes tens of seconds); the scorer is checked with an
oracle that returns the truth, and a wrong "recovery" that calls everything metal.
"""

import json
import math

import pytest
import torch

from torchbrdf.bench import recovery_panel as rp
from torchbrdf.brdf.principled import principled
from torchbrdf.capture.families import FAMILIES, make_family_material
from torchbrdf.capture.format import load_capture

F64 = torch.float64


def test_grid_split_once_and_covered():
    tuning, report, every = (rp.panel_cases(s) for s in ("tuning", "report", "all"))
    assert {c.seed for c in tuning}.isdisjoint({c.seed for c in report})
    assert sorted(map(str, every)) == sorted(map(str, tuning + report))
    materials = {(c.family, c.seed) for c in every}
    assert len(materials) >= 40 and len({f for f, _ in materials}) >= 8
    for split in (tuning, report):
        by_mat: dict = {}
        for c in split:
            by_mat.setdefault((c.family, c.seed), set()).add(c.lights)
            assert c.split == ("tuning" if c in tuning else "report")
        assert all({12, 17} <= ls for ls in by_mat.values())  # every material at 12 and 17 lights
        assert 0 < sum(8 in ls for ls in by_mat.values()) < len(by_mat)  # 8 lights on a subset
        assert {(c.model, c.calibration_error) for c in split} == {(m, e) for m in rp.FORWARD_MODELS
                                                                    for e in (False, True)}
    quick = rp.panel_cases("report", quick=True)
    assert len(quick) == 4 and len({(c.model, c.calibration_error) for c in quick}) == 4
    with pytest.raises(ValueError, match="split"):
        rp.panel_cases("holdout")


def _dirs(theta_l, theta_v, phi=math.pi):
    def d(t, p):
        return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=F64)

    l, v = d(theta_l, 0.0), d(theta_v, phi)
    return l[None], v[None], torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)


MATERIALS = [
    {"base_color": torch.tensor([[0.6, 0.3, 0.2]], dtype=F64), "roughness": 0.7, "metallic": 0.0, "specular": 0.4},
    {"base_color": torch.tensor([[0.2, 0.5, 0.3]], dtype=F64), "roughness": 0.2, "metallic": 0.0, "specular": 0.6},
    {"base_color": torch.tensor([[0.95, 0.64, 0.54]], dtype=F64), "roughness": 0.35, "metallic": 1.0,
     "specular": 0.5},
]


@pytest.mark.parametrize("mat", MATERIALS)
def test_second_model_agrees_at_normal_incidence(mat):
    # l = v = n: D and G agree (G = 1), exact Fresnel at the IOR of F0 = 0.08 specular is F0,
    # Schlick's is F0 (base for metals), and Burley's diffuse is Lambert's there.
    l, v, n = _dirs(0.0, 0.0)
    a, b = rp.exact_fresnel_brdf(l, v, n, **mat), principled(l, v, n, **mat)
    assert torch.allclose(a, b, rtol=1e-9, atol=0), (a, b)


def test_second_model_differs_on_purpose():
    rough, glossy, metal = MATERIALS
    # Rough dielectric seen at grazing angles: Burley's retro-reflection vs Lambert.
    l, v, n = _dirs(math.radians(75), math.radians(75), phi=0.0)
    a, b = rp.exact_fresnel_brdf(l, v, n, **rough), principled(l, v, n, **rough)
    assert (b / a - 1).abs().min() > 0.2
    # Its diffuse is Lambert: with no specular and metallic 0, f = base / pi away from grazing,
    # a white furnace of albedo = base (the specular lobe has F0 -> 0).
    flat = {**rough, "specular": 0.0}
    for tl, tv in ((0.1, 0.2), (0.6, 0.3), (1.0, 0.9)):
        l, v, n = _dirs(tl, tv)
        assert torch.allclose(rp.exact_fresnel_brdf(l, v, n, **flat), flat["base_color"] / math.pi, rtol=1e-3)
    # Glossy dielectric near its mirror direction off normal: exact Fresnel vs Schlick.
    l, v, n = _dirs(math.radians(70), math.radians(70), phi=math.pi)
    a, b = rp.exact_fresnel_brdf(l, v, n, **glossy), principled(l, v, n, **glossy)
    assert (a / b - 1).abs().max() > 0.01
    # Zero below the horizon, like the principled model.
    l, v, n = _dirs(math.radians(100), 0.3)
    assert (rp.exact_fresnel_brdf(l, v, n, **metal) == 0).all()


def test_calibration_error_is_three_percent_and_one_centimetre(tmp_path):
    pos = torch.randn(17, 3)
    inten = torch.full((17, 3), 30.0)
    p2, i2 = rp.calibration_error(pos, inten, seed=5)
    assert torch.allclose((p2 - pos).norm(dim=-1), torch.full((17,), 0.01), atol=1e-6)
    log_ratio = (i2 / inten).log()[:, 0].double()
    assert abs(float(log_ratio.mean())) < 1e-6 and 0.015 < float(log_ratio.std()) < 0.05
    assert torch.equal(rp.calibration_error(pos, inten, seed=5)[0], p2)
    # The capture states the erroneous lights; the returned truth is the rendered one.
    case = rp.PanelCase("plaster", 2, 8, "exact_fresnel", True)
    truth, (tp, ti) = rp.render_case(case, tmp_path, size=16)
    cap = load_capture(tmp_path)
    assert cap.images.shape[0] == 8 and torch.equal(truth["roughness"], make_family_material("plaster", 2, 16)[
        "roughness"])
    assert torch.allclose((cap.light_positions - tp).norm(dim=-1), torch.full((8,), 0.01), atol=1e-5)


def test_scores_of_an_oracle_and_of_a_false_metal_recovery():
    case = rp.PanelCase("cloth", 2, 12, "principled", False)
    row = rp.run_case(case, 24, recover_fn=lambda p: make_family_material("cloth", 2, 24))
    assert row["case"] == case.name and row["split"] == "report"
    assert all(row[m] < 1e-4 for m in ("base_rmse", "roughness_rmse", "metallic_rmse", "specular_rmse",
                                        "normal_deg"))
    assert row["false_metal"] == 0 and row["heldout_worst_db"] > 80

    def all_metal(p):
        m = make_family_material("cloth", 2, 24)
        return {**m, "metallic": torch.ones_like(m["metallic"])}

    bad = rp.run_case(case, 24, recover_fn=all_metal)
    assert bad["false_metal"] == 1.0 and bad["metallic_rmse"] == 1.0 and bad["heldout_worst_db"] < 30
    # The other forward model: the truth maps are not a perfect principled answer.
    other = rp.run_case(rp.PanelCase("cloth", 2, 12, "exact_fresnel", False), 24,
                        recover_fn=lambda p: make_family_material("cloth", 2, 24))
    assert 30 < other["heldout_worst_db"] < row["heldout_worst_db"]


def _row(case, **kw):
    base = {"case": case, "base_rmse": 0.01, "roughness_rmse": 0.03, "metallic_rmse": 0.0, "specular_rmse": 0.05,
            "normal_deg": 0.5, "heldout_mean_db": 40.0, "heldout_worst_db": 33.0, "false_metal": 0.0,
            "seconds": 10.0}
    return {**base, **kw}


def test_compare_flags_a_worse_case_and_not_an_unchanged_one(tmp_path, capsys):
    baseline = [_row("a"), _row("b"), _row("c"), _row("d"), _row("gone")]
    rows = [_row("a"),  # unchanged
            _row("b", heldout_worst_db=30.5, roughness_rmse=0.04),  # worse beyond noise
            _row("c", base_rmse=0.0105, heldout_worst_db=32.5, seconds=12.0),  # within noise
            _row("d", false_metal=0.004, base_rmse=0.005),  # better base, but false metal
            _row("new")]
    changes = {c["case"]: c for c in rp.compare(rows, baseline)}
    assert set(changes) == {"a", "b", "c", "d"}
    assert changes["a"]["worse"] == [] and changes["c"]["worse"] == []
    assert changes["b"]["worse"] == ["roughness_rmse", "heldout_worst_db"]
    assert changes["d"]["worse"] == ["false_metal"]
    assert changes["b"]["delta"]["heldout_worst_db"] == pytest.approx(-2.5)
    text = rp.format_compare(list(changes.values()))
    assert "b: " in text and "WORSE: roughness_rmse, heldout_worst_db" in text and "2 of 4 cases worse" in text
    # Infinite PSNR (an exact answer) compares without NaN.
    inf = rp.compare([_row("a", heldout_worst_db=math.inf)], [_row("a", heldout_worst_db=math.inf)])
    assert inf[0]["worse"] == [] and inf[0]["delta"]["heldout_worst_db"] == 0.0
    # The command reads a baseline JSON and refuses one that is not.
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"not": "rows"}))
    with pytest.raises(SystemExit):
        rp.main(["--compare", str(bad), "--only", "nothing"])
    assert "not a panel JSON" in capsys.readouterr().err


def test_tables():
    rows = [_row("cloth/2 L12 principled")]
    text, md = rp.format_rows(rows), rp.format_rows(rows, markdown=True)
    assert "cloth/2 L12 principled" in text and "33.0" in text
    assert md.splitlines()[0].startswith("| case |") and md.count("\n") == 2


def test_table_of_a_stored_run_and_size_mismatch(tmp_path, capsys):
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"meta": {"size": 128}, "rows": [_row("cloth/2 L12 principled"),
                                                               _row("lacquer/3 L17 principled")]}))
    assert rp.main(["--table", str(run), "--markdown", "--only", "cloth", "--compare", str(run)]) == 0
    out = capsys.readouterr().out
    assert "| cloth/2 L12 principled |" in out and "lacquer" not in out and "0 of 1 cases worse" in out
    assert rp.main(["--table", str(run), "--only", "cloth/2,lacquer"]) == 0
    assert "2 cases" in capsys.readouterr().out
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"meta": {"size": 64}, "rows": []}))
    with pytest.raises(SystemExit):
        rp.main(["--table", str(run), "--compare", str(other)])
    assert "compare runs of one size" in capsys.readouterr().err


def test_ulp_seed_moves_half_the_values_by_one_ulp(tmp_path):
    # The same capture but for rounding: a random half of the values one float32 ulp up.
    case = rp.PanelCase("rusted_metal", 1, 8, "principled", False)
    rp.render_case(case, tmp_path / "a", size=16)
    rp.render_case(case, tmp_path / "b", size=16, ulp_seed=3)
    a, b = load_capture(tmp_path / "a").images, load_capture(tmp_path / "b").images
    assert a.dtype == b.dtype == torch.float32
    up = torch.nextafter(a, torch.tensor(float("inf")))
    assert bool(((b == a) | (b == up)).all())
    assert 0.45 < float((b != a).float().mean()) < 0.55
