"""torchbrdf.bench.cg_time: saving a fit's pcg calls, timing them per tree, and its flags."""

import pytest

from torchbrdf.bench import cg_time


@pytest.mark.slow
def test_saved_calls_are_timed_per_tree_and_a_tree_agrees_with_itself(tmp_path, capsys):
    """A tiny demo fit's calls saved, then timed twice alternating with this tree under two names:
    one table row each, and the same solutions (difference 0)."""
    folder = tmp_path / "calls"
    tiny = "--demo-size 16 --iters 2 --levels 1"
    assert cg_time.main(["--save", str(folder), "--every", "4", "--cli", tiny]) == 0
    assert list(folder.glob("pcg_*.pt"))
    tree = str(cg_time.Path(cg_time.__file__).resolve().parents[2])
    assert cg_time.main(["--args", str(folder), "--tree", f"a={tree}", "--tree", f"b={tree}",
                         "--reps", "2"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(("| a ", "| b "))]
    assert len(rows) == 2 and all(r.endswith("| 0.0e+00 |") for r in rows)


@pytest.mark.parametrize("argv, message", [
    ([], "give one of --save DIR and --args DIR"),
    (["--save", "x", "--args", "y"], "give one of --save DIR and --args DIR"),
    (["--save", "x", "--every", "0"], "--every: expected a positive number"),
    (["--args", "/tmp", "--tree", "nodir"], "--tree: expected NAME=DIR"),
    (["--args", "/tmp"], "--args needs at least one --tree"),
])
def test_bad_flags_are_one_line_naming_the_flag(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cg_time.main(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err
