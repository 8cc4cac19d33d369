"""SVBRDF recovery's entry point: :func:`recover` checks the input, runs the solver and writes the outputs.

The algorithm (parametrisation, Levenberg–Marquardt, propagation, priors, the two
metal/dielectric hypotheses) lives in :mod:`torchbrdf.recovery.solver`; the output folder
in :mod:`~torchbrdf.recovery.outputs` (layout and guarantees: ``docs/capture_format.md``).

* **Refuse up front.** Bad settings, a capture that does not load or cannot be a capture, a
  ``--gt`` folder without maps or an output location that cannot be written give one line
  and exit status 2, and no output folder is created. A capture that loads but cannot
  determine the maps gives a warning, in the log and in ``report.json``.
* **A checkpoint knows what it belongs to** (:mod:`~torchbrdf.recovery.checkpoint`), and
  is resumed only when its checksum, schema and values check out.
* **Outputs are one unit**, and a run whose final state is not finite writes nothing.
* **Prompt stop.** SIGINT/SIGTERM stop within one inner step (the iteration in progress is
  rolled back to its start), then a checkpoint and the partial outputs are written.
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import json
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf._types import PathLike
from torchbrdf.capture.format import Capture, check_capture, load_capture
from torchbrdf.recovery.levels import render_fit
from torchbrdf.io import read_exr
from torchbrdf.recovery.checkpoint import (
    capture_differences,
    capture_fingerprint,
    checkpoint_problems,
    digest,
    settings_differences,
    settings_fingerprint,
    state_checksum,
)
from torchbrdf.recovery.checks import RecoveryError, check_config, check_gt
from torchbrdf.recovery.outputs import (
    RecoveryResult,
    check_out,
    clean_leftovers,
    commit_outputs,
    locked_out,
    write_failure,
    write_outputs,
)
from torchbrdf.recovery.progress import StageProgress, fit_losses, last_fit_loss, stage_seconds
from torchbrdf.recovery.config import RecoveryConfig, Settings, settings_of
from torchbrdf.recovery.engine import CHECKPOINT, Recovery, psnr
from torchbrdf.recovery.prior import LearnedPrior, Prior, estimator_errors, prior_maps_at

__all__ = ["recover", "save_checkpoint", "map_errors", "fractional_metallic_fraction", "learned_prior_checksum"]


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
                fm = gt_dir / "metallic.exr"
                gm = read_exr(fm) if fm.is_file() else None
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


def fractional_metallic_fraction(metallic: Tensor) -> float:
    """Fraction of the pixels of ``metallic (1, H, W)`` strictly between 0 and 1."""
    return float(((metallic > 0) & (metallic < 1)).float().mean())


class _Interrupt(BaseException):
    """Raised by the signal handler inside an iteration (rolled back by the driver)."""


def recover(capture: PathLike | Capture, config: RecoveryConfig | Settings | None = None, out: PathLike | None = None, *,
            gt: PathLike | None = None, resume: bool = False, force: bool = False, progress: bool = True,
            log: Callable[[str], None] | None = None, allow_other_files: bool = False,
            prior: Prior | PathLike | None = None) -> RecoveryResult:
    """Recover per-pixel principled maps from a capture.

    Args:
        capture: a capture folder (``capture.json`` + EXRs, see ``docs/capture_format.md``)
            or a loaded :class:`~torchbrdf.capture.Capture`.
        config: settings (default :class:`RecoveryConfig`).
        out: output folder; when given, the maps, previews, ``comparison.png``, ``loss.png``,
            ``report.json`` and ``checkpoint.pt`` are written there (as a unit).
        gt: folder of ground-truth maps; their errors go into ``report["errors"]``.
        resume: continue from ``out/checkpoint.pt`` (which must belong to this capture and,
            unless ``force``, these settings).
        force: with ``resume``, accept a checkpoint made with other settings (never another
            capture, nor another schedule: iters/size/levels).
        progress: show stage messages and a progress bar (stderr).
        log: where messages go (default: stderr).
        allow_other_files: let ``out`` hold entries a recovery did not write (they are left
            untouched; the outputs are then committed file by file). Without it such an
            ``out`` is refused.
        prior: a learned prior (:class:`~torchbrdf.recovery.Prior`, a weights file, or
            ``"default"`` for the shipped one for the capture's light count,
            :meth:`~torchbrdf.recovery.Prior.default`). The fit keeps a Gaussian pull toward the
            network's maps, with the network's measured error, that vanishes wherever the
            data determine a value, and weighs its metallic in the class choice
            (``docs/recovery.md``, "Learned prior"). None: no learned prior.

    Returns:
        A :class:`RecoveryResult`: ``maps`` (``(C, H, W)`` tensors at the capture's size),
        ``report`` (``report.json``'s contents), ``confidence`` (``(1, H, W)`` or None).

    Raises:
        TypeError: ``capture``, ``config``, ``out`` or ``gt`` of the wrong type (named).
        RecoveryError: bad settings, capture, ``gt`` or ``out`` (``rc`` 2, nothing created),
            an ``out`` another run is writing (2), a checkpoint that does not match, is
            corrupt or fails its checksum, schema or finiteness check (2), a fit whose final
            state is not finite, a full disk or another write failure (``rc`` 1; the previous
            outputs stay intact).
    """
    # Backward compatibility: recover(capture, out, cfg), the earlier argument order, still works.
    # (The annotations give only the current order, so the type checker sees this branch as unreachable.)
    if isinstance(config, (str, os.PathLike)) or isinstance(out, (RecoveryConfig, Settings)):
        config, out = out, config
    _check_argument_types(capture, config, out, gt)
    cfg = settings_of(config if config is not None else RecoveryConfig())
    log = log or (lambda msg: print(msg, file=sys.stderr))
    check_config(cfg)
    out = check_out(out, allow_other_files) if out is not None else None
    try:
        cap = capture if isinstance(capture, Capture) else load_capture(capture)
        capture_warnings = check_capture(cap)
    except (OSError, ValueError) as e:
        raise RecoveryError(str(e)) from e
    if gt is not None:
        gt = check_gt(gt, (cap.height, cap.width))
    cap = cap.to(device=cfg.device, dtype=torch.float32)
    if cfg.holdout is not None and not -1 <= cfg.holdout < len(cap):
        raise RecoveryError(f"--holdout {cfg.holdout}: the capture has {len(cap)} lights "
                            f"(0-{len(cap) - 1}, or -1 for none)")
    fingerprint = {"capture": capture_fingerprint(capture, cap), "settings": settings_fingerprint(cfg)}
    learned = None
    if prior is not None:
        if cfg.threads:  # the network's rounding follows the thread count: predict as the fit runs
            torch.set_num_threads(cfg.threads)
        resolved = _resolve_prior(prior, cap)
        learned = _learned_prior(resolved, cap, cfg.size or max(cap.width, cap.height))
        # a checkpoint made with another prior (or none) is another fit
        fingerprint["settings"]["learned_prior"] = _prior_checksum(resolved)
    if resume and out is None:
        raise RecoveryError("--resume needs --out (the folder holding checkpoint.pt)")
    for warning in capture_warnings:
        log(f"warning: {warning}")
    with contextlib.ExitStack() as held:
        if out is not None:
            try:
                out.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise RecoveryError(f"--out {out}: cannot create it ({e.strerror or e})") from e
            held.enter_context(locked_out(out))
            clean_leftovers(out, log)
        rec = _start_or_resume(cap, cfg, out, fingerprint, resume, force, log, learned)
        # torch imports torch._dynamo (seconds) on a process's first custom-op call and in its
        # Python decompositions under torch.func: take that one-time library import before the
        # clock starts, so `seconds` is the fit's own time.
        importlib.import_module("torch._dynamo")
        interrupted, seconds = _iterate_until_done_or_stopped(rec, cfg, progress, log)
        return _finish(rec, cap, cfg, out, gt, fingerprint, capture_warnings, interrupted, seconds, log)


def _check_argument_types(capture: object, config: object, out: object, gt: object) -> None:
    """Refuse an argument of the wrong type by name (pathlib's own TypeError names none).

    Raises:
        TypeError: naming the argument and what it takes.
    """
    if not isinstance(capture, (str, os.PathLike, Capture)):
        raise TypeError("recover: capture must be a capture folder (str or os.PathLike) or a "
                        f"torchbrdf.capture.Capture, got {type(capture).__name__}")
    if config is not None and not isinstance(config, (RecoveryConfig, Settings)):
        raise TypeError(f"recover: config must be a RecoveryConfig, got {type(config).__name__}")
    for name, value in (("out", out), ("gt", gt)):
        if value is not None and not isinstance(value, (str, os.PathLike)):
            raise TypeError(f"recover: {name} must be a folder path (str or os.PathLike), got {type(value).__name__}")


def learned_prior_checksum(prior: Prior | PathLike, capture: PathLike | Capture) -> str:
    """What a fit of ``capture`` with ``prior`` records as ``learned_prior`` in its settings fingerprint.

    The checksum of the estimator's weights and model card (``"default"`` resolved for the
    capture's light count): a finished fit made with another prior (or none) carries another
    value (or none), so a batch can tell it is not this fit. No network runs.

    Args:
        prior, capture: as in :func:`recover`.

    Raises:
        RecoveryError: an unreadable capture, or a ``prior`` :func:`recover` would refuse.
    """
    try:
        cap = capture if isinstance(capture, Capture) else load_capture(capture)
    except (OSError, ValueError) as e:
        raise RecoveryError(str(e)) from e
    return _prior_checksum(_resolve_prior(prior, cap))


def _prior_checksum(prior: Prior) -> str:
    # the weights, not the maps they predict: those round differently on another thread count
    return state_checksum(dict(prior.model.state_dict()), [json.dumps(prior.card, sort_keys=True, default=str)],
                          torch.zeros(0))


def _learned_prior(prior: Prior, cap: Capture, size: int) -> LearnedPrior:
    """The network's maps for ``cap`` at the working ``size``, with its card's errors."""
    with torch.no_grad():
        maps = prior.predict(cap)
    return LearnedPrior(prior_maps_at(maps, size), estimator_errors(prior.card))


def _resolve_prior(prior: Prior | PathLike, cap: Capture) -> Prior:
    """``prior`` as a :class:`Prior` for ``cap``.

    Raises:
        RecoveryError: ``prior`` is not a Prior, ``"default"`` or a readable weights file, or
            its estimator takes more images than the capture has (``rc`` 2).
    """
    if not isinstance(prior, Prior):
        if not isinstance(prior, (str, os.PathLike)):
            raise RecoveryError(f"prior: expected a Prior, a weights file or 'default', got {type(prior).__name__}")
        try:
            prior = Prior.default(len(cap)) if str(prior) == "default" else Prior.from_file(prior)
        except (OSError, ValueError) as e:
            raise RecoveryError(f"prior: {e}") from e
    if len(cap) < prior.lights:
        raise RecoveryError(f"prior: the estimator takes {prior.lights} images per capture "
                            f"(Prior.capture_lights), the capture has {len(cap)}; use a prior trained on "
                            f"{len(cap)} or fewer images")
    return prior


def _start_or_resume(cap: Capture, cfg: Settings, out: Path | None, fingerprint: dict, resume: bool,
                     force: bool, log: Callable[[str], None], prior: LearnedPrior | None = None) -> Recovery:
    """A solver at its first iteration, or restored from ``out/checkpoint.pt`` once that passes its checks."""
    ck = out / CHECKPOINT if out is not None else None
    if resume and ck is not None and not ck.is_file():
        log(f"resume: no checkpoint in {out}; starting from scratch")
        resume = False
    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    # not a setting of the result, but its rounding: a resume on another count is told so
    fingerprint["threads"] = torch.get_num_threads()
    rec = Recovery(cap, cfg, out, log, prior)
    rec.fingerprint = fingerprint  # type: ignore[attr-defined]  # stored by save_checkpoint
    if not resume:
        with torch.no_grad():
            rec.init_state()
        return rec
    forced: list[str] = []

    def check(blob):
        old = blob.get("fingerprint")
        if not old:
            raise RecoveryError(f"{ck}: made by an older version without a fingerprint; it cannot be "
                                "checked against this capture; delete it to start over")
        problems = checkpoint_problems(blob)
        if problems:
            raise RecoveryError(f"{ck}: cannot be resumed: {'; '.join(problems)}; delete it to start over")
        cdiff = capture_differences(old["capture"], fingerprint["capture"])
        if cdiff:
            raise RecoveryError(f"--resume: {ck} belongs to another capture ({'; '.join(cdiff)} differ); "
                                "use another --out or delete the checkpoint")
        sdiff = settings_differences(old["settings"], fingerprint["settings"])
        if sdiff and not force:
            raise RecoveryError(f"--resume: {ck} was made with other settings ({', '.join(sdiff)}); "
                                "pass the same settings, or --force to continue with the new ones")
        if sdiff and blob["plan"] != rec.plan:
            raise RecoveryError(f"--resume --force: {ck} has another schedule ({', '.join(sdiff)}); "
                                "iterations, size and levels cannot change in a resumed run")
        forced.extend(sdiff)
        if old.get("threads", fingerprint["threads"]) != fingerprint["threads"]:
            log(f"warning: --resume: {ck} was made with {old['threads']} thread(s), this run has "
                f"{fingerprint['threads']}; the maps will differ from an uninterrupted run's by rounding "
                "(--threads repeats a run bit for bit)")

    try:
        rec.load_checkpoint(cast(Path, ck), check=check)
    except ValueError as e:
        raise RecoveryError(str(e)) from e
    if forced:
        st0 = rec.state
        st0["events"].append({"iteration": st0["global_it"], "event": "resumed with --force",
                              "changed": forced})
        if any(d.startswith("lr ") for d in forced):
            st0["lr"] = float(cfg.lr)  # the step multiplier the run continues with
    log(f"resumed from {ck} at iteration {rec.state['global_it']}"
        + (f" with changed settings: {', '.join(forced)}" if forced else ""))
    return rec


def save_checkpoint(rec: Recovery) -> None:
    """Write ``checkpoint.pt`` through the solver, with the checksum of the state it holds.

    Raises:
        RecoveryError: the write failed (``rc`` 1, one line).
    """
    rec.fingerprint = {**rec.fingerprint,  # type: ignore[attr-defined]
                       "state_sha256": state_checksum(rec.state, rec.plan, torch.get_rng_state())}
    try:
        rec.save_checkpoint()
    except OSError as e:
        raise write_failure(e, str(rec.out / CHECKPOINT) if rec.out is not None else CHECKPOINT) from e


def _finish(rec: Recovery, cap: Capture, cfg: Settings, out: Path | None, gt: Path | None,
            fingerprint: dict, capture_warnings: list[str], interrupted: bool, seconds: float,
            log: Callable[[str], None]) -> RecoveryResult:
    """The maps, the report and (with ``out``) the committed output folder of a run that stopped."""
    st = rec.state
    final_loss = float(st["history"][-1]["loss"]) if st["history"] else float("nan")
    if not interrupted and not (math.isfinite(final_loss) and all(bool(torch.isfinite(t).all())
                                                                   for t in st["theta"])):
        kept = f"the outputs in {out} are unchanged" if out else "nothing written"
        raise RecoveryError(f"the fit ended in a non-finite state (final loss {final_loss}); {kept}", rc=1)
    with torch.no_grad():
        fin = _finite_maps(_resize_maps(rec.current_params(), cap.height, cap.width))
        pred = render_fit(fin, cap, cap.camera_position, cfg.model)
        conf_fn = getattr(rec, "confidence_map", None)  # provided by newer solvers
        confidence = conf_fn() if callable(conf_fn) else None
        if confidence is not None and tuple(confidence.shape[-2:]) != (cap.height, cap.width):
            confidence = F.interpolate(confidence.reshape(1, 1, *confidence.shape[-2:]).float(),
                                       size=(cap.height, cap.width), mode="bilinear", align_corners=False)[0]
        if confidence is not None and capture_warnings:
            confidence = torch.zeros_like(confidence)  # the capture cannot determine the maps: nothing measured
    report = {
        "iterations": int(st["global_it"]),
        "seconds": float(seconds),
        "final_loss": final_loss,
        "final_fit_loss": last_fit_loss(st["history"]),
        "completed": not interrupted,
        "model": cfg.model,
        "schedule": [{"size": s, "stage": k, "iterations": n} for s, k, n in rec.plan],
        "held_out_light": st.get("validation"),
        "metal_fraction": float(st["metal"].mean()) if st["metal"] is not None else None,
        # 0 < metallic < 1 in the written map (the soft-metal stage; the others are exactly 0 or 1)
        "fractional_metallic_fraction": fractional_metallic_fraction(fin["metallic"]),
        "soft_metal": st.get("soft_metal"),
        "events": st["events"],
        "warnings": capture_warnings,
        "seed": cfg.seed,
        "per_image_psnr": {f: psnr(pred[k], cap.images[k]) for k, f in enumerate(cap.files)},
        "loss_history": [{k: h[k] for k in ("iteration", "stage", "size", "loss", "fit", "skipped", "seconds")
                          if k in h} for h in st["history"]],
        "stage_seconds": stage_seconds(st["history"]),
        "fingerprint": {"capture_sha256": digest(fingerprint["capture"]),
                        "settings": fingerprint["settings"]},
        "light_intensity_scale": rec.light_corrections(),  # estimated / stated, per image (calibration)
        "light_position_offset": rec.light_position_corrections(),  # estimated − stated, per image
    }
    if rec.prior is not None:  # the network's errors the prior's precision came from
        report["learned_prior"] = {"map_errors": rec.prior.errors, "noise_variance": st.get("prior_noise"),
                                   "measured_map_errors": st.get("prior_map_errors"),
                                   "measured_metallic_error": st.get("prior_metallic_error")}
    cpu_maps = {k: v.cpu() for k, v in fin.items()}  # the ground truth and the files live on the CPU
    if gt is not None:
        report["errors"] = map_errors(cpu_maps, gt)
    if out is not None:
        try:
            commit_outputs(out, lambda folder: write_outputs(folder, cap, cpu_maps, pred, report,
                                                             st["history"], plots=not interrupted,
                                                             confidence=None if interrupted else confidence),
                           keep_checkpoint=interrupted)
        except OSError as e:
            raise write_failure(e, f"the outputs in {out}") from e
        if interrupted:
            log(f"interrupted at iteration {st['global_it']}: checkpoint and partial maps in {out}; "
                "rerun with --resume to continue")
        log(f"outputs written to {out}")
    return RecoveryResult(maps=fin, report=report, confidence=confidence, out=out)


def _iterate_until_done_or_stopped(rec: Recovery, cfg: Settings, progress: bool,
                                   log: Callable[[str], None]) -> tuple[bool, float]:
    """Iterate to the end or until a signal; returns ``(interrupted, seconds)``.

    A SIGINT/SIGTERM inside an iteration raises :class:`_Interrupt` at the next Python step
    (between two tensor operations — within one inner step of LM, CG or propagation); the
    iteration is rolled back to its start (state and RNG), so the checkpoint written then
    resumes bit for bit. Outside an iteration the signal only sets ``rec.stop_requested``.
    """
    in_iteration = [False]  # set while Recovery.step runs: a signal then rolls the iteration back

    def on_signal(signum, frame):
        rec.stop_requested = True
        if in_iteration[0]:
            in_iteration[0] = False
            raise _Interrupt()

    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, on_signal)
        except ValueError:  # not the main thread: no signal handling
            pass

    # Record the fit losses of a dual stage before end_stage merges its two hypotheses.
    pending = {}
    plain_end_stage = rec.end_stage

    def end_stage():
        pending["fit"] = fit_losses(rec)
        plain_end_stage()

    rec.end_stage = end_stage  # type: ignore[method-assign]
    bar = StageProgress(rec.plan, rec.state["stage"], rec.state["it"], progress, log)
    t0 = time.perf_counter() - rec.state["seconds"]
    interrupted = False

    try:
        with torch.no_grad():
            while not rec.finished() and not rec.stop_requested:
                bar.stage_start(rec.state["stage"], rec)
                snapshot = (copy.deepcopy(rec.state), torch.get_rng_state())
                pending.clear()
                t_it = time.perf_counter()  # after the rollback snapshot: the run's bookkeeping
                try:
                    in_iteration[0] = True
                    if rec.stop_requested:  # the signal came between two iterations
                        raise _Interrupt()
                    rec.step()
                    in_iteration[0] = False
                    rec.state["history"][-1]["fit"] = pending.get("fit") or fit_losses(rec)
                    # the iteration's own time; a stage's end work (class choice, fusion, soft metal,
                    # the next stage's setup: its level, tie, validation) is in its last iteration
                    rec.state["history"][-1]["seconds"] = time.perf_counter() - t_it
                except _Interrupt:
                    rec.state = snapshot[0]
                    torch.set_rng_state(snapshot[1])
                    break
                finally:
                    in_iteration[0] = False
                rec.state["seconds"] = time.perf_counter() - t0
                bar.iteration_done(rec)
                if cfg.signal_at is not None and rec.state["global_it"] == cfg.signal_at:
                    os.kill(os.getpid(), signal.SIGTERM)
                if rec.out is not None and rec.state["global_it"] % cfg.checkpoint_every == 0:
                    save_checkpoint(rec)
        interrupted = not rec.finished()
        if interrupted and rec.out is not None:
            save_checkpoint(rec)
    finally:
        bar.close()
        del rec.end_stage
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return interrupted, time.perf_counter() - t0


