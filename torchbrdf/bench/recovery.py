"""``python -m torchbrdf.bench.recovery``: the recovery's per-pixel normal equations, before and after fusing.

One Gauss–Newton linearisation of the fit's log residuals over every light: per pixel the
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
"""

from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace
from typing import Any

import torch

from torchbrdf.recovery.params import decode_pattern, decode_slots

__all__ = ["main", "synthetic_level", "normal_equations_before", "normal_equations_after", "DECODE_PATTERN",
           "DECODE_SLOTS"]

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


def _stats(xs: list[float]) -> str:
    return f"{min(xs):9.3g} {statistics.median(xs):9.3g} {max(xs):9.3g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.recovery",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=128, help="capture side in pixels (default 128)")
    ap.add_argument("--lights", type=int, default=17, help="lights (default 17)")
    ap.add_argument("--reps", type=int, default=5, help="alternating repetitions (default 5)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args(argv)
    if args.size < 1 or args.lights < 1 or args.reps < 1:
        ap.error("--size, --lights and --reps must be positive")
    if args.threads:
        torch.set_num_threads(args.threads)
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
