"""Forward mode: fused JVP kernels against eager forward-mode AD, side by side.

``python -m torchbrdf.bench.jvp [--log2n 20] [--threads 1]`` times, on N random lanes with
every principled parameter a per-lane tensor (float32, CPU):

* ``torch.func.jvp`` w.r.t. the roughness (one tangent) — fused (default dispatch) and eager;
* ``torch.func.jacfwd`` w.r.t. one shared material of 5 numbers (base colour, roughness,
  metallic) — fused (5 tangents in one pass of the JVP kernel) and eager.

Each fused time includes the forward evaluation that ``torch.func.jvp`` also returns. The
first call of each (kernel build or load, warm-up) is not timed; the best of a few runs is
reported.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import torch


def _best(fn, reps: int) -> float:
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def run(log2n: int = 20, threads: int = 1, reps: int = 3) -> dict:
    """Time fused and eager forward mode; returns ``{name: seconds}`` and prints a table."""
    import torchbrdf
    from torchbrdf.brdf import principled as P

    torch.set_num_threads(threads)
    n = 1 << log2n
    g = torch.Generator().manual_seed(0)
    up = torch.tensor([0.5, 0.5, -0.2])
    lanes = {
        "l": torch.nn.functional.normalize(torch.rand(n, 3, generator=g) - up, dim=-1),
        "v": torch.nn.functional.normalize(torch.rand(n, 3, generator=g) - up, dim=-1),
        "n": torch.tensor([0.0, 0.0, 1.0]).expand(n, 3),
    }
    params = {k: torch.rand(n, 1, generator=g) for k in ("metallic", "specular", "sheen", "clearcoat")}
    base = torch.rand(n, 3, generator=g)
    rough = torch.rand(n, 1, generator=g)
    tangent = torch.randn(n, 1, generator=g)

    def f(r):
        return torchbrdf.principled(**lanes, base_color=base, roughness=r, **params)

    def m(q):
        return torchbrdf.principled(**lanes, base_color=q[:3], roughness=q[3:4], metallic=q[4:5])

    q = torch.tensor([0.5, 0.4, 0.3, 0.5, 0.2])
    res = {}
    for mode, fast in (("fused", None), ("eager", False)):
        P.set_fast_path(fast)
        try:
            res[f"jvp {mode}"] = _best(lambda: torch.func.jvp(f, (rough,), (tangent,)), reps)
            res[f"jacfwd(5) {mode}"] = _best(lambda: torch.func.jacfwd(m)(q), max(1, reps - 1))
        finally:
            P.set_fast_path(None)
    print(f"N = 2^{log2n} lanes, float32, {threads} thread(s)")
    for what in ("jvp", "jacfwd(5)"):
        fu, ea = res[f"{what} fused"], res[f"{what} eager"]
        print(f"  {what:10s} fused {fu * 1e3:8.1f} ms   eager {ea * 1e3:8.1f} ms   x{ea / fu:.1f}")
    return res


def main(argv: Sequence[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log2n", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args(argv)
    run(a.log2n, a.threads, a.reps)


if __name__ == "__main__":
    main()
