"""Accuracy table of the SVBRDF recovery on synthetic captures it has never seen.

``python -m training.evaluate --out DIR [--materials N] [--size 256] [--light-study]``

For each material (recipe cycled, seeds from ``--seed0``; the recovery was tuned on seed 1),
generates a capture (``--lights`` ring lights + one beside the camera, 1 % noise), runs the
recovery with its default settings, and measures against the ground truth:

* per-map RMSE (base colour, roughness, metallic, specular — specular also on dielectric
  pixels only, since a metal's specular is invisible),
* mean and 95th-percentile normal angular error (degrees),
* PSNR of re-rendering under ``--test-lights`` random point lights that were *not* in the
  capture (peak = the ground-truth image's maximum; reported as the mean over lights and
  the worst light),
* wall time of the recovery.

Writes ``DIR/results.json`` and ``DIR/results.md`` (a Markdown table) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from torchbrdf.capture.synthetic import RECIPES, generate_capture, make_material, random_lights, render_capture
from torchbrdf.recovery.svbrdf import RecoveryConfig, keep_freed_memory, map_errors, psnr, recover

THRESHOLDS = {"base_color_rmse": 0.02, "roughness_rmse": 0.06, "metallic_rmse": 0.05, "normal_mean_deg": 1.0}
PHOTO_THRESHOLDS = {**THRESHOLDS, "roughness_rmse": 0.05}  # the photo-derived set
MIN_PSNR = {"heldout_psnr_min": 30.0}  # worst single held-out light


def heldout_psnr(maps: dict, gt: dict, n_lights: int, seed: int) -> list[float]:
    """PSNR of ``maps`` vs ``gt`` rendered under random lights not in the capture."""
    pos, inten = random_lights(n_lights, seed=seed)
    with torch.no_grad():
        ref = render_capture(gt, (pos, inten), backend="compact")
        pred = render_capture(maps, (pos, inten), backend="compact")
    return [psnr(pred[k], ref[k]) for k in range(n_lights)]


def soft_metal_fields(rep: dict, metallic, gt_metallic) -> dict:
    """The soft-metal stage's columns: the fraction of fractional pixels (report.json), the share of
    the *clear* pixels (ground truth exactly 0 or 1) given a fractional value (should stay ~0),
    and the stage's seconds. ``metallic``, ``gt_metallic``: ``(1, H, W)``."""
    m = metallic.to(gt_metallic.device)
    clear = (gt_metallic == 0) | (gt_metallic == 1)
    on_clear = (((m > 0) & (m < 1)) & clear).float().sum() / clear.float().sum().clamp(min=1)
    return {"fractional_metallic_fraction": rep.get("fractional_metallic_fraction"),
            "fractional_on_clear": float(on_clear),
            "soft_metal_seconds": (rep.get("soft_metal") or {}).get("seconds")}


def evaluate_photo(folder: Path, name: str, seed: int, size: int, lights: int, noise: float, test_lights: int,
                   calibration: bool = True, cfg: RecoveryConfig | None = None, diffuse: str = "lambert") -> dict:
    """One photo-derived capture (:mod:`training.photo_set`): recover, then errors and held-out PSNR.

    The held-out reference images are rendered by the photo set's own forward model (not the
    fitted one) from the true maps, under the ``test_lights`` random lights at their true
    positions; the recovered maps are rendered by the fitted model.
    """
    if __package__:  # python -m training.evaluate
        from training.photo_set import photo_capture, photo_material, render_other_model
    else:  # run as a file: its folder is sys.path[0]
        from photo_set import photo_capture, photo_material, render_other_model

    suffix = ("" if calibration else "_nocal") + ("" if diffuse == "lambert" else f"_{diffuse}")
    cap_dir = folder / f"photo_{name}_s{seed}_L{lights}{suffix}"
    if not (cap_dir / "capture.json").is_file():  # overwrite: what an interrupted run left
        photo_capture(cap_dir, name, seed, size, lights, noise, calibration, diffuse, overwrite=True)
    t0 = time.perf_counter()
    rep = recover(cap_dir, None, cfg or RecoveryConfig(), progress=False)
    seconds = time.perf_counter() - t0
    maps = rep["maps"]
    err = map_errors(maps, cap_dir / "gt")
    gt = photo_material(name, seed, size)
    pos, inten = random_lights(test_lights, seed=seed)
    with torch.no_grad():
        ref = render_other_model(gt, (pos, inten), diffuse=diffuse)
        pred = render_capture(maps, (pos, inten), backend="compact")
    ps = [psnr(pred[k], ref[k]) for k in range(test_lights)]
    true = torch.load(cap_dir / "true_lights.pt")
    stated = torch.tensor([30.0] * lights + [15.0])
    true_scale = (true["true_intensity"][:, 0] / stated).tolist()
    est = list(rep.get("light_intensity_scale", {}).values())
    row = {"recipe": f"photo:{name}" + ("" if diffuse == "lambert" else f" ({diffuse} diffuse)"), "seed": seed, "lights": lights, "size": size, "seconds": seconds, **err,
           "heldout_psnr_mean": statistics.mean(ps), "heldout_psnr_min": min(ps), "heldout_psnr": ps,
           "calibration_error": calibration, "true_intensity_scale": true_scale, "estimated_intensity_scale": est,
           "validation_psnr": (rep.get("held_out_light") or {}).get("psnr"), "iterations": rep["iterations"],
           **soft_metal_fields(rep, maps["metallic"], gt["metallic"])}
    return row


