"""Batch SVBRDF recovery of many captures: one Ray task per capture, or sequential without Ray.

``python -m training.recover_many`` / ``torchbrdf-recover-many`` recovers every
capture folder into ``OUT/<capture folder name>/`` (the output layout of the single
recovery) and writes ``OUT/summary.json``, ``OUT/summary.csv`` and ``OUT/overview.png``.

- Each capture is one Ray task (``num_cpus = --threads-per-task``). Without ``--address`` a
  local Ray instance with ``--workers`` task slots is started; with one the job joins that
  cluster, and the capture and output folders must be on a path every node sees (a shared
  file system). Ray is optional (the ``[cluster]`` extra): without it the captures run one
  after another in this process.
- A rerun skips captures whose ``report.json`` says ``"completed": true`` and carries the
  fingerprints of the same capture and settings (those ``--resume`` checks), and resumes the
  others from their checkpoints. A task whose worker dies is retried (``--retries``, Ray's
  ``max_retries``; exceptions raised by the recovery itself are not retried). A capture that
  fails on its own (a bad file) is recorded with a one-line error; the batch goes on.
- ``--prior PATH|default`` gives every fit the learned prior (as the single command); a rerun
  with another prior, or none, recovers again.
- Ctrl-C cancels the outstanding tasks, writes the summary and leaves every finished capture
  intact (the interrupted ones keep their checkpoints for the next run).

See ``docs/cluster.md``.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import glob
import json
import math
import os
import signal
import sys
import textwrap
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from torchbrdf._types import PathLike
from torchbrdf.capture.format import CAPTURE_JSON
from torchbrdf.io import file_in_the_way
from torchbrdf.recovery.checkpoint import digest, folder_fingerprint, settings_fingerprint
from torchbrdf.recovery.checks import RecoveryError, check_config
from torchbrdf.recovery.outputs import OutputBusyError
from torchbrdf.recovery.prior import Prior
from torchbrdf.recovery.config import RecoveryConfig, Settings

__all__ = ["find_captures", "is_complete", "recover_capture", "run_batch", "write_summary", "write_overview",
           "main"]

REPORT = "report.json"
SUMMARY_FIELDS = ("name", "status", "seconds", "iterations", "final_loss", "held_out_psnr", "error",
                  "capture", "out")
#: How long a task waits for the lock of its output folder (held by a cancelled task's worker that is ending).
LOCK_WAIT_SECONDS = 60.0
# Single-recovery flags that are RecoveryConfig fields but mean something else in a batch.
_NOT_PASSED = {"threads"}  # replaced by --threads-per-task


# --------------------------------------------------------------------------------------
# Captures and completion
# --------------------------------------------------------------------------------------


def find_captures(specs: Iterable[PathLike]) -> list[Path]:
    """Capture folders named by ``specs``: folders, glob patterns, or parents of capture folders.

    A folder holding ``capture.json`` is a capture; any other folder contributes its direct
    sub-folders that hold one. Glob patterns are expanded first. Order: as given, each
    expansion sorted; duplicates dropped.

    Raises:
        FileNotFoundError: a spec matches nothing, or no capture is found at all.
        ValueError: two captures share a folder name (their outputs would collide).
    """
    found: list[Path] = []
    for spec in specs:
        spec = str(spec)
        matches = sorted(glob.glob(spec)) if glob.has_magic(spec) else [spec]
        if not matches or not all(os.path.exists(m) for m in matches):
            raise FileNotFoundError(f"--captures: {spec!r} matches no file or folder")
        for m in map(Path, matches):
            if (m / CAPTURE_JSON).is_file():
                found.append(m)
            elif m.is_dir():
                found.extend(sorted(d for d in m.iterdir() if (d / CAPTURE_JSON).is_file()))
    unique = list(dict.fromkeys(p.resolve() for p in found))
    if not unique:
        given = " ".join(map(str, specs))
        raise FileNotFoundError(f"--captures {given}: no folder holding {CAPTURE_JSON} found")
    names: dict[str, Path] = {}
    for p in unique:
        if p.name in names:
            raise ValueError(f"--captures: two captures are named {p.name!r} ({names[p.name]} and {p}); "
                             "outputs go to OUT/<folder name>, so names must be unique")
        names[p.name] = p
    return unique


def _read_report(out_dir: Path) -> dict | None:
    try:
        return json.loads((Path(out_dir) / REPORT).read_text())
    except (OSError, ValueError):
        return None


def is_complete(out_dir: PathLike, capture: PathLike | None = None,
                cfg: RecoveryConfig | None = None, prior: Prior | PathLike | None = None) -> bool:
    """Whether ``out_dir`` holds a finished recovery of ``capture`` with the settings ``cfg``.

    That is a ``report.json`` with ``"completed": true`` whose fingerprint matches the
    capture folder's current contents and the settings' result-changing fields (when
    ``capture`` / ``cfg`` are given): a capture changed since, or other settings, are not done.
    With ``cfg``, a fit made with another learned prior than ``prior`` (``None``: none) is not
    done either (its weights' checksum, :func:`~torchbrdf.recovery.api.learned_prior_checksum`;
    ``capture`` is then needed, else ``ValueError``).
    """
    rep = _read_report(Path(out_dir))
    if not (rep and rep.get("completed") is True):
        return False
    fingerprint = rep.get("fingerprint") or {}
    if capture is not None:
        now = folder_fingerprint(capture)
        if now is None or fingerprint.get("capture_sha256") != digest(now):
            return False
    if cfg is None:
        return True
    settings = fingerprint.get("settings") or {}
    if prior is None or "learned_prior" not in settings:
        return prior is None and settings == settings_fingerprint(cfg)
    if capture is None:
        raise ValueError("is_complete: telling a learned prior's fit apart needs its capture")
    from torchbrdf.recovery.api import learned_prior_checksum

    try:
        wanted = {**settings_fingerprint(cfg), "learned_prior": learned_prior_checksum(prior, capture)}
    except RecoveryError:  # a prior this capture cannot take: the task reports why
        return False
    return settings == wanted


# --------------------------------------------------------------------------------------
# One capture (runs inside a Ray task or in-process)
# --------------------------------------------------------------------------------------


def _run_single(capture: Path, out: Path, cfg: RecoveryConfig, gt: Path | None, resume: bool,
                prior: Prior | PathLike | None) -> None:
    """The one call into the single-capture API; its outputs (``out/report.json``) are the result.

    ``out`` belongs to this batch, so a lock on it is a cancelled task's worker that has not
    ended yet (Ray stops workers asynchronously): wait up to :data:`LOCK_WAIT_SECONDS` for it.
    """
    from torchbrdf.recovery.api import recover

    deadline = time.monotonic() + LOCK_WAIT_SECONDS
    while True:
        try:
            recover(capture, cfg, out, gt=gt, resume=resume, progress=False, prior=prior)
            return
        except OutputBusyError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _import_before_interrupts() -> None:
    """Take every import a recovery makes, with Ctrl-C held back until they are complete.

    Ray cancels a running task by interrupting its worker's main thread (a simulated SIGINT)
    and then reuses the worker. An interrupt that lands inside a first import leaves a
    half-imported module behind, so the next task in that worker fails: "module
    'triton.language' has no attribute 'core'" (``torch._dynamo``, slow to import, imports
    Triton when it is installed). Held back here, the interrupt is raised once the imports are
    done; later imports (the plots at the end) then find their modules whole.
    """
    held: list[int] = []
    main_thread = True
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    except ValueError:  # not the main thread: no interrupt can reach it
        main_thread = False
    try:
        import kornia.color  # noqa: F401
        import PIL.Image  # noqa: F401
        import torch._dynamo  # noqa: F401

        from torchbrdf.recovery.previews import pyplot

        pyplot()
    finally:
        if main_thread:  # None: a handler installed outside Python, which cannot be put back
            signal.signal(signal.SIGINT, signal.default_int_handler if previous is None else previous)
    if held:
        signal.raise_signal(signal.SIGINT)  # now, to whatever handled it before (ignored stays ignored)


def _kill_hook() -> None:
    """Testing: kill this worker once, as a lost node would, so that Ray's retry is exercised.

    The first task to find the file ``$TORCHBRDF_BATCH_KILL_ONCE`` removes it and exits hard.
    """
    armed = os.environ.get("TORCHBRDF_BATCH_KILL_ONCE")
    if armed:
        try:
            os.remove(armed)  # exactly one task wins the race
        except FileNotFoundError:
            return
        os._exit(1)


def _one_line(e: BaseException) -> str:
    msg = str(e).strip().splitlines()
    return f"{type(e).__name__}: {msg[0] if msg else ''}"[:300]


def _finite(x):
    return x if isinstance(x, (int, float)) and math.isfinite(x) else None


def _row(name: str, capture: Path, out: Path, status: str, error: str = "") -> dict:
    """A summary row; the numbers come from ``out/report.json`` when there is one."""
    rep = _read_report(out) or {}
    held = rep.get("held_out_light") or {}
    row = {"name": name, "status": status, "seconds": _finite(rep.get("seconds")),
           "iterations": rep.get("iterations"), "final_loss": _finite(rep.get("final_loss")),
           "held_out_psnr": _finite(held.get("psnr")), "error": error,
           "capture": str(capture), "out": str(out)}
    if rep.get("errors"):
        row["errors"] = {k: _finite(v) for k, v in rep["errors"].items()}
    return row


def _gt_folder(capture: Path, gt_name: str | None) -> Path | None:
    if gt_name is None:
        return None
    gt = capture / gt_name
    return gt if gt.is_dir() else None


def recover_capture(capture: PathLike, out_root: PathLike, cfg: RecoveryConfig, gt_name: str | None = "gt", threads: int = 1,
                    force: bool = False, prior: Prior | PathLike | None = None) -> dict:
    """Recover one capture into ``out_root/<capture name>/``; the body of each Ray task.

    Skips a completed output (unless ``force``), resumes from a checkpoint when there is one,
    and turns an exception of the recovery (a bad file, ...) into a ``"failed"`` row. A worker
    that dies never returns: Ray retries the task, which then resumes from the checkpoint.

    Returns:
        The summary row (see :data:`SUMMARY_FIELDS`; ``"errors"`` when ground truth exists).
    """
    import torch

    _import_before_interrupts()
    capture, out_root = Path(capture), Path(out_root)
    name, out = capture.name, Path(out_root) / capture.name
    if not force and is_complete(out, capture, cfg, prior):
        return _row(name, capture, out, "skipped")
    _kill_hook()
    torch.set_num_threads(max(1, int(threads)))
    cfg = dataclasses.replace(cfg, threads=max(1, int(threads)))
    # An existing output folder that is not complete was interrupted: resume from its checkpoint
    # (recover() starts from scratch, with a log line, when there is none).
    resume = not force and out.is_dir()
    try:
        _run_single(capture, out, cfg, _gt_folder(capture, gt_name), resume, prior)
    except Exception as e:  # the capture's own failure: record it, keep the batch going
        if isinstance(e, (ValueError, OSError, RecoveryError)):  # bad input: the message says what and why
            print(f"{name}: {_one_line(e)}", file=sys.stderr)
        else:  # unexpected: keep the traceback in the worker's log
            traceback.print_exc(file=sys.stderr)
        return _row(name, capture, out, "failed", _one_line(e))
    if not is_complete(out):  # stopped by a signal: partial maps + checkpoint
        return _row(name, capture, out, "interrupted", "stopped early; a rerun resumes from the checkpoint")
    return _row(name, capture, out, "done")


# --------------------------------------------------------------------------------------
# The batch
# --------------------------------------------------------------------------------------


def _import_ray():
    try:
        import ray
    except ImportError as e:
        return None, f"Ray is not installed ({e}); pip install 'torchbrdf[cluster]' to run on Ray"
    return ray, ""


def run_batch(captures: Iterable[PathLike], out: PathLike, cfg: RecoveryConfig | None = None, *, address: str | None = None,
              workers: int = 1, threads_per_task: int = 1, gpus_per_task: float = 0.0, retries: int = 3,
              gt_name: str | None = "gt", force: bool = False, use_ray: bool = True, progress: bool = True,
              log: Callable[[str], None] | None = None, prior: Prior | PathLike | None = None) -> list[dict]:
    """Recover every capture into ``out/<name>/``; write the summary files and the overview.

    Args:
        captures: capture folders (see :func:`find_captures`).
        out: output root.
        cfg: recovery options shared by every capture (same seed for each, as the single CLI).
        address: Ray cluster to join (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``);
            ``None`` starts a local Ray instance with ``workers`` task slots.
        workers: task slots of the local instance (ignored with ``address`` or ``$RAY_ADDRESS``).
        threads_per_task: torch threads of each task, and the CPUs Ray reserves for it.
        gpus_per_task: GPUs Ray reserves per task (with ``cfg.device = "cuda"``).
        retries: how often a task whose worker died is retried.
        gt_name: sub-folder of each capture holding ground-truth maps, if present (``None``: none).
        force: recover again even when a completed output exists (no resume).
        use_ray: ``False`` runs sequentially in-process; so does a missing Ray (logged).
        progress: tqdm bar over captures, with ETA.
        log: where one-line messages go (default: stderr).
        prior: the learned prior of every fit, as in :func:`~torchbrdf.recovery.recover`
            (``"default"`` picks the shipped one per capture's light count); ``None``: none.

    Returns:
        The summary rows, in the order of ``captures``. Also written to ``out/summary.json``
        and ``out/summary.csv``.

    Raises:
        KeyboardInterrupt: after Ctrl-C, once the outstanding tasks are cancelled and the
            summary (with ``"interrupted"`` rows) is written.
    """
    cfg = cfg or RecoveryConfig()
    log = log or (lambda msg: print(msg, file=sys.stderr))
    dirs = [Path(c).resolve() for c in captures]
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    ray = None
    if use_ray:
        ray, why = _import_ray()
        if ray is None:
            log(f"running sequentially in this process: {why}")
    rows: dict[int, dict] = {}
    interrupted = False
    from tqdm import tqdm

    bar = tqdm(total=len(dirs), desc="captures", unit="capture", disable=not progress, file=sys.stderr)
    # Completed captures are skipped here, without a task.
    todo = []
    for i, c in enumerate(dirs):
        if not force and is_complete(out / c.name, c, cfg, prior):
            rows[i] = _row(c.name, c, out / c.name, "skipped")
            bar.update(1)
        else:
            todo.append(i)
    try:
        if ray is None:
            _run_sequential(dirs, todo, out, cfg, gt_name, threads_per_task, force, rows, bar, prior)
        else:
            _run_ray(ray, dirs, todo, out, cfg, gt_name, address, workers, threads_per_task,
                     gpus_per_task, retries, force, rows, bar, log, prior)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
    for i, c in enumerate(dirs):
        if i not in rows:  # after Ctrl-C; a task may have finished while the others were cancelled
            rows[i] = (_row(c.name, c, out / c.name, "done") if is_complete(out / c.name) else
                       _row(c.name, c, out / c.name, "interrupted", "cancelled (Ctrl-C); a rerun resumes it"))
    result = [rows[i] for i in range(len(dirs))]
    write_summary(out, result)
    try:
        write_overview(out / "overview.png", result)
    except Exception as e:  # the overview is a convenience; the summary files are the record
        log(f"overview.png not written: {_one_line(e)}")
    counts = {s: sum(r["status"] == s for r in result) for s in ("done", "skipped", "failed", "interrupted")}
    log(", ".join(f"{n} {s}" for s, n in counts.items() if n) + f"; summary in {out / 'summary.csv'}")
    if interrupted:
        raise KeyboardInterrupt
    return result


def _run_sequential(captures, todo, out, cfg, gt_name, threads, force, rows, bar, prior):
    for i in todo:
        c = captures[i]
        bar.set_postfix_str(c.name)
        rows[i] = recover_capture(c, out, cfg, gt_name, threads, force, prior)
        bar.update(1)
        if rows[i]["status"] == "interrupted":  # recover() turned Ctrl-C into a clean stop
            raise KeyboardInterrupt


def _run_ray(ray, captures, todo, out, cfg, gt_name, address, workers, threads, gpus, retries, force,
             rows, bar, log, prior):
    started_here = not ray.is_initialized()
    address = address or os.environ.get("RAY_ADDRESS")  # as ray.init() itself would
    if started_here:
        if address:
            ray.init(address=address, log_to_driver=True)
        else:
            ray.init(num_cpus=max(1, workers) * max(1, threads), include_dashboard=False, log_to_driver=True)
    log(f"Ray: {ray.cluster_resources().get('CPU', 0):g} CPUs in the cluster, {threads} per task")
    # The driver's TORCHBRDF_* settings (backend, kernel cache, ...) apply on every node.
    env = {k: v for k, v in os.environ.items() if k.startswith("TORCHBRDF_")}
    task = ray.remote(recover_capture).options(
        name="recover_capture", num_cpus=max(1, threads), num_gpus=gpus, max_retries=max(0, retries),
        retry_exceptions=False, runtime_env={"env_vars": env} if env else None)
    prior = str(prior) if isinstance(prior, os.PathLike) else prior
    pending = {task.remote(str(captures[i]), str(out), cfg, gt_name, threads, force, prior): i for i in todo}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                i = pending.pop(ref)
                c = captures[i]
                try:
                    rows[i] = ray.get(ref)
                except ray.exceptions.RayTaskError as e:  # raised in the task, past recover_capture's net
                    rows[i] = _row(c.name, c, out / c.name, "failed", _one_line(e.cause or e))
                except ray.exceptions.RayError as e:  # the worker or node died more than --retries times
                    rows[i] = _row(c.name, c, out / c.name, "failed",
                                   f"task lost after {retries} retries: {_one_line(e)}")
                bar.set_postfix_str(c.name)
                bar.update(1)
    except KeyboardInterrupt:
        log(f"Ctrl-C: cancelling {len(pending)} outstanding task(s); finished captures are kept")
        for ref in pending:
            ray.cancel(ref)
        # Give the running ones a moment to stop (recover() saves a checkpoint on interrupt).
        ray.wait(list(pending), num_returns=len(pending), timeout=10.0)
        raise
    finally:
        if started_here:
            ray.shutdown()


# --------------------------------------------------------------------------------------
# Summary files
# --------------------------------------------------------------------------------------


def write_summary(out: PathLike, rows: list[dict]) -> None:
    """``out/summary.json`` (the rows) and ``out/summary.csv`` (one line each; errors as columns)."""
    from torchbrdf.io import atomic_path

    out = Path(out)
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(rows, indent=2) + "\n")
    err_keys = sorted({k for r in rows for k in (r.get("errors") or {})})
    with atomic_path(out / "summary.csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(list(SUMMARY_FIELDS) + err_keys)
            for r in rows:
                errs = r.get("errors") or {}
                w.writerow([_csv_value(r.get(k)) for k in SUMMARY_FIELDS]
                           + [_csv_value(errs.get(k)) for k in err_keys])


def _csv_value(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def write_overview(path: PathLike, rows: list[dict], max_rows: int = 24, thumb: int = 64) -> None:
    """Write the overview PNG: thumbnail rows per capture and a histogram of the held-out PSNR.

    Each of the first ``max_rows`` captures gets a row of base colour, roughness, metallic and
    normal thumbnails (at most ``thumb`` pixels) with its name, status and PSNR.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch.nn.functional as F

    from torchbrdf.io import atomic_path, read_exr, to_display

    shown = rows[:max_rows]
    cols = ("base_color", "roughness", "metallic", "normal")
    titles = ("base colour (sRGB)", "roughness 0-1", "metallic 0-1", "normal (n+1)/2")
    n = max(1, len(shown))
    fig = plt.figure(figsize=(7.0, 1.15 * n + 2.6))
    gs = fig.add_gridspec(n + 1, 5, height_ratios=[1.0] * n + [2.0], width_ratios=[1, 1, 1, 1, 1.5],
                          hspace=0.25, wspace=0.08)
    for r, row in enumerate(shown):
        folder = Path(row["out"])
        for c, name in enumerate(cols):
            ax = fig.add_subplot(gs[r, c])
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c], fontsize=8)
            f = folder / f"{name}.exr"
            if row["status"] in ("done", "skipped") and f.is_file():
                m = read_exr(f)
                if max(m.shape[-2:]) > thumb:
                    m = F.interpolate(m[None], size=(thumb, thumb), mode="area")[0]
                if name == "normal":
                    m = m * 0.5 + 0.5
                img = to_display(m.clamp(0, 1), srgb=(name == "base_color"))
                if img.shape[0] == 1:
                    img = img.expand(3, -1, -1)
                ax.imshow(img.permute(1, 2, 0).numpy(), interpolation="nearest")
            else:  # failed or interrupted: a grey square of the same size
                ax.imshow([[0.9]], cmap="gray", vmin=0, vmax=1)
        ax = fig.add_subplot(gs[r, 4])
        ax.axis("off")
        p = row.get("held_out_psnr")
        text = f"{row['name']}\n{row['status']}"
        if p is not None:
            text += f", {p:.1f} dB"
        if row.get("error"):
            text += "\n" + "\n".join(textwrap.wrap(row["error"], 34, max_lines=3, placeholder=" ..."))
        ax.text(0.03, 0.5, text, fontsize=6.5, va="center", transform=ax.transAxes,
                color="firebrick" if row["status"] == "failed" else "black")
    ax = fig.add_subplot(gs[n, :])
    psnrs = [r["held_out_psnr"] for r in rows if r.get("held_out_psnr") is not None]
    if psnrs:
        ax.hist(psnrs, bins=min(20, max(5, len(psnrs))), color="steelblue", edgecolor="white")
    ax.set_xlabel("held-out light PSNR (dB)")
    ax.set_ylabel("captures")
    # The default locator is a MaxNLocator (it takes integer=); the stub types it as the base Locator.
    ax.yaxis.get_major_locator().set_params(integer=True)  # type: ignore[call-arg]
    title = f"{len(psnrs)} of {len(rows)} captures with a held-out PSNR"
    if len(rows) > len(shown):
        title += f" (thumbnails: first {len(shown)})"
    ax.set_title(title, fontsize=9)
    h = fig.get_figheight()
    fig.subplots_adjust(left=0.09, right=0.98, top=1 - 0.35 / h, bottom=0.5 / h)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    from torchbrdf.recovery.options import OFF_SWITCHES
    from torchbrdf.recovery.options import build_parser as single_parser

    p = argparse.ArgumentParser(prog="torchbrdf-recover-many", description=__doc__.split("\n\n")[0],
                                allow_abbrev=False)  # --threads must not pass for --threads-per-task
    p.add_argument("--captures", nargs="+", required=True, metavar="DIR_OR_GLOB",
                   help="capture folders, glob patterns, or folders of capture folders")
    p.add_argument("--out", type=Path, required=True, help="output root: OUT/<capture name>/ + summary files")
    p.add_argument("--address", default=None,
                   help="Ray cluster to join (auto, ray://host:10001, host:6379); default: start a local one")
    p.add_argument("--workers", type=int, default=None,
                   help="task slots of the local Ray instance (default: CPU count / threads per task)")
    p.add_argument("--threads-per-task", type=int, default=1, help="torch threads (and Ray CPUs) per capture")
    p.add_argument("--gpus-per-task", type=float, default=0.0, help="GPUs per task (--device cuda)")
    p.add_argument("--retries", type=int, default=3, help="retries of a task whose worker or node died")
    p.add_argument("--gt-name", default="gt", help="ground-truth sub-folder, if present")
    p.add_argument("--no-ray", action="store_true", help="run sequentially in this process")
    p.add_argument("--force", action="store_true", help="recover completed captures again, from scratch")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    # The recovery options: the single CLI's own flags (same names, defaults and help).
    rec = p.add_argument_group("recovery options (as python -m training.recover_svbrdf)")
    fields = {f.name for f in dataclasses.fields(Settings)} - _NOT_PASSED
    for action in single_parser()._actions:
        if action.dest in fields or action.dest in OFF_SWITCHES or action.dest in ("schedule", "prior"):
            rec._add_action(action)
    return p


