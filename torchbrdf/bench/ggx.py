"""``python -m torchbrdf.bench.ggx``: the SVBRDF-capture GGX (``svbrdf_ggx``) fused, eager and compiled.

All variants of a row alternate call by call (:func:`torchbrdf.bench.timing.time_alternating`),
timed in **CPU seconds** of this process (steadier than wall time on a shared machine) and in
wall seconds, float32:

* forward + backward of ``svbrdf_ggx`` on ``N`` lanes (every map per lane, every input needing
  a gradient): the fused kernels, the eager formula, ``torch.compile`` (inductor) of the eager
  formula, and the fused ``principled`` on the same lanes (diffuse + specular lobes) for scale;
* one ``rendering_loss(layout="svbrdf_ggx")`` step (forward + backward of the prediction) on
  ``(B, 10, S, S)`` maps, 9 configurations: the library's route (fused) against eager.

Prints markdown tables: median (min–max) milliseconds.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence

import torch

import torchbrdf
from torchbrdf import losses
from torchbrdf.bench.timing import Spread, time_alternating

__all__ = ["brdf_variants", "loss_variants", "main"]


def _ms(s: Spread) -> str:
    return f"{s.median * 1e3:.3g} ({s.min * 1e3:.3g}–{s.max * 1e3:.3g})"


def _with_fast_path(mode: bool | None, fn: Callable[[], object]) -> Callable[[], object]:
    def run() -> object:
        torchbrdf.set_fast_path(mode)
        try:
            return fn()
        finally:
            torchbrdf.set_fast_path(None)
    return run


def brdf_variants(lanes: int) -> tuple[dict[str, Callable[[], object]], float]:
    """The forward + backward variants on ``lanes`` lanes, and inductor's compile seconds."""
    g = torch.Generator().manual_seed(0)
    up = torch.tensor([0.0, 0.0, 1.5])
    l, v, n = (torch.nn.functional.normalize(torch.randn(lanes, 3, generator=g) + up, dim=-1) for _ in range(3))
    maps = {"diffuse_albedo": torch.rand(lanes, 3, generator=g), "specular_albedo": torch.rand(lanes, 3, generator=g),
            "roughness": torch.rand(lanes, 1, generator=g)}
    leaves = [t.requires_grad_() for t in (l, v, n, *maps.values())]

    def ggx(fn: Callable[..., torch.Tensor]) -> Callable[[], object]:
        def run() -> object:
            return torch.autograd.grad(fn(l, v, n, **maps).sum(), leaves)
        return run

    compiled = torch.compile(torchbrdf.svbrdf_ggx)
    t0 = time.perf_counter()
    _with_fast_path(False, ggx(compiled))()  # traced with the fast path off: the eager formula
    compile_s = time.perf_counter() - t0
    base, rough = maps["diffuse_albedo"], maps["roughness"]

    def principled() -> object:
        out = torchbrdf.principled(l, v, n, base_color=base, roughness=rough)
        return torch.autograd.grad(out.sum(), [l, v, n, base, rough])

    return {"fused": _with_fast_path(True, ggx(torchbrdf.svbrdf_ggx)),
            "eager": _with_fast_path(False, ggx(torchbrdf.svbrdf_ggx)),
            "inductor": _with_fast_path(False, ggx(compiled)),
            "fused principled": _with_fast_path(True, principled)}, compile_s


def loss_variants(batch: int, size: int) -> dict[str, Callable[[], object]]:
    """One ``rendering_loss(layout="svbrdf_ggx")`` step, the library's route and eager."""
    g = torch.Generator().manual_seed(1)
    C = sum(losses.GGX_LAYOUT.values())
    pred, target = torch.rand(batch, C, size, size, generator=g), torch.rand(batch, C, size, size, generator=g)
    configs = losses.random_configurations(batch, generator=g)

    def step() -> object:
        p = pred.clone().requires_grad_()
        return torch.autograd.grad(losses.rendering_loss(p, target, layout="svbrdf_ggx", configs=configs), p)

    return {"fused (library's route)": _with_fast_path(None, step), "eager": _with_fast_path(False, step)}


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lanes", type=int, default=65536, help="lanes of the forward + backward rows")
    ap.add_argument("--batch", type=int, default=2, help="maps per rendering_loss call")
    ap.add_argument("--size", type=int, default=128, help="rendering_loss map resolution S")
    ap.add_argument("--reps", type=int, default=9, help="alternating rounds")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    a = ap.parse_args(argv)
    for flag, value in (("--lanes", a.lanes), ("--batch", a.batch), ("--size", a.size), ("--reps", a.reps),
                        ("--threads", a.threads)):
        if value < 1:
            ap.error(f"{flag} must be at least 1, got {value}")
    torch.set_num_threads(a.threads)
    variants, compile_s = brdf_variants(a.lanes)
    tables = [(f"`svbrdf_ggx` forward + backward, {a.lanes} lanes (inductor compiled in {compile_s:.1f} s)",
               variants),
              (f"`rendering_loss(layout=\"svbrdf_ggx\")` step, {a.batch}×9×{a.size}²", loss_variants(a.batch, a.size))]
    for title, vs in tables:
        cpu = time_alternating(vs, a.reps, clock=time.process_time)
        wall = time_alternating(vs, a.reps)
        print(f"\n{title}, float32, {a.threads} thread(s), {a.reps} alternating rounds\n")
        print("| variant | CPU ms | wall ms |")
        print("|---|---|---|")
        for name in vs:
            print(f"| {name} | {_ms(cpu[name])} | {_ms(wall[name])} |")


if __name__ == "__main__":
    main()
