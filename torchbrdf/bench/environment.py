"""Environment lighting in the benchmark: error vs time of Monte Carlo and the split sum.

Each measurement runs on its own (see the docstrings) and is gathered by ``python -m
torchbrdf.bench`` into the "environment" sections of the report: :func:`environment` (each
proposal of :data:`torchbrdf.render.envmap.ENV_SAMPLINGS` and the split sum against the
quadrature), :func:`environment_lobes` (per lobe on a sphere under a sky with a sun),
:func:`environment_skies` (the split sum's bias on other skies) and :func:`split_sum_cost`.
The ``*_section`` functions turn their results into markdown lines.
"""

from __future__ import annotations

import functools
import importlib
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

import torchbrdf
from torchbrdf.bench.timing import format_or_dash, median_time, time_alternating

# Where progress lines go (print, or a collector).
_Log = Callable[[str], object]

#: Monte Carlo proposals measured by :func:`environment` (``sampling=`` of
#: :func:`torchbrdf.render.envmap.integrate_environment_mc`), with their labels in the report.
ENV_METHODS = (
    ("mis", "MC, MIS (BRDF + map sampling)"),
    ("brdf", "MC, BRDF sampling only"),
    ("map", "MC, map sampling only"),
    ("uniform", "MC, uniform hemisphere (no importance sampling)"),
)


def environment(points: int, log: _Log, sample_counts: Sequence[int] = (1, 4, 16, 64, 256, 1024), repeats: int = 3) -> dict | None:
    """Error vs time of MC (each proposal) at increasing sample counts and of the split sum.

    The reference is the per-texel quadrature (:func:`torchbrdf.render.envmap.integrate_environment_quadrature`,
    4×4 sub-cells per texel); its own convergence is reported as the relative L1 difference
    to 2×2 sub-cells. Times are medians of ``repeats`` calls after a warm-up; each error
    comes from one estimate at a fixed seed.

    Runs on its own (e.g. to refresh only this section of ``docs/benchmarks.md``)::

        from torchbrdf.bench import environment, report
        env = environment.environment(256, print)
        lines = environment.environment_section(env)      # the markdown of the section
        report.write_plots({"environment": env}, "docs")  # writes only bench_pareto_env.png
    """
    try:
        envmap = importlib.import_module("torchbrdf.render.envmap")
        mc = envmap.integrate_environment_mc
        quad = envmap.integrate_environment_quadrature
        split = envmap.integrate_environment_split_sum
        SplitEnv = envmap.SplitSumEnvironment
        samplings = envmap.ENV_SAMPLINGS
    except (ImportError, AttributeError) as exc:
        log(f"  environment section skipped: {exc}")
        return None
    g = torch.Generator().manual_seed(7)
    H, W = 32, 64
    yy = torch.linspace(0, 1, H)[:, None]
    xx = torch.linspace(0, 1, W)[None, :]
    sky = torch.stack([0.4 + 0.6 * (1 - yy) + 0 * xx, 0.5 + 0.5 * (1 - yy) + 0 * xx, 0.8 + 0.2 * (1 - yy) + 0 * xx])
    sun = torch.exp(-(((yy - 0.3) / 0.05) ** 2 + ((xx - 0.6) / 0.03) ** 2)) * 30.0
    radiance = (sky + sun).to(torch.float64)
    n = torch.nn.functional.normalize(torch.randn(4 * points, 3, generator=g, dtype=torch.float64) * 0.2
                                      + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(4 * points, 3, generator=g, dtype=torch.float64) * 0.5 + n, dim=-1)
    keep = ((n * v).sum(-1) > 0.1).nonzero()[:points, 0]  # viewers above the surface only
    n, v = n[keep].contiguous(), v[keep].contiguous()
    material = dict(base_color=torch.rand(points, 3, generator=g, dtype=torch.float64),
                    roughness=torch.rand(points, 1, generator=g, dtype=torch.float64) * 0.8 + 0.2,
                    metallic=torch.rand(points, 1, generator=g, dtype=torch.float64))
    try:
        t0 = time.perf_counter()
        ref = quad(torchbrdf.principled, n, v, radiance, material, subdivisions=4)
        t_ref = time.perf_counter() - t0
        coarse = quad(torchbrdf.principled, n, v, radiance, material, subdivisions=2)
        rows = []

        def err(est):  # relative L1 error of the outgoing radiance over all points and channels
            return float((est - ref).abs().sum() / ref.abs().sum())

        ref_check = err(coarse)
        configs = {(label, sampling, s): (lambda s=s, sampling=sampling: mc(
                       torchbrdf.principled, n, v, radiance, material, samples=s, seed=11, sampling=sampling))
                   for sampling, label in ENV_METHODS if sampling in samplings for s in sample_counts}
        # every configuration once per round: the comparisons between them see the same load
        times = time_alternating(configs, repeats)
        for (label, sampling, s), run in configs.items():
            t = times[(label, sampling, s)]
            rows.append(dict(method=label, sampling=sampling, samples=s, seconds=t.median, spread=t.as_dict(),
                             mean_rel_err=err(run())))
        t0 = time.perf_counter()
        env = SplitEnv(radiance)
        t_pre = time.perf_counter() - t0
        split(torchbrdf.principled, n, v, env, material)  # warm-up: builds the cached BRDF table once
        t0 = time.perf_counter()
        est = split(torchbrdf.principled, n, v, env, material)
        rows.append(dict(method="split sum", sampling=None, samples=None, seconds=time.perf_counter() - t0,
                         prefilter_seconds=t_pre, mean_rel_err=err(est)))
    except Exception as exc:  # noqa: BLE001 - keep the rest of the report if this section fails
        log(f"  environment section failed: {type(exc).__name__}: {exc}")
        return None
    for r in rows:
        log(f"  {r['method']:48s} samples={r['samples']!s:5s} {r['seconds'] * 1e3:8.1f} ms  rel L1 err {r['mean_rel_err']:.3e}")
    log(f"  reference (quadrature 4x4 per texel, {t_ref:.1f} s) vs 2x2: rel L1 {ref_check:.1e}")
    return dict(points=points, reference_seconds=t_ref, reference_check=ref_check, env_size=[H, W],
                threads=torch.get_num_threads(), repeats=repeats, rows=rows)


