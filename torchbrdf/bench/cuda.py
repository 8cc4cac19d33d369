"""``python -m torchbrdf.bench --device cuda``: the GPU paths of ``principled`` and ``shade``, side by side.

One run, same GPU and inputs (float32, all eleven parameters and l, v, n, x, y per lane):

* :func:`torchbrdf.principled` forward and forward+backward throughput (evaluations/s, median
  of repeats after a warm-up, ``torch.cuda.synchronize`` around each call) and peak GPU memory
  of one forward+backward (``torch.cuda.max_memory_allocated``, total and above the inputs) at
  N = 2^20 … 2^24 for

  - ``triton``: the generated Triton kernels (``set_backend("triton")``),
  - ``eager``: the eager reference path on CUDA (ATen kernels),
  - ``compile``: ``torch.compile`` (inductor) of the eager formula,
  - ``mitsuba``: Mitsuba 3's ``principled`` BSDF in ``cuda_ad_rgb`` when Mitsuba is installed;

* :func:`torchbrdf.shade` at 1024² pixels with 16 lights (8 point, 8 directional), per-pixel
  material maps requiring grad, forward and forward+backward time and peak memory, with the
  ``triton`` and ``eager`` backends.

Without a CUDA device it prints one line and exits 0. The measurement code takes a ``device``
argument, so its CPU side runs in the tests (``run(device="cpu", ...)``). Out-of-memory
configurations are reported as such, not skipped silently.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import torch
from torch import Tensor

import torchbrdf

PATHS = ("triton", "eager", "compile", "mitsuba")
SIZES = tuple(1 << s for s in range(20, 25))  # N = 2^20 ... 2^24
NO_CUDA = ("torchbrdf.bench --device cuda: no CUDA device here (torch.cuda.is_available() is False); "
           "nothing measured.")


# ---------------------------------------------------------------------------------------------
# Device helpers (no-ops on CPU so the logic is testable without a GPU)
# ---------------------------------------------------------------------------------------------

def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)


def _allocated(device: torch.device):
    return torch.cuda.memory_allocated(device) if device.type == "cuda" else None


def _peak(device: torch.device):
    return torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None


def _time_and_peak(fwd: Callable[[], Any], fwd_bwd: Callable[[], Any], device: torch.device, repeats: int,
                   before_peak: Callable[[], Any] | None = None) -> dict[str, Any]:
    """Median times of ``fwd`` and ``fwd_bwd`` and the peak memory of one more ``fwd_bwd``.

    Returns ``fwd_s``, ``fwdbwd_s``, ``peak_bytes`` and ``peak_above_inputs_bytes`` (the peak
    above what was allocated before that run; None where the device reports no memory).
    """
    out: dict[str, Any] = {"fwd_s": _median_time(fwd, device, repeats),
                           "fwdbwd_s": _median_time(fwd_bwd, device, repeats)}
    if before_peak is not None:
        before_peak()
    base = _allocated(device)
    _reset_peak(device)
    fwd_bwd()
    _sync(device)
    peak = _peak(device)
    out["peak_bytes"] = peak
    out["peak_above_inputs_bytes"] = None if peak is None else peak - base
    return out


def _median_time(fn, device: torch.device, repeats: int) -> float:
    fn()  # warm-up: kernel compile/load, caching allocator
    _sync(device)
    ts = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


class _Backend:
    """Context manager: ``principled`` with one backend, fused at every batch size."""

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        from torchbrdf.kernels import backend

        self.old = (backend.explicit_backend(), torchbrdf.fast_path_enabled())
        torchbrdf.set_backend(self.name)
        torchbrdf.set_fast_path(None if self.name == "eager" else True)

    def __exit__(self, *exc):
        torchbrdf.set_backend(self.old[0])
        torchbrdf.set_fast_path(self.old[1])


# ---------------------------------------------------------------------------------------------
# principled
# ---------------------------------------------------------------------------------------------

def _inputs(N: int, device: torch.device, requires_grad: bool) -> dict:
    from torchbrdf.bench.brdf import make_inputs

    x = {k: t.to(device) for k, t in make_inputs(N, torch.float32, seed=11).items()}
    if requires_grad:
        for t in x.values():
            t.requires_grad_()
    return x


def _principled_fns(path: str, x: dict, xg: dict):
    """``(fwd, fwdbwd)`` callables of one path, or ``None`` when it is not available."""
    if path in ("triton", "eager"):
        def fwd():
            with _Backend(path), torch.no_grad():
                torchbrdf.principled(**x)

        def fb():
            for t in xg.values():
                t.grad = None
            with _Backend(path):
                torchbrdf.principled(**xg).sum().backward()
        return fwd, fb
    if path == "compile":
        from torchbrdf.brdf import principled as _P

        cf = torch.compile(lambda **kw: _P.principled_eager(dict(kw), torchbrdf.LOBES), dynamic=False)

        def fwd():
            with torch.no_grad():
                cf(**x)

        def fb():
            for t in xg.values():
                t.grad = None
            cf(**xg).sum().backward()
        return fwd, fb
    if path == "mitsuba":
        from torchbrdf.bench import mitsuba

        if mitsuba.mitsuba_available("cuda_ad_rgb") is None:
            return None
        s = mitsuba.mitsuba_setup({k: t.detach().cpu().numpy() for k, t in x.items()}, variant="cuda_ad_rgb")
        return mitsuba.mitsuba_fwd(s, world=True), mitsuba.mitsuba_fwdbwd(s, world=True)
    raise ValueError(f"path: expected one of {PATHS}, got {path!r}")


def principled_rows(sizes: Iterable[int], paths: Sequence[str], device: torch.device, repeats: int,
                    log: Callable[[str], object]) -> list:
    """One row per (path, N): rates, times, peak memory (bytes; None off CUDA) or an error."""
    rows = []
    for N in sizes:
        try:
            x = _inputs(N, device, False)
            xg = {k: t.clone().requires_grad_() for k, t in x.items()}
        except torch.cuda.OutOfMemoryError:
            rows += [dict(path=p, N=N, error="out of memory (inputs)") for p in paths]
            log(f"  N=2^{int(math.log2(N))}: the inputs do not fit")
            continue
        for path in paths:
            row: dict[str, Any] = dict(path=path, N=N)  # a JSON row: numbers, strings, None
            fns = None
            try:
                fns = _principled_fns(path, x, xg)
                if fns is None:
                    log(f"  {path:8s} N=2^{int(math.log2(N))}: not available")
                    continue
                fwd, fb = fns

                def clear_grads(g: dict[str, Tensor] = xg) -> None:  # the peak run starts without grads
                    for t in g.values():
                        t.grad = None

                row.update(_time_and_peak(fwd, fb, device, repeats, before_peak=clear_grads))
                row["fwd_rate"], row["fwdbwd_rate"] = N / row["fwd_s"], N / row["fwdbwd_s"]
                log(f"  {path:8s} N=2^{int(math.log2(N)):<2d} fwd {row['fwd_rate']:10.3e}/s  "
                    f"fwd+bwd {row['fwdbwd_rate']:10.3e}/s  peak {_mib(row['peak_bytes'])}")
            except torch.cuda.OutOfMemoryError:
                row["error"] = "out of memory"
                log(f"  {path:8s} N=2^{int(math.log2(N))}: out of memory")
            except Exception as e:  # noqa: BLE001 - report and go on with the other paths
                row["error"] = f"{type(e).__name__}: {e}"[:300]
                log(f"  {path:8s} N=2^{int(math.log2(N))}: failed ({row['error']})")
            finally:
                fns = None
                for t in xg.values():
                    t.grad = None
                if device.type == "cuda":
                    torch.cuda.empty_cache()
            rows.append(row)
        del x, xg  # free the inputs before the next size
    return rows


# ---------------------------------------------------------------------------------------------
# shade
# ---------------------------------------------------------------------------------------------

def shade_rows(size: int, lights: int, backends: Iterable[str], device: torch.device, repeats: int,
               log: Callable[[str], object]) -> list:
    """``shade`` at ``size``² with ``lights`` lights (half point, half directional)."""
    from torchbrdf.render.geometry import plane_gbuffer
    from torchbrdf.render.lights import DirectionalLight, Light, PointLight

    g = torch.Generator().manual_seed(0)
    nm = torch.randn(1, 3, size, size, generator=g) * 0.2
    nm[:, 2] = 1.0
    maps = {"base_color": torch.rand(1, 3, size, size, generator=g),
            "roughness": 0.2 + 0.6 * torch.rand(1, 1, size, size, generator=g),
            "metallic": torch.rand(1, 1, size, size, generator=g),
            "clearcoat": torch.rand(1, 1, size, size, generator=g)}
    maps = {k: v.to(device).requires_grad_() for k, v in maps.items()}
    gbuf = plane_gbuffer(size, size, normal_map=nm.to(device), material=maps, device=device)
    light_list: list[Light] = []
    for i in range(lights):
        a = 2.0 * math.pi * i / max(lights, 1)
        if i % 2 == 0:
            pos = torch.tensor([1.5 * math.cos(a), 1.5 * math.sin(a), 2.0], device=device)
            light_list.append(PointLight(pos, torch.full((3,), 4.0, device=device)))
        else:
            light_list.append(DirectionalLight(torch.tensor([math.cos(a), math.sin(a), 2.0], device=device),
                                               torch.full((3,), 1.0, device=device)))
    rows = []
    for backend in backends:
        row: dict[str, Any] = dict(backend=backend, size=size, lights=lights)
        try:
            def fwd():
                with _Backend(backend), torch.no_grad():
                    torchbrdf.shade(gbuf, light_list)

            def fb():
                for t in maps.values():
                    t.grad = None
                with _Backend(backend):
                    torchbrdf.shade(gbuf, light_list).sum().backward()

            row.update(_time_and_peak(fwd, fb, device, repeats))
            peak = row["peak_bytes"]
            log(f"  shade {backend:8s} {size}² {lights} lights: fwd {row['fwd_s'] * 1e3:.1f} ms  "
                f"fwd+bwd {row['fwdbwd_s'] * 1e3:.1f} ms  peak {_mib(peak)}")
        except torch.cuda.OutOfMemoryError:
            row["error"] = "out of memory"
        except Exception as e:  # noqa: BLE001
            row["error"] = f"{type(e).__name__}: {e}"[:300]
            log(f"  shade {backend}: failed ({row['error']})")
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------

def _mib(b) -> str:
    return "n/a" if b is None else f"{b / 2 ** 20:.0f} MiB"


def _rate(r, key) -> str:
    return r.get("error", "n/a") if key not in r else f"{r[key]:.3g}"


def report(res: dict) -> str:
    """Markdown tables of a :func:`run` result."""
    lines = [f"GPU: {res['gpu']}; torch {res['torch']}; triton {res['triton']}; Mitsuba {res['mitsuba']}"
             + (f"; {res['date']}" if res.get("date") else ""), "",
             "### principled, float32, every parameter per lane", "",
             "| N | path | forward (eval/s) | forward+backward (eval/s) | peak GPU memory | above inputs |",
             "|---|---|---|---|---|---|"]
    for r in res["principled"]:
        lines.append(f"| 2^{int(math.log2(r['N']))} | {r['path']} | {_rate(r, 'fwd_rate')} | "
                     f"{_rate(r, 'fwdbwd_rate')} | {_mib(r.get('peak_bytes'))} | "
                     f"{_mib(r.get('peak_above_inputs_bytes'))} |")
    lines += ["", "### shade", "",
              "| size | lights | backend | forward (ms) | forward+backward (ms) | peak GPU memory |",
              "|---|---|---|---|---|---|"]
    for r in res["shade"]:
        fwd = r.get("error", "n/a") if "fwd_s" not in r else f"{r['fwd_s'] * 1e3:.1f}"
        fb = r.get("error", "n/a") if "fwdbwd_s" not in r else f"{r['fwdbwd_s'] * 1e3:.1f}"
        lines.append(f"| {r['size']}² | {r['lights']} | {r['backend']} | {fwd} | {fb} | "
                     f"{_mib(r.get('peak_bytes'))} |")
    return "\n".join(lines) + "\n"


def gpu_section(out_dir: str) -> list:
    """The ``## GPU (CUDA)`` section of ``docs/benchmarks.md``: which GPU numbers exist, how to get them."""
    measured = os.path.exists(os.path.join(out_dir, "benchmarks_cuda.md"))
    L = ["## GPU (CUDA)", ""]
    if measured:
        L += ["Measured on a GPU: see [benchmarks_cuda.md](benchmarks_cuda.md) (written by the command "
              "below, with the GPU's name; raw numbers in `benchmarks_cuda.json`).", ""]
    else:
        L += ["**No GPU numbers have been measured yet** (no machine used so far had a GPU). The Triton "
              "kernels are tested for correctness on the CPU through Triton's interpreter "
              "(`tests/kernels/test_triton_backend.py`) and compiled for sm_90 without a GPU, but their speed and "
              "memory on a GPU are unknown.", ""]
    L += ["On a machine with CUDA (and `pip install -e \".[triton]\"`; Mitsuba optional):", "", "```bash",
          "python -m torchbrdf.bench --device cuda", "```", "",
          "It measures, in one run, float32 with every parameter per lane: `principled` forward and "
          "forward+backward throughput and peak GPU memory (`torch.cuda.max_memory_allocated`) at "
          "N = 2^20 … 2^24 for the Triton kernels, eager on CUDA, `torch.compile` of the eager formula and "
          "Mitsuba's `cuda_ad_rgb` principled (when installed); and `shade` at 1024² with 16 lights "
          "(8 point, 8 directional) with the Triton and eager backends. It writes `benchmarks_cuda.md` and "
          "`benchmarks_cuda.json` into `--out` (default `docs/`). Without CUDA it prints one line and "
          "exits 0.", ""]
    return L


