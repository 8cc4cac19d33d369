"""Peak memory of :func:`torchbrdf.shade` forward+backward versus the number of lights.

Usage::

    python -m torchbrdf.bench_shading --size 1024 --lights 1 16
    python -m torchbrdf.bench_shading --size 1024 --lights 1 16 --mmap-threshold 65536
    python -m torchbrdf.bench_shading --size 1024 --lights 1 4 --no-recompute   # for comparison

Each configuration runs in a fresh subprocess so peak resident memory (``VmHWM`` from
``/proc/self/status``, Linux) belongs to that configuration alone. The scene is the flat
``[-1, 1]²`` sample (every pixel shaded) with a normal map, principled material maps for
``base_color``, ``roughness`` and ``metallic`` that require grad, and ``N`` point lights whose
intensities require grad; the loss is the image sum. Reported per configuration: resident
memory before shading, peak during forward+backward, their difference and wall time.
``--no-recompute`` disables the per-light checkpointing to show what it saves.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time


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


def _child(size: int, lights: int, threads: int, recompute: bool, brdf_name: str) -> dict:
    import torch

    from . import shading
    from .geometry import plane_gbuffer
    from .lights import PointLight

    torch.set_num_threads(threads)
    if not recompute:
        shading._pass = lambda elements, fn, *a, **k: fn(*a, **k)
    brdf = None
    if brdf_name == "lambert":
        from .lambert import lambert as brdf
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
        inten = torch.full((3,), 4.0).requires_grad_()
        intensities.append(inten)
        light_list.append(PointLight(torch.tensor([1.5 * math.cos(a), 1.5 * math.sin(a), 2.0]), inten))
    # Warm up on a tiny scene first: the first checkpointed call imports torch._dynamo, whose
    # tens of MiB must not be charged to the measurement.
    warm = plane_gbuffer(8, 8, material={"base_color": torch.rand(1, 3, 8, 8).requires_grad_()})
    shading.shade(warm, [PointLight([0.0, 0.0, 2.0], 1.0)], brdf).sum().backward()
    before = _status_mib("VmRSS")
    reset = _reset_peak()
    t0 = time.perf_counter()
    img = shading.shade(gbuf, light_list, brdf)
    img.sum().backward()
    seconds = time.perf_counter() - t0
    peak = _status_mib("VmHWM")
    assert all(torch.isfinite(t.grad).all() for t in material.values())
    return {
        "size": size,
        "lights": lights,
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


def main(argv=None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024, help="image is size x size")
    ap.add_argument("--lights", type=int, nargs="+", default=[1, 16], help="light counts to measure")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--brdf", choices=("principled", "lambert"), default="principled")
    ap.add_argument("--no-recompute", action="store_true", help="disable per-light checkpointing (comparison)")
    ap.add_argument("--mmap-threshold", type=int, default=None, metavar="BYTES",
                    help="set MALLOC_MMAP_THRESHOLD_ in the children (glibc: return freed large blocks to the OS, "
                    "so RSS reflects live tensors instead of heap fragmentation)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(_child(args.size, args.child, args.threads, not args.no_recompute, args.brdf)))
        return 0
    rows = []
    for n in args.lights:
        cmd = [sys.executable, "-m", "torchbrdf.bench_shading", "--size", str(args.size), "--threads", str(args.threads),
               "--brdf", args.brdf, "--child", str(n)]
        if args.no_recompute:
            cmd.append("--no-recompute")
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
            print(f"{r['lights']} lights / {rows[0]['lights']} light(s): peak increase ratio "
                  f"{r['peak_minus_before_mib'] / base:.2f}, absolute peak ratio {r['peak_mib'] / rows[0]['peak_mib']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