#: Lobes measured one by one by :func:`environment_lobes`: label -> (brdf kind, material).
ENV_LOBES: tuple[tuple[str, str, dict[str, float]], ...] = (
    ("Lambert", "lambert", {}),
    ("Burley diffuse, roughness 0", "diffuse", {"roughness": 0.0}),
    ("Burley diffuse, roughness 0.5", "diffuse", {"roughness": 0.5}),
    ("GGX, roughness 0.2", "specular", {"roughness": 0.2, "metallic": 1.0}),
    ("GGX, roughness 0.5", "specular", {"roughness": 0.5, "metallic": 1.0}),
    ("GGX, roughness 0.9", "specular", {"roughness": 0.9, "metallic": 1.0}),
)


def sky_with_sun(height: int = 64, dtype: torch.dtype = torch.float64,
                 sun_elevation: float = 35.0) -> torch.Tensor:
    """``(3, height, 2·height)`` lat-long sky: a blue gradient, a darker ground and a small sun.

    The sun is a disc of 2.5° radius at ``sun_elevation`` degrees (default 35°), 2000× the
    zenith sky (2 texels at 64 rows): at 35° it gives 60–80 % (blue–red) of the irradiance of
    an upward-facing surface.
    """
    from torchbrdf.render.sampling import latlong_directions

    d = latlong_directions(height, 2 * height, dtype=dtype)  # (H, W, 3)
    z = d[..., 2:3]
    sky = torch.where(z > 0, torch.tensor([0.35, 0.5, 0.9], dtype=dtype) * (0.6 + 0.4 * z),
                      torch.tensor([0.25, 0.2, 0.15], dtype=dtype) * (1.0 + z))
    el = math.radians(sun_elevation)
    az = 0.6
    sun = torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)], dtype=dtype)
    disc = ((d * sun).sum(-1, keepdim=True) > math.cos(math.radians(2.5))).to(dtype)
    return (sky + 2000.0 * disc * torch.tensor([1.0, 0.95, 0.85], dtype=dtype)).permute(2, 0, 1).contiguous()


