"""``python -m torchbrdf.bench.fit_time``: a recovery's time, one source tree against another, alternated.

Each repetition runs, for each capture and thread count asked for, one fit per source tree
(``--tree NAME=DIR``, at least one; each fit a fresh process with ``PYTHONPATH=DIR``, the trees
in alternating order), and records the fit's wall time (``seconds`` of its ``report.json``)
and its CPU time (the process's, all threads, around the iterations alone: less sensitive
to other processes' load than wall time on a shared machine). The table gives min / median /
max over the repetitions and the held-out PSNRs seen (one value per row when every fit of a
tree took the same decisions). ``--busy`` runs everything beside one
``python -c "while True: pass"``. ``--part MODULE.NAME`` (e.g.
``torchbrdf.recovery.engine.propagate_passes``) also records the CPU time spent in that
function, patched on its module (a piece's time within the same alternated fits). ``--model
svbrdf_ggx`` times the recovery's GGX model.

The fits run as the ``torchbrdf-recover`` command does (its OpenMP wait included: :data:`AS_COMMAND`).

Captures: ``demo`` (the CLI's ``--demo``, 128²) or a capture folder (e.g. the 256² 17-light
``generate_capture(folder, recipe="tiles", seed=7)``). Results: docs/recovery_measurements.md.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

#: The child's first lines: it runs as the ``torchbrdf-recover`` command does, which chooses how
#: OpenMP threads wait when torchbrdf is first imported (``torchbrdf/__init__.py``); a plain
#: ``python -c`` would time libgomp's spinning wait instead, which users of the command never get.
AS_COMMAND = """import sys
sys.argv[0] = "torchbrdf-recover"
"""
#: The child: the CLI, with the fit's process CPU time written to argv[1] (only the public CLI
#: and ``api``'s loop are used, so any tree of the project runs it).
_CHILD = AS_COMMAND + r"""
import importlib, sys, time
import torchbrdf.recovery.api as api
inner = api._iterate_until_done_or_stopped
part = [0.0]
if sys.argv[2]:  # MODULE.NAME: its CPU time too
    mod, name = sys.argv[2].rsplit(".", 1)
    mod = importlib.import_module(mod)
    fn = getattr(mod, name)
    def counted(*a, **k):
        c = time.process_time()
        try:
            return fn(*a, **k)
        finally:
            part[0] += time.process_time() - c
    setattr(mod, name, counted)
def timed(*a, **k):
    c = time.process_time()
    try:
        return inner(*a, **k)
    finally:
        open(sys.argv[1], "w").write(repr((time.process_time() - c, part[0])))
api._iterate_until_done_or_stopped = timed
from torchbrdf.recovery.cli import main
sys.exit(main(sys.argv[3:]))
"""


def run_fit(tree: str, capture: str, threads: int, part: str | None = None, model: str = "principled") -> dict:
    """One fit of ``capture`` (``"demo"`` or a folder) with the sources of ``tree`` in a fresh process:
    ``{"seconds", "cpu", "psnr"}``, and ``"part_cpu"``: the CPU s in ``part`` (``MODULE.NAME``) if given.
    ``model``: the recovery's ``--model``."""
    with tempfile.TemporaryDirectory(prefix="fit_time_") as d:
        cpu_file = os.path.join(d, "cpu")
        args = ["--demo"] if capture == "demo" else ["--capture", capture]
        subprocess.run([sys.executable, "-c", _CHILD, cpu_file, part or "", *args, "--out", os.path.join(d, "out"),
                        "--threads", str(threads), "--model", model, "--quiet"], cwd=tree, check=True,
                       env=dict(os.environ, PYTHONPATH=tree), stdout=subprocess.DEVNULL)
        report = json.loads(Path(d, "out", "report.json").read_text())
        cpu, part_cpu = ast.literal_eval(Path(cpu_file).read_text())
        row = {"seconds": float(report["seconds"]), "cpu": float(cpu),
               "psnr": (report.get("held_out_light") or {}).get("psnr")}
        return {**row, "part_cpu": float(part_cpu)} if part else row


