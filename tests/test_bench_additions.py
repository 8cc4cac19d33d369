"""``python -m torchbrdf.bench.additions``: the on/off timing of issue 18's additions.

Timings are in docs/recovery.md, not here: these tests check what is run, in which order, how
the pairs are formed, and that bad arguments are refused.
"""

import json
import subprocess

import pytest

from torchbrdf.bench import additions
from torchbrdf.recovery.svbrdf import RecoveryConfig


def test_off_turns_each_addition_away_from_its_default():
    """*off* changes every addition's setting from its default."""
    d = RecoveryConfig()
    assert additions.OFF and all(getattr(d, k) != v for k, v in additions.OFF.items())


def test_pairs_are_on_over_off_of_the_same_round():
    """A pair is on / off − 1; unequal lists are refused."""
    assert additions.pair_ratios([11.0, 9.0], [10.0, 10.0]) == pytest.approx([0.1, -0.1])
    with pytest.raises(ValueError, match="as many on as off"):
        additions.pair_ratios([1.0], [])


@pytest.mark.parametrize("bad", [["--captures", "marble:1"], ["--captures", "rusted_metal"],
                                 ["--captures", "rusted_metal:²"], ["--rounds", "0"], ["--threads", "0"]])
def test_bad_arguments_exit_2(bad):
    """An unknown recipe, a missing or non-ASCII seed, or no rounds or threads: exit 2."""
    with pytest.raises(SystemExit) as e:
        additions.main(bad)
    assert e.value.code == 2


def test_runs_go_on_off_off_on_and_pair_neighbours(tmp_path, monkeypatch, capsys):
    """Each round runs on / off / off / on; run 1 pairs with run 2 and run 4 with run 3."""
    cap = tmp_path / "rusted_metal_s1"
    cap.mkdir()
    (cap / "capture.json").write_text("{}")  # present: the benchmark does not generate it again
    seen, clock = [], iter([20.0, 10.0, 10.0, 11.0, 30.0, 20.0, 20.0, 30.0])

    def fake(cmd, env, busy, require_seconds=False):
        assert require_seconds and busy is False
        assert cmd == additions.recover_command(cap, json.loads(cmd[4]), 1)
        seen.append(json.loads(cmd[4]))
        return next(clock)

    monkeypatch.setattr(additions, "run_timed", fake)
    assert additions.main(["--captures", " rusted_metal:1", "--rounds", "2", "--threads", "1",
                           "--folder", str(tmp_path)]) == 0
    off = additions.OFF
    assert seen == [{}, off, off, {}] * 2
    out = capsys.readouterr().out
    # pairs: 20/10, 11/10, 30/20, 30/20 -> +100 +10 +50 +50 %, median +50 %
    assert "pairs +100% +10% +50% +50%  median +50.0%" in out, out


def test_a_timed_run_prints_the_recoverys_own_seconds(tmp_path):
    """The command of one run recovers a capture and prints report.json's seconds."""
    from torchbrdf.capture.synthetic import generate_capture

    generate_capture(tmp_path, recipe="metal_inlay", seed=2, size=12, lights=6, noise=0.01)
    cmd = additions.recover_command(tmp_path, {**additions.OFF, "iters": 4}, 1)
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    line = [x for x in out.stdout.splitlines() if x.startswith("SECONDS ")]
    assert len(line) == 1 and 0 < float(line[0].split()[1]) < 300
