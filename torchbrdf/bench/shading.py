"""Peak memory of :func:`torchbrdf.shade` forward+backward versus the number of lights.

Usage::

    python -m torchbrdf.bench.shading --size 1024 --lights 1 16
    python -m torchbrdf.bench.shading --size 1024 --lights 1 16 --mmap-threshold 65536
    python -m torchbrdf.bench.shading --size 1024 --lights 1 4 --no-recompute   # for comparison
    python -m torchbrdf.bench.shading --env-errors   # error tables of the environment strategies
    python -m torchbrdf.bench.shading --fused-compare --size 512 --lights 16   # eager vs fused vs hand loop
    python -m torchbrdf.bench.shading --size 512 --lights 1 16 --fused   # fused peak memory vs lights
    python -m torchbrdf.bench.shading --light-grad --size 256 --lights 8 --threads 1 --rounds 5

Each configuration runs in a fresh subprocess so peak resident memory (``VmHWM`` from
``/proc/self/status``, Linux) belongs to that configuration alone. The scene is the flat
``[-1, 1]²`` sample (every pixel shaded) with a normal map, principled material maps for
``base_color``, ``roughness`` and ``metallic`` that require grad, and ``N`` point lights whose
intensities require grad; the loss is the image sum. Reported per configuration: resident
memory before shading, peak during forward+backward, their difference and wall time.
``--no-recompute`` disables the per-light checkpointing to show what it saves.

``--fused-compare`` times, in one process and interleaved round by round, forward+backward
(w.r.t. the material maps and the normal map; lights without grad) of today's eager shader
(``set_fast_path(False)``: one checkpointed pass per light), the fused shader
(``set_fast_path(True)``: all lights in one kernel pass) and a hand-written per-light torch
loop (Lambert + GGX), and prints pixel-lights/s with the load average. ``--fused`` makes the
memory children use the fused path (light intensities then do not require grad); without it they
take one checkpointed pass per light (:func:`per_light_passes`).

``--light-grad`` times forward+backward w.r.t. the lights (half point lights: position and
intensity; half directional: direction and irradiance) and the camera, the material fixed
(light calibration): the fused shader against one checkpointed pass per light (with the
principled kernels, and fully eager), alternating, CPU time and wall time (min / median / max).

``--env-errors`` prints the error of both environment strategies against brute-force
quadrature on a small sphere (float64), the numbers quoted in ``docs/shading.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence


def _status_mib(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"{field} not found in /proc/self/status")


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


@contextlib.contextmanager
def per_light_passes(on: bool = True) -> Iterator[None]:
    """While ``on``: ``shade`` takes one checkpointed pass per light even where its fused light
    loop applies (each pass still calls the principled kernels): the route being compared."""
    from torchbrdf.render import prepare

    rule = prepare.fused_lights_wanted
    if on:
        prepare.fused_lights_wanted = lambda *a, **k: False
    try:
        yield
    finally:
        prepare.fused_lights_wanted = rule


def _child(
    size: int, lights: int, threads: int, recompute: bool, brdf_name: str, fused: bool = False
) -> dict:
    import torch

    import torchbrdf
    from torchbrdf.render import passes, shading
    from torchbrdf.render.geometry import plane_gbuffer
    from torchbrdf.render.lights import PointLight

    torch.set_num_threads(threads)
    torchbrdf.set_fast_path(True if fused else None)
    if not recompute:
        passes.checkpointed_pass = lambda elements, fn, *a, **k: fn(*a, **k)
    brdf: Callable[..., torch.Tensor] | None = None  # None: shade's default (principled)
    if brdf_name == "lambert":
        from torchbrdf.brdf.lambert import lambert as brdf
    g = torch.Generator().manual_seed(0)
    nm = torch.randn(1, 3, size, size, generator=g) * 0.2
    nm[:, 2] = 1.0
    material = {
        "base_color": torch.rand(1, 3, size, size, generator=g).requires_grad_(),
        "roughness": (0.2 + 0.6 * torch.rand(1, 1, size, size, generator=g)).requires_grad_(),
        "metallic": torch.rand(1, 1, size, size, generator=g).requires_grad_(),
    }
    gbuf = plane_gbuffer(size, size, normal_map=nm, material=material)
    intensities = []
    light_list = []
    for i in range(lights):
        a = 2.0 * math.pi * i / max(lights, 1)
        inten = torch.full((3,), 4.0).requires_grad_(not fused)
        intensities.append(inten)
        light_list.append(PointLight(torch.tensor([1.5 * math.cos(a), 1.5 * math.sin(a), 2.0]), inten))
    # Warm up on a tiny scene first: the first checkpointed call imports torch._dynamo, whose
    # tens of MiB must not be charged to the measurement.
    warm = plane_gbuffer(8, 8, material={"base_color": torch.rand(1, 3, 8, 8).requires_grad_()})
    shading.shade(warm, [PointLight([0.0, 0.0, 2.0], 1.0)], brdf).sum().backward()
    before = _status_mib("VmRSS")
    reset = _reset_peak()
    t0 = time.perf_counter()
    with per_light_passes(not fused):
        img = shading.shade(gbuf, light_list, brdf)
    img.sum().backward()
    seconds = time.perf_counter() - t0
    peak = _status_mib("VmHWM")
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in material.values())
    return {
        "size": size,
        "lights": lights,
        "fused": fused,
        "brdf": brdf_name,
        "recompute": recompute,
        "threads": threads,
        "rss_before_mib": round(before, 1),
        "peak_mib": round(peak, 1),
        "peak_minus_before_mib": round(peak - before, 1),
        "peak_reset": reset,
        "malloc_mmap_threshold": os.environ.get("MALLOC_MMAP_THRESHOLD_"),
        "seconds": round(seconds, 2),
    }


def _hand_loop(pos, normal, cam, base, rough, metal, lights):
    """A hand-written per-light torch loop, Lambert + GGX (Smith-Schlick G, Schlick F), on
    ``(B, C, H, W)`` maps: the baseline a user would write without the library."""
    import torch

    def unit(a):
        return a * torch.rsqrt((a * a).sum(1, keepdim=True).clamp_min(1e-12))

    n = unit(normal)
    v = unit(cam.reshape(1, 3, 1, 1) - pos)
    nv = (n * v).sum(1, keepdim=True).clamp_min(1e-7)
    a = rough * rough
    a2 = a * a
    k = a * 0.5
    f0 = 0.04 * (1 - metal) + base * metal
    diffuse = base * (1 - metal) / math.pi
    out = 0.0
    for q, inten in lights:
        d = q.reshape(1, 3, 1, 1) - pos
        dist2 = (d * d).sum(1, keepdim=True).clamp_min(1e-12)
        l = d * torch.rsqrt(dist2)
        h = unit(l + v)
        nl = (n * l).sum(1, keepdim=True).clamp_min(0.0)
        nh = (n * h).sum(1, keepdim=True).clamp_min(0.0)
        lh = (l * h).sum(1, keepdim=True).clamp(0.0, 1.0)
        dd = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
        g = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
        f = f0 + (1 - f0) * (1 - lh) ** 5
        spec = dd * g * f / (4 * nl * nv + 1e-7)
        out = out + (diffuse + spec) * inten.reshape(1, 3, 1, 1) * (nl / dist2)
    return out


def fused_compare(size: int, lights: int, threads: int, rounds: int, eager: bool = True) -> str:
    """Forward+backward time of eager shade, fused shade and a hand loop, interleaved."""
    import statistics

    import torch

    import torchbrdf
    from torchbrdf.render.gbuffer import GBuffer
    from torchbrdf.render.geometry import plane_gbuffer
    from torchbrdf.render.lights import PointLight

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    nm = torch.randn(1, 3, size, size, generator=g) * 0.2
    nm[:, 2] = 1.0
    nm.requires_grad_()
    material = {
        "base_color": torch.rand(1, 3, size, size, generator=g).requires_grad_(),
        "roughness": (0.2 + 0.6 * torch.rand(1, 1, size, size, generator=g)).requires_grad_(),
        "metallic": torch.rand(1, 1, size, size, generator=g).requires_grad_(),
    }
    plane = plane_gbuffer(size, size)
    gbuf = GBuffer(plane.position, nm, plane.camera_position, material)
    qs = [
        torch.tensor(
            [1.5 * math.cos(2 * math.pi * i / lights), 1.5 * math.sin(2 * math.pi * i / lights), 2.0]
        )
        for i in range(lights)
    ]
    light_list = [PointLight(q, torch.full((3,), 4.0)) for q in qs]
    leaves = [nm, *material.values()]

    def run_shade(fast):
        def f():
            torchbrdf.set_fast_path(fast)
            img = torchbrdf.shade(gbuf, light_list)
            return torch.autograd.grad(img.sum(), leaves)

        return f

    def run_hand():
        img = _hand_loop(
            plane.position,
            nm,
            plane.camera_position,
            material["base_color"],
            material["roughness"],
            material["metallic"],
            [(q, torch.full((3,), 4.0)) for q in qs],
        )
        return torch.autograd.grad(img.sum(), leaves)

    methods = {"fused shade": run_shade(True), "hand loop (Lambert+GGX)": run_hand}
    if eager:
        methods["eager shade (today)"] = run_shade(False)
    run_shade(True)()  # warm-up: builds (or loads) the kernels
    times: dict[str, list[float]] = {k: [] for k in methods}
    loads = [os.getloadavg()[0]]
    for _ in range(rounds):
        for name, fn in methods.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
        loads.append(os.getloadavg()[0])
    torchbrdf.set_fast_path(None)
    work = size * size * lights
    lines = [
        f"{size}x{size}, {lights} point lights, float32, forward+backward w.r.t. maps and normals, "
        f"{threads} threads, {rounds} interleaved rounds; load average (1 min) during: "
        f"{min(loads):.1f}-{max(loads):.1f} on {os.cpu_count()} CPUs",
        "",
        "| method | median s | min s | pixel-lights/s (median) | fused speed-up (median) |",
        "|---|---|---|---|---|",
    ]
    fused_med = statistics.median(times["fused shade"])
    for name, ts in times.items():
        med = statistics.median(ts)
        lines.append(f"| {name} | {med:.3f} | {min(ts):.3f} | {work / med:.3g} | {med / fused_med:.1f}x |")
    return "\n".join(lines)


def light_grad_compare(size: int, lights: int, threads: int, rounds: int) -> str:
    """Forward+backward w.r.t. lights and camera: fused vs eager shade, alternating."""
    import statistics

    import torch

    import torchbrdf
    from torchbrdf.render.gbuffer import GBuffer
    from torchbrdf.render.geometry import plane_gbuffer
    from torchbrdf.render.lights import DirectionalLight, PointLight

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    nm = torch.randn(1, 3, size, size, generator=g) * 0.2
    nm[:, 2] = 1.0
    material = {
        "base_color": torch.rand(1, 3, size, size, generator=g),
        "roughness": 0.2 + 0.6 * torch.rand(1, 1, size, size, generator=g),
        "metallic": torch.rand(1, 1, size, size, generator=g),
    }
    plane = plane_gbuffer(size, size)
    cam = plane.camera_position.clone().requires_grad_()
    gbuf = GBuffer(plane.position, nm, cam, material)
    n_point = (lights + 1) // 2
    light_list: list = []
    for i in range(lights):
        a = 2 * math.pi * i / lights
        if i < n_point:
            q = torch.tensor([1.5 * math.cos(a), 1.5 * math.sin(a), 2.0])
            light_list.append(PointLight(q.requires_grad_(), torch.full((3,), 4.0).requires_grad_()))
        else:
            d = torch.tensor([0.5 * math.cos(a), 0.5 * math.sin(a), 1.0])
            light_list.append(DirectionalLight(d.requires_grad_(), torch.full((3,), 1.0).requires_grad_()))
    leaves = [cam] + [t for light in light_list for t in light._light_tensors()]

    def run(mode):
        # "passes": the route light gradients took before the light loop differentiated the
        # uniforms: one checkpointed pass per light, each calling the fused principled kernels
        torchbrdf.set_fast_path(mode != "eager")
        with per_light_passes(mode == "passes"):
            img = torchbrdf.shade(gbuf, light_list)
        return torch.autograd.grad(img.sum(), leaves)

    methods = {"fused shade": "fused", "per-light passes, principled kernels": "passes",
               "eager shade (set_fast_path(False))": "eager"}
    for mode in methods.values():  # warm-up: kernels built or loaded, first-call costs paid
        run(mode)
    cpu: dict[str, list[float]] = {k: [] for k in methods}
    wall: dict[str, list[float]] = {k: [] for k in methods}
    loads = [os.getloadavg()[0]]
    for _ in range(rounds):
        for name, mode in methods.items():
            c0, t0 = time.process_time(), time.perf_counter()
            run(mode)
            cpu[name].append(time.process_time() - c0)
            wall[name].append(time.perf_counter() - t0)
        loads.append(os.getloadavg()[0])
    torchbrdf.set_fast_path(None)

    def mmm(ts):
        return f"{min(ts):.3f} / {statistics.median(ts):.3f} / {max(ts):.3f}"

    lines = [
        f"{size}x{size}, {n_point} point + {lights - n_point} directional lights, float32, forward+backward "
        f"w.r.t. the lights and the camera, {threads} thread(s), {rounds} alternating rounds; load average "
        f"(1 min) during: {min(loads):.1f}-{max(loads):.1f} on {os.cpu_count()} CPUs",
        "",
        "| method | CPU s (min / median / max) | wall s (min / median / max) | fused speed-up (median CPU) |",
        "|---|---|---|---|",
    ]
    fused_med = statistics.median(cpu["fused shade"])
    for name in methods:
        lines.append(f"| {name} | {mmm(cpu[name])} | {mmm(wall[name])} | "
                     f"{statistics.median(cpu[name]) / fused_med:.1f}x |")
    return "\n".join(lines)


def env_errors() -> str:
    """Markdown tables: Monte Carlo and split-sum error against quadrature on a sphere."""
    import torch

    from torchbrdf._math import safe_normalize
    from torchbrdf.brdf.principled import principled
    from torchbrdf.render.envmap import (
        SplitSumEnvironment,
        integrate_environment_mc,
        integrate_environment_quadrature,
        integrate_environment_split_sum,
    )
    from torchbrdf.render.geometry import sphere_gbuffer
    from torchbrdf.render.sampling import latlong_directions

    d64 = torch.float64
    gen = torch.Generator().manual_seed(0)
    gb = sphere_gbuffer(9, 9, dtype=d64)
    assert gb.mask is not None  # sphere_gbuffer always sets one
    m = gb.mask[0, 0]
    n = gb.normal[0].permute(1, 2, 0)[m]
    v = safe_normalize(gb.camera_position - gb.position[0].permute(1, 2, 0)[m])
    k = len(n)
    glossy = {
        "base_color": 0.1 + 0.8 * torch.rand(k, 3, generator=gen, dtype=d64),
        "roughness": 0.35 + 0.45 * torch.rand(k, 1, generator=gen, dtype=d64),
        "metallic": torch.rand(k, 1, generator=gen, dtype=d64),
        "clearcoat": 0.5,
        "clearcoat_gloss": 0.4,
    }
    noisy = torch.rand(3, 8, 16, generator=torch.Generator().manual_seed(1), dtype=d64) ** 2 * 2.0
    dirs = latlong_directions(16, 32, dtype=d64)
    smooth = (
        (1.0 + 0.6 * dirs[..., 2:3] + 0.3 * dirs[..., 0:1]).expand(16, 32, 3).permute(2, 0, 1).contiguous()
    )
    maps = {"noisy 8x16": noisy, "smooth 16x32": smooth}

    def rel_rms(a, b):
        return float((a - b).norm() / b.norm())

    lines = [
        f"Monte Carlo, principled glossy material (roughness 0.35-0.8, clearcoat), {k} sphere pixels;",
        "relative RMS error against quadrature, mean of 4 seeds:",
        "",
        "| map | 16 spp | 64 spp | 256 spp | 1024 spp |",
        "|---|---|---|---|---|",
    ]
    for name, env in maps.items():
        ref = integrate_environment_quadrature(principled, n, v, env, glossy, subdivisions=6)
        row = []
        for spp in (16, 64, 256, 1024):
            errs = [
                rel_rms(integrate_environment_mc(principled, n, v, env, glossy, samples=spp, seed=s), ref)
                for s in range(4)
            ]
            row.append(f"{100 * sum(errs) / 4:.1f} %")
        lines.append(f"| {name} | " + " | ".join(row) + " |")
    lines += [
        "",
        "Split sum, metal (base colour 1), per-pixel relative error against quadrature, median / max:",
        "",
        "| map | roughness 0.3 | 0.5 | 0.7 | 0.9 | glossy material above |",
        "|---|---|---|---|---|---|",
    ]
    for name, env in maps.items():
        prepared = SplitSumEnvironment(env)
        row = []
        for mat in [{"base_color": 1.0, "metallic": 1.0, "roughness": r} for r in (0.3, 0.5, 0.7, 0.9)] + [
            glossy
        ]:
            ref = integrate_environment_quadrature(principled, n, v, env, mat, subdivisions=6)
            rel = ((integrate_environment_split_sum(principled, n, v, prepared, mat) - ref) / ref).abs()
            row.append(f"{100 * float(rel.median()):.1f} / {100 * float(rel.max()):.0f} %")
        lines.append(f"| {name} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024, help="image is size x size")
    ap.add_argument("--lights", type=int, nargs="+", default=[1, 16], help="light counts to measure")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--brdf", choices=("principled", "lambert"), default="principled")
    ap.add_argument(
        "--no-recompute", action="store_true", help="disable per-light checkpointing (comparison)"
    )
    ap.add_argument(
        "--mmap-threshold",
        type=int,
        default=None,
        metavar="BYTES",
        help="set MALLOC_MMAP_THRESHOLD_ in the children (glibc: return freed large blocks to the OS, "
        "so RSS reflects live tensors instead of heap fragmentation)",
    )
    ap.add_argument(
        "--env-errors", action="store_true", help="print the environment strategies' error tables"
    )
    ap.add_argument(
        "--fused-compare",
        action="store_true",
        help="time eager shade, fused shade and a hand-written loop (first --lights count)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of --fused-compare")
    ap.add_argument("--no-eager", action="store_true", help="--fused-compare without the (slow) eager shader")
    ap.add_argument(
        "--light-grad", action="store_true",
        help="time forward+backward w.r.t. lights and camera, fused vs eager (first --lights count)",
    )
    ap.add_argument(
        "--fused", action="store_true", help="memory children use the fused path (lights without grad)"
    )
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.env_errors:
        print(env_errors())
        return 0
    if args.light_grad:
        print(light_grad_compare(args.size, args.lights[-1], args.threads, args.rounds))
        return 0
    if args.fused_compare:
        print(fused_compare(args.size, args.lights[-1], args.threads, args.rounds, not args.no_eager))
        return 0
    if args.child is not None:
        print(
            json.dumps(
                _child(args.size, args.child, args.threads, not args.no_recompute, args.brdf, args.fused)
            )
        )
        return 0
    rows = []
    for n in args.lights:
        cmd = [
            sys.executable,
            "-m",
            "torchbrdf.bench.shading",
            "--size",
            str(args.size),
            "--threads",
            str(args.threads),
            "--brdf",
            args.brdf,
            "--child",
            str(n),
        ]
        if args.no_recompute:
            cmd.append("--no-recompute")
        if args.fused:
            cmd.append("--fused")
        env = dict(os.environ)
        if args.mmap_threshold is not None:
            env["MALLOC_MMAP_THRESHOLD_"] = str(args.mmap_threshold)
        res = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if res.returncode != 0:
            sys.stderr.write(res.stderr)
            return res.returncode
        row = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(json.dumps(row), flush=True)
    if len(rows) > 1:
        base = rows[0]["peak_minus_before_mib"]
        for r in rows[1:]:
            print(
                f"{r['lights']} lights / {rows[0]['lights']} light(s): peak increase ratio "
                f"{r['peak_minus_before_mib'] / base:.2f}, "
                f"absolute peak ratio {r['peak_mib'] / rows[0]['peak_mib']:.2f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