def config_from_args(args: argparse.Namespace) -> RecoveryConfig:
    """The :class:`RecoveryConfig` of the recovery flags in ``args``."""
    from torchbrdf.recovery.options import OFF_SWITCHES, SCHEDULE_FLAGS

    fields = {f.name for f in dataclasses.fields(Settings)} - _NOT_PASSED
    off: dict[str, Any] = {field: not getattr(args, flag) for flag, field in OFF_SWITCHES.items()}
    # (a schedule flag left out is None: the chosen schedule's value stands)
    given = {k: v for k, v in vars(args).items() if k in fields and not (k in SCHEDULE_FLAGS and v is None)}
    return RecoveryConfig(schedule=getattr(args, "schedule", "default"), **given, **off)


def _device_name(device: str) -> None:
    import torch

    try:
        torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise RecoveryError(f"--device {device!r} is not a device ({e})") from e


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point.

    Returns:
        The exit status: 0 all done or skipped, 1 some failed, 130 Ctrl-C, 2 bad arguments.
    """
    args = _parser().parse_args(argv)
    counts = (("--threads-per-task", args.threads_per_task, 1), ("--workers", args.workers, 1),
              ("--retries", args.retries, 0), ("--gpus-per-task", args.gpus_per_task, 0))
    for flag, value, least in counts:
        if value is not None and not value >= least:
            print(f"error: {flag} must be at least {least}, got {value}", file=sys.stderr)
            return 2
    try:
        cfg = config_from_args(args)
        # the single command's refusals, before any capture runs; whether the device exists is
        # for the workers to say (a CPU-only head can send --device cuda to GPU nodes)
        check_config(dataclasses.replace(cfg, device="cpu"))
        _device_name(cfg.device)
    except RecoveryError as e:
        print("error: " + " ".join(str(e).split()), file=sys.stderr)
        return 2
    if args.workers is None:
        args.workers = max(1, (os.cpu_count() or 1) // max(1, args.threads_per_task))
    try:
        captures = find_captures(args.captures)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if (blocked := file_in_the_way(args.out)) is not None:
        print(f"error: --out {args.out}: {blocked} is a file, not a folder", file=sys.stderr)
        return 2
    if args.prior not in (None, "default"):  # one refusal up front, not one failure per capture
        try:
            Prior.from_file(args.prior)
        except (OSError, ValueError) as e:
            print(f"error: --prior {args.prior}: {_one_line(e)}", file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    try:
        rows = run_batch(captures, args.out, cfg, address=args.address,
                         workers=args.workers, threads_per_task=args.threads_per_task,
                         gpus_per_task=args.gpus_per_task, retries=args.retries, gt_name=args.gt_name,
                         force=args.force, use_ray=not args.no_ray, progress=not args.quiet,
                         prior=args.prior)
    except KeyboardInterrupt:
        print("interrupted: finished captures are intact; rerun the command to continue", file=sys.stderr)
        return 130
    dt = time.perf_counter() - t0
    print(f"{len(rows)} captures in {dt:.1f} s: {args.out / 'summary.csv'}", file=sys.stderr)
    return 1 if any(r["status"] == "failed" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