def source_trees(specs: Sequence[str], ap: argparse.ArgumentParser) -> dict[str, str]:
    """``--tree NAME=DIR`` options as ``{name: absolute DIR}``; a bad one is an ``ap.error``."""
    trees = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not Path(path, "torchbrdf").is_dir():
            ap.error(f"--tree: expected NAME=DIR with DIR/torchbrdf a folder, got {spec!r}")
        trees[name] = str(Path(path).resolve())
    return trees


def min_median_max(xs: Sequence[float], digits: int = 2) -> str:
    """``"min / median / max"`` of ``xs``, ``digits`` decimals each."""
    return f"{min(xs):.{digits}f} / {statistics.median(xs):.{digits}f} / {max(xs):.{digits}f}"


def table(rows: Sequence[dict]) -> str:
    """Markdown rows: capture, threads, tree, seconds and CPU seconds (min / median / max), PSNRs;
    and the ``--part``'s CPU seconds where the rows have them."""
    part = all("part_cpu" in r for r in rows)
    out = ["| capture | threads | tree | seconds (min / median / max) | CPU s (min / median / max) | "
           + ("part's CPU s (min / median / max) | " if part else "") + "held-out PSNR |",
           "|---|---|---|---|---|" + ("---|" if part else "") + "---|"]
    keys = dict.fromkeys((r["capture"], r["threads"], r["tree"]) for r in rows)
    for cap, th, tree in keys:
        sel = [r for r in rows if (r["capture"], r["threads"], r["tree"]) == (cap, th, tree)]
        psnr = ", ".join(f"{p:.6f}" for p in sorted({r["psnr"] for r in sel if r["psnr"] is not None}))
        part_col = f"{min_median_max([r['part_cpu'] for r in sel])} | " if part else ""
        out.append(f"| {Path(cap).name} | {th} | {tree} | {min_median_max([r['seconds'] for r in sel])} | "
                   f"{min_median_max([r['cpu'] for r in sel])} | {part_col}{psnr} |")
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.fit_time", description=__doc__.split("\n")[0])
    ap.add_argument("--tree", action="append", required=True, metavar="NAME=DIR",
                    help="a source tree to time (repeat: the trees alternate)")
    ap.add_argument("--capture", action="append", default=None,
                    help="'demo' or a capture folder (repeat; default: demo)")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts (default 1,2)")
    ap.add_argument("--reps", type=int, default=5, help="repetitions (default 5)")
    ap.add_argument("--busy", action="store_true", help="beside one busy Python process")
    ap.add_argument("--model", default="principled", choices=("principled", "svbrdf_ggx"),
                    help="the recovery's --model (default principled)")
    ap.add_argument("--json", default=None, help="write the fits' rows to this file")
    ap.add_argument("--part", default=None, metavar="MODULE.NAME",
                    help="also the CPU s spent in this function (e.g. torchbrdf.recovery.engine.propagate_passes)")
    args = ap.parse_args(argv)
    if args.part is not None and (args.part.count(".") < 1 or not all(args.part.split("."))):
        ap.error(f"--part: expected MODULE.NAME (a dotted path), got {args.part!r}")
    trees = source_trees(args.tree, ap)
    threads = [int(t) for t in args.threads.split(",")]
    captures = args.capture or ["demo"]
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.busy else None
    rows = []
    try:
        for rep in range(args.reps):
            for cap in captures:
                for k, th in enumerate(threads):
                    names = list(trees)
                    order = names if (rep + k) % 2 == 0 else names[::-1]
                    for name in order:
                        rows.append({"capture": cap, "threads": th, "tree": name, "rep": rep,
                                     **run_fit(trees[name], cap, th, args.part, args.model)})
                        print(json.dumps(rows[-1]), flush=True)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
