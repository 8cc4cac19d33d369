"""Timing for the benchmarks: compared variants alternate in one loop, every figure keeps its spread.

On a shared machine the load moves during a run: timing one variant after the other puts the
load's changes into the ratio. :func:`time_alternating` runs one call of each variant per
round (order reversed every round), so each variant sees the same load; :class:`Spread` keeps
min, median and max; :func:`ratio_text` prints a ratio only where the two spreads are apart
and flags it otherwise.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

__all__ = ["Spread", "time_alternating", "median_time", "overlaps", "ratio_text", "spread_text",
           "format_or_dash"]

_Key = TypeVar("_Key", bound=Hashable)


@dataclass(frozen=True)
class Spread:
    """Wall times (seconds) of repeated calls: ``min``, ``median``, ``max`` and how many."""

    min: float
    median: float
    max: float
    repeats: int

    @classmethod
    def of(cls, seconds: Sequence[float]) -> Spread:
        """The spread of ``seconds`` (at least one time)."""
        if not seconds:
            raise ValueError("seconds: expected at least one time")
        return cls(min(seconds), statistics.median(seconds), max(seconds), len(seconds))

    def rate(self, work: float) -> tuple[float, float, float]:
        """``work`` per second at (slowest, median, fastest) call."""
        return work / self.max, work / self.median, work / self.min

    def as_dict(self) -> dict[str, float]:
        return {"min_s": self.min, "median_s": self.median, "max_s": self.max, "repeats": self.repeats}


def time_alternating(variants: Mapping[_Key, Callable[[], object]], repeats: int,
                     budget: float = float("inf"), clock: Callable[[], float] | None = None
                     ) -> dict[_Key, Spread]:
    """Time each of ``variants`` ``repeats`` times, one call of each per round.

    One untimed warm-up call of each first (kernel build, page-in); fewer rounds when the
    warm-ups show that ``repeats`` rounds would take longer than ``budget`` seconds (at least
    one). Odd rounds run the variants in reverse order, so none always runs first. ``clock``:
    wall time (``time.perf_counter``) by default; ``time.process_time`` (this process's CPU
    time) is steadier on a shared machine.
    """
    clock = clock or time.perf_counter
    if repeats < 1:
        raise ValueError(f"repeats: expected >= 1, got {repeats}")
    names = list(variants)
    t0 = time.perf_counter()
    for name in names:
        variants[name]()
    per_round = time.perf_counter() - t0
    rounds = repeats if per_round * repeats <= budget else max(1, int(budget / max(per_round, 1e-9)))
    times: dict[_Key, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            t0 = clock()
            variants[name]()
            times[name].append(clock() - t0)
    return {name: Spread.of(ts) for name, ts in times.items()}


def overlaps(a: Spread, b: Spread) -> bool:
    """Whether the [min, max] ranges of ``a`` and ``b`` meet: their order is not measured."""
    return a.min <= b.max and b.min <= a.max


def ratio_text(slow: Spread, fast: Spread) -> str:
    """``"×R"`` (``slow`` median / ``fast`` median) when the spreads are apart, else a flag
    ``"≈ (spreads overlap, ×R)"``: the load moved more than the variants differ."""
    r = slow.median / fast.median
    return f"≈ (spreads overlap, ×{r:.2f})" if overlaps(slow, fast) else f"×{r:.2f}"


def spread_text(s: Spread, work: float | None = None, spec: str = ".3g") -> str:
    """``"median (min–max)"`` in seconds, or as ``work``/s (slowest–fastest) when ``work`` is given."""
    if work is None:
        return f"{s.median:{spec}} ({s.min:{spec}}–{s.max:{spec}})"
    lo, med, hi = s.rate(work)
    return f"{med:{spec}} ({lo:{spec}}–{hi:{spec}})"


def median_time(fn: Callable[[], object], repeats: int, budget: float) -> tuple[float, int]:
    """Median wall time (seconds) of ``fn()`` after one warm-up call, and the repeats taken
    (fewer than ``repeats`` when slow; see :func:`time_alternating`'s ``budget``)."""
    s = time_alternating({"fn": fn}, repeats, budget)["fn"]
    return s.median, s.repeats


def format_or_dash(x: float | None, spec: str = ".3g") -> str:
    """``x`` formatted with ``spec``, or "—" for a value not measured (``None``)."""
    return "—" if x is None else format(x, spec)
