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
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

import torchbrdf
from torchbrdf.bench.timing import Spread, ratio_text, spread_text, time_alternating

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

def _median_time(fn, repeats: int, budget: float) -> tuple[float, int]:
    """Median wall time of ``fn()`` after one warm-up call; fewer repeats when slow."""
    s = time_alternating({"fn": fn}, repeats, budget)["fn"]
    return s.median, s.repeats


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
        mi_state = _mitsuba_setup({k: t.numpy() for k, t in inputs.items()})
        del inputs, np
        rss1 = _status_mib("VmRSS")
        for _ in range(2):
            _mitsuba_fwdbwd(mi_state)()
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

        tf, _ = _median_time(fwd, repeats, budget)
        tb, _ = _median_time(fb, repeats, budget)
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


# ---------------------------------------------------------------------------------------------
# Mitsuba 3
# ---------------------------------------------------------------------------------------------

def mitsuba_available(variant: str = "llvm_ad_rgb") -> str | None:
    """Mitsuba version string when ``mitsuba`` with ``variant`` imports, else None."""
    try:
        import mitsuba as mi

        mi.set_variant(variant)
        return mi.__version__
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return None


def _mitsuba_setup(inp: dict, variant: str = "llvm_ad_rgb") -> dict:
    """Mitsuba ``principled`` with per-lane parameters.

    Mitsuba's BSDF parameters are textures: each lane reads its own texel of a bitmap with
    nearest filtering (the way per-pixel SVBRDF parameters are fed to Mitsuba). Directions are
    handed over in the local frame (Mitsuba's BSDF interface); ``specular`` is a scalar
    there (it sets the IOR), so it is held at the mean of ours; ``subsurface`` has no
    counterpart.
    """
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    N = inp["l"].shape[0]
    W = 2048 if N % 2048 == 0 else 1
    H = N // W

    def tex(a):
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(a.reshape(H, W, -1), dtype=np.float32)),
                "filter_type": "nearest", "raw": True, "wrap_mode": "clamp"}

    names = {"metallic": "metallic", "roughness": "roughness", "specular_tint": "spec_tint",
             "anisotropic": "anisotropic", "sheen": "sheen", "sheen_tint": "sheen_tint",
             "clearcoat": "clearcoat", "clearcoat_gloss": "clearcoat_gloss"}
    d = {"type": "principled", "base_color": tex(inp["base_color"]),
         "specular": float(inp["specular"].mean())}
    for ours, theirs in names.items():
        d[theirs] = tex(inp[ours])
    bsdf = mi.load_dict(d)
    params = mi.traverse(bsdf)

    def local(w):
        return np.stack([(w * inp[k]).sum(-1) for k in ("x", "y", "n")]).astype(np.float32)

    def vec(a):
        return mi.Vector3f(np.ascontiguousarray(a.T, dtype=np.float32))

    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    uv = mi.Point2f(np.stack([(jj.ravel() + 0.5) / W, (ii.ravel() + 0.5) / H]).astype(np.float32))
    wi, wo = mi.Vector3f(local(inp["v"])), mi.Vector3f(local(inp["l"]))
    world = {k: vec(inp[k]) for k in ("l", "v", "n", "x", "y")}
    dr.eval(uv, wi, wo, *world.values())
    keys = [k for k in params.keys() if k.endswith(".data")]
    return dict(bsdf=bsdf, params=params, keys=keys, uv=uv, wi=wi, wo=wo, world=world, N=N, ctx=mi.BSDFContext())


def _mitsuba_eval(s, world: bool, grad: bool):
    """One evaluation; ``world``: from the same world-space l, v, n, x, y as torchbrdf (the frame
    change to Mitsuba's local coordinates is part of the timed call), else from local directions."""
    import drjit as dr
    import mitsuba as mi

    if world:
        w = {k: mi.Vector3f(t) for k, t in s["world"].items()} if grad else s["world"]
        if grad:
            for t in w.values():
                dr.enable_grad(t)
        frame = mi.Frame3f(w["x"], w["y"], w["n"])
        wi, wo = frame.to_local(w["v"]), frame.to_local(w["l"])
        leaves = list(w.values())
    else:
        wi, wo = (mi.Vector3f(s["wi"]), mi.Vector3f(s["wo"])) if grad else (s["wi"], s["wo"])
        if grad:
            dr.enable_grad(wi)
            dr.enable_grad(wo)
        leaves = [wi, wo]
    return s["bsdf"].eval(s["ctx"], _mitsuba_si(s, wi), wo), leaves


