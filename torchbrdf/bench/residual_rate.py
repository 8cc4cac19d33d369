"""``python -m torchbrdf.bench.residual_rate``: pixel-lights per second of the recovery's residual kernels.

At a fit's shapes (``N`` pixels gathered by a ``rows`` index, ``L`` lights, the principled
model's decoded maps, float32), alternating call by call
(:func:`torchbrdf.bench.timing.time_alternating`, this process's CPU seconds):

* ``LevelData.residual``'s work: the ``rows`` gathers, :func:`~torchbrdf.recovery.params.decode`
  and the residual (the library's route);
* its parts: the gathers alone, the decode alone;
* the residual on pre-decoded, pre-gathered inputs by the library's route (without a derivative:
  the light-loop kernel) and by the per-lane kernel (:func:`torchbrdf.kernels.ops.capture_fast`,
  the route of a differentiated call), checked bit-identical;
* the cost-only kernel (``torch.ops.torchbrdf.data_cost``) on the same inputs;
* ``LevelData.normal_equations``' work (the ``rows`` gathers, the decode's tangents
  (:func:`~torchbrdf.recovery.params.decode_directions`), the normal equations of the 7
  unknowns with the residuals, ``JᵀJ`` unpacked), and the normal equations alone on pre-decoded,
  pre-gathered inputs (``torch.ops.torchbrdf.normal_equations``), with ``JᵀJ`` unpacked;
* a joint light step's elimination (``torch.ops.torchbrdf.light_schur``: each pixel's 7
  unknowns eliminated, 4 unknowns per light) on the residuals and Jacobian columns of as many
  pixel-lights (random, float32), its ``Σ YᵀY`` products included;
* :func:`torchbrdf.shade`'s fused forward on as many pixel-lights (a ``N/128 × 128`` plane).

Prints a markdown table per ``N``: CPU milliseconds min / median / max and millions of
pixel-lights per second at the median call.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence

import torch

import torchbrdf
from torchbrdf.bench.timing import Spread, time_alternating
from torchbrdf.brdf import capture_residual
from torchbrdf.recovery.levels import log_residual
from torchbrdf.recovery.params import decode, decode_directions, decode_pattern, decode_slots

EPS = 1e-3  # the log's ε (the fit's default order of magnitude)


def _fit_case(n: int, lights: int, seed: int = 0):
    """Pixels on the z = 0 plane seen from (0, 0, 3) under a ring of lights, random unknowns and
    targets, and a ``rows`` index of ``n`` pixels (repeats allowed), float32."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.cat([torch.rand(n, 2, generator=g) * 2 - 1, torch.zeros(n, 1)], -1)
    ang = torch.arange(lights) * 2 * math.pi / lights
    lpos = torch.stack([1.5 * torch.cos(ang), 1.5 * torch.sin(ang), 2.0 + 0 * ang], -1)
    lint = torch.full((lights, 3), 4.0)
    log_all = torch.randn(n, lights, 3, generator=g) * 0.5 - 2
    rows = torch.randint(0, n, (n,), generator=g)
    theta = torch.randn(n, 7, generator=g) * 0.5
    metal = (torch.rand(n, 1, generator=g) > 0.7).float()
    return theta, metal, pts, torch.tensor([0.0, 0.0, 3.0]), lpos, lint, log_all, rows


def _shade(n: int, lights: int) -> Callable[[], object]:
    from torchbrdf.render.geometry import plane_gbuffer
    from torchbrdf.render.lights import PointLight

    g = torch.Generator().manual_seed(1)
    h = n // 128
    nm = torch.randn(1, 3, h, 128, generator=g) * 0.2
    nm[:, 2] = 1.0
    material = {"base_color": torch.rand(1, 3, h, 128, generator=g),
                "roughness": 0.2 + 0.6 * torch.rand(1, 1, h, 128, generator=g),
                "metallic": torch.rand(1, 1, h, 128, generator=g)}
    gbuf = plane_gbuffer(h, 128, normal_map=nm, material=material)
    ring = [PointLight(torch.tensor([1.5 * math.cos(2 * math.pi * i / lights),
                                     1.5 * math.sin(2 * math.pi * i / lights), 2.0]), torch.full((3,), 4.0))
            for i in range(lights)]
    return lambda: torchbrdf.shade(gbuf, ring)


