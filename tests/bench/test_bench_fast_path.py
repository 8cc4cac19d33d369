"""torchbrdf.bench.fast_path: each row times its two variants and prints a markdown table."""

import time

import pytest

from torchbrdf.bench import fast_path, timing


def test_rows_time_both_variants_of_each_case():
    rows = fast_path.rows(batch=1, size=8, sample_size=8, repeats=1, shade_size=8)
    assert [r[0].split(",")[0] for r in rows] == ["`rendering_loss` fwd+bwd", "`MaterialDataset` sample",
                                                  "`principled` forward", "`shade` with `svbrdf_ggx` fwd+bwd"]
    assert all(r[2].repeats == r[4].repeats == 1 and r[2].median > 0 and r[4].median > 0 for r in rows)


def test_time_alternating_takes_the_clock_it_is_given():
    ticks = iter(range(100))
    s = timing.time_alternating({"a": lambda: None}, 3, clock=lambda: float(next(ticks)))
    assert s["a"] == timing.Spread(1.0, 1.0, 1.0, 3)
    assert timing.time_alternating({"a": lambda: time.sleep(0.01)}, 1, clock=time.process_time)["a"].median < 0.01


@pytest.mark.parametrize("flag", ["--batch", "--size", "--sample-size", "--shade-size", "--reps", "--threads"])
def test_a_non_positive_count_is_one_line_naming_the_flag(flag, capsys):
    with pytest.raises(SystemExit) as e:
        fast_path.main([flag, "0"])
    assert e.value.code == 2 and f"{flag} must be at least 1, got 0" in capsys.readouterr().err
