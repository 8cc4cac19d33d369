"""torchbrdf.bench.fit_time: the table of alternated fits, and its flags."""

import pytest

from torchbrdf.bench import fit_time


def test_table_gives_min_median_max_per_capture_threads_and_tree():
    rows = [{"capture": "demo", "threads": 1, "tree": t, "rep": k, "seconds": s, "cpu": c, "psnr": 70.5}
            for k, (s, c) in enumerate([(3.0, 2.9), (2.0, 1.9), (4.0, 3.5)]) for t in ("base", "new")]
    rows.append({"capture": "/tmp/cap256", "threads": 2, "tree": "new", "rep": 0, "seconds": 5.0, "cpu": 8.0,
                 "psnr": None})
    lines = fit_time.table(rows).splitlines()
    assert len(lines) == 5
    assert lines[2] == "| demo | 1 | base | 2.00 / 3.00 / 4.00 | 1.90 / 2.90 / 3.50 | 70.500000 |"
    assert lines[4] == "| cap256 | 2 | new | 5.00 / 5.00 / 5.00 | 8.00 / 8.00 / 8.00 |  |"


@pytest.mark.parametrize("tree", ["nodir", "x=/nonexistent/tree", "=/tmp"])
def test_a_bad_tree_is_one_line_naming_the_flag(tree, capsys):
    with pytest.raises(SystemExit) as e:
        fit_time.main(["--tree", tree])
    assert e.value.code == 2 and "--tree: expected NAME=DIR" in capsys.readouterr().err


def test_table_adds_the_parts_cpu_seconds_when_the_rows_have_them():
    rows = [{"capture": "demo", "threads": 1, "tree": t, "rep": 0, "seconds": 3.0, "cpu": 2.9, "psnr": 70.5,
             "part_cpu": p} for t, p in (("base", 0.75), ("new", 0.5))]
    lines = fit_time.table(rows).splitlines()
    assert "part's CPU s" in lines[0] and lines[1].count("|") == 8
    assert lines[3] == "| demo | 1 | new | 3.00 / 3.00 / 3.00 | 2.90 / 2.90 / 2.90 | 0.50 / 0.50 / 0.50 | 70.500000 |"


@pytest.mark.parametrize("part", ["propagate_passes", "torchbrdf..x", "x."])
def test_a_bad_part_is_one_line_naming_the_flag(part, tmp_path, capsys):
    (tmp_path / "torchbrdf").mkdir()
    with pytest.raises(SystemExit) as e:
        fit_time.main(["--tree", f"t={tmp_path}", "--part", part])
    assert e.value.code == 2 and "--part: expected MODULE.NAME" in capsys.readouterr().err


def test_the_fits_wait_for_threads_as_the_recovery_command_does():
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    probe = fit_time.AS_COMMAND + "import os, torchbrdf\nprint(os.environ.get('OMP_WAIT_POLICY'))\n"
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"


def test_the_model_reaches_the_fit(monkeypatch, tmp_path, capsys):
    seen = []

    def run(cmd, **kw):
        seen.append(cmd)
        raise RuntimeError("stop")

    monkeypatch.setattr(fit_time.subprocess, "run", run)
    with pytest.raises(RuntimeError, match="stop"):
        fit_time.run_fit("/tmp", "demo", 1, model="svbrdf_ggx")
    assert seen[0][seen[0].index("--model") + 1] == "svbrdf_ggx"
    (tmp_path / "torchbrdf").mkdir()
    with pytest.raises(SystemExit) as e:
        fit_time.main(["--tree", f"t={tmp_path}", "--model", "lambert"])
    assert e.value.code == 2 and "--model: invalid choice" in capsys.readouterr().err
