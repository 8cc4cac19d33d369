"""``python -m torchbrdf.bench.panel_rounding``: whether a panel case's change between two solvers is rounding.

A case flagged by ``recovery_panel --compare`` may differ between the solvers only because
each amplifies rounding differently. Each case is written once per ``--ulp-seed`` (0 is the
panel's own capture; ``N > 0`` moves a random half of the image values up by one float32 ulp,
:func:`~torchbrdf.bench.recovery_panel.render_case`) and recovered by every source tree
(``--tree NAME=DIR``, each fit a fresh process with ``PYTHONPATH=DIR``, one thread, every
captured light in the fit), all scored by this tree's
:func:`~torchbrdf.bench.recovery_panel.score_maps`. Per case and metric the table gives each
tree's range over the seeds and the change of the medians, with a verdict against the first
tree: ``worse`` when the medians moved the wrong way by more than the panel's band
(:data:`~torchbrdf.bench.recovery_panel.TOLERANCES`) and the two ranges do not overlap;
``rounding`` when beyond the band but the ranges overlap; blank within the band.

Run it only on cases a ``--compare`` already flagged: it reports, it chooses nothing.
Results: docs/recovery_panel.md ("Rounding sensitivity").
"""

from __future__ import annotations

import argparse
import json
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

__all__ = ["recover_in_tree", "verdicts", "table", "main"]

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


def verdicts(rows: Sequence[Mapping], reference: str) -> list[dict]:
    """Per case, metric and tree other than ``reference``: the ranges, the medians' change and the verdict.

    Args:
        rows: one dict per (case, ulp seed, tree): ``case``, ``tree`` and the metrics of
            :data:`TOLERANCES`.
        reference: the tree the others are judged against.
    """
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        by_tree: dict[str, list[Mapping]] = {}
        for r in rows:
            if r["case"] == case:
                by_tree.setdefault(r["tree"], []).append(r)
        for tree, sel in by_tree.items():
            if tree == reference or reference not in by_tree:
                continue
            for metric, (better, absolute, relative) in TOLERANCES.items():
                ref = [r[metric] for r in by_tree[reference]]
                new = [r[metric] for r in sel]
                change = statistics.median(new) - statistics.median(ref)
                band = max(absolute, relative * abs(statistics.median(ref)))
                overlap = min(new) <= max(ref) and min(ref) <= max(new)
                verdict = "" if better * change >= -band else ("rounding" if overlap else "worse")
                out.append({"case": case, "metric": metric, "tree": tree, "reference": (min(ref), max(ref)),
                            "new": (min(new), max(new)), "change": change, "verdict": verdict})
    return out


def table(found: Sequence[Mapping], reference: str, all_metrics: bool = False) -> str:
    """Markdown rows of :func:`verdicts`: the flagged metrics only unless ``all_metrics``."""
    lines = [f"| case | metric | {reference}, range | tree: range | change of the medians | verdict |",
             "|---|---|---|---|---|---|"]
    for v in found:
        if v["verdict"] or all_metrics:
            lines.append(f"| {v['case']} | {v['metric']} | {v['reference'][0]:.4g}–{v['reference'][1]:.4g} | "
                         f"{v['tree']}: {v['new'][0]:.4g}–{v['new'][1]:.4g} | {v['change']:+.4g} | {v['verdict']} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.panel_rounding", description=__doc__.split("\n")[0])
    ap.add_argument("--tree", action="append", required=True, metavar="NAME=DIR",
                    help="a solver's source tree (repeat; the first is the reference)")
    ap.add_argument("--only", required=True, help="comma-separated panel case names (exact)")
    ap.add_argument("--ulp-seeds", type=int, default=4, help="rounding seeds 0..N-1 (default 4)")
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
    if args.ulp_seeds < 2:
        ap.error(f"--ulp-seeds: need at least 2 to see a range, got {args.ulp_seeds}")
    rows = []
    for name in names:
        case = by_name[name]
        for ulp in range(args.ulp_seeds):
            with tempfile.TemporaryDirectory(prefix="panel_rounding_cap_") as cap:
                truth, _ = render_case(case, cap, args.size, ulp_seed=ulp)
                order = list(trees) if ulp % 2 == 0 else list(trees)[::-1]
                for tree in order:
                    maps = recover_in_tree(trees[tree], cap)
                    rows.append({"case": name, "ulp": ulp, "tree": tree,
                                 **score_maps(maps, truth, case.model, seed=case_seed(case))})
                    print(json.dumps(rows[-1]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(table(verdicts(rows, next(iter(trees))), next(iter(trees)), args.all_metrics))
    return 0


if __name__ == "__main__":
    sys.exit(main())