def _mitsuba_si(s, wi):
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, s["N"])
    si.wi = wi
    si.uv = s["uv"]
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    return si


def _mitsuba_fwd(s, world: bool = True):
    import drjit as dr

    def run():
        val, _ = _mitsuba_eval(s, world, grad=False)
        dr.eval(val)
        dr.sync_thread()
    return run


def _mitsuba_fwdbwd(s, world: bool = True):
    import drjit as dr

    def run():
        params = s["params"]
        for k in s["keys"]:
            dr.enable_grad(params[k])
        params.update()
        val, leaves = _mitsuba_eval(s, world, grad=True)
        dr.backward_from(val)
        grads = [dr.grad(params[k]) for k in s["keys"]] + [dr.grad(t) for t in leaves]
        dr.eval(*grads)
        dr.sync_thread()
        for k in s["keys"]:
            dr.disable_grad(params[k])
    return run


def head_to_head(N: int, repeats: int, log: _Log, with_mitsuba: bool) -> dict:
    """Ours (as a user calls it) vs eager vs Mitsuba at N, float32, per-lane; runs interleaved."""
    x = make_inputs(N, torch.float32, seed=6)
    xg = {k: t.clone().requires_grad_() for k, t in x.items()}
    fns = {"torchbrdf": (_fwd(x), _fwdbwd(xg))}
    if with_mitsuba:
        s = _mitsuba_setup({k: t.numpy() for k, t in x.items()})
        fns["mitsuba"] = (_mitsuba_fwd(s, world=True), _mitsuba_fwdbwd(s, world=True))
        fns["mitsuba_local"] = (_mitsuba_fwd(s, world=False), _mitsuba_fwdbwd(s, world=False))
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
        return _P._principled_eager(dict(kw), torchbrdf.LOBES)

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

    tf, _ = _median_time(fwd, repeats, 60.0)
    tb, _ = _median_time(fb, repeats, 60.0)
    res = dict(N=N, fwd_rate=N / tf, fwdbwd_rate=N / tb, compile_fwd_s=c_fwd, compile_fwdbwd_s=c_bwd)
    log(f"  torch.compile N=2^{int(math.log2(N))} fwd {N / tf:.3e}/s  fwd+bwd {N / tb:.3e}/s "
        f"(compile {c_fwd:.0f} s + {c_bwd:.0f} s)")
    return res


# ---------------------------------------------------------------------------------------------
# Environment lighting (needs torchbrdf.render.envmap)
# ---------------------------------------------------------------------------------------------

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

        from torchbrdf.bench.brdf import brdf
        env = bench.environment(256, print)
        lines = bench.environment_section(env)      # the markdown of the section
        bench._plots({"environment": env}, "docs")  # writes only bench_pareto_env.png
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

        from torchbrdf.bench import brdf as bench
        lobes = bench.environment_lobes(print)                    # sun at 35° elevation
        other = bench.environment_lobes(print, sun_elevation=15)  # the same at another sun
        bench._plots({"environment_lobes": lobes}, "docs")  # writes only bench_pareto_env_lobes.png
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
        t, _ = _median_time(split, repeats, 2.0)
        rows.append(dict(method="split sum", samples=None, seconds=t, **metrics(split())))
        for s in sample_counts:
            t, _ = _median_time(lambda s=s: mc(s, 11), repeats, 8.0)
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

        from torchbrdf.bench import brdf as bench
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

        from torchbrdf.bench import brdf as bench
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

            t_f, _ = _median_time(fwd, repeats, 10.0)
            t_b, _ = _median_time(fwd_bwd, repeats, 10.0)
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
                cells.append(_fmt(e, ".2e") + ratio)
            L.append(f"| {c} | " + " | ".join(cells) + " |")
        L += ["", "Every Monte Carlo variant is unbiased (`sampling=` of `integrate_environment_mc`, "
              "`env_sampling=` of `shade`); only the variance differs. The split sum's error is a bias: "
              "it does not shrink with more work.", ""]
    return L


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------