def sphere_points(side: int, grazing: int,
                  dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normals and view of an orthographic sphere: ``(n, v, n_graze)``.

    ``n`` ``(P, 3)``: the pixels of a ``side × side`` image of the sphere (so means over it are
    means over the picture); ``n_graze`` ``(grazing, 3)``: extra normals with ``n·v`` uniform in
    (0, 0.1), spread around the silhouette (the band the picture holds few pixels of). The view
    ``v`` ``(3,)`` looks slightly down on the sphere, so it sees sky, sun and ground.
    """
    v = torch.nn.functional.normalize(torch.tensor([1.0, 0.0, 0.35], dtype=dtype), dim=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(up, v), dim=0)
    e2 = torch.linalg.cross(v, e1)
    c = (torch.arange(side, dtype=dtype) + 0.5) / side * 2 - 1
    a, b = torch.meshgrid(c, c, indexing="xy")
    inside = a * a + b * b < 1
    a, b = a[inside], b[inside]
    nz = torch.sqrt(1 - a * a - b * b)
    n = a[:, None] * e1 + b[:, None] * e2 + nz[:, None] * v
    k = torch.arange(grazing, dtype=dtype)
    nv = (k + 0.5) / grazing * 0.1
    phi = k * 2.399963  # golden angle: azimuths spread evenly whatever the count
    st = torch.sqrt(1 - nv * nv)
    ng = (st * torch.cos(phi))[:, None] * e1 + (st * torch.sin(phi))[:, None] * e2 + nv[:, None] * v
    return n, v, ng


def environment_lobes(log: _Log, side: int = 32, grazing: int = 128,
                      sample_counts: Sequence[int] = (64, 256, 1024, 4096),
                      ref_samples: int = 16384, height: int = 64, repeats: int = 3,
                      sun_elevation: float = 35.0) -> dict:
    """Split sum vs Monte Carlo per lobe on a sphere under :func:`sky_with_sun` (float64).

    For each lobe of :data:`ENV_LOBES` (white base colour): the reference is MIS Monte Carlo
    at ``ref_samples`` per point (another seed than the measured runs); reported are the
    relative L1 error (Σ|est − ref| / Σ ref, over the picture and the channels), the bias
    (Σ(est − ref) / Σ ref) over the picture and over the grazing band n·v < 0.1, and the
    time of one call (median of ``repeats`` after a warm-up), for the split sum and for MIS
    at each of ``sample_counts``. Runs on its own::

        from torchbrdf.bench import environment, report
        lobes = environment.environment_lobes(print)                    # sun at 35° elevation
        other = environment.environment_lobes(print, sun_elevation=15)  # the same at another sun
        report.write_plots({"environment_lobes": lobes}, "docs")  # writes only bench_pareto_env_lobes.png
    """
    from torchbrdf.brdf.lambert import lambert
    from torchbrdf.brdf.principled import PrincipledBRDF
    from torchbrdf.render.envmap import (
        SplitSumEnvironment,
        integrate_environment_mc,
        integrate_environment_split_sum,
    )

    radiance = sky_with_sun(height, sun_elevation=sun_elevation)
    n, v, ng = sphere_points(side, grazing)
    npix = n.shape[0]
    n_all = torch.cat((n, ng))
    v_all = v.expand_as(n_all).contiguous()
    t0 = time.perf_counter()
    env = SplitSumEnvironment(radiance)
    t_pre = time.perf_counter() - t0
    out: dict[str, Any] = dict(side=side, pixels=npix, grazing=grazing, env_size=[height, 2 * height],
               ref_samples=ref_samples, prefilter_seconds=t_pre, threads=torch.get_num_threads(),
               sun_elevation=sun_elevation,
               repeats=repeats, lobes=[])
    for label, kind, mat in ENV_LOBES:
        brdf = lambert if kind == "lambert" else PrincipledBRDF(lobes=(kind,))
        material = dict(base_color=1.0, **mat)

        def mc(s, seed, pts=n_all):
            return integrate_environment_mc(brdf, pts, v.expand_as(pts).contiguous(), radiance, material,
                                            samples=s, seed=seed, samples_per_pass=1024)

        t0 = time.perf_counter()
        ref = mc(ref_samples, 1234)
        t_ref = time.perf_counter() - t0

        def metrics(est):
            e, r = est[:npix], ref[:npix]
            eg, rg = est[npix:], ref[npix:]
            return dict(rel_l1=float((e - r).abs().sum() / r.sum()), bias=float((e - r).sum() / r.sum()),
                        bias_grazing=float((eg - rg).sum() / rg.sum()),
                        bias_rgb=[float(x) for x in (e - r).sum(0) / r.sum(0)])

        rows = []
        split = lambda: integrate_environment_split_sum(brdf, n_all, v_all, env, material)  # noqa: E731
        t, _ = median_time(split, repeats, 2.0)
        rows.append(dict(method="split sum", samples=None, seconds=t, **metrics(split())))
        for s in sample_counts:
            t, _ = median_time(functools.partial(mc, s, 11), repeats, 8.0)
            rows.append(dict(method="MC (MIS)", samples=s, seconds=t, **metrics(mc(s, 11))))
        for r in rows:
            log(f"  {label:32s} {r['method']:9s} {r['samples']!s:5s} {r['seconds'] * 1e3:8.1f} ms  rel L1 "
                f"{r['rel_l1']:.2e}  bias {r['bias']:+.2e}  bias n·v<0.1 {r['bias_grazing']:+.2e}")
        out["lobes"].append(dict(label=label, reference_seconds=t_ref, rows=rows))
    return out


#: Skies of :func:`environment_skies`: name -> (map height, [(elevation °, azimuth rad,
#: disc radius °, radiance over the sky)]): suns in front of and behind the viewer, two suns,
#: a sun too large for the peak budget, no sun, and broad patches too dim to be peaks.
ENV_SKIES: tuple[tuple[str, int, tuple[tuple[float, float, float, float], ...]], ...] = (
    ("sun at 60°", 64, ((60.0, 0.6, 2.5, 2000.0),)),
    ("sun behind the viewer", 64, ((20.0, 3.0, 2.5, 2000.0),)),
    ("two suns", 64, ((35.0, 0.6, 2.5, 2000.0), (50.0, 2.5, 1.5, 3000.0))),
    ("8° sun, 128 rows (> peak budget)", 128, ((30.0, 0.3, 8.0, 300.0),)),
    ("no sun", 64, ()),
    ("20° patch 5×", 64, ((40.0, 0.6, 20.0, 5.0),)),
    ("20° patch 20×", 64, ((40.0, 0.6, 20.0, 20.0),)),
    ("15° patch 20× at the horizon", 64, ((10.0, 0.0, 15.0, 20.0),)),
)


def sky_with_discs(height: int, discs: Sequence[tuple[float, float, float, float]],
                   dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(3, height, 2·height)`` sky of :func:`sky_with_sun` with other discs added.

    Each disc is ``(elevation °, azimuth rad, radius °, radiance)``, warm white.
    """
    from torchbrdf.render.sampling import latlong_directions

    d = latlong_directions(height, 2 * height, dtype=dtype)
    z = d[..., 2:3]
    out = torch.where(z > 0, torch.tensor([0.35, 0.5, 0.9], dtype=dtype) * (0.6 + 0.4 * z),
                      torch.tensor([0.25, 0.2, 0.15], dtype=dtype) * (1.0 + z))
    for el, az, radius, k in discs:
        e = math.radians(el)
        c = torch.tensor([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)],
                         dtype=dtype)
        disc = ((d * c).sum(-1, keepdim=True) > math.cos(math.radians(radius))).to(dtype)
        out = out + k * disc * torch.tensor([1.0, 0.9, 0.8], dtype=dtype)
    return out.permute(2, 0, 1).contiguous()