def evaluate_one(folder: Path, recipe: str, seed: int, size: int, lights: int, noise: float, test_lights: int,
                 cfg: RecoveryConfig | None = None) -> dict:
    cap_dir = folder / f"{recipe}_s{seed}_L{lights}"
    if not (cap_dir / "capture.json").is_file():  # overwrite: what an interrupted run left
        generate_capture(cap_dir, recipe=recipe, seed=seed, size=size, lights=lights, noise=noise,
                         overwrite=True)
    t0 = time.perf_counter()
    res = recover(cap_dir, cfg or RecoveryConfig(), progress=False)
    seconds = time.perf_counter() - t0
    rep, maps = res.report, res.maps
    err = map_errors(maps, cap_dir / "gt")
    gt = make_material(recipe, seed, size)
    ps = heldout_psnr(maps, gt, test_lights, seed)
    row = {"recipe": recipe, "seed": seed, "lights": lights, "size": size, "seconds": seconds, **err,
           "heldout_psnr_mean": statistics.mean(ps), "heldout_psnr_min": min(ps),
           "validation_psnr": (rep.get("held_out_light") or {}).get("psnr"), "iterations": rep["iterations"],
           **soft_metal_fields(rep, maps["metallic"], gt["metallic"])}
    return row


def table(rows: list[dict]) -> str:
    cols = [("recipe", "material"), ("seed", "seed")]
    if any("calibration_error" in r for r in rows):
        cols.append(("calibration_error", "calib. error"))
    cols += [("lights", "lights"), ("base_color_rmse", "base RMSE"),
            ("roughness_rmse", "rough RMSE"), ("metallic_rmse", "metal RMSE"), ("specular_rmse", "spec RMSE"),
            ("specular_rmse_dielectric", "spec RMSE (diel.)"), ("normal_mean_deg", "normal mean °"),
            ("normal_p95_deg", "normal p95 °"), ("heldout_psnr_mean", "held-out PSNR mean"),
            ("heldout_psnr_min", "held-out PSNR min"), ("fractional_metallic_fraction", "fractional px"),
            ("fractional_on_clear", "fractional on clear px"), ("seconds", "time s"),
            ("soft_metal_seconds", "soft-metal stage s")]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        thr = PHOTO_THRESHOLDS if str(r.get("recipe", "")).startswith("photo:") else THRESHOLDS
        for k, _ in cols:
            v = r.get(k)
            if isinstance(v, float):
                mark = " ✗" if (k in thr and v > thr[k]) or (k in MIN_PSNR and v < MIN_PSNR[k]) else ""
                cells.append(f"{v:.3f}{mark}" if "rmse" in k else f"{v:.4f}" if "fractional" in k
                             else f"{v:.1f}{mark}" if "seconds" not in k else f"{v:.0f}")
            else:
                cells.append("–" if v is None else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """CLI: evaluate the recovery on N unseen synthetic materials (and the light-count study)."""
    p = argparse.ArgumentParser(prog="python -m training.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for the captures, recovered maps and the table")
    p.add_argument("--materials", type=int, default=3, help="number of captures (materials) to evaluate")
    p.add_argument("--recipes", default=",".join(RECIPES), help="comma-separated recipes to cycle")
    p.add_argument("--seed0", type=int, default=100,
                   help="first material seed (seeds < 100 are the tuning set, >= 100 held out)")
    p.add_argument("--size", type=int, default=256, help="capture width and height in pixels")
    p.add_argument("--lights", type=int, default=16, help="ring lights per capture (plus one beside the camera)")
    p.add_argument("--noise", type=float, default=0.01, help="relative sensor noise (0.01 = 1 %%)")
    p.add_argument("--test-lights", type=int, default=8,
                   help="held-out point lights (not in the capture) for the held-out PSNR")
    p.add_argument("--light-study", action="store_true", help="also run 4/8/16/32 lights on the first material")
    p.add_argument("--study-counts", default="4,8,16,32", help="light counts of --light-study, comma-separated")
    p.add_argument("--threads", type=int, default=2, help="torch threads per recovery")
    p.add_argument("--no-soft-metal", action="store_true",
                   help="without the final continuous-metallic stage (metallic only 0 or 1; for comparison)")
    p.add_argument("--set", choices=("synthetic", "photo"), default="synthetic",
                   help="synthetic: the generator's recipes; photo: maps from scikit-image photographs, "
                        "another forward model, light calibration error (training/photo_set.py)")
    p.add_argument("--photos", default="glazed_brick,coffee,coins,gravel,grass", help="photo materials to cycle")
    p.add_argument("--no-calibration-error", action="store_true", help="photo set: lights exactly as stated")
    p.add_argument("--both-calibrations", action="store_true", help="photo set: each capture with and without error")
    p.add_argument("--photo-diffuse", choices=("lambert", "burley"), default="lambert",
                   help="photo set: the forward model's diffuse lobe (burley: the fitted model's, which takes "
                        "the roughness-diffuse coupling out of the mismatch)")
    args = p.parse_args(argv)
    keep_freed_memory()  # as torchbrdf-recover does, so the times are the command's
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    recipes = args.recipes.split(",")
    rows, study = [], []
    if args.set == "photo":
        if args.seed0 < 100:
            print("note: seeds < 100 are the tuning set; seeds >= 100 are held out", flush=True)
        names = args.photos.split(",")
        cals = (True, False) if args.both_calibrations else ((False,) if args.no_calibration_error else (True,))
        for k in range(args.materials):
            for cal in cals:
                rows.append(evaluate_photo(args.out, names[k % len(names)], args.seed0 + k, args.size, args.lights,
                                           args.noise, args.test_lights, cal, diffuse=args.photo_diffuse))
                print(table(rows[-1:]).splitlines()[-1], flush=True)
                _save(args.out, rows, study)
        print(table(rows))
        return 0
    for k in range(args.materials):
        recipe, seed = recipes[k % len(recipes)], args.seed0 + k
        cfg = RecoveryConfig(soft_metal=not args.no_soft_metal)
        rows.append(evaluate_one(args.out, recipe, seed, args.size, args.lights, args.noise, args.test_lights,
                                 cfg))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
        _save(args.out, rows, study)
    if args.light_study:
        for count in [int(c) for c in args.study_counts.split(",")]:
            for k in range(min(args.materials, 2)):
                recipe, seed = recipes[k % len(recipes)], args.seed0 + k
                study.append(evaluate_one(args.out, recipe, seed, args.size, count, args.noise, args.test_lights))
                print(table(study[-1:]).splitlines()[-1], flush=True)
                _save(args.out, rows, study)
    print(table(rows))
    if study:
        print(table(study))
    return 0


def _save(out: Path, rows, study):
    (out / "results.json").write_text(json.dumps({"materials": rows, "light_study": study}, indent=2))
    md = "## Accuracy on unseen materials\n\n" + table(rows) + "\n"
    if study:
        md += "\n## Light-count study\n\n" + table(study) + "\n"
    (out / "results.md").write_text(md)


if __name__ == "__main__":
    raise SystemExit(main())