def _machine() -> dict:
    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        gcc = subprocess.run(["gcc", "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    except (OSError, IndexError):
        gcc = "none"
    return dict(cpu=cpu, cores=os.cpu_count(), torch_threads=torch.get_num_threads(), torch=torch.__version__,
                python=platform.python_version(), gcc=gcc, load_start=os.getloadavg())


def _fmt(x, spec=".3g"):
    return "—" if x is None else format(x, spec)


def _rate_cell(row: dict | None, kind: str) -> str:
    """A throughput table cell: ``median (slowest–fastest)`` evaluations/s, ``—`` when not run."""
    if row is None:
        return "—"
    sp = row.get(f"{kind}_spread")
    if sp is None:
        return _fmt(row[f"{kind}_rate"], ".3e")
    return spread_text(Spread(sp["min_s"], sp["median_s"], sp["max_s"], int(sp["repeats"])), row["N"], ".3e")


def write_report(res: dict, out_dir: str, argv: Sequence[str]) -> None:
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "benchmarks.json"), "w") as fh:
        json.dump(res, fh, indent=1, default=str)
    plots = _plots(res, out_dir)
    m = res["machine"]
    L = ["# torchbrdf benchmarks", "",
         "Regenerate (writes this file, `benchmarks.json` and the PNG plots into `--out`):", "",
         "```bash", "python -m torchbrdf.bench " + " ".join(argv), "```", "",
         f"Machine: {m['cpu']}, {m['cores']} cores ({m['torch_threads']} torch threads), torch {m['torch']}, "
         f"Python {m['python']}, {m['gcc']}" + (f", Mitsuba {res['mitsuba_version']}" if res.get("mitsuba_version") else "")
         + f". Load average (1/5/15 min) at start {tuple(round(x, 2) for x in m['load_start'])}, at end "
         f"{tuple(round(x, 2) for x in m['load_end'])} — the machine is shared, so absolute numbers move with the "
         "load; the side-by-side columns were measured in the same run (the head-to-head alternates blocks "
         "of calls of each implementation, an untimed call then 2 timed ones, order reversed every round).", "",
         "All throughputs are evaluations per second of the full principled BRDF (all lobes), median of "
         "repeats after a warm-up; `fwd+bwd` includes the backward pass to every input. The first use of a "
         "fused-kernel family compiles it with gcc (~1–3 s, once per machine: cached in "
         "`~/.cache/torchbrdf/kernels`); warm-ups exclude it.", ""]
    h = res.get("head_to_head")
    if h:
        L += ["## Headline: N = 2^22, float32, per-lane parameters", "",
              "| implementation | forward / s | forward+backward / s |", "|---|---|---|"]
        names = {"torchbrdf": "torchbrdf.principled (default dispatch → fused kernels)",
                 "mitsuba": "Mitsuba 3 `principled` (llvm_ad_rgb), same world-space inputs",
                 "mitsuba_local": "Mitsuba 3 `principled`, directions pre-projected to its local frame"}
        for k, name in names.items():
            if k in h:
                L.append(f"| {name} | {h[k]['fwd_rate']:.3e} | {h[k]['fwdbwd_rate']:.3e} |")
        eager = [r for r in res.get("throughput", []) if r["path"] == "eager" and r["dtype"] == "float32"]
        tc = res.get("torch_compile")
        if tc:
            L.append(f"| `torch.compile` of the eager path (inductor; compile {tc['compile_fwd_s']:.0f} s + "
                     f"{tc['compile_fwdbwd_s']:.0f} s) | {tc['fwd_rate']:.3e} | {tc['fwdbwd_rate']:.3e} |")
        if eager:
            r = max(eager, key=lambda r: r["N"])
            L.append(f"| torchbrdf eager reference path (N = 2^{int(math.log2(r['N']))}) | {r['fwd_rate']:.3e} | {r['fwdbwd_rate']:.3e} |")
        if "ratio_fwd" in h:
            L += ["", f"**Ratio torchbrdf / Mitsuba (same world-space inputs): forward ×{h['ratio_fwd']:.2f}, "
                  f"forward+backward ×{h['ratio_fwdbwd']:.2f}.** Against Mitsuba fed pre-projected local "
                  f"directions: forward ×{h['ratio_fwd_local']:.2f}, forward+backward ×{h['ratio_fwdbwd_local']:.2f}."]
        L += ["", "Mitsuba reads its per-lane parameters from nearest-filtered bitmap textures (one texel per "
              "lane), which is how Mitsuba takes spatially varying parameters; its `specular` is a scalar "
              "(it sets the IOR) and it has no `subsurface`. torchbrdf's API takes world-space `l, v, n, x, y` "
              "(15 floats per lane) and projects them itself; the first Mitsuba row gets exactly those "
              "tensors and does the same projection (`Frame3f(x, y, n).to_local`) inside the timed call, "
              "the second row is handed local `wi, wo` (6 floats per lane) computed beforehand — the "
              "evaluation is largely memory-bound, so this matters.", ""]
    if res.get("peak_memory"):
        L += ["## Peak memory of forward+backward (fresh process each)", "",
              "| path | N | RSS after import (MiB) | after inputs (MiB) | peak VmHWM (MiB) |", "|---|---|---|---|---|"]
        for r in res["peak_memory"]:
            L.append(f"| {r['what']} | 2^{int(math.log2(r['N']))} | {r['rss_start_MiB']:.0f} | {r['rss_after_inputs_MiB']:.0f} | {r['peak_MiB']:.0f} |")
        L += ["", "The inputs (16 tensors, 28 floats per lane) take 448 MiB at 2^22 and their gradients as much "
              "again; the fused path holds no intermediates (the backward recomputes the forward lane by lane).", ""]
    if res.get("throughput"):
        L += ["## Throughput (evaluations / s)", "",
              "Median (slowest–fastest call); eager and fused alternate call by call. A speed-up is printed "
              "only where the two spreads are apart, else flagged ≈.", "",
              "| dtype | N | eager fwd | fused fwd | speed-up fwd | eager fwd+bwd | fused fwd+bwd | speed-up fwd+bwd |",
              "|---|---|---|---|---|---|---|---|"]
        t = {(r["dtype"], r["N"], r["path"]): r for r in res["throughput"]}
        for d in res["config"]["dtypes"]:
            for N in res["config"]["sizes"]:
                e, f = t.get((d, N, "eager")), t.get((d, N, "fast"))
                L.append(f"| {d} | 2^{int(math.log2(N))} | {_rate_cell(e, 'fwd')} | {_rate_cell(f, 'fwd')} | "
                         f"{(f or {}).get('fwd_vs_eager', '—')} | {_rate_cell(e, 'fwdbwd')} | {_rate_cell(f, 'fwdbwd')} | "
                         f"{(f or {}).get('fwdbwd_vs_eager', '—')} |")
        L += ["", f"Eager is run up to N = 2^{int(math.log2(res['config']['eager_max']))} (above that one call takes "
              "tens of seconds and several GiB).", ""]
    if res.get("accuracy"):
        a = res["accuracy"]
        L += [f"## Accuracy against float64 (N = 2^{int(math.log2(a['rows'][0]['N']))}, same rounded inputs)", "",
              "| dtype | path | max rel. error | p99 rel. error |", "|---|---|---|---|"]
        for r in a["rows"]:
            L.append(f"| {r['dtype']} | {r['path']} | {r['max_rel']:.2e} | {r['p99_rel']:.2e} |")
        if a.get("fast_vs_eager"):
            L += ["", f"float32 fused vs float32 eager: max rel. difference {a['fast_vs_eager'][0]:.2e}, p99 "
                  f"{a['fast_vs_eager'][1]:.2e} (the fused kernels round like ATen except ATen's float32 `sqrt`, "
                  "which on this build is not correctly rounded: the fused path is the more accurate of the two)."]
        L += ["", "Relative error over all lanes and channels whose float64 value exceeds 1e-6 × the maximum. "
              "Half types are evaluated in float32 and rounded once at the end, so their error is the output "
              "rounding (2^-11 for float16, 2^-8 for bfloat16).", ""]
    if res.get("models"):
        L += [f"## Model choices (`torchbrdf.microfacet`, eager, float32, N = 2^{int(math.log2(res['models'][0]['N']))})", "",
              "| choice | fwd / s | fwd+bwd / s | float32 max rel. err. | differs from | p99 rel. difference |",
              "|---|---|---|---|---|---|"]
        for r in res["models"]:
            L.append(f"| {r['choice']} | {r['fwd_rate']:.3e} | {r['fwdbwd_rate']:.3e} | {r['f32_max_rel']:.1e} | "
                     f"{r['ref'] or '—'} | {_fmt(r.get('diff_p99_rel'), '.2e')} |")
        L += ["", "The first row's difference is Schlick's approximation against the exact dielectric Fresnel "
              "(IOR 1.5, F0 = 0.04); the others compare a model change against GGX with height-correlated Smith.", ""]
    if res.get("pruned"):
        L += [f"## Lobe pruning (principled, float32, N = 2^{int(math.log2(res['pruned'][0]['N']))})", "",
              "| path | all lobes fwd / s | diffuse+specular fwd / s | speed-up fwd | all lobes fwd+bwd / s | diffuse+specular fwd+bwd / s | speed-up fwd+bwd |",
              "|---|---|---|---|---|---|---|"]
        for r in res["pruned"]:
            sf = r.get("speedup_fwd_text", f"×{r['speedup_fwd']:.2f}")
            sb = r.get("speedup_fwdbwd_text", f"×{r['speedup_fwdbwd']:.2f}")
            L.append(f"| {r['path']} | {r['full_fwd_rate']:.3e} | {r['pruned_fwd_rate']:.3e} | {sf} | "
                     f"{r['full_fwdbwd_rate']:.3e} | {r['pruned_fwdbwd_rate']:.3e} | {sb} |")
        L += ["", "Pruned = `subsurface`, `sheen`, `clearcoat` passed as Python `0.0` (exactly the same values as "
              "tensors of zeros; the lobes are skipped).", ""]
    L += environment_section(res.get("environment"))
    L += environment_lobes_section(res.get("environment_lobes"))
    L += environment_skies_section(res.get("environment_skies"))

    from torchbrdf.bench.cuda import gpu_section

    L += gpu_section(out_dir)
    if plots:
        L += ["## Plots", ""] + [f"![{p}]({p})" for p in plots] + [""]
    with open(os.path.join(out_dir, "benchmarks.md"), "w") as fh:
        fh.write("\n".join(L))