def environment_skies(log: _Log, side: int = 20, grazing: int = 64,
                      roughness: Sequence[float] = (0.2, 0.5, 0.9)) -> dict:
    """The split sum's GGX bias on other skies (:data:`ENV_SKIES`), with and without peaks.

    A white metal on the sphere of :func:`sphere_points` (``side``, ``grazing``), float64,
    against :func:`~torchbrdf.render.envmap.integrate_environment_quadrature` (2×2 cells per
    texel at 64 rows, 1 at 128); for each sky and roughness the bias over the picture and the
    n·v < 0.1 band and the L1 error, with the default peaks and with ``peak_directions=0``
    (the whole map prefiltered). Runs on its own::

        from torchbrdf.bench import environment as bench
        lines = bench.environment_skies_section(bench.environment_skies(print))
    """
    from torchbrdf.brdf.principled import PrincipledBRDF
    from torchbrdf.render.envmap import (
        SplitSumEnvironment,
        integrate_environment_quadrature,
        integrate_environment_split_sum,
    )

    n, v, ng = sphere_points(side, grazing)
    npix = n.shape[0]
    n_all = torch.cat((n, ng))
    v_all = v.expand_as(n_all).contiguous()
    brdf = PrincipledBRDF(lobes=("specular",))
    rows = []
    for name, height, discs in ENV_SKIES:
        radiance = sky_with_discs(height, discs)
        envs = {"peaks": SplitSumEnvironment(radiance),
                "whole map": SplitSumEnvironment(radiance, peak_directions=0)}
        used = envs["peaks"].peak_directions.shape[1]
        for r in roughness:
            material = dict(base_color=1.0, roughness=r, metallic=1.0)
            ref = integrate_environment_quadrature(brdf, n_all, v_all, radiance, material,
                                                   subdivisions=2 if height <= 64 else 1)
            row: dict[str, Any] = dict(sky=name, roughness=r, peak_directions=used)
            for key, env in envs.items():
                est = integrate_environment_split_sum(brdf, n_all, v_all, env, material)
                e, f = est[:npix], ref[:npix]
                row[key] = dict(bias=float((e - f).sum() / f.sum()),
                                bias_grazing=float((est[npix:] - ref[npix:]).sum() / ref[npix:].sum()),
                                rel_l1=float((e - f).abs().sum() / f.sum()))
            rows.append(row)
            p, w = row["peaks"], row["whole map"]
            log(f"  {name:34s} GGX {r:.1f}: peaks ({used:2d} dirs) bias {p['bias'] * 100:+6.2f} % "
                f"n·v<0.1 {p['bias_grazing'] * 100:+6.1f} % L1 {p['rel_l1'] * 100:5.2f} % | whole map bias "
                f"{w['bias'] * 100:+6.2f} % n·v<0.1 {w['bias_grazing'] * 100:+6.1f} % "
                f"L1 {w['rel_l1'] * 100:5.2f} %")
    return dict(side=side, pixels=npix, grazing=grazing, rows=rows)


