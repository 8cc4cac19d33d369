"""``python -m torchbrdf.bench.panel_rounding``: whether a panel case's change between two solvers is beyond its noise.

A case flagged by ``recovery_panel --compare`` may differ between the solvers only because
each amplifies rounding differently, or because the one noise draw the panel renders happens
to land one solver's error where a held-out light sees it. Each case is written once per
``--ulp-seed`` (0 is the panel's own capture; ``N > 0`` moves a random half of the image values
up by one float32 ulp) and per ``--noise-seeds`` draw (0 is the panel's own sensor noise; each
further draw renders the same material, lights and calibration error with fresh sensor noise,
:func:`~torchbrdf.bench.recovery_panel.render_case`). Every source tree (``--tree NAME=DIR``,
each fit a fresh process with ``PYTHONPATH=DIR``, one thread, every captured light in the fit)
recovers each capture, all scored by this tree's
:func:`~torchbrdf.bench.recovery_panel.score_maps`. The verdict is against the first tree, with
the panel's band (:data:`~torchbrdf.bench.recovery_panel.TOLERANCES`):

* one noise draw: per metric each tree's range over the ulp seeds and the change of the
  medians; ``worse`` when the medians moved the wrong way by more than the band and the two
  ranges do not overlap, ``rounding`` when beyond the band but the ranges overlap;
* several noise draws (at least :data:`MIN_NOISE_DRAWS`): the trees are paired on each draw
  (each tree's median over the ulp seeds), and the change is the median of the paired
  differences; ``worse`` when it goes the wrong way by more than the band and a one-sided sign
  test over the draws rejects "no difference" at :data:`SIGN_TEST_LEVEL`, ``noise`` when
  beyond the band but the draws do not agree on the sign.

Blank: within the band. Run it only on cases a ``--compare`` already flagged: it reports, it
chooses nothing. Results: docs/recovery_panel.md ("Rounding sensitivity").
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from torchbrdf.bench.fit_time import source_trees
from torchbrdf.bench.recovery_panel import TOLERANCES, case_seed, panel_cases, render_case, score_maps

__all__ = ["MIN_NOISE_DRAWS", "SIGN_TEST_LEVEL", "recover_in_tree", "sign_test", "verdicts", "table", "main"]

#: One-sided level of the sign test over noise draws.
SIGN_TEST_LEVEL = 0.05
#: Fewest noise draws whose sign test can reach :data:`SIGN_TEST_LEVEL` (all 5 the same way: p = 1/32).
MIN_NOISE_DRAWS = 5

#: The child: recover the capture in argv[1] with the tree on ``PYTHONPATH`` and save its maps to
#: argv[2]; fields the tree's ``RecoveryConfig`` lacks are left out, so any tree of the project runs it.
_CHILD = r"""
import dataclasses, sys, torch
from torchbrdf.recovery import RecoveryConfig, recover
names = {f.name for f in dataclasses.fields(RecoveryConfig)}
cfg = RecoveryConfig(**{k: v for k, v in {"threads": 1, "holdout": -1}.items() if k in names})
torch.set_num_threads(1)
maps = recover(sys.argv[1], cfg, progress=False, log=lambda m: None).maps
torch.save({k: v.detach().cpu() for k, v in maps.items()}, sys.argv[2])
"""


def recover_in_tree(tree: str, capture: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The maps ``(C, H, W)`` the sources of ``tree`` recover from ``capture``, in a fresh process."""
    with tempfile.TemporaryDirectory(prefix="panel_rounding_") as d:
        out = os.path.join(d, "maps.pt")
        subprocess.run([sys.executable, "-c", _CHILD, str(capture), out], cwd=tree, check=True,
                       env=dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS="1"))
        return torch.load(out)


def sign_test(worse: int, draws: int) -> float:
    """One-sided sign-test p-value: the chance of at least ``worse`` of ``draws`` fair coin flips."""
    return sum(math.comb(draws, k) for k in range(worse, draws + 1)) / 2 ** draws


