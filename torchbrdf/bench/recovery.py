"""``python -m torchbrdf.bench.recovery``: the normal equations before and after fusing, and the schedules.

**Normal equations** (``--part normal-equations``). One Gauss–Newton linearisation of the fit's log residuals over every light: per pixel the
data cost, ``JᵀJ (7, 7)`` and ``Jᵀr (7,)`` w.r.t. the recovery's seven unknowns.

* ``before``: the solver's unfused path, :func:`torchbrdf.recovery.lm.gauss_newton` with
  ``fused=False`` (the fused residual and JVP operators under ``vmap`` of ``jvp`` for the
  decode, then the 7×7 products as batched matrix products);
* ``after``: the solver's path, :func:`~torchbrdf.recovery.lm.gauss_newton` (one light-loop
  kernel, :func:`torchbrdf.kernels.normal_eq_ops.normal_equations`, writes the residuals, the
  cost, ``JᵀJ`` and ``Jᵀr``; the decode's Jacobian by ``torch.func`` first).

Both run alternately on the same synthetic capture (``--size``² pixels, ``--lights`` lights,
float32 as the recovery runs), ``--reps`` times each, and the table gives pixel-lights per
second of wall time and per second of the process's CPU time (all its threads; less
sensitive to other processes' load), min / median / max over the repetitions, and the largest
difference of ``JᵀJ`` between the two, relative to its largest entry.

**Schedules** (``--part schedules``): the cost of accuracy. Each schedule a user can choose
(:data:`~torchbrdf.recovery.config.SCHEDULES`: fast / default / thorough) recovers the same
panel captures (:func:`~torchbrdf.bench.recovery_panel.render_case`, ``--schedule-size``²
pixels, every light in the fit), ``--schedule-reps`` times each, the schedules alternating;
one row per schedule and capture (:func:`schedule_table`): wall time per capture (min /
median / max), held-out mean and worst-light PSNR and the map errors
(:func:`~torchbrdf.bench.recovery_panel.score_maps`). ``--json FILE`` keeps the rows (the
figure of docs/recovery.md is drawn from them by ``docs/recovery_schedules.py``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections.abc import Mapping, Sequence
from types import SimpleNamespace
from typing import Any

import torch

from torchbrdf.recovery.params import decode_pattern, decode_slots

__all__ = ["main", "synthetic_level", "normal_equations_before", "normal_equations_after", "DECODE_PATTERN",
           "DECODE_SLOTS", "SCHEDULE_CASES", "schedule_rows", "schedule_table"]

#: The panel captures the schedules are compared on (names of
#: :func:`~torchbrdf.bench.recovery_panel.panel_cases`, report split): glazed tiles with grout
#: under the library's model, rusted metal under the other forward model; both with calibration error.
SCHEDULE_CASES = ("ceramic_tiles/2 L12 principled +cal", "rusted_metal/2 L12 exact_fresnel +cal")

#: The non-zero ``(direction, channel, slot)`` tangents of the decode's parameters along the
#: seven unknowns, and the unknowns each slot's tangent moves
#: (:func:`torchbrdf.recovery.params.decode_pattern`, :func:`~torchbrdf.recovery.params.decode_slots`).
DECODE_PATTERN = decode_pattern()
DECODE_SLOTS = decode_slots()


def synthetic_level(size: int, lights: int, seed: int = 0, dtype: torch.dtype = torch.float32
                    ) -> tuple[Any, torch.Tensor, torch.Tensor]:
    """A ``LevelData`` of a random capture (ring of lights), and a fit state ``theta (P, 7)``,
    ``metal (P, 1)`` (half the pixels metal)."""
    from torchbrdf.capture.synthetic import light_layout
    from torchbrdf.recovery.levels import LevelData

    g = torch.Generator().manual_seed(seed)
    pos, inten = light_layout(lights - 1, near_camera=True)
    cap = SimpleNamespace(images=0.05 + torch.rand(lights, 3, size, size, generator=g),
                          camera_position=torch.tensor([0.0, 0.0, 3.0]), light_positions=pos,
                          light_intensities=inten)
    cap.images, cap.camera_position = cap.images.to(dtype), cap.camera_position.to(dtype)
    cap.light_positions, cap.light_intensities = pos.to(dtype), inten.to(dtype)
    level = LevelData(cap, size, list(range(lights)), 1e-3)  # type: ignore[arg-type]
    theta = torch.randn(size * size, 7, generator=g).to(dtype)
    theta[:, 5:7] *= 0.2
    metal = (torch.rand(size * size, 1, generator=g) < 0.5).to(dtype)
    return level, theta, metal


def normal_equations_before(level: Any, theta: torch.Tensor, metal: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(cost (P,), JᵀJ (P, 7, 7), Jᵀr (P, 7))`` by the solver's unfused :func:`gauss_newton`."""
    from torchbrdf.recovery.lm import gauss_newton

    r, jtj, jtr = gauss_newton(level, theta, metal, level.train_idx, "principled", fused=False)
    return (r * r).sum(-1), jtj, jtr


