"""``python -m torchbrdf.bench.threads``: wall time quiet vs with one competing busy process.

Why: OpenMP threads that spin-wait collapse on a shared machine (an earlier demo recovery
took 97 s quiet, 507 s next to one busy process). This runs a workload in a fresh process,
alternately on its own and next to ``python -c "while True: pass"``, for each OpenMP wait
policy asked for, and prints the median wall times and their ratio. Results: docs/fast_path.md.

Workloads:
    brdf      ``principled`` forward+backward on the fused kernels, 2^20 lanes, float32, repeated.
    recovery  ``python -m training.recover_svbrdf --demo --quiet`` (more options with ``--cli``;
              ``--threads torch,1,auto`` alternates the CLI's thread choices).
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence

_BRDF = r"""
import sys, time, torch, torchbrdf
from torchbrdf.brdf.principled import set_fast_path
set_fast_path(True)
N, reps = int(sys.argv[1]), int(sys.argv[2])
g = torch.Generator().manual_seed(0)
up = torch.tensor([0.0, 0.0, 1.2])
nrm = lambda x: torch.nn.functional.normalize(x, dim=-1)
l, v = nrm(torch.rand(N, 3, generator=g) - 0.5 + up), nrm(torch.rand(N, 3, generator=g) - 0.5 + up)
n = nrm(torch.rand(N, 3, generator=g) * 0.2 - 0.1 + up)
p = dict(base_color=torch.rand(N, 3, generator=g), roughness=torch.rand(N, 1, generator=g),
         metallic=torch.rand(N, 1, generator=g), specular=torch.rand(N, 1, generator=g))
for t in p.values():
    t.requires_grad_(True)
def step():
    out = torchbrdf.principled(l, v, n, **p)
    out.backward(torch.ones_like(out))
step()  # build/load the kernels outside the timing
t0 = time.perf_counter()
for _ in range(reps):
    step()
print("SECONDS", time.perf_counter() - t0)
"""


#: The line a timed workload prints: ``SECONDS <its own seconds>``.
SECONDS = "SECONDS"


def run_workload(cmd: Sequence[str], env: dict | None, busy: bool) -> tuple[float, str]:
    """Run ``cmd`` in a fresh process (beside one busy process with ``busy``).

    Returns ``(wall seconds, its standard output)``; a failing command raises with the end of
    its stderr.
    """
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        if hog is not None:
            time.sleep(0.2)
        t0 = time.perf_counter()
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    if res.returncode != 0:
        raise RuntimeError(f"{cmd} failed:\n{res.stderr[-3000:]}")
    return wall, res.stdout


def tagged_line(stdout: str, tag: str) -> str | None:
    """What follows ``tag`` on the first line of ``stdout`` that starts with it (None: no such line)."""
    for line in stdout.splitlines():
        if line.startswith(tag + " "):
            return line[len(tag) + 1:]
    return None


def workload_seconds(cmd: Sequence[str], stdout: str, wall: float | None) -> float:
    """The workload's own time: the number on its ``SECONDS`` line.

    That is its time without the interpreter's start; without the line, ``wall``, or an error
    where ``wall`` is None.
    """
    seconds = tagged_line(stdout, SECONDS)
    if seconds is not None:
        return float(seconds)
    if wall is None:
        raise RuntimeError(f"{cmd} printed no {SECONDS} line:\n{stdout[-2000:]}")
    return wall


def run_timed(cmd: Sequence[str], env: dict | None, busy: bool, require_seconds: bool = False) -> float:
    """Run ``cmd`` as :func:`run_workload` and return its time (:func:`workload_seconds`).

    With ``require_seconds`` a missing ``SECONDS`` line is an error instead of the wall time.
    """
    wall, stdout = run_workload(cmd, env, busy)
    return workload_seconds(cmd, stdout, None if require_seconds else wall)


def _mmm(xs: list[float]) -> str:
    """min / median / max."""
    return f"{min(xs):7.2f} / {statistics.median(xs):7.2f} / {max(xs):7.2f}"


def _with_threads(cmd: list[str], choice: str, busy: bool) -> list[str]:
    """``cmd`` with the recovery CLI's ``--threads`` for ``choice`` ('torch': none; 'auto':
    :func:`torchbrdf.parallel.default_threads`, read as the run starts)."""
    if choice == "torch":
        return cmd
    if choice == "auto":
        from torchbrdf.parallel import default_threads

        # (this process is idle while it waits: its own share of the load is 0)
        return cmd + ["--threads", str(default_threads(own_load=0.0))]
    return cmd + ["--threads", str(int(choice))]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; prints one line per (policy, quiet/busy) and the busy/quiet ratio."""
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.threads",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("workload", choices=("brdf", "recovery"))
    p.add_argument("--lanes", type=int, default=1 << 20)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--repeat", type=int, default=3, help="alternating quiet/busy runs per policy")
    p.add_argument("--policies", default="default,PASSIVE",
                   help="OMP_WAIT_POLICY values ('default': libgomp's spinning; 'cli': "
                        "unset, as the recovery CLI chooses)")
    p.add_argument("--cli", default="", help="extra options of the recovery CLI, e.g. '--iters 6'")
    p.add_argument("--threads", default="torch",
                   help="recovery: comma-separated thread choices, alternated: 'torch' (the CLI's default), "
                        "'auto' (torchbrdf.parallel.default_threads() when the run starts) or a number")
    args = p.parse_args(argv)
    out = tempfile.mkdtemp(prefix="tb-threads-")
    if args.workload == "brdf":
        cmd = [sys.executable, "-c", _BRDF, str(args.lanes), str(args.reps)]
    else:
        extra = shlex.split(args.cli)
        cmd = [sys.executable, "-m", "training.recover_svbrdf", "--demo", "--out", out, "--quiet", *extra]
    print(f"workload: {args.workload}  cores: {os.cpu_count()}  load average: {os.getloadavg()}")
    choices = args.threads.split(",") if args.workload == "recovery" else ["torch"]
    for pol in args.policies.split(","):
        env = dict(os.environ)
        env.pop("OMP_WAIT_POLICY", None)
        env.pop("GOMP_SPINCOUNT", None)
        if pol == "default":
            env["GOMP_SPINCOUNT"] = "300000"  # libgomp's default, set so the recovery CLI keeps it
        elif pol != "cli":  # 'cli': neither set, the recovery CLI's own choice
            env["OMP_WAIT_POLICY"] = pol
        times: dict[tuple[str, bool], list[float]] = {(c, b): [] for c in choices for b in (False, True)}
        for _ in range(args.repeat):
            for choice in choices:
                for busy in (False, True):
                    times[choice, busy].append(run_timed(_with_threads(cmd, choice, busy), env, busy))
        for choice in choices:
            q, b = times[choice, False], times[choice, True]
            mq, mb = statistics.median(q), statistics.median(b)
            print(f"OMP_WAIT_POLICY={pol:8s} threads={choice:5s} quiet {_mmm(q)} s  busy {_mmm(b)} s  "
                  f"busy/quiet (medians) {mb / mq:5.2f}")
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
