"""``python -m torchbrdf.bench.recovery``'s schedule table: rows, columns, order, and its cases exist."""

import pytest

from torchbrdf.bench import recovery as bench
from torchbrdf.bench.recovery_panel import panel_cases
from torchbrdf.recovery.config import SCHEDULES


def _row(schedule, case, seconds, db):
    return {"schedule": schedule, "case": case, "seconds": seconds, "heldout_mean_db": db,
            "heldout_worst_db": db - 3.0, "base_rmse": 0.01, "roughness_rmse": 0.02, "metallic_rmse": 0.0,
            "specular_rmse": 0.03, "normal_deg": 1.5, "false_metal": 0.0}


def test_schedule_table_rows_and_time_spread():
    rows = [_row("fast", "tiles", [3.0, 1.0, 2.0], 30.0) | {"cpu_seconds": [0.5, 0.7, 0.6]},
            _row("thorough", "tiles", [9.0], 33.25)]
    lines = bench.schedule_table(rows).splitlines()
    assert len(lines) == 3
    assert lines[0].split()[:6] == ["schedule", "capture", "wall", "s", "min", "median"]
    fast = lines[1].split()
    # min, median, max of the wall times, median CPU time, held-out mean and worst
    assert fast[:8] == ["fast", "tiles", "1.0", "2.0", "3.0", "0.6", "30.00", "27.00"]
    assert lines[2].split()[2:7] == ["9.0", "9.0", "9.0", "–", "33.25"]
    md = bench.schedule_table(rows, markdown=True).splitlines()
    assert md[0].startswith("| schedule | capture |") and md[1].startswith("|---|")
    assert md[2].startswith("| fast | tiles | 1.0 | 2.0 | 3.0 | 0.6 | 30.00 | 27.00 | 0.0100 |")


def test_schedule_rows_alternate_the_schedules(monkeypatch):
    """The schedules run alternately on one rendered capture; each row keeps every time."""
    from torchbrdf.bench import recovery_panel
    import torchbrdf.recovery as recovery

    calls = []

    class Result:
        maps = {"x": 1}

    def fake_recover(folder, cfg, **kw):
        calls.append((cfg.iters, cfg.converge_tol, cfg.threads, cfg.holdout))
        return Result()

    monkeypatch.setattr(recovery, "recover", fake_recover)
    monkeypatch.setattr(recovery_panel, "render_case", lambda case, folder, size: (None, None))
    monkeypatch.setattr(recovery_panel, "score_maps", lambda *a, **k: {"heldout_mean_db": 1.0})
    case = panel_cases("all")[0]
    rows = bench.schedule_rows([case], ["fast", "thorough"], size=16, reps=2, threads=1)
    assert [r["schedule"] for r in rows] == ["fast", "thorough"]
    assert all(len(r["seconds"]) == len(r["cpu_seconds"]) == 2 and r["case"] == case.name for r in rows)
    fast, thorough = (SCHEDULES[s]["iters"] for s in ("fast", "thorough"))
    assert [c[0] for c in calls] == [fast, thorough, thorough, fast]  # odd rounds reversed
    assert all(c[2:] == (1, -1) for c in calls)


@pytest.mark.parametrize("name", bench.SCHEDULE_CASES)
def test_schedule_cases_are_panel_cases(name):
    assert name in {c.name for c in panel_cases("all")}
