"""SVBRDF recovery: the entry point (:func:`recover`), its outputs and the ``torchbrdf-recover`` CLI.

The algorithm (parametrisation, Levenberg–Marquardt, propagation, priors, the two
metal/dielectric hypotheses) lives in :mod:`torchbrdf.recovery.solver`; this module loads the
capture, runs the solver with checkpoints and signals, and writes the output folder.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.capture.format import Capture, load_capture
from torchbrdf.capture.synthetic import render_capture, write_maps
from torchbrdf.io import atomic_path, read_exr, write_exr, write_png
from torchbrdf.recovery.solver import CHECKPOINT, Recovery, RecoveryConfig, psnr

__all__ = ["RecoveryConfig", "recover", "main", "psnr", "map_errors", "CHECKPOINT"]


# --------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------


def _finite_maps(maps: dict) -> dict:
    out = {}
    for k, v in maps.items():
        v = torch.nan_to_num(v.detach().float(), nan=0.0, posinf=1.0, neginf=0.0)
        if k == "normal":
            v = torch.where(torch.isfinite(v), v, torch.zeros_like(v))
            v[2] = v[2].clamp(min=1e-3)
            v = v / v.norm(dim=0, keepdim=True)
        else:
            v = v.clamp(0, 1)
        out[k] = v
    return out


def _resize_maps(maps: dict, h: int, w: int) -> dict:
    out = {}
    for k, v in maps.items():
        if v.shape[-2:] != (h, w):
            if k == "metallic":
                v = F.interpolate(v[None], size=(h, w), mode="nearest")[0]
            else:
                v = F.interpolate(v[None], size=(h, w), mode="bilinear", align_corners=False)[0]
            if k == "normal":
                v = v / v.norm(dim=0, keepdim=True)
        out[k] = v
    return out


def map_errors(maps: dict, gt_dir: Path) -> dict:
    """Per-map RMSE and normal angular errors against ``gt_dir/*.exr``."""
    err = {}
    for name in ("base_color", "roughness", "metallic", "specular"):
        f = gt_dir / f"{name}.exr"
        if f.is_file():
            gt = read_exr(f)
            if gt.shape[-2:] != maps[name].shape[-2:]:
                gt = F.interpolate(gt[None], size=maps[name].shape[-2:], mode="area")[0]
            err[f"{name}_rmse"] = float(((maps[name] - gt) ** 2).mean().sqrt())
            if name == "specular":
                gm = read_exr(gt_dir / "metallic.exr") if (gt_dir / "metallic.exr").is_file() else None
                if gm is not None and gm.shape[-2:] == gt.shape[-2:] and (gm < 0.5).any():
                    m = gm < 0.5
                    err["specular_rmse_dielectric"] = float(((maps[name] - gt)[m] ** 2).mean().sqrt())
    f = gt_dir / "normal.exr"
    if f.is_file():
        gt = read_exr(f)
        if gt.shape[-2:] != maps["normal"].shape[-2:]:
            gt = F.interpolate(gt[None], size=maps["normal"].shape[-2:], mode="area")[0]
            gt = gt / gt.norm(dim=0, keepdim=True)
        cos = (maps["normal"] * gt).sum(0).clamp(-1, 1)
        ang = torch.rad2deg(torch.acos(cos)).flatten()
        err["normal_mean_deg"] = float(ang.mean())
        err["normal_p95_deg"] = float(torch.quantile(ang.double(), 0.95))
    return err


def write_outputs(out: Path, cap: Capture, maps: dict, report: dict, history: list, partial: bool = False):
    """Contract §4 files: EXR maps + PNG previews, report.json, comparison and loss plot."""
    out.mkdir(parents=True, exist_ok=True)
    maps = _finite_maps(_resize_maps(maps, cap.height, cap.width))
    write_maps(out, maps, previews=True)
    if not partial:
        with torch.no_grad():
            pred = render_capture(maps, cap, cap.camera_position, backend="compact")
        report["per_image_psnr"] = {f: psnr(pred[k], cap.images[k]) for k, f in enumerate(cap.files)}
        _side_by_side(out / "comparison.png", cap.images, pred)
        _loss_plot(out / "loss.png", history)
    with atomic_path(out / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n")


def _side_by_side(path: Path, captured: Tensor, pred: Tensor, max_rows: int = 6):
    from torchbrdf.io import to_display

    n = captured.shape[0]
    pick = sorted({round(k * (n - 1) / max(1, min(n, max_rows) - 1)) for k in range(min(n, max_rows))})
    scale = float(torch.quantile(captured.flatten()[:: max(1, captured.numel() // 200000)].clamp(min=0), 0.9))
    exposure = -math.log2(max(scale, 1e-6)) - 1.0
    rows = []
    for k in pick:
        a = to_display(captured[k], exposure=exposure, tonemap="aces")
        b = to_display(pred[k], exposure=exposure, tonemap="aces")
        diff = ((pred[k] - captured[k]).abs() * 10 * 2 ** exposure).clamp(0, 1)
        rows.append(torch.cat((a, b, diff), -1))
    write_png(path, torch.cat(rows, -2), srgb=False)


def _loss_plot(path: Path, history: list):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    it = [h["iteration"] for h in history]
    loss = [h["loss"] for h in history]
    ax.semilogy(it, loss, "-o", ms=2)
    for k in range(1, len(history)):
        if history[k]["size"] != history[k - 1]["size"] or history[k]["stage"] != history[k - 1]["stage"]:
            ax.axvline(it[k] - 0.5, color="grey", lw=0.5)
            ax.text(it[k], max(loss), f"{history[k]['stage']} {history[k]['size']}", fontsize=6, rotation=90, va="top")
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean squared log residual")
    ax.set_title("SVBRDF recovery loss")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------


def recover(capture, out=None, cfg: RecoveryConfig | None = None, gt=None, resume: bool = False,
            progress: bool = True, log=None) -> dict:
    """Run the recovery on a capture folder or :class:`Capture`; write outputs when ``out`` is given.

    Returns:
        The report dict (also ``report.json``), with the maps under the ``"maps"`` key
        (not written to JSON).
    """
    cfg = cfg or RecoveryConfig()
    log = log or (lambda msg: print(msg, file=sys.stderr))
    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    cap = load_capture(capture) if not isinstance(capture, Capture) else capture
    cap = cap.to(device=cfg.device, dtype=torch.float32)
    out = Path(out) if out is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    rec = Recovery(cap, cfg, out, log)
    ck = out / CHECKPOINT if out is not None else None
    if resume and ck is not None and ck.is_file():
        rec.load_checkpoint(ck)
        log(f"resumed from {ck} at iteration {rec.state['global_it']}")
    else:
        if resume:
            log(f"--resume: no checkpoint in {out}; starting from scratch")
        with torch.no_grad():
            rec.init_state()

    def on_signal(signum, frame):
        rec.stop_requested = True

    old = {}
    if out is not None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                old[sig] = signal.signal(sig, on_signal)
            except ValueError:  # not the main thread
                pass
    total_iters = sum(p[2] for p in rec.plan)
    t0 = time.perf_counter() - rec.state["seconds"]
    interrupted = False
    try:
        from tqdm import tqdm

        bar = tqdm(total=total_iters, initial=rec.state["global_it"], disable=not progress, desc="recover",
                   file=sys.stderr)
        with torch.no_grad():
            while not rec.finished():
                rec.tick()
                if cfg.signal_at is not None and rec.state["global_it"] == cfg.signal_at:
                    os.kill(os.getpid(), signal.SIGTERM)
                rec.state["seconds"] = time.perf_counter() - t0
                h = rec.state["history"][-1]
                bar.set_postfix(loss=f"{h['loss']:.3g}", size=h["size"], stage=h["stage"])
                bar.update(1)
                if ck is not None and (rec.stop_requested or rec.state["global_it"] % cfg.checkpoint_every == 0):
                    rec.save_checkpoint()
                if rec.stop_requested:
                    interrupted = True
                    break
        bar.close()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    st = rec.state
    maps = rec.current_params()
    report = {
        "iterations": int(st["global_it"]),
        "seconds": float(time.perf_counter() - t0),
        "final_loss": float(st["history"][-1]["loss"]) if st["history"] else float("nan"),
        "completed": not interrupted,
        "model": cfg.model,
        "schedule": [{"size": s, "stage": k, "iterations": n} for s, k, n in rec.plan],
        "held_out_light": st.get("validation"),
        "metal_fraction": float(st["metal"].mean()) if st["metal"] is not None else None,
        "events": st["events"],
        "seed": cfg.seed,
        "light_intensity_scale": rec.light_corrections(),  # estimated / stated, per image (calibration)
        "light_position_offset": rec.light_position_corrections(),  # estimated − stated, per image
    }
    if out is not None:
        write_outputs(out, cap, maps, report, st["history"], partial=interrupted)
        if not interrupted:  # what the data measured (1) vs what the priors inferred (0)
            conf = _resize_maps({"c": rec.confidence_map()}, cap.height, cap.width)["c"].clamp(0, 1)
            write_exr(out / "confidence.exr", conf, channels=["Y"])
            write_png(out / "confidence.png", conf, srgb=False)
        fin = _finite_maps(_resize_maps(maps, cap.height, cap.width))
    else:
        fin = _finite_maps(_resize_maps(maps, cap.height, cap.width))
        with torch.no_grad():
            pred = render_capture(fin, cap, cap.camera_position, backend="compact")
        report["per_image_psnr"] = {f: psnr(pred[k], cap.images[k]) for k, f in enumerate(cap.files)}
    if gt is not None:
        report["errors"] = map_errors(fin, Path(gt))
        if out is not None:
            with atomic_path(out / "report.json") as tmp:
                tmp.write_text(json.dumps(report, indent=2) + "\n")
    if interrupted:
        log(f"interrupted at iteration {st['global_it']}: checkpoint and partial maps in {out}; "
            "rerun with --resume to continue")
    report["maps"] = fin
    return report


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m training.recover_svbrdf", description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--capture", type=Path, help="capture folder (capture.json + EXR images)")
    src.add_argument("--demo", action="store_true", help="use the built-in synthetic capture (generated on first use)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--gt", type=Path, help="folder of ground-truth maps (base_color.exr, ...) for errors")
    p.add_argument("--iters", type=int, default=0, help="total LM iterations (0 = default schedule, ~45)")
    p.add_argument("--lr", type=float, default=1.0, help="LM step multiplier (1 = full damped Gauss-Newton step)")
    p.add_argument("--size", type=int, default=None, help="working resolution (maps are written at capture size)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--model", choices=("principled", "svbrdf_ggx"), default="principled")
    p.add_argument("--levels", type=int, default=3, help="coarse-to-fine levels")
    p.add_argument("--prior-roughness", type=float, default=RecoveryConfig.prior_roughness, help="weight of the roughness smoothness prior")
    p.add_argument("--prior-specular", type=float, default=RecoveryConfig.prior_specular, help="weight of the specular smoothness prior")
    p.add_argument("--prior-metal-base", type=float, default=RecoveryConfig.prior_metal_base,
                   help="weight pulling a metal's base colour (F0) toward its metal neighbours")
    p.add_argument("--prior-nonlocal-base", type=float, default=RecoveryConfig.prior_nonlocal_base,
                   help="precision of the final non-local fusion of a metal's base colour (0: off)")
    p.add_argument("--holdout", type=int, default=None, help="index of the validation light (-1: none)")
    p.add_argument("--checkpoint-every", type=int, default=5)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--demo-size", type=int, default=128, help="resolution of the demo capture")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    """CLI entry point (contract §4)."""
    args = _parser().parse_args(argv)
    gt = args.gt
    if args.demo:
        from torchbrdf.capture.synthetic import default_capture

        capture = default_capture(size=args.demo_size)
        gt = gt or capture / "gt"
    else:
        capture = args.capture
    cfg = RecoveryConfig(
        iters=args.iters, lr=args.lr, size=args.size, seed=args.seed, device=args.device, levels=args.levels,
        prior_roughness=args.prior_roughness, prior_specular=args.prior_specular,
        prior_metal_base=args.prior_metal_base, prior_nonlocal_base=args.prior_nonlocal_base,
        holdout=(None if args.holdout is None else args.holdout), checkpoint_every=args.checkpoint_every,
        model=args.model, threads=args.threads,
    )
    if cfg.holdout is not None and cfg.holdout < 0:
        cfg.holdout = 10**9  # out of range: no held-out light
    try:
        report = recover(capture, args.out, cfg, gt=gt, resume=args.resume, progress=not args.quiet)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    summary = {k: report[k] for k in ("iterations", "seconds", "final_loss", "completed")}
    if report.get("held_out_light"):
        summary["held_out_psnr"] = report["held_out_light"]["psnr"]
    if "errors" in report:
        summary["errors"] = report["errors"]
    print(json.dumps(summary, indent=2))
    return 0 if report["completed"] else 130


if __name__ == "__main__":
    sys.exit(main())
