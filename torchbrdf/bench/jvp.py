"""Forward mode: fused JVP kernels against eager forward-mode AD, side by side.

``python -m torchbrdf.bench.jvp [--log2n 20] [--threads 1]`` times, on N random lanes with
every principled parameter a per-lane tensor (float32, CPU):

* ``torch.func.jvp`` w.r.t. the roughness (one tangent) — fused (default dispatch) and eager;
* ``torch.func.jacfwd`` w.r.t. one shared material of 5 numbers (base colour, roughness,
  metallic) — fused (5 tangents in one pass of the JVP kernel) and eager.

Each fused time includes the forward evaluation that ``torch.func.jvp`` also returns. The
first call of each (kernel build or load, warm-up) is not timed; the best of a few runs is
reported.

``python -m torchbrdf.bench.jvp --fit [--threads 2]`` times the SVBRDF recovery's Jacobian
(:func:`torchbrdf.recovery.lm.fit_jacobian`, the soft-metal fit's 8 unknowns: 6 directions)
on the demo capture (128², 16 lights and the flash) for a few pixel counts: the fused operators
called directly (:meth:`~torchbrdf.recovery.levels.LevelData.residual_jvp`) against
``torch.func.vmap`` over ``torch.func.jvp`` of the residual, side by side; medians of ``reps``.

``python -m torchbrdf.bench.jvp --light-step [--threads 1]`` times one joint light step
(5 + 4 directions) on the demo capture with the JVP kernel's passes of 8 and of 12 tangents
alternated, CPU and wall seconds.
"""

from __future__ import annotations

import argparse
import math
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


def fit_jacobian_times(sizes: Sequence[int] = (16, 256, 4096, 16384), threads: int = 1, reps: int = 7,
                       capture: str | None = None) -> dict:
    """Median seconds of the recovery's 6-direction Jacobian, ``{(pixels, "direct" | "vmap"): s}``.

    On the capture folder ``capture`` (default: the demo capture). Prints a table; see the
    module docstring.
    """
    from torchbrdf.capture import default_capture, load_capture

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _fit_jacobian_times(load_capture(capture or default_capture()), sizes, threads, reps)
    finally:
        torch.set_num_threads(before)


