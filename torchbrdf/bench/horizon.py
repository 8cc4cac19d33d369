"""The split sum's per-pixel error under a sky with a soft horizon and a small sun.

``python -m torchbrdf.bench.horizon [--side 32] [--samples 16384]``

A horizon is a sharp-edged feature too broad to be one of the map's peaks: reflected in a
sphere it runs across the picture, and a symmetric prefiltering kernel blurs it. The sky here
is a bright sky over a dark ground, blended linearly across ±5° of elevation, with a 2° sun
(2000× the sky) at three positions. The material is a white GGX metal (roughness 0.2, 0.5, 0.9)
on the orthographic sphere of :func:`torchbrdf.bench.environment.sphere_points`, float64. The reference
is the library's own MIS Monte Carlo (:func:`~torchbrdf.render.envmap.integrate_environment_mc`)
at ``--samples`` per point; a second reference at another seed gives its noise floor.
Reported per sky and roughness: bias Σ(est − ref) / Σ ref and per-pixel L1 Σ|est − ref| / Σ ref
over the picture.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch

from torchbrdf.bench.environment import sphere_points

#: Sun positions (elevation °, azimuth rad) of :func:`horizon_sky`'s three skies.
SUNS: tuple[tuple[float, float], ...] = ((10.0, 0.6), (35.0, 0.6), (20.0, 3.0))


def horizon_sky(height: int = 128, sun: tuple[float, float] | None = (35.0, 0.6), blend: float = 5.0,
                sun_radius: float = 2.0, sun_power: float = 2000.0,
                dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(3, height, 2·height)`` lat-long map: sky 1.0 over ground 0.1, blended over ±``blend``°.

    ``sun``: (elevation °, azimuth rad) of a disc of ``sun_radius``° at ``sun_power`` × the sky,
    or None for no sun.
    """
    from torchbrdf.render.sampling import latlong_directions

    d = latlong_directions(height, 2 * height, dtype=dtype)  # (H, W, 3)
    elevation = torch.rad2deg(torch.asin(d[..., 2:3].clamp(-1.0, 1.0)))
    t = ((elevation + blend) / (2 * blend)).clamp(0.0, 1.0)
    sky = torch.tensor([0.6, 0.75, 1.0], dtype=dtype)
    ground = torch.tensor([0.12, 0.1, 0.08], dtype=dtype)
    out = ground + t * (sky - ground)
    if sun is not None:
        e, az = math.radians(sun[0]), sun[1]
        c = torch.tensor([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)], dtype=dtype)
        disc = ((d * c).sum(-1, keepdim=True) > math.cos(math.radians(sun_radius))).to(dtype)
        out = out + sun_power * disc
    return out.permute(2, 0, 1).contiguous()


def horizon_errors(log: Callable[[str], Any] = print, side: int = 32, height: int = 128, samples: int = 16384,
                   roughness: Sequence[float] = (0.2, 0.5, 0.9)) -> list[dict]:
    """Split sum vs Monte Carlo on :func:`horizon_sky` for each of :data:`SUNS`; one row per sky and roughness."""
    from torchbrdf.brdf.principled import PrincipledBRDF
    from torchbrdf.render.envmap import SplitSumEnvironment, integrate_environment_mc, integrate_environment_split_sum

    n, v, _ = sphere_points(side, 0)
    v_all = v.expand_as(n).contiguous()
    brdf = PrincipledBRDF(lobes=("specular",))
    rows = []
    for sun in SUNS:
        radiance = horizon_sky(height, sun)
        env = SplitSumEnvironment(radiance)
        for r in roughness:
            material = dict(base_color=1.0, roughness=r, metallic=1.0)
            ref, ref2 = (integrate_environment_mc(brdf, n, v_all, radiance, material, samples=samples, seed=s,
                                                  samples_per_pass=1024) for s in (1234, 4321))
            est = integrate_environment_split_sum(brdf, n, v_all, env, material)
            row = dict(sun_elevation=sun[0], sun_azimuth=sun[1], roughness=r,
                       bias=float((est - ref).sum() / ref.sum()),
                       rel_l1=float((est - ref).abs().sum() / ref.sum()),
                       reference_l1=float((ref2 - ref).abs().sum() / ref.sum()))
            rows.append(row)
            log(f"  sun {sun[0]:4.0f}° az {sun[1]:.1f}  GGX {r:.1f}: bias {row['bias'] * 100:+6.2f} %  "
                f"L1 {row['rel_l1'] * 100:5.2f} %  (two references differ by {row['reference_l1'] * 100:.2f} %)")
    return rows


def horizon_table(rows: list[dict]) -> str:
    """Markdown table of :func:`horizon_errors`' rows."""
    lines = ["| sun elevation / azimuth | GGX roughness | bias | per-pixel L1 | MC reference noise (L1 of two seeds) |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['sun_elevation']:g}° / {r['sun_azimuth']:g} rad | {r['roughness']:g} | "
                     f"{r['bias'] * 100:+.2f} % | {r['rel_l1'] * 100:.2f} % | {r['reference_l1'] * 100:.2f} % |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: measure and print the table."""
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.horizon", description=__doc__.split("\n\n")[0])
    p.add_argument("--side", type=int, default=32, help="sphere picture side in pixels")
    p.add_argument("--height", type=int, default=128, help="environment map rows (width = 2 × rows)")
    p.add_argument("--samples", type=int, default=16384, help="Monte Carlo samples per point of the reference")
    p.add_argument("--roughness", type=float, nargs="+", default=[0.2, 0.5, 0.9], help="GGX roughness values")
    a = p.parse_args(argv)
    for name in ("side", "height", "samples"):
        if getattr(a, name) < 2:
            p.error(f"--{name} must be an integer >= 2, got {getattr(a, name)}")
    print(horizon_table(horizon_errors(print, a.side, a.height, a.samples, a.roughness)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