def _plots(res: dict, out_dir: str) -> list:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    files = []
    if res.get("throughput"):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
        for ax, key, title in ((axes[0], "fwd_rate", "forward"), (axes[1], "fwdbwd_rate", "forward+backward")):
            for d in res["config"]["dtypes"]:
                for path, ls in (("fast", "-"), ("eager", "--")):
                    pts = sorted((r["N"], r[key]) for r in res["throughput"] if r["dtype"] == d and r["path"] == path)
                    if pts:
                        ax.plot([p[0] for p in pts], [p[1] for p in pts], ls, marker="o", label=f"{d} {path}")
            h = res.get("head_to_head", {})
            if "mitsuba" in h:
                ax.scatter([res["config"]["head_N"]], [h["mitsuba"][key]], marker="*", s=160, c="k", label="Mitsuba 3 (fp32)")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel("N (lanes)")
            ax.set_title(title)
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel("evaluations / s")
        axes[1].legend(fontsize=7, ncol=2)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "bench_throughput.png"), dpi=110)
        plt.close(fig)
        files.append("bench_throughput.png")
    if res.get("accuracy") and res.get("throughput"):
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        a = {(r["dtype"], r["path"]): r for r in res["accuracy"]["rows"]}
        Nref = max(r["N"] for r in res["throughput"])
        for r in res["throughput"]:
            if r["N"] != Nref or (r["dtype"], r["path"]) not in a:
                continue
            e = a[(r["dtype"], r["path"])]["p99_rel"]
            ax.scatter(1e9 / r["fwdbwd_rate"], max(e, 1e-17), label=f"{r['dtype']} {r['path']}",
                       marker="o" if r["path"] == "fast" else "s")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"ns per forward+backward evaluation (N = 2^{int(math.log2(Nref))})")
        ax.set_ylabel("p99 relative error vs float64")
        ax.set_title("principled: accuracy vs time (lower-left is better)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "bench_pareto_dtype.png"), dpi=110)
        plt.close(fig)
        files.append("bench_pareto_dtype.png")
    env = res.get("environment")
    if env:
        fig, ax = plt.subplots(figsize=(7.5, 5.0))
        mc = [r for r in env["rows"] if r["samples"]]
        for (_, label), marker in zip(ENV_METHODS, "osD^"):
            mrows = [r for r in mc if r["method"] == label]
            if not mrows:
                continue
            (line,) = ax.plot([r["seconds"] for r in mrows], [r["mean_rel_err"] for r in mrows], "-", marker=marker,
                              ms=4, label=label.replace("MC, ", "MC: "))
            for r in mrows:
                ax.annotate(str(r["samples"]), (r["seconds"], r["mean_rel_err"]), fontsize=6,
                            color=line.get_color(), xytext=(3, 2), textcoords="offset points")
        ss = [r for r in env["rows"] if not r["samples"]]
        if ss:
            ax.scatter([ss[0]["seconds"]], [ss[0]["mean_rel_err"]], marker="*", s=150, c="r", label="split sum")
            if "prefilter_seconds" in ss[0]:
                ax.scatter([ss[0]["seconds"] + ss[0]["prefilter_seconds"]], [ss[0]["mean_rel_err"]], marker="*",
                           s=150, facecolors="none", edgecolors="r", label="split sum incl. prefiltering")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds")
        ax.set_ylabel("relative L1 error vs quadrature")
        ax.set_title("environment lighting: error vs time (labels: samples per point)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "bench_pareto_env.png"), dpi=110)
        plt.close(fig)
        files.append("bench_pareto_env.png")
    lobes = res.get("environment_lobes")
    if lobes:
        files.append(_plot_env_lobes(plt, lobes, out_dir))
    return files


def _plot_env_lobes(plt, res: dict, out_dir: str) -> str:
    """One panel per lobe: MC error vs time (labels: samples per point) and the split sum."""
    k = len(res["lobes"])
    cols = 3
    rows = -(-k // cols)
    # (the legend goes below the panels, in a band of its own)
    fig, grid = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows + 0.9), sharey=True, squeeze=False)
    axes = list(grid.ravel())
    for ax, lobe in zip(axes, res["lobes"]):
        mc = [r for r in lobe["rows"] if r["samples"]]
        ss = [r for r in lobe["rows"] if not r["samples"]][0]
        ax.plot([r["seconds"] for r in mc], [100 * r["rel_l1"] for r in mc], "-o", color="C0", ms=4,
                label="MC (MIS): rel. L1 error")
        for r in mc:
            ax.annotate(str(r["samples"]), (r["seconds"], 100 * r["rel_l1"]), fontsize=7, color="C0",
                        xytext=(3, 3), textcoords="offset points")
        ax.plot([ss["seconds"]], [100 * ss["rel_l1"]], "*", color="C3", ms=13,
                label="split sum: rel. L1 error")
        ax.plot([ss["seconds"] + res["prefilter_seconds"]], [100 * ss["rel_l1"]], "*", ms=13, mfc="none",
                color="C3", label="split sum incl. prefiltering")
        ax.axhline(100 * max(abs(ss["bias"]), 1e-6), color="C3", ls="--", lw=1, label="split sum: |bias|")
        ax.axhline(100 * max(abs(ss["bias_grazing"]), 1e-6), color="C2", ls=":", lw=1.5,
                   label="split sum: |bias| at n·v < 0.1")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(lobe["label"], fontsize=9)
        ax.set_xlabel("seconds per call (log)")
        ax.grid(True, which="both", alpha=0.3)
        ax.yaxis.set_tick_params(labelleft=True)
    for i in range(0, len(axes), cols):
        axes[i].set_ylabel("error vs reference (%, log)")
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[k:]:
        ax.axis("off")
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8,
               title="MC labels: samples per point", title_fontsize=8)
    fig.suptitle(f"environment lighting per lobe: split sum vs Monte Carlo ({res['pixels']}-pixel sphere, "
                 f"{res['env_size'][0]}×{res['env_size'][1]} sky with a sun)", fontsize=10)
    fig.tight_layout(rect=(0, 0.9 / (3.4 * rows + 0.9) * 1.2, 1, 1))
    name = "bench_pareto_env_lobes.png"
    fig.savefig(os.path.join(out_dir, name), dpi=110)
    plt.close(fig)
    return name


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--_rss-child"]:
        print(json.dumps(_rss_child(int(argv[1]), argv[2])))
        return 0
    ap = argparse.ArgumentParser(prog="torchbrdf-bench", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="reduced sweep (N up to 2^18 except the headline, 3 repeats)")
    ap.add_argument("--out", default="bench_out",
                    help="folder for benchmarks.md/.json and the plots (default bench_out/; 'docs' updates the committed report)")
    ap.add_argument("--sizes", type=int, nargs="*", help="log2 of the batch sizes (default 12 14 16 18 20 22)")
    ap.add_argument("--dtypes", nargs="*", choices=list(DTYPES), help="default: all four")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per measurement (best is kept)")
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
    res: dict[str, Any] = dict(machine=_machine(), mitsuba_version=mver,
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
