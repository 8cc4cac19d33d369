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