def split_sum_cost(log: _Log, points: int = 262144, repeats: int = 5) -> list[dict]:
    """Time of one split-sum call (and forward+backward) with and without the map's peaks.

    ``points`` random normals and views, float32, a principled material with random base
    colour and metallic and roughness in [0.3, 1] or [0, 1] (the latter with lobes sharp
    enough for the peaks' fine cells), under :func:`sky_with_sun`; medians of ``repeats``::

        from torchbrdf.bench import environment as bench
        bench.split_sum_cost(print)
    """
    import torchbrdf
    from torchbrdf.render.envmap import SplitSumEnvironment, integrate_environment_split_sum

    g = torch.Generator().manual_seed(0)
    up = torch.tensor([0, 0, 1.0])
    n = torch.nn.functional.normalize(torch.randn(points, 3, generator=g) * 0.3 + up, dim=-1)
    v = torch.nn.functional.normalize(torch.randn(points, 3, generator=g) * 0.3 + n, dim=-1)
    radiance = sky_with_sun(64, dtype=torch.float32)
    rows = []
    for lo in (0.3, 0.0):
        mat = dict(base_color=torch.rand(points, 3, generator=g), metallic=torch.rand(points, 1, generator=g),
                   roughness=lo + (1.0 - lo) * torch.rand(points, 1, generator=g))
        for peaks in (0, 64):
            env = SplitSumEnvironment(radiance, peak_directions=peaks)

            def fwd(env=env, mat=mat):
                return integrate_environment_split_sum(torchbrdf.principled, n, v, env, mat)

            def fwd_bwd(env=env, mat=mat):
                m = {k: t.detach().requires_grad_() for k, t in mat.items()}
                integrate_environment_split_sum(torchbrdf.principled, n, v, env, m).sum().backward()

            t_f, _ = median_time(fwd, repeats, 10.0)
            t_b, _ = median_time(fwd_bwd, repeats, 10.0)
            row = dict(roughness_min=lo, peak_directions=int(env.peak_directions.shape[1]), seconds=t_f,
                       seconds_fwd_bwd=t_b)
            rows.append(row)
            log(f"  roughness {lo:.1f}-1, {row['peak_directions']:3d} peak cells: {t_f * 1e3:7.1f} ms, "
                f"forward+backward {t_b * 1e3:7.1f} ms")
    return rows