def verdicts(rows: Sequence[Mapping], reference: str) -> list[dict]:
    """Per case, metric and tree other than ``reference``: the ranges, the change and the verdict.

    Args:
        rows: one dict per (case, noise draw, ulp seed, tree): ``case``, ``tree``, ``noise``
            (the draw; 0 when absent) and the metrics of :data:`TOLERANCES`.
        reference: the tree the others are judged against.

    Returns one dict per (case, metric, tree): ``reference`` and ``new`` ranges (over the ulp
    seeds with one noise draw, over the draws' medians with several), ``change`` (of the
    medians, or the median paired change), ``worse_draws`` (``"w/n"`` draws that went the wrong
    way, with several draws; else ``""``) and ``verdict`` (module docstring).
    """
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        by_tree: dict[str, dict[int, list[Mapping]]] = {}
        for r in rows:
            if r["case"] == case:
                by_tree.setdefault(r["tree"], {}).setdefault(int(r.get("noise", 0)), []).append(r)
        if reference not in by_tree:
            continue
        ref_draws = by_tree[reference]
        for tree, draws in by_tree.items():
            if tree == reference:
                continue
            shared = [k for k in draws if k in ref_draws]
            for metric, (better, absolute, relative) in TOLERANCES.items():
                if len(shared) > 1:
                    ref = [statistics.median(r[metric] for r in ref_draws[k]) for k in shared]
                    new = [statistics.median(r[metric] for r in draws[k]) for k in shared]
                    diffs = [n - r for n, r in zip(new, ref)]
                    change = statistics.median(diffs)
                    worse = sum(better * d < 0 for d in diffs)
                    undecided = sign_test(worse, len(diffs)) > SIGN_TEST_LEVEL
                    tally = f"{worse}/{len(diffs)}"
                else:
                    ref = [r[metric] for k in shared for r in ref_draws[k]]
                    new = [r[metric] for k in shared for r in draws[k]]
                    change = statistics.median(new) - statistics.median(ref)
                    undecided = min(new) <= max(ref) and min(ref) <= max(new)
                    tally = ""
                band = max(absolute, relative * abs(statistics.median(ref)))
                loose = "noise" if len(shared) > 1 else "rounding"
                verdict = "" if better * change >= -band else (loose if undecided else "worse")
                out.append({"case": case, "metric": metric, "tree": tree, "reference": (min(ref), max(ref)),
                            "new": (min(new), max(new)), "change": change, "worse_draws": tally,
                            "verdict": verdict})
    return out


def table(found: Sequence[Mapping], reference: str, all_metrics: bool = False) -> str:
    """Markdown rows of :func:`verdicts`: the flagged metrics only unless ``all_metrics``."""
    lines = [f"| case | metric | {reference}, range | tree: range | change | draws worse | verdict |",
             "|---|---|---|---|---|---|---|"]
    for v in found:
        if v["verdict"] or all_metrics:
            lines.append(f"| {v['case']} | {v['metric']} | {v['reference'][0]:.4g}–{v['reference'][1]:.4g} | "
                         f"{v['tree']}: {v['new'][0]:.4g}–{v['new'][1]:.4g} | {v['change']:+.4g} | {v['worse_draws']} | "
                         f"{v['verdict']} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.panel_rounding", description=__doc__.split("\n")[0])
    ap.add_argument("--tree", action="append", required=True, metavar="NAME=DIR",
                    help="a solver's source tree (repeat; the first is the reference)")
    ap.add_argument("--only", required=True, help="comma-separated panel case names (exact)")
    ap.add_argument("--ulp-seeds", type=int, default=None,
                    help="rounding seeds 0..N-1 (default 4 with one noise draw, else 1)")
    ap.add_argument("--noise-seeds", type=int, default=1,
                    help=f"sensor-noise draws 0..N-1 (default 1; several: at least {MIN_NOISE_DRAWS})")
    ap.add_argument("--size", type=int, default=128, help="capture size (default 128, the panel's)")
    ap.add_argument("--all-metrics", action="store_true", help="print every metric, not only the flagged")
    ap.add_argument("--json", default=None, help="write the scored fits here")
    args = ap.parse_args(argv)
    trees = source_trees(args.tree, ap)
    names = [n.strip() for n in args.only.split(",")]
    by_name = {c.name: c for c in panel_cases("all")}
    missing = [n for n in names if n not in by_name]
    if missing:
        ap.error(f"--only: not panel cases: {missing} (names as `recovery_panel` prints them)")
    if args.noise_seeds < 1 or 1 < args.noise_seeds < MIN_NOISE_DRAWS:
        ap.error(f"--noise-seeds: expected 1 or at least {MIN_NOISE_DRAWS} (a sign test over fewer draws "
                 f"cannot reach p ≤ {SIGN_TEST_LEVEL}), got {args.noise_seeds}")
    if args.ulp_seeds is None:
        args.ulp_seeds = 4 if args.noise_seeds == 1 else 1
    if args.ulp_seeds < (2 if args.noise_seeds == 1 else 1):
        ap.error(f"--ulp-seeds: need at least 2 to see a range with one noise draw, got {args.ulp_seeds}")
    rows = []
    for name in names:
        case = by_name[name]
        runs = [(noise, ulp) for noise in range(args.noise_seeds) for ulp in range(args.ulp_seeds)]
        for i, (noise, ulp) in enumerate(runs):
            with tempfile.TemporaryDirectory(prefix="panel_rounding_cap_") as cap:
                truth, _ = render_case(case, cap, args.size, noise_seed=noise, ulp_seed=ulp)
                order = list(trees) if i % 2 == 0 else list(trees)[::-1]
                for tree in order:
                    maps = recover_in_tree(trees[tree], cap)
                    rows.append({"case": name, "noise": noise, "ulp": ulp, "tree": tree,
                                 **score_maps(maps, truth, case.model, seed=case_seed(case))})
                    print(json.dumps(rows[-1]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(table(verdicts(rows, next(iter(trees))), next(iter(trees)), args.all_metrics))
    return 0


if __name__ == "__main__":
    sys.exit(main())
