"""The broad recovery panel: materials nobody tuned the recovery on, scored from outside.

``python -m torchbrdf.bench.recovery_panel [--split report] [--compare BASELINE.json]``

Forty materials, four seeds of each of the ten :data:`~torchbrdf.capture.families.FAMILIES`,
are rendered into captures and recovered through the public API only
(:func:`torchbrdf.recovery.recover` on a capture folder), so the panel judges any version
of the solver. The grid a material covers is fixed by its family index ``f`` and seed ``s``:

* **Forward model** (:data:`FORWARD_MODELS`): ``"principled"`` (the library's, the one the
  recovery fits with) or ``"exact_fresnel"`` (:func:`exact_fresnel_brdf`: exact dielectric
  Fresnel, height-correlated Smith G and a Lambert diffuse; metals keep the Schlick
  F0 tint), and **calibration error** (the ``capture.json`` handed to the recovery states
  light intensities off by ~3 % and positions off by 1 cm from those rendered): the pair is
  ``(f + s) mod 4`` through :data:`_COMBOS`, so each split holds every pair.
* **Light layouts**: every material at 12 and 17 lights (a ring of 11 or 16 plus a flash,
  :func:`~torchbrdf.capture.synthetic.light_layout`), and at 8 lights where ``(f + s) mod 3
  = 0``.

**Split** (fixed once): seeds 0 and 1 of each family are *tuning* materials, seeds 2 and 3
*report* materials. Report seeds are run only to report a change, never to choose a setting.

Each capture: ``--size`` pixels square (default 128), 1 % sensor noise
(:func:`~torchbrdf.capture.synthetic.add_noise`), held-out PSNR over 8 point lights not in the
capture (:func:`~torchbrdf.capture.synthetic.random_lights`), the truth rendered with the
case's forward model and the recovered maps with the library's. One row per case: base,
roughness, metallic and specular RMSE, mean normal error (degrees), held-out mean and worst
light PSNR (dB), false-metal fraction (recovered metallic > 0.5 where the truth is < 0.5) and
the recovery's wall time.

``--compare BASELINE.json`` prints the change of every case present in both runs and flags a
case that got worse beyond the noise band of :data:`TOLERANCES` (see :func:`compare`);
``--table RUN.json`` prints a stored run's table (``--markdown``) and comparison without running.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchbrdf.brdf.diffuse import diffuse_lambert
from torchbrdf.brdf.distributions import roughness_to_alpha
from torchbrdf.brdf.fresnel import SPECULAR_TO_F0, ior_from_f0
from torchbrdf.brdf.microfacet import microfacet
from torchbrdf.capture import synthetic
from torchbrdf.capture.families import FAMILIES, make_family_material
from torchbrdf.capture.format import write_capture
from torchbrdf.recovery.engine import psnr

__all__ = [
    "FORWARD_MODELS", "LAYOUTS", "SPLITS", "TUNING_SEEDS", "REPORT_SEEDS", "TOLERANCES", "METRICS",
    "PanelCase", "panel_cases", "exact_fresnel_brdf", "calibration_error", "render_case", "score_maps",
    "run_case", "run_panel", "compare", "format_rows", "main",
]

#: The forward models that render the captures.
FORWARD_MODELS = ("principled", "exact_fresnel")
#: Light layouts by total light count: ring lights + the flash beside the camera.
LAYOUTS = {8: 7, 12: 11, 17: 16}
#: Seeds of each family used to tune the recovery, and those only ever reported.
TUNING_SEEDS = (0, 1)
REPORT_SEEDS = (2, 3)
SPLITS = ("tuning", "report", "all")
#: (forward model, calibration error) by ``(family index + seed) mod 4``.
_COMBOS = (("principled", False), ("exact_fresnel", True), ("principled", True), ("exact_fresnel", False))
#: Held-out evaluation lights per capture.
HELD_OUT_LIGHTS = 8
#: Relative sensor noise of the captures.
NOISE = 0.01
#: Calibration error of the stated lights: log-intensity spread and position offset (world units).
INTENSITY_ERROR = 0.03
POSITION_ERROR = 0.01

#: Metrics of a row: name -> (better direction, absolute tolerance, relative tolerance). A change
#: counts as worse when it goes the wrong way by more than ``max(absolute, relative × |baseline|)``.
#: Two noise draws of the same four captures (``--quick --noise-seed 1`` against the report
#: baseline) moved the maps' RMSEs by at most 1e-4 (base), 5e-4 (roughness), 4e-3 (specular),
#: the normals by 0.01° and the held-out PSNR by 0.3 dB (mean) and 0.8 dB (worst light): each
#: band is at least twice that (docs/recovery_panel.md), so an unchanged solver is not flagged.
TOLERANCES: dict[str, tuple[int, float, float]] = {
    "base_rmse": (-1, 0.002, 0.15),
    "roughness_rmse": (-1, 0.005, 0.15),
    "metallic_rmse": (-1, 0.005, 0.15),
    "specular_rmse": (-1, 0.01, 0.15),
    "normal_deg": (-1, 0.1, 0.15),
    "heldout_mean_db": (1, 0.7, 0.0),
    "heldout_worst_db": (1, 1.5, 0.0),
    "false_metal": (-1, 0.0005, 0.25),
}
#: Columns of a row, in print order.
METRICS = tuple(TOLERANCES) + ("seconds",)


@dataclasses.dataclass(frozen=True)
class PanelCase:
    """One capture of the panel: a material under one forward model, light layout and calibration."""

    family: str
    seed: int
    lights: int
    model: str
    calibration_error: bool

    @property
    def name(self) -> str:
        """A unique, readable key: ``family/seed L<lights> <model>[ +cal]``."""
        return f"{self.family}/{self.seed} L{self.lights} {self.model}{' +cal' if self.calibration_error else ''}"

    @property
    def split(self) -> str:
        """``"tuning"`` or ``"report"``."""
        return "tuning" if self.seed in TUNING_SEEDS else "report"


def panel_cases(split: str = "report", quick: bool = False) -> list[PanelCase]:
    """The panel's cases of ``split`` (one of :data:`SPLITS`), in a fixed order.

    ``quick``: one material per forward model and calibration state (four cases, 8 and 12
    lights), a smoke test of the whole path.
    """
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
    seeds = {"tuning": TUNING_SEEDS, "report": REPORT_SEEDS, "all": TUNING_SEEDS + REPORT_SEEDS}[split]
    out = []
    for s in seeds:
        for f, fam in enumerate(FAMILIES):
            model, cal = _COMBOS[(f + s) % 4]
            layouts = ([8] if (f + s) % 3 == 0 else []) + [12, 17]
            out += [PanelCase(fam, s, n, model, cal) for n in layouts]
    if quick:
        picked, seen = [], set()
        for c in out:
            if (c.model, c.calibration_error) not in seen and c.lights != 17:
                seen.add((c.model, c.calibration_error))
                picked.append(c)
        return picked
    return out


# --------------------------------------------------------------------------------------
# The second forward model and the calibration error
# --------------------------------------------------------------------------------------


def exact_fresnel_brdf(l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None, *,
                       base_color: Tensor, roughness: Tensor | float = 0.5, metallic: Tensor | float = 0.0,
                       specular: Tensor | float = 0.5) -> Tensor:
    """A reflectance model that differs from the principled one on purpose, over the same maps.

    ``(1 − m) [base / π + GGX·F_dielectric(η)·G2] + m · GGX·F_Schlick(base)·G2``:
    GGX with ``α = max(0.001, roughness²)``, height-correlated Smith G2, exact unpolarised
    dielectric Fresnel at the IOR whose normal-incidence reflectance is ``0.08 · specular``
    (as the principled model's F0), Schlick Fresnel with F0 = ``base_color`` for metals, and
    a Lambert diffuse. The principled model instead has Burley's retro-reflective diffuse
    (equal to Lambert's away from grazing angles, so the base colour keeps its meaning),
    Schlick for dielectrics, separable Smith G and a linear blend of F0 rather than of lobes.

    Args:
        l, v, n: unit vectors ``(*, 3)``; ``x``, ``y`` unused (isotropic).
        base_color: ``(*, 3)``; roughness, metallic, specular: ``(*, 1)`` or floats.

    Returns:
        ``(*, 3)`` BRDF values (no cosine), in ``l``'s dtype; 0 where ``n·l <= 0`` or ``n·v <= 0``.
    """
    alpha = roughness_to_alpha(roughness)
    f0 = SPECULAR_TO_F0 * torch.as_tensor(specular, dtype=l.dtype, device=l.device)
    eta = ior_from_f0(f0.clamp(1e-6, 0.99))  # F0 → 0 would give η = 1: no interface at all
    spec_d = microfacet(l, v, n, alpha=alpha, fresnel="dielectric", ior=eta, masking="smith_correlated")
    spec_m = microfacet(l, v, n, alpha=alpha, fresnel="schlick", f0=base_color, masking="smith_correlated")
    valid = ((n * l).sum(-1, keepdim=True) > 0) & ((n * v).sum(-1, keepdim=True) > 0)
    diff = torch.where(valid, diffuse_lambert(base_color), torch.zeros_like(spec_m))
    return (1 - metallic) * (diff + spec_d) + metallic * spec_m


def calibration_error(pos: Tensor, inten: Tensor, seed: int) -> tuple[Tensor, Tensor]:
    """Stated lights ``(positions (L, 3), intensities (L, 3))`` off from the true ``pos``, ``inten``.

    Each light's intensity is scaled by ``exp(0.03 z)`` (``z`` standard normal, recentred to
    mean 0 so the rig's overall scale stays right: a common factor is indistinguishable from
    the base colour's) and its position moved by 1 cm in a random direction. Deterministic in
    ``seed``.
    """
    gen = torch.Generator().manual_seed(int(seed) + 7_000_001)
    z = torch.randn(pos.shape[0], generator=gen, dtype=torch.float64)
    z = z - z.mean()
    d = torch.randn(pos.shape[0], 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    return ((pos.double() + POSITION_ERROR * d).to(pos.dtype),
            (inten.double() * (INTENSITY_ERROR * z).exp()[:, None]).to(inten.dtype))


def _brdf(model: str) -> Callable[..., Tensor] | None:
    if model not in FORWARD_MODELS:
        raise ValueError(f"model: expected one of {FORWARD_MODELS}, got {model!r}")
    return exact_fresnel_brdf if model == "exact_fresnel" else None


def case_seed(case: PanelCase) -> int:
    return 1000 * FAMILIES.index(case.family) + 10 * case.seed + case.lights


def render_case(case: PanelCase, folder: str | os.PathLike, size: int = 128,
                noise_seed: int = 0, ulp_seed: int = 0) -> tuple[dict[str, Tensor], tuple[Tensor, Tensor]]:
    """Write the capture of ``case`` into ``folder`` (capture.json with the *stated* lights).

    ``ulp_seed`` > 0: half the image values (a random half, by that seed) moved up by one ulp
    of float32, the same capture but for rounding: what the recovery gives then differs from
    the unmoved capture's only by how much it amplifies rounding.

    Returns the truth maps (:func:`~torchbrdf.capture.families.make_family_material`) and
    the true lights ``(positions (L, 3), intensities (L, 3))``.
    """
    maps = make_family_material(case.family, case.seed, size)
    pos, inten = synthetic.light_layout(LAYOUTS[case.lights])
    with torch.no_grad():
        img = synthetic.render_capture(maps, (pos, inten), synthetic.DEFAULT_CAMERA, brdf=_brdf(case.model),
                                       noise=NOISE, seed=case_seed(case) + 100_000 * noise_seed)
    if ulp_seed:
        moved = torch.rand(img.shape, generator=torch.Generator().manual_seed(ulp_seed)) < 0.5
        img = torch.where(moved, torch.nextafter(img, torch.tensor(math.inf, dtype=img.dtype)), img)
    stated = calibration_error(pos, inten, case_seed(case)) if case.calibration_error else (pos, inten)
    write_capture(folder, img, stated, synthetic.DEFAULT_CAMERA)
    return maps, (pos, inten)


def score_maps(pred: Mapping[str, Tensor], truth: Mapping[str, Tensor], model: str, seed: int = 0) -> dict:
    """Score recovered maps against the truth: the metrics of :data:`TOLERANCES` (no time).

    ``pred`` and ``truth`` hold ``(C, H, W)`` maps of the same size. Held-out images: 8
    random lights (:func:`~torchbrdf.capture.synthetic.random_lights` with ``seed``), the truth
    rendered with ``model``, the prediction with the library's principled model.
    """
    out: dict[str, Any] = {}
    for name in ("base_color", "roughness", "metallic", "specular"):
        key = "base_rmse" if name == "base_color" else f"{name}_rmse"
        out[key] = float(((pred[name].float() - truth[name]) ** 2).mean().sqrt())
    pn, tn = pred["normal"].double(), truth["normal"].double()
    # atan2(|a × b|, a · b): exact near 0°, where acos of a rounded cosine is not
    ang = torch.atan2(torch.linalg.cross(pn, tn, dim=0).norm(dim=0), (pn * tn).sum(0))
    out["normal_deg"] = float(torch.rad2deg(ang).mean())
    out["false_metal"] = float(((pred["metallic"] > 0.5) & (truth["metallic"] < 0.5)).float().mean())
    lights = synthetic.random_lights(HELD_OUT_LIGHTS, seed=seed)
    with torch.no_grad():
        ref = synthetic.render_capture(truth, lights, brdf=_brdf(model))
        est = synthetic.render_capture({k: v.float() for k, v in pred.items()}, lights)
    per = [psnr(est[i], ref[i]) for i in range(ref.shape[0])]
    out["heldout_mean_db"] = sum(per) / len(per)
    out["heldout_worst_db"] = min(per)
    return out


def _recovery_config() -> Any:
    """One thread per capture, every captured light in the fit; fields this solver lacks are left out."""
    from torchbrdf.recovery import RecoveryConfig

    names = {f.name for f in dataclasses.fields(RecoveryConfig)}
    wanted: dict[str, Any] = {"threads": 1, "holdout": -1}
    return RecoveryConfig(**{k: v for k, v in wanted.items() if k in names})


def run_case(case: PanelCase, size: int = 128, noise_seed: int = 0,
             recover_fn: Callable[[Path], Mapping[str, Tensor]] | None = None, ulp_seed: int = 0) -> dict:
    """Render, recover and score one case; returns its row (``case`` fields + metrics + seconds).

    ``recover_fn(capture_folder) -> maps`` replaces :func:`torchbrdf.recovery.recover` (tests).
    """
    with tempfile.TemporaryDirectory(prefix="panel_") as tmp:
        truth, _ = render_case(case, tmp, size, noise_seed, ulp_seed)
        t0 = time.perf_counter()
        maps: Mapping[str, Tensor]
        if recover_fn is None:
            from torchbrdf.recovery import recover

            maps = recover(tmp, _recovery_config(), progress=False, log=lambda m: None).maps
        else:
            maps = recover_fn(Path(tmp))
        seconds = time.perf_counter() - t0
    row = {"case": case.name, **dataclasses.asdict(case), "split": case.split}
    row.update(score_maps(maps, truth, case.model, seed=case_seed(case)))
    row["seconds"] = seconds
    return row


def _worker_init() -> None:
    torch.set_num_threads(1)


def _run_one(args: tuple[PanelCase, int, int, int]) -> dict:
    case, size, noise_seed, ulp_seed = args
    return run_case(case, size, noise_seed, ulp_seed=ulp_seed)


def run_panel(cases: Sequence[PanelCase], size: int = 128, workers: int = 1, noise_seed: int = 0,
              on_row: Callable[[dict], None] | None = None, ulp_seed: int = 0) -> list[dict]:
    """Run ``cases`` (``workers`` processes, one thread each); rows in the order of ``cases``."""
    jobs = [(c, size, noise_seed, ulp_seed) for c in cases]
    rows: list[dict] = []
    if workers <= 1:
        _worker_init()
        for j in jobs:
            rows.append(_run_one(j))
            if on_row:
                on_row(rows[-1])
        return rows
    with ProcessPoolExecutor(workers, initializer=_worker_init) as pool:
        for row in pool.map(_run_one, jobs):
            rows.append(row)
            if on_row:
                on_row(row)
    return rows


# --------------------------------------------------------------------------------------
# Comparison and tables
# --------------------------------------------------------------------------------------


def _band(metric: str, base: float) -> float:
    _, absolute, relative = TOLERANCES[metric]
    return max(absolute, relative * abs(base))


def compare(rows: Sequence[Mapping], baseline: Sequence[Mapping]) -> list[dict]:
    """Change of every case present in both ``rows`` and ``baseline`` (rows as :func:`run_case` gives).

    Returns one dict per shared case: ``case``, ``delta`` (metric -> new − old), ``worse`` (the
    metrics that moved the wrong way by more than their band, :data:`TOLERANCES`: ``max(absolute,
    relative × |old|)``; a held-out PSNR that was infinite counts only when it becomes finite
    and below the other's band).
    """
    old = {r["case"]: r for r in baseline}
    out = []
    for r in rows:
        if r["case"] not in old:
            continue
        b = old[r["case"]]
        delta, worse = {}, []
        for m in METRICS:
            if m not in r or m not in b:
                continue
            d = r[m] - b[m] if math.isfinite(r[m]) and math.isfinite(b[m]) else (
                0.0 if r[m] == b[m] else (-math.inf if r[m] < b[m] else math.inf))
            delta[m] = d
            if m in TOLERANCES and TOLERANCES[m][0] * d < -_band(m, b[m] if math.isfinite(b[m]) else 0.0):
                worse.append(m)
        out.append({"case": r["case"], "delta": delta, "worse": worse})
    return out


_HEAD = ("case", "base", "rough", "metal", "spec", "n°", "held dB", "worst dB", "false metal", "s")


def _cells(r: Mapping) -> list[str]:
    return [r["case"], f"{r['base_rmse']:.4f}", f"{r['roughness_rmse']:.4f}", f"{r['metallic_rmse']:.4f}",
            f"{r['specular_rmse']:.4f}", f"{r['normal_deg']:.2f}", f"{r['heldout_mean_db']:.1f}",
            f"{r['heldout_worst_db']:.1f}", f"{100 * r['false_metal']:.3f} %", f"{r['seconds']:.1f}"]


def format_rows(rows: Sequence[Mapping], markdown: bool = False) -> str:
    """The rows as an aligned text table, or a Markdown table."""
    table = [list(_HEAD)] + [_cells(r) for r in rows]
    if markdown:
        lines = ["| " + " | ".join(table[0]) + " |", "|" + "|".join("---" for _ in _HEAD) + "|"]
        return "\n".join(lines + ["| " + " | ".join(t) + " |" for t in table[1:]])
    widths = [max(len(t[i]) for t in table) for i in range(len(_HEAD))]
    return "\n".join("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(t, widths)))
                     for t in table)


def format_compare(changes: Sequence[Mapping]) -> str:
    """The changes of :func:`compare` as text, one line per case, flagged cases marked ``WORSE``."""
    lines = []
    for c in changes:
        d = c["delta"]
        parts = [f"{m} {d[m]:+.4g}" for m in METRICS if m in d]
        flag = f"  WORSE: {', '.join(c['worse'])}" if c["worse"] else ""
        lines.append(f"{c['case']}: " + ", ".join(parts) + flag)
    n = sum(bool(c["worse"]) for c in changes)
    lines.append(f"{n} of {len(changes)} cases worse beyond noise")
    return "\n".join(lines)


def _summary(rows: Sequence[Mapping]) -> str:
    if not rows:
        return "no rows"
    worst = min(r["heldout_worst_db"] for r in rows)
    fm = max(r["false_metal"] for r in rows)
    t = sorted(r["seconds"] for r in rows)
    return (f"{len(rows)} cases; worst held-out light {worst:.1f} dB; max false metal {100 * fm:.3f} %; "
            f"time min/median/max {t[0]:.1f}/{t[len(t) // 2]:.1f}/{t[-1]:.1f} s")


def _selected(name: str, only: str) -> bool:
    """Whether ``name`` contains one of the comma-separated texts of ``only`` (all: empty)."""
    return any(t in name for t in only.split(","))


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.recovery_panel",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=SPLITS, default="report", help="which seeds (default: report)")
    ap.add_argument("--size", type=int, default=128, help="capture size in pixels, square (default 128)")
    ap.add_argument("--workers", type=int, default=1, help="captures in parallel processes, one thread each")
    ap.add_argument("--quick", action="store_true", help="four small cases: a smoke test of the whole path")
    ap.add_argument("--noise-seed", type=int, default=0, help="another noise draw of the same captures")
    ap.add_argument("--ulp-seed", type=int, default=0, help="N > 0: half the image values one float32 ulp up "
                    "(the same captures but for rounding)")
    ap.add_argument("--only", default="", help="only cases whose name contains this text (or any of several, "
                    "comma separated)")
    ap.add_argument("--json", help="write the rows (and the run's settings) here")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table")
    ap.add_argument("--compare", help="a baseline JSON of an earlier run: print the change per case")
    ap.add_argument("--table", help="run nothing: print the table (and --compare) of this JSON")
    args = ap.parse_args(argv)
    if args.size < 16:
        ap.error(f"--size: at least 16 pixels, got {args.size}")
    if args.workers < 1:
        ap.error(f"--workers: at least 1, got {args.workers}")
    def read_run(flag: str, path: str) -> dict:
        try:
            run = json.loads(Path(path).read_text())
            run["rows"], run["meta"]["size"]  # noqa: B018  (both must be there)
            return run
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"{flag} {path}: not a panel JSON ({e})")

    base_run = read_run("--compare", args.compare) if args.compare else None
    baseline = base_run["rows"] if base_run else None
    if args.table:
        run = read_run("--table", args.table)
        if base_run and base_run["meta"]["size"] != run["meta"]["size"]:
            ap.error(f"--compare: {args.compare} is at {base_run['meta']['size']}², {args.table} at "
                     f"{run['meta']['size']}²; compare runs of one size")
        rows = [r for r in run["rows"] if _selected(r["case"], args.only)]
        print(format_rows(rows, args.markdown))
        print(_summary(rows))
        if baseline is not None:
            print(format_compare(compare(rows, baseline)))
        return 0
    if base_run and base_run["meta"]["size"] != args.size:
        ap.error(f"--compare: {args.compare} is at {base_run['meta']['size']}², this run at {args.size}² "
                 "(--size); compare runs of one size")
    cases = [c for c in panel_cases(args.split, args.quick) if _selected(c.name, args.only)]
    print(f"recovery panel: {len(cases)} cases, split {args.split}, {args.size}², workers {args.workers}",
          file=sys.stderr)

    t0 = time.perf_counter()
    done: list[dict] = []

    def write_json(complete: bool) -> None:
        meta = {"split": args.split, "size": args.size, "noise": NOISE, "noise_seed": args.noise_seed,
                "ulp_seed": args.ulp_seed,
                "workers": args.workers, "quick": args.quick, "only": args.only, "complete": complete,
                "cases": len(cases), "wall_seconds": time.perf_counter() - t0,
                "date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, "
                f"{os.cpu_count()} cores", "torch": torch.__version__,
                "command": "python -m torchbrdf.bench.recovery_panel " + " ".join(sys.argv[1:] if argv is None
                                                                                   else argv)}
        tmp = Path(f"{args.json}.partial")
        tmp.write_text(json.dumps({"meta": meta, "rows": done}, indent=1) + "\n")
        tmp.replace(args.json)

    def progress(row: dict) -> None:
        print(f"  {row['case']}: worst {row['heldout_worst_db']:.1f} dB, {row['seconds']:.1f} s",
              file=sys.stderr, flush=True)
        done.append(row)
        if args.json:  # after every case, so an interrupted run keeps what it measured
            write_json(False)

    rows = run_panel(cases, args.size, args.workers, args.noise_seed, on_row=progress, ulp_seed=args.ulp_seed)
    print(format_rows(rows, args.markdown))
    print(_summary(rows))
    if args.json:
        write_json(True)
    if baseline is not None:
        print(format_compare(compare(rows, baseline)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