def normal_equations_after(level: Any, theta: torch.Tensor, metal: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The same by the solver's fused path (:func:`gauss_newton`: one light-loop kernel, which
    writes the residuals too)."""
    from torchbrdf.recovery.lm import gauss_newton

    r, jtj, jtr = gauss_newton(level, theta, metal, level.train_idx, "principled")
    return (r * r).sum(-1), jtj, jtr


def schedule_rows(cases: Sequence[Any], schedules: Sequence[str], size: int = 64, reps: int = 1,
                  threads: int = 1) -> list[dict]:
    """Recover each of ``cases`` (:class:`~torchbrdf.bench.recovery_panel.PanelCase`) with each
    schedule in ``schedules``, ``reps`` times, the schedules alternating (odd rounds reversed).

    Each capture is rendered once at ``size``² pixels; the recovery runs on ``threads`` threads
    with every light in the fit. Returns one row per schedule and case: ``schedule``,
    ``case``, ``seconds`` (the list of wall times), ``cpu_seconds`` (the process's CPU time of
    each, all threads: less sensitive to other processes' load), and the metrics of
    :func:`~torchbrdf.bench.recovery_panel.score_maps` of the last repetition (a seeded
    recovery is deterministic).
    """
    from torchbrdf.bench.recovery_panel import case_seed, render_case, score_maps
    from torchbrdf.recovery import RecoveryConfig, recover

    rows = []
    for case in cases:
        with tempfile.TemporaryDirectory(prefix="schedules_") as tmp:
            truth, _ = render_case(case, tmp, size)
            times: dict[str, list[float]] = {s: [] for s in schedules}
            cpu: dict[str, list[float]] = {s: [] for s in schedules}
            scores: dict[str, dict] = {}
            for rep in range(reps):
                for name in (schedules if rep % 2 == 0 else schedules[::-1]):
                    cfg = RecoveryConfig(schedule=name, threads=threads, holdout=-1)
                    t0, c0 = time.perf_counter(), time.process_time()
                    maps = recover(tmp, cfg, progress=False, log=lambda m: None).maps
                    times[name].append(time.perf_counter() - t0)
                    cpu[name].append(time.process_time() - c0)
                    scores[name] = score_maps(maps, truth, case.model, seed=case_seed(case))
        rows += [{"schedule": n, "case": case.name, "seconds": times[n], "cpu_seconds": cpu[n], **scores[n]}
                 for n in schedules]
    return rows


_SCHEDULE_HEAD = ("schedule", "capture", "wall s min", "median", "max", "CPU s median", "held dB", "worst dB",
                  "base", "rough", "metal", "spec", "n°")


def schedule_table(rows: Sequence[Mapping[str, Any]], markdown: bool = False) -> str:
    """The rows of :func:`schedule_rows` as an aligned text table (or Markdown), one line each.

    Columns: schedule, capture, wall seconds per capture (min, median, max), the median CPU
    seconds (``cpu_seconds``; a dash where a row has none), held-out mean and
    worst-light PSNR (dB), base-colour / roughness / metallic / specular RMSE, mean normal
    error (degrees).
    """
    table = [list(_SCHEDULE_HEAD)]
    for r in rows:
        t = sorted(r["seconds"])
        cpu = f"{statistics.median(r['cpu_seconds']):.1f}" if r.get("cpu_seconds") else "–"
        table.append([r["schedule"], r["case"], f"{t[0]:.1f}", f"{statistics.median(t):.1f}", f"{t[-1]:.1f}", cpu,
                      f"{r['heldout_mean_db']:.2f}", f"{r['heldout_worst_db']:.2f}", f"{r['base_rmse']:.4f}",
                      f"{r['roughness_rmse']:.4f}", f"{r['metallic_rmse']:.4f}", f"{r['specular_rmse']:.4f}",
                      f"{r['normal_deg']:.2f}"])
    if markdown:
        lines = ["| " + " | ".join(table[0]) + " |", "|" + "|".join("---" for _ in table[0]) + "|"]
        return "\n".join(lines + ["| " + " | ".join(t) + " |" for t in table[1:]])
    widths = [max(len(t[i]) for t in table) for i in range(len(table[0]))]
    return "\n".join("  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(t, widths)))
                     for t in table)


def _stats(xs: list[float]) -> str:
    return f"{min(xs):9.3g} {statistics.median(xs):9.3g} {max(xs):9.3g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.recovery",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=128, help="capture side in pixels (default 128)")
    ap.add_argument("--lights", type=int, default=17, help="lights (default 17)")
    ap.add_argument("--reps", type=int, default=5, help="alternating repetitions (default 5)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--part", choices=("all", "normal-equations", "schedules"), default="all",
                    help="what to measure (default: both)")
    ap.add_argument("--schedule-size", type=int, default=64,
                    help="capture side of the schedule table, in pixels (default 64)")
    ap.add_argument("--schedule-reps", type=int, default=3,
                    help="recoveries per schedule and capture (default 3)")
    ap.add_argument("--markdown", action="store_true", help="the schedule table as Markdown")
    ap.add_argument("--json", default=None, help="write the schedule rows to this file")
    args = ap.parse_args(argv)
    if min(args.size, args.lights, args.reps, args.schedule_size, args.schedule_reps) < 1:
        ap.error("--size, --lights, --reps, --schedule-size and --schedule-reps must be positive")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.part in ("all", "normal-equations"):
        _normal_equations_table(args)
    if args.part in ("all", "schedules"):
        from torchbrdf.bench.recovery_panel import panel_cases
        from torchbrdf.recovery.config import SCHEDULES

        cases = [c for c in panel_cases("all") if c.name in SCHEDULE_CASES]
        threads = torch.get_num_threads()
        rows = schedule_rows(cases, list(SCHEDULES), args.schedule_size, args.schedule_reps, threads)
        print(f"\nschedules, {args.schedule_size}² captures, {threads} thread(s), "
              f"{args.schedule_reps} alternating recoveries each")
        print(schedule_table(rows, args.markdown))
        if args.json:
            with open(args.json, "w", encoding="utf-8") as fh:
                json.dump({"size": args.schedule_size, "threads": threads, "rows": rows}, fh, indent=1)
    return 0


def _normal_equations_table(args: argparse.Namespace) -> None:
    level, theta, metal = synthetic_level(args.size, args.lights)
    variants = {"before": normal_equations_before, "after": normal_equations_after}
    res = {k: f(level, theta, metal) for k, f in variants.items()}  # warm-up (kernel builds)
    scale = res["before"][1].abs().amax().item()
    diff = (res["before"][1] - res["after"][1]).abs().amax().item() / max(scale, 1e-30)
    work = args.size * args.size * args.lights
    rates: dict[str, list[float]] = {k: [] for k in variants}
    cpu: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(args.reps):
        for k, f in variants.items():
            t0, c0 = time.perf_counter(), time.process_time()
            f(level, theta, metal)
            rates[k].append(work / (time.perf_counter() - t0))
            cpu[k].append(work / max(time.process_time() - c0, 1e-9))
    print(f"normal equations, {args.size}² pixels × {args.lights} lights, float32, "
          f"{torch.get_num_threads()} threads, {args.reps} alternating repetitions")
    print(f"{'path':8s} {'pixel-lights/s: min':>20s} {'median':>9s} {'max':>9s}   "
          f"{'per CPU-second: min':>20s} {'median':>9s} {'max':>9s}")
    for k in variants:
        print(f"{k:8s} {'':10s} {_stats(rates[k])}   {'':10s} {_stats(cpu[k])}")
    gain = statistics.median(rates["after"]) / statistics.median(rates["before"])
    print(f"after / before (medians): {gain:.2f}×;"
          f"  max |JᵀJ difference| / max |JᵀJ|: {diff:.2e}")


if __name__ == "__main__":
    raise SystemExit(main())
