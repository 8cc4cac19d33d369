"""``python -m torchbrdf.bench.soft_metal_cost``: what the metal refinements cost a recovery in wall time.

The refinements are the final continuous-metallic stage, the second round of the non-local F0
fusion and the F0 tie inside the fit. *on* is the default RecoveryConfig; *off* leaves out all
three: soft_metal=False, fuse_rounds=1 and fit_nonlocal_tie=False. Each capture is generated
once (generate_capture: a recipe, a seed, 256², 16 ring lights + the flash, 1 % noise). Each run
is a fresh process; its time is the recovery's own clock (report.json's "seconds": the fit,
without the interpreter's start, the imports, loading the capture or writing outputs). Runs go
on / off / off / on per round, so that a drift of the machine's speed falls on both, and the
printed ratio is the median over the rounds' on/off pairs. Below it, per stage (report.json's
"stage_seconds"), the median of the pairs' on − off seconds. The ties are made at the end of the
stage before a single-class stage (the 256² two-hypothesis and the polish stage), and the first
one's pass is reused by the polish stage's first step, so work moves between those two stages
and only their sum says what the ties cost; the last stage's end holds the second fusion round
and the final stage; the two-hypothesis stages below full size run the same code on and off, so
their differences show how much the machine's noise moves a stage. With --busy every run has one
competing `python -c "while True: pass"` beside it, as on a machine shared with a data loader.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from torchbrdf.bench.threads import SECONDS, run_workload, tagged_line, workload_seconds

#: The settings that turn the metal refinements off.
OFF = {"soft_metal": False, "fuse_rounds": 1, "fit_nonlocal_tie": False}

_RECOVER = r"""
import json, sys
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery.svbrdf import keep_freed_memory
keep_freed_memory()  # as the recovery's command does
cfg = RecoveryConfig(threads=int(sys.argv[3])).settings(**json.loads(sys.argv[2]))
rec = recover(sys.argv[1], cfg, progress=False, log=lambda m: None)
print(sys.argv[4], rec.report["seconds"])
print(sys.argv[5], json.dumps(rec.report["stage_seconds"]))
"""

#: The line of a run's per-stage seconds (report.json's ``stage_seconds``, as JSON).
STAGES = "STAGES"


def recover_command(capture: str | os.PathLike, overrides: dict, threads: int) -> list[str]:
    """The command of one timed run: ``recover(capture)`` with ``RecoveryConfig().settings(**overrides)``.

    On ``threads`` threads; it prints ``SECONDS <the recovery's own seconds>`` and ``STAGES <its
    stage_seconds as JSON>``.
    """
    return [sys.executable, "-c", _RECOVER, str(capture), json.dumps(overrides), str(threads),
            SECONDS, STAGES]


def run_recovery(cmd: Sequence[str], busy: bool) -> tuple[float, list[dict]]:
    """Run one :func:`recover_command` (beside a busy process with ``busy``).

    Returns ``(the recovery's own seconds, its stage_seconds)``; a run that does not print both
    lines is an error.
    """
    _, out = run_workload(cmd, None, busy)
    seconds, stages = workload_seconds(cmd, out, None), tagged_line(out, STAGES)
    if stages is not None:
        return seconds, json.loads(stages)
    raise RuntimeError(f"{cmd} printed no {STAGES} line:\n{out[-2000:]}")


def _stage_times(stages: list[dict]) -> dict[tuple[str, int], float | None]:
    """A run's stage seconds by (name, occurrence): ``("polish 256²", 0)`` for its first polish stage."""
    out: dict[tuple[str, int], float | None] = {}
    for e in stages:
        name = f"{e['stage']} {e['size']}²"
        k = sum(1 for n, _ in out if n == name)
        out[(name, k)] = e["seconds"]
    return out


def stage_differences(on: Sequence[list[dict]], off: Sequence[list[dict]]) -> dict[str, float]:
    """Per stage, the median over the pairs of its on − off seconds.

    ``on[i]``, ``off[i]``: the ``stage_seconds`` of one pair's runs. Stages are matched by name
    (``"polish 256²"``) and occurrence (a stage met again after another is its own entry,
    ``"dual 64² (2)"``), in the order of the first on run; a stage missing from a run of a pair,
    or without a time, leaves that pair out for it.
    """
    out: dict[str, float] = {}
    runs = [(_stage_times(a), _stage_times(b)) for a, b in zip(on, off)]
    for name, k in _stage_times(on[0]) if on else {}:
        diffs = []
        for a, b in runs:
            ta, tb = a.get((name, k)), b.get((name, k))
            if ta is not None and tb is not None:
                diffs.append(ta - tb)
        if diffs:
            out[name if k == 0 else f"{name} ({k + 1})"] = statistics.median(diffs)
    return out


def pair_ratios(on: Sequence[float], off: Sequence[float]) -> list[float]:
    """``on[i] / off[i] − 1`` for each pair (the seconds of one round's on and off runs)."""
    if len(on) != len(off) or not on:
        raise ValueError(f"pair_ratios: expected as many on as off times (≥ 1), "
                         f"got {len(on)} and {len(off)}")
    return [a / b - 1.0 for a, b in zip(on, off)]


class _Help(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    pass


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; prints one line per capture: median on / off seconds, the pairs and their median."""
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.soft_metal_cost", description=__doc__,
                                formatter_class=_Help)
    p.add_argument("--captures", default="rusted_metal:101,dusty_metal:102",
                   help="recipe:seed list, comma-separated (by default the held-out soft materials)")
    p.add_argument("--rounds", type=int, default=3, help="on/off/off/on rounds per capture (2 pairs each)")
    p.add_argument("--threads", type=int, default=2, help="torch threads of each recovery")
    p.add_argument("--busy", action="store_true", help="one competing busy process beside every run")
    p.add_argument("--folder", default=None,
                   help="where the captures are generated (None: a new temporary folder, printed)")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        p.error("--rounds and --threads must be at least 1")
    from torchbrdf.capture.synthetic import RECIPES, SOFT_RECIPES, generate_capture

    names = sorted((*RECIPES, *SOFT_RECIPES))
    items = []
    for it in args.captures.split(","):
        recipe, _, seed = it.strip().partition(":")
        if recipe not in names or not seed.isdecimal() or not seed.isascii():
            p.error(f"--captures: expected recipe:seed with a recipe of {names}, got {it!r}")
        items.append((recipe, int(seed)))
    folder = Path(args.folder or tempfile.mkdtemp(prefix="tb-soft-metal-cost-"))
    omp = {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    print(f"cores: {os.cpu_count()}  threads: {args.threads}  busy: {args.busy}  {omp}  "
          f"load average: {os.getloadavg()}  captures in: {folder}")
    for recipe, seed in items:
        cap = folder / f"{recipe}_s{seed}"
        if not (cap / "capture.json").is_file():
            generate_capture(cap, recipe=recipe, seed=seed)
        times: dict[str, list[float]] = {"on": [], "off": []}
        stages: dict[str, list[list[dict]]] = {"on": [], "off": []}
        for _ in range(args.rounds):
            for mode in ("on", "off", "off", "on"):
                cmd = recover_command(cap, {} if mode == "on" else OFF, args.threads)
                seconds, per_stage = run_recovery(cmd, args.busy)
                times[mode].append(seconds)
                stages[mode].append(per_stage)
        pairs = pair_ratios(times["on"], times["off"])
        on, off = statistics.median(times["on"]), statistics.median(times["off"])
        shown = " ".join(f"{100 * r:+.0f}%" for r in pairs)
        print(f"{recipe} {seed}: on {on:.2f} s  off {off:.2f} s  pairs {shown}  "
              f"median {100 * statistics.median(pairs):+.1f}%", flush=True)
        # Where the difference lies (see the module's docstring)
        diff = stage_differences(stages["on"], stages["off"])
        print("  per stage, on − off (median of the pairs): "
              + (", ".join(f"{k} {v:+.2f} s" for k, v in diff.items()) or "no stage times"), flush=True)
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
