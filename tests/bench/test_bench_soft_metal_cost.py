"""``python -m torchbrdf.bench.soft_metal_cost``: the on/off timing of the metal refinements.

The command prints the timings; these tests check what is run, in which order, how the pairs are
formed, and that bad arguments are refused.
"""

import json
import subprocess

import pytest

from torchbrdf.bench import soft_metal_cost
from torchbrdf.recovery.config import Settings


def test_off_turns_each_addition_away_from_its_default():
    """*off* changes every addition's setting from its default."""
    d = Settings()
    assert soft_metal_cost.OFF and all(getattr(d, k) != v for k, v in soft_metal_cost.OFF.items())


def test_pairs_are_on_over_off_of_the_same_round():
    """A pair is on / off − 1; unequal lists are refused."""
    assert soft_metal_cost.pair_ratios([11.0, 9.0], [10.0, 10.0]) == pytest.approx([0.1, -0.1])
    with pytest.raises(ValueError, match="as many on as off"):
        soft_metal_cost.pair_ratios([1.0], [])


@pytest.mark.parametrize("bad", [["--captures", "marble:1"], ["--captures", "rusted_metal"],
                                 ["--captures", "rusted_metal:²"], ["--rounds", "0"], ["--threads", "0"]])
def test_bad_arguments_exit_2(bad):
    """An unknown recipe, a missing or non-ASCII seed, or no rounds or threads: exit 2."""
    with pytest.raises(SystemExit) as e:
        soft_metal_cost.main(bad)
    assert e.value.code == 2


def test_runs_go_on_off_off_on_and_pair_neighbours(tmp_path, monkeypatch, capsys):
    """Each round runs on / off / off / on; pairs are runs 1 and 2, 4 and 3: whole runs and stages.

    Pair by pair, as the summary line and the per-stage line print them.
    """
    cap = tmp_path / "rusted_metal_s1"
    cap.mkdir()
    (cap / "capture.json").write_text("{}")  # present: the benchmark does not generate it again
    seen, clock = [], iter([20.0, 10.0, 10.0, 11.0, 30.0, 20.0, 20.0, 30.0])
    last = iter([5.0, 1.0, 2.0, 4.0, 6.0, 3.0, 3.0, 6.0])  # the "all 8²" stage of each run

    def fake(cmd, busy):
        assert busy is False
        assert cmd == soft_metal_cost.recover_command(cap, json.loads(cmd[4]), 1)
        seen.append(json.loads(cmd[4]))
        stages = [{"size": 4, "stage": "dual", "iterations": 3, "seconds": 1.0},
                  {"size": 8, "stage": "all", "iterations": 2, "seconds": next(last)}]
        return next(clock), stages

    monkeypatch.setattr(soft_metal_cost, "run_recovery", fake)
    assert soft_metal_cost.main(["--captures", " rusted_metal:1", "--rounds", "2", "--threads", "1",
                           "--folder", str(tmp_path)]) == 0
    off = soft_metal_cost.OFF
    assert seen == [{}, off, off, {}] * 2
    out = capsys.readouterr().out
    # pairs: 20/10, 11/10, 30/20, 30/20 -> +100 +10 +50 +50 %, median +50 %
    assert "pairs +100% +10% +50% +50%  median +50.0%" in out, out
    # the last stage: 5-1, 4-2, 6-3, 6-3 -> median 3 s; the first: 0 in every pair
    assert "dual 4² +0.00 s, all 8² +3.00 s" in out, out


def test_stage_differences_match_stages_by_kind_and_size():
    """A stage missing from one run of a pair, or without a time, leaves that pair out for it."""
    a = [{"size": 4, "stage": "dual", "seconds": 2.0}, {"size": 8, "stage": "all", "seconds": 5.0}]
    b = [{"size": 8, "stage": "all", "seconds": 1.0}]
    c = [{"size": 4, "stage": "dual", "seconds": None}, {"size": 8, "stage": "all", "seconds": 2.0}]
    assert soft_metal_cost.stage_differences([a, a], [b, c]) == {"all 8²": 3.5}
    assert soft_metal_cost.stage_differences([], []) == {}
    # one stage met twice: each occurrence its own entry
    d, p = {"size": 4, "stage": "dual", "seconds": 3.0}, {"size": 8, "stage": "polish", "seconds": 1.0}
    twice = [d, p, {**d, "seconds": 5.0}]
    assert soft_metal_cost.stage_differences([twice], [[{**d, "seconds": 1.0}, p, d]]) == \
        {"dual 4²": 2.0, "polish 8²": 0.0, "dual 4² (2)": 2.0}


def test_a_timed_run_prints_the_recoverys_own_seconds(tmp_path):
    """The command of one run recovers a capture and prints report.json's seconds and stage_seconds."""
    from torchbrdf.capture.synthetic import generate_capture

    generate_capture(tmp_path, recipe="metal_inlay", seed=2, size=12, lights=6, noise=0.01)
    cmd = soft_metal_cost.recover_command(tmp_path, {**soft_metal_cost.OFF, "iters": 4}, 1)
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    line = [x for x in out.stdout.splitlines() if x.startswith("SECONDS ")]
    assert len(line) == 1 and 0 < float(line[0].split()[1]) < 300
    stages = [json.loads(x.split(" ", 1)[1]) for x in out.stdout.splitlines() if x.startswith("STAGES ")]
    assert len(stages) == 1 and stages[0] and all(e["seconds"] > 0 for e in stages[0])
    # the stages' times are parts of the run's (iterations only: no checkpoint or plot)
    assert sum(e["seconds"] for e in stages[0]) <= float(line[0].split()[1])
