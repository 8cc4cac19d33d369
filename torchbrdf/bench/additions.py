"""``python -m torchbrdf.bench.additions``: what continuous metallic costs a recovery in wall time.

Issue 18 allows its additions at most +15 % of the recovery's wall time. *on* is the default
:class:`~torchbrdf.recovery.RecoveryConfig`; *off* leaves out all three additions:
``soft_metal=False`` (the final soft-metal stage), ``fuse_rounds=1`` (the second fusion round)
and ``fit_nonlocal_tie=False`` (the metal tie inside the fit). Each capture is generated once
(``generate_capture``: a recipe, a seed, 256², 16 ring lights + the flash, 1 % noise). Each run
is a fresh process timed by the recovery's own clock (not the interpreter's start), in the order
on / off / off / on per round, so that a drift of the machine's speed falls on both. The printed
ratio is the median over the rounds' on/off pairs. With ``--busy`` every run has one competing
``python -c "while True: pass"`` beside it, as on a machine shared with a data loader.
Results: docs/recovery.md (issue 18, *Time*).
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

from torchbrdf.bench.threads import _run

#: The settings that turn issue 18's additions off.
OFF = {"soft_metal": False, "fuse_rounds": 1, "fit_nonlocal_tie": False}

_RECOVER = r"""
import json, sys, time
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery.svbrdf import keep_freed_memory
keep_freed_memory()  # as the recovery's command does
cfg = RecoveryConfig(threads=int(sys.argv[3]), **json.loads(sys.argv[2]))
t0 = time.perf_counter()
rec = recover(sys.argv[1], cfg, progress=False, log=lambda m: None)
print("SECONDS", time.perf_counter() - t0)
"""


def pair_ratios(on: Sequence[float], off: Sequence[float]) -> list[float]:
    """``on[i] / off[i] − 1`` for each pair (wall seconds of the same round)."""
    if len(on) != len(off) or not on:
        raise ValueError(f"pair_ratios: expected as many on as off times (≥ 1), "
                         f"got {len(on)} and {len(off)}")
    return [a / b - 1.0 for a, b in zip(on, off)]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; prints one line per capture: median on / off seconds, the pairs and their median."""
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.additions",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--captures", default="rusted_metal:101,dusty_metal:102",
                   help="recipe:seed list, comma-separated (default: the held-out soft materials)")
    p.add_argument("--rounds", type=int, default=3, help="on/off/off/on rounds per capture (2 pairs each)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--busy", action="store_true", help="one competing busy process beside every run")
    p.add_argument("--folder", default=None,
                   help="where the captures are generated (default: a temporary folder)")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        p.error("--rounds and --threads must be at least 1")
    from torchbrdf.capture.synthetic import RECIPES, SOFT_RECIPES, generate_capture

    items = []
    for it in args.captures.split(","):
        recipe, _, seed = it.partition(":")
        if recipe not in (*RECIPES, *SOFT_RECIPES) or not seed.isdigit():
            names = sorted((*RECIPES, *SOFT_RECIPES))
            p.error(f"--captures: expected recipe:seed with a recipe of {names}, got {it!r}")
        items.append((recipe, int(seed)))
    folder = Path(args.folder or tempfile.mkdtemp(prefix="tb-additions-"))
    env = dict(os.environ)
    print(f"cores: {os.cpu_count()}  threads: {args.threads}  busy: {args.busy}  "
          f"load average: {os.getloadavg()}")
    for recipe, seed in items:
        cap = folder / f"{recipe}_s{seed}"
        if not (cap / "capture.json").is_file():
            generate_capture(cap, recipe=recipe, seed=seed)
        cmd = lambda kw: [sys.executable, "-c", _RECOVER, str(cap), json.dumps(kw), str(args.threads)]  # noqa: E731
        times: dict[str, list[float]] = {"on": [], "off": []}
        for _ in range(args.rounds):
            for mode in ("on", "off", "off", "on"):
                times[mode].append(_run(cmd({} if mode == "on" else OFF), env, args.busy))
        pairs = pair_ratios(times["on"], times["off"])
        on, off = statistics.median(times["on"]), statistics.median(times["off"])
        shown = " ".join(f"{100 * r:+.0f}%" for r in pairs)
        print(f"{recipe} {seed}: on {on:.2f} s  off {off:.2f} s  pairs {shown}  "
              f"median {100 * statistics.median(pairs):+.1f}%", flush=True)
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