def _light_schur(n: int, lights: int) -> Callable[[], object] | None:
    """A joint light step's elimination of ``n`` pixels under ``lights`` lights (offset and log
    scale per light), or None where its C kernel is not available."""
    from torchbrdf.kernels import schur_ops

    g = torch.Generator().manual_seed(2)
    m = 3 * lights
    r = torch.randn(n, m, generator=g) * 0.05
    if not schur_ops.available(r):
        return None
    cols = torch.randn(7 + 4, n, m, generator=g)
    prior = torch.zeros(n, 7, dtype=torch.float64)
    return lambda: schur_ops.light_schur(r, cols, prior, prior, 1e-3, 0.15)


def rows(n: int, lights: int, repeats: int) -> tuple[list[tuple[str, Spread]], bool]:
    """``([(call, its CPU-time spread)], whether both residual routes gave the same bits)``."""
    from torchbrdf.kernels.ops import capture_fast

    theta, metal, pts, cam, lpos, lint, log_all, idx = _fit_case(n, lights)
    p = decode(theta, metal)
    pp, lo = pts.index_select(0, idx), log_all.index_select(0, idx)
    inputs = capture_residual.residual_inputs(p["normal"], pp, cam, lpos, lint, p, lo, EPS, any_size=True)
    c, active, need_tint, frame, backend, _ = inputs

    def level_residual() -> object:
        q, lq = pts.index_select(0, idx), log_all.index_select(0, idx)
        return log_residual(decode(theta, metal), q, cam, lpos, lint, lq, EPS)

    pattern = decode_pattern(7)
    dp = decode_directions(theta, metal, decode_slots(7))[1]
    tangents = {k: dp[k] for k in pattern}

    def level_normal_equations() -> object:  # LevelData.normal_equations' work
        q, lq = pts.index_select(0, idx), log_all.index_select(0, idx)
        pd, dpd = decode_directions(theta, metal, decode_slots(7))
        return capture_residual.normal_equations(pd["normal"], q, cam, lpos, lint, pd, lq, EPS,
                                                 {k: dpd[k] for k in pattern}, pattern, 7)

    calls: dict[str, Callable[[], object]] = {
        "`LevelData.residual` (gathers, decode, residual)": level_residual,
        "gathers (`rows` of points and targets)": lambda: (pts.index_select(0, idx),
                                                           log_all.index_select(0, idx)),
        "decode": lambda: decode(theta, metal),
        "residual, library's route": lambda: capture_residual.log_residual(inputs),
        "residual, per-lane kernel": lambda: capture_fast(c, active, need_tint, frame, backend or "c"),
        "`data_cost` kernel": lambda: capture_residual.data_cost(p["normal"], pp, cam, lpos, lint, p, lo,
                                                                 EPS),
        "`LevelData.normal_equations`'s work (gathers, decode's tangents, normal equations)":
            level_normal_equations,
        "normal equations, 7 unknowns and the residuals (`capture_residual.normal_equations`)": lambda: (
            capture_residual.normal_equations(
                p["normal"], pp, cam, lpos, lint, p, lo, EPS, tangents, pattern, 7)),
        "`shade` fused forward": _shade(n, lights),
    }
    schur = _light_schur(n, lights)
    if schur is not None:
        calls["`light_schur` (4 unknowns per light)"] = schur
    with torch.no_grad():
        lane = capture_fast(c, active, need_tint, frame, backend or "c")
        same = torch.equal(capture_residual.log_residual(inputs), lane)
        t = time_alternating(calls, repeats, clock=time.process_time)
    return [(k, t[k]) for k in calls], same


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, nargs="+", default=[16384, 65536], help="N, multiples of 128")
    ap.add_argument("--lights", type=int, default=17)
    ap.add_argument("--reps", type=int, default=7, help="alternating rounds")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    a = ap.parse_args(argv)
    for flag, values in (("--pixels", a.pixels), ("--lights", [a.lights]), ("--reps", [a.reps]),
                         ("--threads", [a.threads])):
        bad = [v for v in values if v < 1 or flag == "--pixels" and v % 128]
        if bad:
            ap.error(f"{flag} must be at least 1{' and a multiple of 128' if flag == '--pixels' else ''}, "
                     f"got {bad[0]}")
    torch.set_num_threads(a.threads)
    for n in a.pixels:
        out, same = rows(n, a.lights, a.reps)
        print(f"\nN = {n} pixels, {a.lights} lights, {a.threads} thread(s); "
              f"the residual's routes bit-identical: {same}\n")
        print("| call | CPU ms min / median / max | M pixel-lights/s (median) |")
        print("|---|---|---|")
        for name, s in out:
            print(f"| {name} | {s.min * 1e3:.2f} / {s.median * 1e3:.2f} / {s.max * 1e3:.2f} | "
                  f"{n * a.lights / s.median / 1e6:.1f} |")


if __name__ == "__main__":
    main()
