import pytest

from torchbrdf.bench import panel_rounding
from torchbrdf.bench.recovery_panel import TOLERANCES


def _rows(case, tree, worst_values):
    base = {m: 0.0 for m in TOLERANCES}
    return [{**base, "case": case, "tree": tree, "heldout_worst_db": w} for w in worst_values]


def _verdict(found, case):
    return next(v["verdict"] for v in found if v["case"] == case and v["metric"] == "heldout_worst_db")


def test_verdicts_tell_rounding_from_a_loss():
    rows = (_rows("within", "old", [40.0, 40.2, 40.4]) + _rows("within", "new", [39.5, 39.6, 40.0])
            + _rows("rounding", "old", [40.0, 41.0, 44.0]) + _rows("rounding", "new", [38.0, 38.5, 40.5])
            + _rows("worse", "old", [43.8, 43.8, 43.8]) + _rows("worse", "new", [36.5, 36.6, 36.6])
            + _rows("better", "old", [36.5, 36.6, 36.6]) + _rows("better", "new", [43.8, 43.8, 43.8]))
    found = panel_rounding.verdicts(rows, "old")
    assert {c: _verdict(found, c) for c in ("within", "rounding", "worse", "better")} == {
        "within": "", "rounding": "rounding", "worse": "worse", "better": ""}
    text = panel_rounding.table(found, "old")
    assert "| worse | heldout_worst_db | 43.8–43.8 | new: 36.5–36.6 |" in text
    assert "| within |" not in text


def test_main_refuses_unknown_cases_and_single_seed(tmp_path, capsys):
    tree = f"a={panel_rounding.__file__.rsplit('/torchbrdf/', 1)[0]}"
    with pytest.raises(SystemExit):
        panel_rounding.main(["--tree", tree, "--only", "no_such/9 L3 principled"])
    assert "--only: not panel cases" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        panel_rounding.main(["--tree", tree, "--only", "lacquer/0 L12 exact_fresnel +cal", "--ulp-seeds", "1"])
    assert "--ulp-seeds" in capsys.readouterr().err


def _drawn(case, tree, worst_by_draw):
    base = {m: 0.0 for m in TOLERANCES}
    return [{**base, "case": case, "tree": tree, "noise": k, "heldout_worst_db": w}
            for k, w in enumerate(worst_by_draw)]


def test_sign_test_is_the_binomial_tail():
    assert panel_rounding.sign_test(5, 5) == 1 / 32
    assert panel_rounding.sign_test(7, 8) == 9 / 256
    assert panel_rounding.sign_test(0, 6) == 1.0
    assert panel_rounding.sign_test(panel_rounding.MIN_NOISE_DRAWS, panel_rounding.MIN_NOISE_DRAWS) \
        <= panel_rounding.SIGN_TEST_LEVEL < panel_rounding.sign_test(4, 4)


def test_noise_draws_pair_the_trees_and_judge_by_the_sign_of_the_differences():
    # a median loss beyond the band (one draw −7.7 dB) among draws that go both ways is the
    # capture's noise;
    # a 2 dB loss on every draw is a loss, though its range overlaps the reference's
    old_scatter, new_scatter = [43.8, 36.0, 40.0, 38.0, 41.0, 39.0], [36.1, 34.0, 38.2, 39.0, 41.5, 37.4]
    old_steady, new_steady = [40.0, 44.0, 42.0, 41.0, 43.0, 45.0], [38.0, 42.0, 40.0, 39.0, 41.0, 43.0]
    rows = (_drawn("scatter", "old", old_scatter) + _drawn("scatter", "new", new_scatter)
            + _drawn("steady", "old", old_steady) + _drawn("steady", "new", new_steady))
    found = panel_rounding.verdicts(rows, "old")
    assert _verdict(found, "scatter") == "noise"
    assert _verdict(found, "steady") == "worse"
    steady = next(v for v in found if v["case"] == "steady" and v["metric"] == "heldout_worst_db")
    assert steady["change"] == -2.0 and steady["worse_draws"] == "6/6"
    assert "| steady | heldout_worst_db | 40–45 | new: 38–43 | -2 | 6/6 | worse |" in panel_rounding.table(found, "old")


def test_main_refuses_too_few_noise_draws_for_the_sign_test(capsys):
    tree = f"a={panel_rounding.__file__.rsplit('/torchbrdf/', 1)[0]}"
    with pytest.raises(SystemExit):
        panel_rounding.main(["--tree", tree, "--only", "lacquer/0 L12 exact_fresnel +cal", "--noise-seeds", "3"])
    assert "--noise-seeds: expected 1 or at least 5" in capsys.readouterr().err
