"""The benchmark's report: ``benchmarks.md`` (tables, the command, the machine),
``benchmarks.json`` (raw numbers) and the PNG plots, from the results of ``python -m
torchbrdf.bench`` (:func:`torchbrdf.bench.brdf.main`)."""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import subprocess
from collections.abc import Sequence

import torch

from torchbrdf.bench.environment import (
    ENV_METHODS,
    environment_lobes_section,
    environment_section,
    environment_skies_section,
)
from torchbrdf.bench.timing import Spread, format_or_dash, spread_text


def machine_description() -> dict:
    """The machine the benchmark ran on: CPU, cores, load, torch and Python versions, and the date (UTC)."""
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
                python=platform.python_version(), gcc=gcc, load_start=os.getloadavg(),
                date=datetime.datetime.now(datetime.timezone.utc).date().isoformat())


def _rate_cell(row: dict | None, kind: str) -> str:
    """A throughput table cell: ``median (slowest–fastest)`` evaluations/s, ``—`` when not run."""
    if row is None:
        return "—"
    sp = row.get(f"{kind}_spread")
    if sp is None:
        return format_or_dash(row[f"{kind}_rate"], ".3e")
    return spread_text(Spread(sp["min_s"], sp["median_s"], sp["max_s"], int(sp["repeats"])), row["N"], ".3e")


def write_report(res: dict, out_dir: str, argv: Sequence[str]) -> None:
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "benchmarks.json"), "w") as fh:
        json.dump(res, fh, indent=1, default=str)
    plots = write_plots(res, out_dir)
    m = res["machine"]
    L = ["# torchbrdf benchmarks", "",
         "Regenerate (writes this file, `benchmarks.json` and the PNG plots into `--out`):", "",
         "```bash", "python -m torchbrdf.bench " + " ".join(argv), "```", "",
         f"Machine: {m['cpu']}, {m['cores']} cores ({m['torch_threads']} torch threads), torch {m['torch']}, "
         f"Python {m['python']}, {m['gcc']}" + (f", Mitsuba {res['mitsuba_version']}" if res.get("mitsuba_version") else "")
         + (f", {m['date']}" if m.get("date") else "")
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
                     f"{r['ref'] or '—'} | {format_or_dash(r.get('diff_p99_rel'), '.2e')} |")
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


def write_plots(res: dict, out_dir: str) -> list:
    """Writes the PNG plots of the results ``res`` present into ``out_dir``; returns their file names."""
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
        files.append(_save_log_log(
            plt, fig, ax, os.path.join(out_dir, "bench_pareto_dtype.png"),
            f"ns per forward+backward evaluation (N = 2^{int(math.log2(Nref))})",
            "p99 relative error vs float64", "principled: accuracy vs time (lower-left is better)"))
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
        files.append(_save_log_log(
            plt, fig, ax, os.path.join(out_dir, "bench_pareto_env.png"), "seconds",
            "relative L1 error vs quadrature", "environment lighting: error vs time (labels: samples per point)"))
    lobes = res.get("environment_lobes")
    if lobes:
        files.append(_plot_env_lobes(plt, lobes, out_dir))
    return files


def _save_log_log(plt, fig, ax, path: str, xlabel: str, ylabel: str, title: str) -> str:
    """Log-log axes with labels, grid and legend; saves ``fig`` to ``path`` and closes it.

    Returns the file name (the last part of ``path``)."""
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.path.basename(path)


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