def environment_skies_section(res: dict | None) -> list:
    """Markdown table of :func:`environment_skies`."""
    if not res:
        return []
    L = [f"The split sum's GGX error on other skies (`bench.environment_skies(print)`): a white metal "
         f"on a {res['side']}×{res['side']} sphere picture ({res['pixels']} pixels) plus {res['grazing']} "
         "normals with n·v < 0.1, float64, against per-texel quadrature; with the default peaks and "
         "with the whole map prefiltered (`peak_directions=0`):", "",
         "| sky | peak directions | roughness | bias | bias, n·v < 0.1 | rel. L1 | whole map: bias | "
         "n·v < 0.1 | rel. L1 |", "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        p, w = r["peaks"], r["whole map"]
        L.append(f"| {r['sky']} | {r['peak_directions']} | {r['roughness']:.1f} | {p['bias'] * 100:+.2f} % | "
                 f"{p['bias_grazing'] * 100:+.1f} % | {p['rel_l1'] * 100:.2f} % | {w['bias'] * 100:+.2f} % | "
                 f"{w['bias_grazing'] * 100:+.1f} % | {w['rel_l1'] * 100:.2f} % |")
    return L + [""]


def environment_lobes_section(res: dict | None) -> list:
    """Markdown lines of the per-lobe split-sum section (heading included)."""
    L = ["## Environment lighting per lobe: split sum vs Monte Carlo", ""]
    if not res:
        return L + ["TODO: not measured in this run.", ""]
    h, w = res["env_size"]
    L += [f"An orthographic sphere ({res['pixels']} pixels of a {res['side']}×{res['side']} picture, "
          f"plus {res['grazing']} normals with n·v < 0.1) under a {h}×{w} sky with a sun "
          f"(`bench.sky_with_sun`: 2.5° disc at {res.get('sun_elevation', 35.0):g}° elevation, 2000× the "
          "zenith sky), white base colour, float64. "
          f"Reference: MIS Monte Carlo at {res['ref_samples']} samples per point (another seed). "
          "Error = relative L1 (Σ|est − ref| / Σ ref over the picture); bias = Σ(est − ref) / Σ ref "
          f"over the picture, and over the n·v < 0.1 band; time = median of {res['repeats']} call(s) "
          f"after a warm-up, {res['threads']} torch thread(s); the split sum's prefiltering "
          f"({res['prefilter_seconds'] * 1e3:.0f} ms, once per map) is not in its time.", "",
          "| lobe | method | samples | time (ms) | rel. L1 error | bias | bias, n·v < 0.1 |",
          "|---|---|---|---|---|---|---|"]
    for lobe in res["lobes"]:
        for r in lobe["rows"]:
            L.append(f"| {lobe['label']} | {r['method']} | {r['samples'] or '—'} | "
                     f"{r['seconds'] * 1e3:.1f} | {r['rel_l1'] * 100:.2f} % | {r['bias'] * 100:+.2f} % | "
                     f"{r['bias_grazing'] * 100:+.2f} % |")
    return L + [""]


def _env_flag(row: dict, rows: list[dict]) -> str:
    """`` ≈`` when ``row``'s time spread overlaps that of the same method at the next smaller
    sample count: the load moved more than the extra samples cost, the order is not measured."""
    if not row.get("spread"):
        return ""
    same = [r for r in rows if r["method"] == row["method"] and r.get("spread") and r["samples"] < row["samples"]]
    if not same:
        return ""
    prev = max(same, key=lambda r: r["samples"])
    a, b = row["spread"], prev["spread"]
    return " ≈" if a["min_s"] <= b["max_s"] and b["min_s"] <= a["max_s"] else ""


def environment_section(env: dict | None) -> list:
    """Markdown lines of the report's environment-lighting section (heading included)."""
    L = ["## Environment lighting: error vs time", ""]
    if not env:
        return L + ["TODO: not measured in this run (`torchbrdf.render.envmap` unavailable or failed; see the log).", ""]
    check = env.get("reference_check")
    L += [f"{env['points']} shading points, float64, a {env['env_size'][0]}×{env['env_size'][1]} sky with a sun "
          "(peak 30× the sky), principled material with random base colour, metallic and roughness 0.2–1; "
          f"reference: per-texel quadrature, 4×4 sub-cells per texel ({env['reference_seconds']:.1f} s"
          + (f"; it differs from 2×2 sub-cells by {check:.1e}, so it is converged well below the errors shown"
             if check is not None else "") + "). Error = relative L1 error of the outgoing radiance "
          "(Σ|estimate − reference| / Σ|reference|), one estimate at a fixed seed; time = median of "
          f"{env.get('repeats', 1)} call(s) after a warm-up"
          + (f", {env['threads']} torch thread(s)" if env.get("threads") else "") + ".", "",
          "| method | samples | time (ms), median (min–max) | rel. L1 error |", "|---|---|---|---|"]
    for r in env["rows"]:
        extra = f" (+ {r['prefilter_seconds'] * 1e3:.0f} ms prefiltering, once per map)" if "prefilter_seconds" in r else ""
        sp = r.get("spread")
        t = (f"{sp['median_s'] * 1e3:.1f} ({sp['min_s'] * 1e3:.1f}–{sp['max_s'] * 1e3:.1f})" if sp
             else f"{r['seconds'] * 1e3:.1f}")
        L.append(f"| {r['method']}{extra} | {r['samples'] or '—'} | {t}{_env_flag(r, env['rows'])} | "
                 f"{r['mean_rel_err']:.3e} |")
    mc = [r for r in env["rows"] if r["samples"]]
    methods = list(dict.fromkeys(r["method"] for r in mc))
    counts = sorted({r["samples"] for r in mc})
    if methods:
        err = {(r["method"], r["samples"]): r["mean_rel_err"] for r in mc}
        mis = methods[0]
        L += ["", "The same errors side by side (in brackets: the ratio to MIS at the same sample count):", "",
              "| samples | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for c in counts:
            cells = []
            for m in methods:
                e = err.get((m, c))
                base = err.get((mis, c))
                ratio = f" (×{e / base:.1f})" if e is not None and base and m != mis else ""
                cells.append(format_or_dash(e, ".2e") + ratio)
            L.append(f"| {c} | " + " | ".join(cells) + " |")
        L += ["", "Every Monte Carlo variant is unbiased (`sampling=` of `integrate_environment_mc`, "
              "`env_sampling=` of `shade`); only the variance differs. The split sum's error is a bias: "
              "it does not shrink with more work.", ""]
    return L