def _fit_jacobian_times(cap, sizes: Sequence[int], threads: int, reps: int) -> dict:
    """:func:`fit_jacobian_times` on a loaded capture ``cap``."""
    import statistics

    from torchbrdf.recovery.levels import LevelData, vmapped_jvp
    from torchbrdf.recovery.lm import fit_jacobian

    data = LevelData(cap, cap.width, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(0)
    x_all = torch.cat((torch.randn(data.points.shape[0], 7, generator=g) * 0.5,
                       torch.rand(data.points.shape[0], 1, generator=g)), -1)
    idx, res = data.train_idx, {}
    print(f"fit_jacobian, 6 directions, {len(idx)} lights, float32, {threads} thread(s), median of {reps}")
    print("  pixels     direct      vmap(jvp)")
    for n in sizes:
        n = min(n, x_all.shape[0])
        sub, x = data.subset(torch.arange(n)), x_all[:n]
        ways = {"direct": lambda v, tg: sub.residual_jvp(v, v[:, 7:8], idx, "principled", tg),  # noqa: B023
                "vmap": vmapped_jvp(lambda v: sub.residual(v[:, :7], v[:, 7:8], idx, "principled"))}  # noqa: B023
        for name, jvp in ways.items():
            fit_jacobian(jvp, x, 8)  # kernel build or load, warm-up
            ts = []
            for _ in range(reps):
                t0 = time.perf_counter()
                fit_jacobian(jvp, x, 8)
                ts.append(time.perf_counter() - t0)
            res[(n, name)] = statistics.median(ts)
        print(f"  {n:6d} {res[(n, 'direct')] * 1e3:9.1f} ms {res[(n, 'vmap')] * 1e3:9.1f} ms")
    return res


def _light_step_pixels() -> int:
    """:func:`~torchbrdf.recovery.calibration.light_joint_step`'s default ``max_pixels``."""
    import inspect

    from torchbrdf.recovery.calibration import light_joint_step

    return int(inspect.signature(light_joint_step).parameters["max_pixels"].default)


def light_step_times(threads: int = 1, reps: int = 9, capture: str | None = None) -> dict:
    """CPU and wall seconds ``{tangents per pass: {"cpu": [...], "wall": [...]}}`` of one joint
    light step (:func:`torchbrdf.recovery.calibration.light_joint_step`, positions and scales:
    5 + 4 directions) on ``capture`` (default: the demo capture; the step's evenly strided
    ``max_pixels`` pixels of it), with the JVP kernel's passes of 8 and of 12 tangents alternated,
    the order reversed every other repetition. Prints min / median / max.
    """
    import statistics

    from torchbrdf.capture import default_capture, load_capture
    from torchbrdf.kernels import c_runner
    from torchbrdf.recovery.calibration import light_joint_step
    from torchbrdf.recovery.levels import LevelData

    cap = load_capture(capture or default_capture())
    data = LevelData(cap, cap.width, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(0)
    theta = torch.randn(data.points.shape[0], 7, generator=g) * 0.5
    metal = torch.zeros(theta.shape[0], 1)
    n_l = len(cap)
    before, kept = torch.get_num_threads(), c_runner.TANGENTS_PER_PASS
    torch.set_num_threads(threads)
    res: dict = {}
    try:
        for per_pass in (8, 12):  # kernel build or load, warm-up
            c_runner.TANGENTS_PER_PASS = per_pass
            light_joint_step(data, theta, metal, torch.zeros(n_l), torch.zeros(n_l, 3), data.train_idx, "principled")
        for rep in range(reps):
            for per_pass in ((8, 12) if rep % 2 == 0 else (12, 8)):  # neither always first
                c_runner.TANGENTS_PER_PASS = per_pass
                c0, t0 = time.process_time(), time.perf_counter()
                light_joint_step(data, theta, metal, torch.zeros(n_l), torch.zeros(n_l, 3), data.train_idx,
                                 "principled")
                row = res.setdefault(per_pass, {"cpu": [], "wall": []})
                row["cpu"].append(time.process_time() - c0)
                row["wall"].append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(before)
        c_runner.TANGENTS_PER_PASS = kept
    n_px = data.points.shape[0]
    used = len(range(0, n_px, max(1, math.ceil(n_px / _light_step_pixels()))))  # light_joint_step's rows
    print(f"joint light step, {n_l} lights, {n_px} pixels ({used} used), {threads} thread(s), "
          f"{reps} alternated runs: ms min / median / max")
    for per_pass, row in res.items():
        cpu, wall = sorted(row["cpu"]), sorted(row["wall"])
        print(f"  passes of {per_pass:2d}: CPU {cpu[0] * 1e3:.1f} / {statistics.median(cpu) * 1e3:.1f} / "
              f"{cpu[-1] * 1e3:.1f}   wall {wall[0] * 1e3:.1f} / {statistics.median(wall) * 1e3:.1f} / "
              f"{wall[-1] * 1e3:.1f}")
    return res


def main(argv: Sequence[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log2n", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--fit", action="store_true", help="time the recovery's Jacobian instead")
    ap.add_argument("--light-step", action="store_true",
                    help="time a joint light step with the JVP kernel's passes of 8 and 12 tangents alternated")
    a = ap.parse_args(argv)
    if a.light_step:
        light_step_times(threads=a.threads, reps=max(a.reps, 9))
    elif a.fit:
        fit_jacobian_times(threads=a.threads, reps=max(a.reps, 7))
    else:
        run(a.log2n, a.threads, a.reps)


if __name__ == "__main__":
    main()
