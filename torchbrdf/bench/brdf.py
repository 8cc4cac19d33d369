"""``python -m torchbrdf.bench``: what each evaluation choice costs, measured side by side.

One command, one run, everything on the same machine and inputs:

* throughput (evaluations/s, median of repeats after a warm-up) of :func:`torchbrdf.principled`,
  forward and forward+backward, eager reference path vs fused path, float64/32/16/bf16,
  N = 2^12 … 2^22, per-lane parameters (all eleven + l, v, n, x, y, each its own tensor);
* peak resident memory (``VmHWM``) of one forward+backward at the largest N, each in a fresh
  subprocess;
* accuracy of each dtype and path against a float64 evaluation of the same (rounded) inputs;
* model choices through :func:`torchbrdf.microfacet` (Schlick vs exact Fresnel, separable vs
  height-correlated Smith, GGX vs GTR γ ≠ 2) and pruned vs full principled lobes;
* Mitsuba 3's ``principled`` BSDF (LLVM backend, ``llvm_ad_rgb``) on the same directions and
  per-lane parameters, when ``mitsuba``/``drjit`` are importable (``pip install -e ".[mitsuba]"``);
* environment lighting: error vs time of Monte Carlo at increasing sample counts with each
  proposal of :data:`torchbrdf.render.envmap.ENV_SAMPLINGS` (MIS, BRDF only, map only, uniform
  hemisphere = no importance sampling) and of the split sum, against a quadrature reference
  (:func:`environment`; it can be run on its own, see its docstring).

It writes ``benchmarks.md`` (tables, the command, the machine), ``benchmarks.json`` (raw
numbers) and PNG plots into ``--out`` (default ``bench_out/``; ``--out docs`` refreshes the
committed report). ``--quick`` runs a reduced sweep (~1-2 min).

This module holds the inputs, the CLI and the BRDF measurements; the environment lighting is
:mod:`torchbrdf.bench.environment`, Mitsuba :mod:`torchbrdf.bench.mitsuba`, and the written
report :mod:`torchbrdf.bench.report`.

``--device cuda`` runs the GPU benchmark instead (:mod:`torchbrdf.bench.cuda`: Triton kernels,
eager on CUDA, ``torch.compile``, Mitsuba ``cuda_ad_rgb``, ``shade``); without CUDA it says so in
one line and exits 0.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

import torchbrdf
from torchbrdf.bench.environment import environment, environment_lobes, environment_skies
from torchbrdf.bench.mitsuba import mitsuba_available, mitsuba_fwd, mitsuba_fwdbwd, mitsuba_setup
from torchbrdf.bench.report import machine_description, write_report
from torchbrdf.bench.timing import median_time, ratio_text, spread_text, time_alternating

_P = importlib.import_module("torchbrdf.brdf.principled")

SCALARS = tuple(torchbrdf.PRINCIPLED_DEFAULTS)
DTYPES = {"float64": torch.float64, "float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
GEN_CHUNK = 1 << 18

# Where progress lines go (print, or a collector).
_Log = Callable[[str], object]


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------

def make_inputs(N: int, dtype: torch.dtype = torch.float32, seed: int = 0, requires_grad: bool = False) -> dict:
    """Per-lane inputs of ``principled``: random frames, directions mostly above the surface.

    Generated chunk by chunk into the final tensors, so the only memory held is the inputs
    themselves (this matters for the peak-memory measurement).
    """
    g = torch.Generator().manual_seed(seed)
    work = torch.float64 if dtype == torch.float64 else torch.float32
    out = {k: torch.empty(N, 3, dtype=dtype) for k in ("l", "v", "n", "x", "y", "base_color")}
    out.update({k: torch.empty(N, 1, dtype=dtype) for k in SCALARS})
    up = torch.tensor([0.0, 0.0, 1.0], dtype=work)
    for s in range(0, N, GEN_CHUNK):
        m = min(GEN_CHUNK, N - s)
        nrm = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=work) * 0.3 + up, dim=-1)
        t = torch.randn(m, 3, generator=g, dtype=work)
        x = torch.nn.functional.normalize(t - (t * nrm).sum(-1, keepdim=True) * nrm, dim=-1)
        y = torch.linalg.cross(nrm, x, dim=-1)
        l = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=work) * 0.6 + nrm, dim=-1)
        v = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=work) * 0.6 + nrm, dim=-1)
        for k, val in (("l", l), ("v", v), ("n", nrm), ("x", x), ("y", y)):
            out[k][s:s + m] = val
        out["base_color"][s:s + m] = torch.rand(m, 3, generator=g, dtype=work)
        for k in SCALARS:
            out[k][s:s + m] = torch.rand(m, 1, generator=g, dtype=work)
    if requires_grad:
        for t in out.values():
            t.requires_grad_()
    return out


def _cast(inputs: dict, dtype) -> dict:
    return {k: t.detach().to(dtype) for k, t in inputs.items()}


# ---------------------------------------------------------------------------------------------
# Timing helpers
# ---------------------------------------------------------------------------------------------

def _on_path(fast: bool, fn: Callable[[], object]) -> Callable[[], object]:
    """``fn`` run with the fused path on (``fast``) or off, so that both paths alternate in one loop."""
    def run():
        with _Path(fast):
            return fn()
    return run


class _Path:
    """Context manager selecting the fast or eager path."""

    def __init__(self, fast: bool):
        self.fast = fast

    def __enter__(self):
        self.old = _P.fast_path_enabled()
        _P.set_fast_path(True if self.fast else False)

    def __exit__(self, *exc):
        _P.set_fast_path(self.old)


def _fwd(inputs):
    def run():
        with torch.no_grad():
            torchbrdf.principled(**inputs)
    return run


def _fwdbwd(inputs):
    def run():
        for t in inputs.values():
            t.grad = None
        torchbrdf.principled(**inputs).sum().backward()
    return run


def throughput(sizes: Sequence[int], dtypes: Sequence[str], paths: Sequence[str], repeats: int, budget: float,
               eager_max: int, log: _Log) -> list:
    rows = []
    for dname in dtypes:
        dt = DTYPES[dname]
        for N in sizes:
            base = make_inputs(N, torch.float64 if dt == torch.float64 else torch.float32, seed=1)
            x = _cast(base, dt)
            xg = {k: t.clone().requires_grad_() for k, t in x.items()}
            del base
            run = [p for p in paths if not (p == "eager" and N > eager_max)]
            # the paths alternate call by call, so both see the same load
            fwd = time_alternating({p: _on_path(p == "fast", _fwd(x)) for p in run}, repeats, budget)
            fb = time_alternating({p: _on_path(p == "fast", _fwdbwd(xg)) for p in run}, repeats, budget)
            for path in run:
                tf, tb = fwd[path], fb[path]
                row = dict(dtype=dname, N=N, path=path, fwd_s=tf.median, fwdbwd_s=tb.median,
                           fwd_rate=N / tf.median, fwdbwd_rate=N / tb.median, repeats=[tf.repeats, tb.repeats],
                           fwd_spread=tf.as_dict(), fwdbwd_spread=tb.as_dict())
                if path == "fast" and "eager" in run:
                    row["fwd_vs_eager"] = ratio_text(fwd["eager"], tf)
                    row["fwdbwd_vs_eager"] = ratio_text(fb["eager"], tb)
                rows.append(row)
                log(f"  {dname:8s} N=2^{int(math.log2(N)):<2d} {path:5s} fwd {spread_text(tf, N, '.3e')}/s  "
                    f"fwd+bwd {spread_text(tb, N, '.3e')}/s")
            del x, xg
    return rows


# ---------------------------------------------------------------------------------------------
# Peak memory (fresh subprocess per configuration)
# ---------------------------------------------------------------------------------------------

def _status_mib(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _rss_child(N: int, what: str) -> dict:
    """Runs in the subprocess: inputs, then forward+backward twice; reports VmHWM."""
    rss0 = _status_mib("VmRSS")
    if what == "mitsuba":
        import numpy as np

        inputs = make_inputs(N, torch.float32, seed=2)
        mi_state = mitsuba_setup({k: t.numpy() for k, t in inputs.items()})
        del inputs, np
        rss1 = _status_mib("VmRSS")
        for _ in range(2):
            mitsuba_fwdbwd(mi_state)()
    else:
        inputs = make_inputs(N, torch.float32, seed=2, requires_grad=True)
        rss1 = _status_mib("VmRSS")
        with _Path(what == "fast"):
            for _ in range(2):
                _fwdbwd(inputs)()
    return dict(what=what, N=N, rss_start_MiB=rss0, rss_after_inputs_MiB=rss1, peak_MiB=_status_mib("VmHWM"))


def peak_memory(N: int, whats: Sequence[str], log: _Log) -> list:
    rows = []
    for what in whats:
        cmd = [sys.executable, "-m", "torchbrdf.bench", "--_rss-child", str(N), what]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            log(f"  peak memory {what}: failed ({res.stderr.strip().splitlines()[-1:]})")
            continue
        row = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append(row)
        log(f"  {what:8s} N=2^{int(math.log2(N))} peak {row['peak_MiB']:.0f} MiB "
            f"(after import {row['rss_start_MiB']:.0f}, after inputs {row['rss_after_inputs_MiB']:.0f})")
    return rows


# ---------------------------------------------------------------------------------------------
# Accuracy against float64
# ---------------------------------------------------------------------------------------------

def _rel_stats(out: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    out, ref = out.double().reshape(-1), ref.reshape(-1)
    keep = ref.abs() > 1e-6 * ref.abs().max()
    err = ((out - ref).abs() / ref.abs())[keep]
    return float(err.max()), float(torch.quantile(err[: 1 << 24], 0.99))


def accuracy(N: int, dtypes: Sequence[str], paths: Sequence[str],
             log: _Log) -> tuple[list[dict], tuple[float, float] | None]:
    rows = []
    base = make_inputs(N, torch.float32, seed=3)
    for dname in dtypes:
        dt = DTYPES[dname]
        x = _cast(base, dt)
        ref_in = _cast(x, torch.float64)  # judged on the rounded inputs
        with _Path(False), torch.no_grad():
            ref = torchbrdf.principled(**ref_in)
        for path in paths:
            with _Path(path == "fast"), torch.no_grad():
                out = torchbrdf.principled(**x)
            mx, p99 = _rel_stats(out, ref)
            rows.append(dict(dtype=dname, path=path, N=N, max_rel=mx, p99_rel=p99))
            log(f"  {dname:8s} {path:5s} max rel {mx:.2e}  p99 {p99:.2e}")
    fast_vs_eager = None
    if "fast" in paths and "eager" in paths:
        x = _cast(base, torch.float32)
        with torch.no_grad():
            with _Path(True):
                a = torchbrdf.principled(**x)
            with _Path(False):
                b = torchbrdf.principled(**x)
        fast_vs_eager = _rel_stats(a, b)
        log(f"  float32 fast vs eager: max rel {fast_vs_eager[0]:.2e}, p99 {fast_vs_eager[1]:.2e}")
    return rows, fast_vs_eager


# ---------------------------------------------------------------------------------------------
# Model choices
# ---------------------------------------------------------------------------------------------

MODEL_CHOICES: list[tuple[str, dict[str, Any], str | None]] = [
    # label, microfacet kwargs, reference label for the "error" column
    ("GGX + Schlick + Smith height-correlated", dict(distribution="ggx", fresnel="schlick", masking="smith_correlated"), None),
    ("GGX + exact dielectric Fresnel", dict(distribution="ggx", fresnel="dielectric", masking="smith_correlated"),
     None),
    ("GGX + Schlick + Smith separable", dict(distribution="ggx", fresnel="schlick", masking="smith_separable"),
     "GGX + Schlick + Smith height-correlated"),
    ("GTR γ=1.5 + Schlick + Smith correlated", dict(distribution="gtr", gamma=1.5, fresnel="schlick",
                                                    masking="smith_correlated"), "GGX + Schlick + Smith height-correlated"),
    ("GTR γ=3 + Schlick + Smith correlated", dict(distribution="gtr", gamma=3.0, fresnel="schlick",
                                                  masking="smith_correlated"), "GGX + Schlick + Smith height-correlated"),
]


def model_choices(N: int, repeats: int, budget: float, log: _Log) -> list:
    rows: list[dict[str, Any]] = []
    x = make_inputs(N, torch.float32, seed=4)
    alpha = torch.clamp(x["roughness"] ** 2, min=1e-3)
    vec = {k: x[k] for k in ("l", "v", "n")}
    results = {}
    for label, kw, ref_label in MODEL_CHOICES:
        kw = dict(kw)
        if kw.get("fresnel") == "dielectric":
            kw["ior"] = 1.5
        else:
            kw["f0"] = 0.04
        a = alpha.clone().requires_grad_()

        def fwd():
            with torch.no_grad():
                torchbrdf.microfacet(**vec, alpha=a, **kw)

        def fb():
            a.grad = None
            torchbrdf.microfacet(**vec, alpha=a, **kw).sum().backward()

        tf, _ = median_time(fwd, repeats, budget)
        tb, _ = median_time(fb, repeats, budget)
        with torch.no_grad():
            v32 = torchbrdf.microfacet(**vec, alpha=alpha, **kw)
            v64 = torchbrdf.microfacet(**_cast(vec, torch.float64), alpha=alpha.double(), **kw)
        results[label] = v64
        rows.append(dict(choice=label, N=N, fwd_rate=N / tf, fwdbwd_rate=N / tb, ref=ref_label,
                         f32_max_rel=_rel_stats(v32, v64)[0]))
    # Schlick's error: against the exact dielectric Fresnel at the matching F0 (IOR 1.5 <-> F0 0.04)
    rows[0]["ref"] = "GGX + exact dielectric Fresnel"
    for row in rows:
        if row["ref"] is not None:
            mx, p99 = _rel_stats(results[row["choice"]], results[row["ref"]])
            row["diff_max_rel"], row["diff_p99_rel"] = mx, p99
        log(f"  {row['choice']:42s} fwd {row['fwd_rate']:9.3e}/s fwd+bwd {row['fwdbwd_rate']:9.3e}/s"
            + (f"  vs {row['ref']}: p99 {row['diff_p99_rel']:.2e}" if row["ref"] else ""))
    return rows


def pruned_lobes(N: int, paths: Sequence[str], repeats: int, budget: float, log: _Log) -> list:
    rows = []
    x = make_inputs(N, torch.float32, seed=5)
    pruned = {k: t for k, t in x.items() if k not in ("subsurface", "sheen", "sheen_tint", "clearcoat",
                                                      "clearcoat_gloss")}
    zeros = dict(subsurface=0.0, sheen=0.0, clearcoat=0.0)
    for path in paths:
        fast = path == "fast"
        pr = {k: t.clone().requires_grad_() for k, t in pruned.items()}

        def pf():
            with torch.no_grad():
                torchbrdf.principled(**pruned, **zeros)

        def pb():
            for t in pr.values():
                t.grad = None
            torchbrdf.principled(**pr, **zeros).sum().backward()

        # full and pruned alternate call by call: the speed-up is not the load's drift
        f = time_alternating({"full": _on_path(fast, _fwd(x)), "pruned": _on_path(fast, pf)}, repeats, budget)
        b = time_alternating({"full": _on_path(fast, _fwdbwd({k: t.clone().requires_grad_() for k, t in x.items()})),
                              "pruned": _on_path(fast, pb)}, repeats, budget)
        rows.append(dict(path=path, N=N, full_fwd_rate=N / f["full"].median, full_fwdbwd_rate=N / b["full"].median,
                         pruned_fwd_rate=N / f["pruned"].median, pruned_fwdbwd_rate=N / b["pruned"].median,
                         speedup_fwd=f["full"].median / f["pruned"].median,
                         speedup_fwdbwd=b["full"].median / b["pruned"].median,
                         speedup_fwd_text=ratio_text(f["full"], f["pruned"]),
                         speedup_fwdbwd_text=ratio_text(b["full"], b["pruned"]),
                         spreads={f"{k}_{w}": s.as_dict() for w, d in (("fwd", f), ("fwdbwd", b)) for k, s in d.items()}))
        log(f"  {path:5s} diffuse+specular only vs all lobes: fwd {rows[-1]['speedup_fwd_text']}, "
            f"fwd+bwd {rows[-1]['speedup_fwdbwd_text']}")
    return rows


def head_to_head(N: int, repeats: int, log: _Log, with_mitsuba: bool) -> dict:
    """Ours (as a user calls it) vs eager vs Mitsuba at N, float32, per-lane; runs interleaved."""
    x = make_inputs(N, torch.float32, seed=6)
    xg = {k: t.clone().requires_grad_() for k, t in x.items()}
    fns = {"torchbrdf": (_fwd(x), _fwdbwd(xg))}
    if with_mitsuba:
        s = mitsuba_setup({k: t.numpy() for k, t in x.items()})
        fns["mitsuba"] = (mitsuba_fwd(s, world=True), mitsuba_fwdbwd(s, world=True))
        fns["mitsuba_local"] = (mitsuba_fwd(s, world=False), mitsuba_fwdbwd(s, world=False))
    old = _P.fast_path_enabled()
    _P.set_fast_path(None)  # the default dispatch, exactly as a user calls it
    try:
        times: dict[str, tuple[list[float], list[float]]] = {k: ([], []) for k in fns}
        for k, (f, b) in fns.items():  # warm-up (kernel builds, Dr.Jit tracing)
            f()
            b()
            f()
            b()
        # Alternating blocks: each implementation runs one untimed call (so the other runtime's
        # worker threads, still spinning after their last job, are not billed to it) and then
        # a few timed calls back to back, as in an application loop; the order alternates.
        for rep in range(repeats):
            order = list(fns.items()) if rep % 2 == 0 else list(fns.items())[::-1]
            for j in (0, 1):
                for k, fb in order:
                    fb[j]()
                    for _ in range(2):
                        t0 = time.perf_counter()
                        fb[j]()
                        times[k][j].append(time.perf_counter() - t0)
    finally:
        _P.set_fast_path(old)
    res: dict[str, Any] = {k: dict(fwd_rate=N / statistics.median(v[0]), fwdbwd_rate=N / statistics.median(v[1]),
                   fwd_times=v[0], fwdbwd_times=v[1]) for k, v in times.items()}
    for k, r in res.items():
        log(f"  {k:9s} N=2^{int(math.log2(N))} fwd {r['fwd_rate']:.3e}/s  fwd+bwd {r['fwdbwd_rate']:.3e}/s")
    if "mitsuba" in res:
        for key, name in (("", "mitsuba"), ("_local", "mitsuba_local")):
            res["ratio_fwd" + key] = res["torchbrdf"]["fwd_rate"] / res[name]["fwd_rate"]
            res["ratio_fwdbwd" + key] = res["torchbrdf"]["fwdbwd_rate"] / res[name]["fwdbwd_rate"]
            log(f"  ratio torchbrdf/{name}: fwd x{res['ratio_fwd' + key]:.2f}, fwd+bwd x{res['ratio_fwdbwd' + key]:.2f}")
    return res


def torch_compile_baseline(N: int, repeats: int, log: _Log) -> dict:
    """``torch.compile`` (inductor) of the eager reference path: the alternative to the fused
    kernels, measured for comparison (its compile time is reported too)."""
    x = make_inputs(N, torch.float32, seed=8)
    xg = {k: t.clone().requires_grad_() for k, t in x.items()}

    def f(**kw):
        return _P.principled_eager(dict(kw), torchbrdf.LOBES)

    cf = torch.compile(f)
    t0 = time.perf_counter()
    with torch.no_grad():
        cf(**x)
    c_fwd = time.perf_counter() - t0
    t0 = time.perf_counter()
    cf(**xg).sum().backward()
    c_bwd = time.perf_counter() - t0

    def fwd():
        with torch.no_grad():
            cf(**x)

    def fb():
        for t in xg.values():
            t.grad = None
        cf(**xg).sum().backward()

    tf, _ = median_time(fwd, repeats, 60.0)
    tb, _ = median_time(fb, repeats, 60.0)
    res = dict(N=N, fwd_rate=N / tf, fwdbwd_rate=N / tb, compile_fwd_s=c_fwd, compile_fwdbwd_s=c_bwd)
    log(f"  torch.compile N=2^{int(math.log2(N))} fwd {N / tf:.3e}/s  fwd+bwd {N / tb:.3e}/s "
        f"(compile {c_fwd:.0f} s + {c_bwd:.0f} s)")
    return res


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--_rss-child"]:
        print(json.dumps(_rss_child(int(argv[1]), argv[2])))
        return 0
    ap = argparse.ArgumentParser(prog="torchbrdf-bench", description=__doc__.split("\n")[0].replace("``", ""))
    ap.add_argument("--quick", action="store_true", help="reduced sweep (N up to 2^18 except the headline, 3 repeats)")
    ap.add_argument("--out", default="bench_out",
                    help="folder for benchmarks.md/.json and the plots (default bench_out/; 'docs' updates the committed report)")
    ap.add_argument("--sizes", type=int, nargs="*", help="log2 of the batch sizes (default 12 14 16 18 20 22)")
    ap.add_argument("--dtypes", nargs="*", choices=list(DTYPES), help="default: all four")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per measurement (their median is reported)")
    ap.add_argument("--eager-max", type=int, default=20, help="log2 of the largest N for the eager path (default 20)")
    ap.add_argument("--head", type=int, default=22, help="log2 of N for the headline/peak-memory runs (default 22)")
    ap.add_argument("--no-mitsuba", action="store_true", help="skip the Mitsuba 3 comparison even if installed")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocess runs")
    ap.add_argument("--no-env", action="store_true", help="skip the environment-lighting error/time section")
    ap.add_argument("--torch-compile", action="store_true",
                    help="also measure torch.compile of the eager path at the headline N (~1 min of compiling)")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cuda: the GPU benchmark of torchbrdf.bench.cuda (Triton, eager, torch.compile, "
                         "Mitsuba cuda_ad_rgb; --sizes default 20..24); exits 0 with one line without CUDA")
    ap.add_argument("--no-compile", action="store_true", help="--device cuda: skip torch.compile")
    ap.add_argument("--shade-size", type=int, default=1024, help="--device cuda: shade image side (default 1024)")
    ap.add_argument("--lights", type=int, default=16, help="--device cuda: shade lights (default 16)")
    args = ap.parse_args(argv)
    if args.device == "cuda":
        from torchbrdf.bench import cuda

        return cuda.main(args)
    sizes = [1 << s for s in (args.sizes or ([12, 14, 16, 18] if args.quick else [12, 14, 16, 18, 20, 22]))]
    dtypes = args.dtypes or list(DTYPES)
    repeats = 3 if args.quick else args.repeats
    budget = 4.0 if args.quick else 12.0
    eager_max = 1 << (min(args.eager_max, 16) if args.quick else args.eager_max)
    head_N = 1 << args.head

    def log(msg):
        print(msg, flush=True)

    mver = None if args.no_mitsuba else mitsuba_available()
    res: dict[str, Any] = dict(machine=machine_description(), mitsuba_version=mver,
               config=dict(sizes=sizes, dtypes=dtypes, repeats=repeats, eager_max=eager_max, head_N=head_N,
                           quick=args.quick))
    log(f"machine: {res['machine']}")
    log(f"fused path available: {importlib.import_module('torchbrdf.kernels.fused').available()}; Mitsuba: {mver or 'not installed'}")
    log("head-to-head (default dispatch vs Mitsuba, alternating blocks):")
    res["head_to_head"] = head_to_head(head_N, 4 if args.quick else 10, log, mver is not None)
    if args.torch_compile:
        log("torch.compile baseline:")
        res["torch_compile"] = torch_compile_baseline(head_N, 3, log)
    if not args.no_memory:
        log("peak memory of forward+backward (fresh subprocesses):")
        whats = ["fast"] + (["eager"] if not args.quick else []) + (["mitsuba"] if mver else [])
        res["peak_memory"] = peak_memory(head_N, whats, log)
    log("throughput sweep:")
    res["throughput"] = throughput(sizes, dtypes, ["eager", "fast"], repeats, budget, eager_max, log)
    log("accuracy against float64:")
    rows, fve = accuracy(1 << 16, dtypes, ["eager", "fast"], log)
    res["accuracy"] = dict(rows=rows, fast_vs_eager=fve)
    log("model choices (microfacet):")
    res["models"] = model_choices(1 << (16 if args.quick else 20), repeats, budget, log)
    log("lobe pruning:")
    res["pruned"] = pruned_lobes(1 << (16 if args.quick else 20), ["eager", "fast"], repeats, budget, log)
    if not args.no_env:
        log("environment lighting:")
        res["environment"] = environment(64 if args.quick else 256, log)
        log("environment lighting per lobe:")
        quick_lobes: dict[str, Any] = dict(side=16, grazing=64, ref_samples=4096) if args.quick else {}
        res["environment_lobes"] = environment_lobes(log, **quick_lobes)
        if not args.quick:
            log("environment lighting on other skies:")
            res["environment_skies"] = environment_skies(log)
    res["machine"]["load_end"] = os.getloadavg()
    write_report(res, args.out, argv)
    log(f"wrote {os.path.join(args.out, 'benchmarks.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
