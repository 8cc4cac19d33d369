"""``python -m torchbrdf.bench.cg_time``: the LM step's coupled solve alone, source trees alternated.

Two steps. ``--save DIR`` runs one fit (the CLI, this tree, one thread: ``--capture demo`` or a
capture folder, ``--cli`` more CLI options) and saves the arguments of every ``--every``-th
call of :func:`torchbrdf.recovery.smoothness_prior.pcg` its LM steps make (``DIR/pcg_NNN.pt``).
``--args DIR --tree NAME=DIR ...`` then times ``pcg`` on those calls: per repetition each tree,
in alternating order, in a fresh process with its own sources (``PYTHONPATH``), solves every
saved call once (a warm-up: kernels built and loaded) and then times one pass over them, CPU
seconds (the process's, all threads) and wall seconds. The table gives min / median / max per
tree and the largest difference of each tree's solutions from the first tree's, relative to
the solution's largest entry (0: the same bits). Results: docs/recovery_measurements.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from torchbrdf.bench.fit_time import min_median_max, source_trees

#: The saving child: the CLI with the LM step's ``pcg`` wrapped (argv: folder, every, CLI options).
_SAVE = r"""
import sys, torch
import torchbrdf.recovery.lm as lm
out, every, inner, calls = sys.argv[1], int(sys.argv[2]), lm.pcg, [0]
def saved(hess, wx, wy, rhs, size, iters, diag=None):
    if calls[0] % every == 0:
        torch.save(dict(hess=hess, wx=wx, wy=wy, rhs=rhs, size=size, iters=iters, diag=diag),
                   f"{out}/pcg_{calls[0]:03d}.pt")
    calls[0] += 1
    return inner(hess, wx, wy, rhs, size, iters, diag=diag)
lm.pcg = saved
from torchbrdf.recovery.cli import main
sys.exit(main(sys.argv[3:]))
"""

#: The timing child (argv: the saved calls' folder, threads, the file for the times and solutions).
_TIME = r"""
import glob, sys, time, torch
from torchbrdf.recovery.smoothness_prior import pcg
torch.set_num_threads(int(sys.argv[2]))
calls = [torch.load(f) for f in sorted(glob.glob(sys.argv[1] + "/pcg_*.pt"))]
def solve(a):
    return pcg(a["hess"], a["wx"], a["wy"], a["rhs"], a["size"], a["iters"], diag=a["diag"])
xs = [solve(a) for a in calls]
c, w = time.process_time(), time.perf_counter()
for a in calls:
    solve(a)
cpu, wall = time.process_time() - c, time.perf_counter() - w
torch.save(dict(cpu=cpu, wall=wall, x=xs), sys.argv[3])
"""


def save_calls(folder: str, capture: str, every: int, cli: Sequence[str] = ()) -> int:
    """Run one fit of ``capture`` (``"demo"`` or a folder) with this tree's sources, one thread,
    saving every ``every``-th ``pcg`` call's arguments to ``folder``; returns how many were saved."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    tree = str(Path(__file__).resolve().parents[2])
    with tempfile.TemporaryDirectory(prefix="cg_time_") as d:
        args = ["--demo"] if capture == "demo" else ["--capture", capture]
        subprocess.run([sys.executable, "-c", _SAVE, folder, str(every), *args,
                        "--out", os.path.join(d, "out"), "--threads", "1", "--quiet", *cli],
                       cwd=tree, check=True, env=dict(os.environ, PYTHONPATH=tree), stdout=subprocess.DEVNULL)
    return len(list(Path(folder).glob("pcg_*.pt")))


def time_tree(tree: str, folder: str, threads: int) -> dict:
    """One timed pass of ``tree``'s ``pcg`` over the calls saved in ``folder``, in a fresh process:
    ``{"cpu", "wall", "x"}`` (seconds; the solutions, one ``(P, 7)`` tensor per call)."""
    import torch

    with tempfile.TemporaryDirectory(prefix="cg_time_") as d:
        out = os.path.join(d, "times.pt")
        subprocess.run([sys.executable, "-c", _TIME, folder, str(threads), out], cwd=tree, check=True,
                       env=dict(os.environ, PYTHONPATH=tree))
        return torch.load(out)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.cg_time", description=__doc__.split("\n")[0])
    ap.add_argument("--save", default=None, metavar="DIR", help="run a fit and save its pcg calls here")
    ap.add_argument("--capture", default="demo", help="with --save: 'demo' or a capture folder")
    ap.add_argument("--every", type=int, default=8, help="with --save: every N-th call (default 8)")
    ap.add_argument("--cli", default="", help="with --save: more CLI options, one string")
    ap.add_argument("--args", default=None, metavar="DIR", help="time pcg on the calls saved here")
    ap.add_argument("--tree", action="append", default=[], metavar="NAME=DIR",
                    help="with --args: a source tree to time (repeat: the trees alternate)")
    ap.add_argument("--threads", type=int, default=1, help="threads of the timed processes (default 1)")
    ap.add_argument("--reps", type=int, default=7, help="repetitions (default 7)")
    args = ap.parse_args(argv)
    if (args.save is None) == (args.args is None):
        ap.error("give one of --save DIR and --args DIR")
    if args.every < 1:
        ap.error(f"--every: expected a positive number of calls, got {args.every}")
    if args.save is not None:
        n = save_calls(args.save, args.capture, args.every, shlex.split(args.cli))
        print(f"{n} calls saved to {args.save}")
        return 0
    trees = source_trees(args.tree or [], ap)
    if not trees:
        ap.error("--args needs at least one --tree NAME=DIR")
    if not any(Path(args.args).glob("pcg_*.pt")):
        ap.error(f"--args: no saved calls (pcg_*.pt) in {args.args!r}")
    runs: dict[str, list[dict]] = {name: [] for name in trees}
    names = list(trees)
    for rep in range(args.reps):
        for name in names if rep % 2 == 0 else names[::-1]:
            runs[name].append(time_tree(trees[name], args.args, args.threads))
            print(json.dumps({"tree": name, "rep": rep, "cpu": runs[name][-1]["cpu"],
                              "wall": runs[name][-1]["wall"]}), flush=True)
    first = runs[names[0]][0]["x"]
    print("| tree | CPU s (min / median / max) | wall s (min / median / max) | max relative difference |")
    print("|---|---|---|---|")
    for name in names:
        diff = max(float((x - x0).abs().max() / x0.abs().max().clamp(min=1e-30))
                   for x, x0 in zip(runs[name][0]["x"], first, strict=True))
        cpu = min_median_max([r["cpu"] for r in runs[name]], 4)
        wall = min_median_max([r["wall"] for r in runs[name]], 4)
        print(f"| {name} | {cpu} | {wall} | {diff:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
