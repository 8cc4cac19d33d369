"""The benchmarks' timing: alternation, spreads and the flagging of ratios the spread cannot carry."""

import pytest

from torchbrdf.bench import environment as bench_brdf
from torchbrdf.bench import timing
from torchbrdf.bench.timing import Spread, overlaps, ratio_text, spread_text, time_alternating


class _Clock:
    """A fake ``time.perf_counter``: each variant call advances it by its next scripted duration."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_spread_of_times():
    s = Spread.of([3.0, 1.0, 2.0, 10.0, 2.5])
    assert (s.min, s.median, s.max, s.repeats) == (1.0, 2.5, 10.0, 5)
    assert s.rate(100.0) == (10.0, 40.0, 100.0)
    assert spread_text(s) == "2.5 (1–10)"
    assert spread_text(s, 100.0) == "40 (10–100)"
    with pytest.raises(ValueError, match="seconds"):
        Spread.of([])


def test_ratio_is_printed_only_when_the_spreads_are_apart():
    slow, fast = Spread.of([2.0, 2.1, 2.4]), Spread.of([1.0, 1.05, 1.3])
    assert not overlaps(slow, fast)
    assert ratio_text(slow, fast) == "×2.00"  # medians 2.1 / 1.05
    # a loaded machine: one slow outlier of the fast variant reaches the slow one's range
    loaded = Spread.of([1.0, 1.05, 2.2])
    assert overlaps(slow, loaded) and overlaps(loaded, slow)
    assert ratio_text(slow, loaded).startswith("≈")
    # "4 samples faster than 1": a smaller median, but inside the other's spread: flagged, not a ratio
    one, four = Spread.of([0.010, 0.013, 0.030]), Spread.of([0.011, 0.012, 0.025])
    assert ratio_text(one, four).startswith("≈")


def test_variants_alternate_and_reverse_order_each_round(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(timing.time, "perf_counter", clock)
    calls = []
    durations = {"a": iter([5.0, 1.0, 1.2, 1.1, 9.0]), "b": iter([5.0, 2.0, 2.2, 2.1, 2.3])}

    def variant(name):
        def run():
            calls.append(name)
            clock.now += next(durations[name])
        return run

    out = time_alternating({"a": variant("a"), "b": variant("b")}, repeats=4)
    assert calls == ["a", "b", "a", "b", "b", "a", "a", "b", "b", "a"]  # warm-ups, then alternating rounds
    for s, want in ((out["a"], (1.0, 1.15, 9.0)), (out["b"], (2.0, 2.15, 2.3))):
        assert (s.min, s.median, s.max) == pytest.approx(want) and s.repeats == 4
    assert ratio_text(out["b"], out["a"]).startswith("≈")  # a's outlier (9 s) spans b's range


def test_rounds_shrink_to_the_budget(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(timing.time, "perf_counter", clock)

    def run():
        clock.now += 1.0

    assert time_alternating({"x": run}, repeats=10, budget=3.5)["x"].repeats == 3
    assert time_alternating({"x": run}, repeats=10, budget=0.1)["x"].repeats == 1


def test_environment_rows_flag_sample_counts_whose_times_overlap():
    def row(samples, lo, med, hi):
        return dict(method="MIS", samples=samples, seconds=med, mean_rel_err=0.1,
                    spread=dict(min_s=lo, median_s=med, max_s=hi, repeats=3))

    rows = [row(1, 0.010, 0.012, 0.030), row(4, 0.011, 0.011, 0.014), row(16, 0.040, 0.041, 0.043)]
    assert bench_brdf._env_flag(rows[0], rows) == ""
    assert bench_brdf._env_flag(rows[1], rows) == " ≈"  # "4 samples faster than 1": not measured
    assert bench_brdf._env_flag(rows[2], rows) == ""
    lines = bench_brdf.environment_section(dict(points=8, env_size=[4, 8], reference_seconds=1.0, rows=rows))
    assert any("| 4 | 11.0 (11.0–14.0) ≈ |" in line for line in lines)
