"""``python -m torchbrdf.bench.fast_path``: the route the library takes for a call against its alternative.

Each row times two ways of the same work, alternating call by call
(:func:`torchbrdf.bench.timing.time_alternating`) in **CPU seconds** of this process
(steadier than wall time on a shared machine), float32:

* ``rendering_loss`` forward + backward of ``(B, 9, S, S)`` maps: the target held constant (its
  rendering needs no backward) against a target that requires grad (one rendering of both
  map sets, the backward over every lane);
* a :class:`torchbrdf.data.MaterialDataset` sample (one flash light, 64² pixels: below
  :data:`~torchbrdf.brdf.principled.FAST_PATH_MIN_LANES`), fused against eager;
* one ``principled`` forward of 4096 lanes, fused against eager;
* ``shade`` forward + backward with the SVBRDF GGX under 8 point lights at ``S_s²`` pixels: the
  light-loop kernel (every light in one pass) against per-light passes of the fused BRDF (what
  a wrapper of ``svbrdf_ggx`` gets).

Prints a markdown table: median (min–max) CPU milliseconds and the ratio where the spreads
are apart.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence

import torch

import torchbrdf
from torchbrdf import data, losses
from torchbrdf.brdf import principled as P
from torchbrdf.bench.timing import Spread, ratio_text, time_alternating


def _ms(s: Spread) -> str:
    return f"{s.median * 1e3:.3g} ({s.min * 1e3:.3g}–{s.max * 1e3:.3g})"


def _eager(fn: Callable[[], object]) -> Callable[[], object]:
    def run() -> object:
        P.set_fast_path(False)
        try:
            return fn()
        finally:
            P.set_fast_path(None)
    return run


def _ggx_shading(size: int, g: torch.Generator) -> tuple[Callable[[], object], Callable[[], object]]:
    """``shade`` fwd+bwd of a ``size²`` SVBRDF GGX plane under 8 point lights: (light loop, per-light passes)."""
    from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx
    from torchbrdf.render.geometry import plane_gbuffer

    maps = {"diffuse_albedo": torch.rand(1, 3, size, size, generator=g),
            "specular_albedo": torch.rand(1, 3, size, size, generator=g),
            "roughness": torch.rand(1, 1, size, size, generator=g)}
    lights = [torchbrdf.PointLight([0.5 * i - 2.0, 0.3 * i - 1.0, 2.0], 10.0) for i in range(8)]

    def wrapped(l, v, n, x=None, y=None, **material):  # the shader cannot see what a wrapper calls
        return svbrdf_ggx(l, v, n, x, y, **material)

    def run(brdf) -> Callable[[], object]:
        def once() -> object:
            leaves = {k: t.clone().requires_grad_() for k, t in maps.items()}
            img = torchbrdf.shade(plane_gbuffer(size, size, material=leaves), lights, brdf)
            return torch.autograd.grad(img.sum(), list(leaves.values()))
        return once

    return run(svbrdf_ggx), run(wrapped)


def rows(batch: int, size: int, sample_size: int, repeats: int,
         shade_size: int = 256) -> list[tuple[str, str, Spread, str, Spread]]:
    """``(case, the library's route, its spread, the alternative, its spread)`` per measured case."""
    g = torch.Generator().manual_seed(0)
    pred, target = torch.rand(batch, 9, size, size, generator=g), torch.rand(batch, 9, size, size, generator=g)
    configs = losses.random_configurations(batch, generator=g)

    def loss(target_grad: bool) -> Callable[[], object]:
        def run() -> object:
            p, t = pred.clone().requires_grad_(), target.clone().requires_grad_(target_grad)
            return torch.autograd.grad(losses.rendering_loss(p, t, configs=configs), p)
        return run

    ds = data.MaterialDataset(length=64, size=sample_size, noise=0.0)
    ds[0]  # the material's synthesis is cached per material: time the rendering's share
    lanes = 4096
    up = torch.tensor([0.0, 0.0, 1.5])
    l, v, n = (torch.nn.functional.normalize(torch.randn(lanes, 3, generator=g) + up, dim=-1) for _ in range(3))
    base, rough = torch.rand(lanes, 3, generator=g), torch.rand(lanes, 1, generator=g)

    def brdf() -> object:
        with P.fused_at_every_size():
            return torchbrdf.principled(l, v, n, base_color=base, roughness=rough)

    loop, per_light = _ggx_shading(shade_size, g)
    out = []
    for case, after, before in (
            (f"`rendering_loss` fwd+bwd, {batch}×9×{size}²", ("target constant", loss(False)),
             ("target requires grad (one rendering of both)", loss(True))),
            (f"`MaterialDataset` sample, {sample_size}² (1 light)", ("fused", lambda: ds[1]), ("eager", _eager(lambda: ds[1]))),
            ("`principled` forward, 4096 lanes", ("fused", brdf), ("eager", _eager(brdf))),
            (f"`shade` with `svbrdf_ggx` fwd+bwd, {shade_size}², 8 point lights",
             ("light-loop kernel", loop), ("per-light passes", per_light))):
        t = time_alternating({"after": after[1], "before": before[1]}, repeats, clock=time.process_time)
        out.append((case, after[0], t["after"], before[0], t["before"]))
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=2, help="maps per rendering_loss call")
    ap.add_argument("--size", type=int, default=128, help="rendering_loss map resolution S")
    ap.add_argument("--sample-size", type=int, default=64, help="MaterialDataset sample resolution (its default)")
    ap.add_argument("--shade-size", type=int, default=256, help="the SVBRDF GGX shading's image size")
    ap.add_argument("--reps", type=int, default=11, help="alternating rounds")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    a = ap.parse_args(argv)
    for flag, value in (("--batch", a.batch), ("--size", a.size), ("--sample-size", a.sample_size),
                        ("--shade-size", a.shade_size), ("--reps", a.reps), ("--threads", a.threads)):
        if value < 1:  # (before any work, in the flag's name rather than a helper's)
            ap.error(f"{flag} must be at least 1, got {value}")
    torch.set_num_threads(a.threads)
    print("| case | library's route: CPU ms | alternative: CPU ms | speed-up |")
    print("|---|---|---|---|")
    for case, an, at, bn, bt in rows(a.batch, a.size, a.sample_size, a.reps, a.shade_size):
        print(f"| {case} | {an}: {_ms(at)} | {bn}: {_ms(bt)} | {ratio_text(bt, at)} |")


if __name__ == "__main__":
    main()