def run(device: torch.device | str | int = "cuda", sizes: Iterable[int] = SIZES, paths: Sequence[str] = PATHS, repeats: int = 10,
        shade_size: int = 1024, lights: int = 16, log: Callable[[str], object] = print) -> dict:
    """Measure everything on ``device``; returns the raw results (see :func:`report`)."""
    device = torch.device(device)
    try:
        import triton

        tver = triton.__version__
    except ImportError:
        tver = None
        paths = [p for p in paths if p != "triton"]
    from torchbrdf.bench.mitsuba import mitsuba_available

    res = dict(gpu=torch.cuda.get_device_name(device) if device.type == "cuda" else str(device),
               torch=torch.__version__, triton=tver,
               date=datetime.datetime.now(datetime.timezone.utc).date().isoformat(),
               mitsuba=mitsuba_available("cuda_ad_rgb") if "mitsuba" in paths else None,
               config=dict(sizes=list(sizes), paths=list(paths), repeats=repeats, shade_size=shade_size,
                           lights=lights))
    log(f"device: {res['gpu']}; triton {tver}; Mitsuba cuda_ad_rgb: {res['mitsuba'] or 'not installed'}")
    log("principled:")
    res["principled"] = principled_rows(sizes, paths, device, repeats, log)
    log("shade:")
    res["shade"] = shade_rows(shade_size, lights, [p for p in ("triton", "eager") if p in paths], device,
                              max(1, repeats // 3), log)
    return res


def main(args: argparse.Namespace) -> int:
    """Entry of ``python -m torchbrdf.bench --device cuda`` (``args`` from ``bench.brdf.main``)."""
    if not torch.cuda.is_available():
        print(NO_CUDA)
        return 0
    sizes = [1 << s for s in (args.sizes or range(20, 25))]
    skip = {"mitsuba"} if args.no_mitsuba else set()
    skip |= {"compile"} if args.no_compile else set()
    paths = [p for p in PATHS if p not in skip]
    res = run("cuda", sizes, paths, args.repeats, args.shade_size, args.lights)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "benchmarks_cuda.json"), "w") as fh:
        json.dump(res, fh, indent=1)
    text = report(res)
    with open(os.path.join(args.out, "benchmarks_cuda.md"), "w") as fh:
        fh.write(text)
    print(text)
    return 0
