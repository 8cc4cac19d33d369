"""SVBRDF recovery: the entry point (:func:`recover`), its outputs and the ``torchbrdf-recover`` CLI.

The algorithm (parametrisation, Levenberg–Marquardt, propagation, priors, the two
metal/dielectric hypotheses) lives in :mod:`torchbrdf.recovery.solver`; this module checks
the input, loads the capture, runs the solver with checkpoints and signals, and writes the
output folder (layout: ``docs/capture_format.md``).

Guarantees (see ``docs/recovery.md``):

* **Refuse up front.** Bad settings, a capture that does not load, a ``--gt`` folder without
  maps or an output location that cannot be written give one line and exit status 2, and
  no output folder is created.
* **A checkpoint knows what it belongs to.** ``checkpoint.pt`` and ``report.json`` carry a
  fingerprint of the capture (``capture.json`` and every image's size and SHA-256) and of
  every setting that changes the result. ``--resume`` refuses another capture, and other
  settings unless ``--force`` is given.
* **Outputs are one unit.** Each run writes its outputs into a staging folder beside OUT
  and swaps it in with one atomic rename; after any interruption OUT holds one whole run,
  the previous one or the new one. Leftovers of killed runs are removed by the next run.
* **Prompt stop.** SIGINT/SIGTERM stop within one inner step (the iteration in progress is
  rolled back to its start), then a checkpoint and the partial outputs are written.
"""

from __future__ import annotations

import argparse
import atexit
import copy
import ctypes
import dataclasses
import errno
import hashlib
import importlib
import json
import math
import os
import re
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn, cast

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf._types import PathLike
from torchbrdf.capture.format import CAPTURE_JSON, Capture, load_capture
from torchbrdf.capture.synthetic import MAP_NAMES, render_capture
from torchbrdf.io import atomic_path, fsync_dir, read_exr, write_exr, write_png
from torchbrdf.recovery.config import RecoveryConfig, Settings, settings_of
from torchbrdf.recovery.engine import CHECKPOINT, Recovery, psnr

__all__ = ["RecoveryConfig", "RecoveryResult", "RecoveryError", "recover", "load_outputs", "main", "cli",
           "psnr", "map_errors", "CHECKPOINT", "REPORT"]

REPORT = "report.json"
#: Settings that do not change the result (excluded from the fingerprint).
RESULT_INDEPENDENT = frozenset({"threads", "device", "checkpoint_every", "signal_at"})


class RecoveryError(Exception):
    """A refusal or failure with a one-line message for a person.

    ``rc`` is the CLI exit status (2: refused before running — bad settings, capture,
    ``--gt`` or output location; 1: failed while running — e.g. no space left on device).
    """

    def __init__(self, message: str, rc: int = 2):
        super().__init__(message)
        self.rc = rc


@dataclass
class RecoveryResult:
    """What :func:`recover` returns.

    Attributes:
        maps: ``{"base_color": (3, H, W), "roughness": (1, H, W), "metallic": (1, H, W),
            "specular": (1, H, W), "normal": (3, H, W)}`` float32 tensors at the capture's
            size, finite (the values written to the EXRs).
        report: the contents of ``report.json`` (iterations, seconds, final_loss, completed,
            fingerprint, per_image_psnr, ...).
        confidence: per-pixel confidence ``(1, H, W)`` when the solver provides one, else None.
        out: the output folder, or None when nothing was written.
    """

    maps: dict
    report: dict
    confidence: Tensor | None = None
    out: Path | None = None

    def __getitem__(self, key: str):
        """Backward compatibility with the old dict return: ``result["maps"]``, ``result["completed"]``."""
        return self.maps if key == "maps" else self.report[key]

    def __contains__(self, key: str) -> bool:
        return key == "maps" or key in self.report

    def get(self, key: str, default: Any = None) -> Any:  # Any: a map dict or any report value
        """Backward compatibility: ``result.get("held_out_light")``."""
        return self[key] if key in self else default


# --------------------------------------------------------------------------------------
# Checking the input (before anything is created)
# --------------------------------------------------------------------------------------


def _setting(name: str) -> str:
    """How an error names a setting.

    ``lr (--lr)`` when the command line has the flag, else ``RecoveryConfig.name`` (an option of
    the Python API only) or ``Settings.name`` (a constant of the method).
    """
    flag = f"--{name.replace('_', '-')}"
    if flag in _parser()._option_string_actions:
        return f"{name} ({flag})"
    return f"RecoveryConfig.{name}" if hasattr(RecoveryConfig, name) else f"Settings.{name}"


def _finite(name: str, v, lo: float, hi: float, lo_open: bool = False) -> None:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    ok = ok and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:  # (the name is looked up in the parser only here: building it costs ~1 ms)
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise RecoveryError(f"{_setting(name)} must be a finite number in {rng}, got {v!r}")


def _integer(name: str, v, lo: int, hi: int, allow_none: bool = False) -> None:
    if v is None and allow_none:
        return
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise RecoveryError(f"{_setting(name)} must be an integer in [{lo}, {hi}], got {v!r}")


def check_config(cfg: RecoveryConfig | Settings) -> None:
    """Refuse settings that cannot give a meaningful result (one-line :class:`RecoveryError`)."""
    cfg = settings_of(cfg)
    _integer("iters", cfg.iters, 0, 1_000_000)
    _finite("lr", cfg.lr, 0.0, 2.0, lo_open=True)
    _integer("size", cfg.size, 8, 16384, allow_none=True)
    _integer("seed", cfg.seed, 0, 2**63 - 1)
    _integer("levels", cfg.levels, 1, 12)
    _integer("checkpoint_every", cfg.checkpoint_every, 1, 1_000_000)
    _integer("threads", cfg.threads, 1, 4096, allow_none=True)
    _integer("cg_iters", cfg.cg_iters, 1, 100_000)
    _integer("propagate_passes", cfg.propagate_passes, 0, 10_000)
    _finite("converge_tol", cfg.converge_tol, 0.0, 1.0)
    _integer("converge_min_iters", cfg.converge_min_iters, 1, 1_000_000)
    priors = ("prior_roughness", "prior_specular", "prior_metal_base", "prior_nonlocal_base",
              "prior_nonlocal")
    for name in priors:
        _finite(name, getattr(cfg, name), 0.0, 1e6)
    _finite("nonlocal_fit_weight", cfg.nonlocal_fit_weight, 0.0, 1e6)
    for name in ("prior_sigma", "nonlocal_range", "nonlocal_sigma"):
        _finite(name, getattr(cfg, name), 0.0, 1e6, lo_open=True)
    _finite("metal_margin", cfg.metal_margin, 0.0, 1.0, lo_open=True)
    for name in ("soft_metal_factor", "soft_metal_well", "soft_metal_gain", "soft_metal_smooth",
                 "soft_metal_edge", "soft_metal_context", "soft_metal_unmix", "soft_metal_line",
                 "soft_metal_quiet"):
        _finite(name, getattr(cfg, name), 0.0, 1e6)
    _finite("soft_metal_max", cfg.soft_metal_max, 0.0, 1.0)
    _integer("soft_metal_iters", cfg.soft_metal_iters, 0, 10_000)
    _integer("fuse_refit_iters", cfg.fuse_refit_iters, 0, 10_000)
    _integer("fuse_rounds", cfg.fuse_rounds, 1, 10_000)
    _integer("soft_metal_grow", cfg.soft_metal_grow, 0, 10_000)
    _integer("soft_metal_passes", cfg.soft_metal_passes, 0, 10_000)
    _integer("soft_metal_band", cfg.soft_metal_band, 0, 10_000)  # a max-pool half width
    _finite("rough_tie", cfg.rough_tie, 0.0, 1e6)
    _finite("rough_tie_glossy", cfg.rough_tie_glossy, 0.0, 1.0)
    _finite("rough_tie_start", cfg.rough_tie_start, 0.03, 1.0)
    _finite("soft_rough_tie", cfg.soft_rough_tie, 0.0, 1e6)
    # (a fit must stay above twice the threshold to count as rough, and start above that)
    _finite("soft_rough_tie_glossy", cfg.soft_rough_tie_glossy, 0.0, 0.45)
    if cfg.soft_rough_tie > 0 and cfg.rough_tie_start <= 2 * cfg.soft_rough_tie_glossy:
        raise RecoveryError(f"{_setting('rough_tie_start')} must be above twice "
                            f"{_setting('soft_rough_tie_glossy')} (the final stage's rough start), got "
                            f"{cfg.rough_tie_start!r} and {cfg.soft_rough_tie_glossy!r}")
    if cfg.holdout is not None and (not isinstance(cfg.holdout, int) or isinstance(cfg.holdout, bool)):
        raise RecoveryError(f"--holdout must be an integer light index, got {cfg.holdout!r}")
    if cfg.model not in ("principled", "svbrdf_ggx"):
        raise RecoveryError(f"--model must be 'principled' or 'svbrdf_ggx', got {cfg.model!r}")
    try:
        dev = torch.device(cfg.device)
    except (RuntimeError, TypeError) as e:
        raise RecoveryError(f"--device {cfg.device!r} is not a device ({e})") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RecoveryError(f"--device {cfg.device}: CUDA is not available on this machine")


def check_gt(gt: str | os.PathLike) -> Path:
    """The ground-truth folder must exist and hold at least one readable map EXR."""
    gt = Path(gt)
    if not gt.is_dir():
        raise RecoveryError(f"--gt {gt}: {'not a folder' if gt.exists() else 'does not exist'}")
    found = [n for n in MAP_NAMES if (gt / f"{n}.exr").is_file()]
    if not found:
        raise RecoveryError(f"--gt {gt}: holds none of the maps {', '.join(n + '.exr' for n in MAP_NAMES)}")
    for n in found:
        try:
            read_exr(gt / f"{n}.exr")
        except (OSError, ValueError) as e:
            raise RecoveryError(f"--gt {gt / (n + '.exr')}: unreadable ({e})") from e
    return gt


def check_out(out: str | os.PathLike) -> Path:
    """Check that ``out`` can be created and replaced as a unit; creates nothing.

    Returns the folder with symbolic links resolved (the swap replaces the real folder).
    """
    out = Path(os.path.realpath(os.fspath(out)))
    if out.exists() and not out.is_dir():
        raise RecoveryError(f"--out {out}: exists and is not a folder")
    if out.parent == out:
        raise RecoveryError(f"--out {out}: the file system root cannot be an output folder")
    cwd = Path(os.path.realpath(os.getcwd()))
    if out == cwd or out in cwd.parents:
        raise RecoveryError(f"--out {out}: is the current folder or one of its parents; "
                            "the recovery replaces its output folder as a unit, so name a folder of its own")
    if out.is_dir() and os.path.ismount(out):
        raise RecoveryError(f"--out {out}: is a mount point; name a folder inside it")
    anc = out if out.exists() else out.parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise RecoveryError(f"--out {out}: {anc} is a file, not a folder")
    need = [out.parent] if out.exists() else [anc]
    if out.exists():
        need.append(out)
    for d in need:
        if d.exists() and not os.access(d, os.W_OK | os.X_OK):
            why = "read-only file system" if _read_only(d) else "permission denied"
            raise RecoveryError(f"--out {out}: cannot write in {d} ({why})")
    return out


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


# --------------------------------------------------------------------------------------
# Fingerprints
# --------------------------------------------------------------------------------------


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def capture_fingerprint(capture: PathLike | Capture, cap: Capture) -> dict:
    """What identifies the capture.

    For a folder: ``capture.json``'s SHA-256 and each image's size and SHA-256; for an
    in-memory :class:`Capture`, the SHA-256 of its tensors.
    """
    if isinstance(capture, Capture):
        h = hashlib.sha256()
        for t in (cap.images, cap.light_positions, cap.light_intensities, cap.camera_position):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        return {"tensors": h.hexdigest()}
    folder = Path(capture)
    images = {}
    for name in cap.files:
        f = folder / name
        images[name] = {"size": f.stat().st_size, "sha256": _sha256_file(f)}
    return {CAPTURE_JSON: _sha256_file(folder / CAPTURE_JSON), "images": images}


def settings_fingerprint(cfg: RecoveryConfig | Settings) -> dict:
    """Every setting that changes the result, as JSON values: the options and the method's
    constants (:class:`Settings`), all but threads, device, checkpoint frequency and the test-only
    signal hook.
    """
    out = {}
    cfg = settings_of(cfg)
    for f in dataclasses.fields(cfg):
        if f.name not in RESULT_INDEPENDENT:
            out[f.name] = json.loads(json.dumps(getattr(cfg, f.name), default=repr))
    return out


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def _capture_differences(old: dict, new: dict) -> list[str]:
    if "tensors" in old or "tensors" in new:
        return ["the capture's images or lights"] if old != new else []
    diffs = []
    if old.get(CAPTURE_JSON) != new.get(CAPTURE_JSON):
        diffs.append(CAPTURE_JSON)
    oi, ni = old.get("images", {}), new.get("images", {})
    changed = [n for n in ni if n in oi and oi[n] != ni[n]]
    added = [n for n in ni if n not in oi]
    removed = [n for n in oi if n not in ni]
    for what, names in (("changed", changed), ("new", added), ("missing", removed)):
        if names:
            more = f" and {len(names) - 3} more" if len(names) > 3 else ""
            diffs.append(f"{what} image(s) {', '.join(names[:3])}{more}")
    return diffs


def _settings_differences(old: dict, new: dict) -> list[str]:
    keys = sorted(set(old) | set(new))
    return [f"{k} {old.get(k, '(unset)')!r} -> {new.get(k, '(unset)')!r}"
            for k in keys if old.get(k) != new.get(k)]


# --------------------------------------------------------------------------------------
# Outputs: staged, then swapped in as a unit
# --------------------------------------------------------------------------------------

#: Every file a run writes into OUT (besides checkpoint.pt); the rest of OUT is carried over.
OUTPUT_FILES = tuple([f"{n}.exr" for n in MAP_NAMES] + [f"{n}.png" for n in MAP_NAMES]
                     + ["confidence.exr", "confidence.png", "comparison.png", "loss.png", REPORT])
_TMP_FILE = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")  # atomic_path's temporaries


def _leftover_pattern(out: Path) -> re.Pattern:
    return re.compile(rf"^\.{re.escape(out.name)}\.(staging|old)-(\d+)-")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_leftovers(out: Path, log: Callable[[str], None] = lambda m: None) -> list[str]:
    """Remove what killed runs left.

    That is staging/old folders beside ``out`` (of processes that are gone) and
    atomic-write temporaries inside it. If ``out`` itself is missing because a run died
    between the two renames of a non-atomic swap, the previous outputs are put back.
    """
    removed = []
    pat = _leftover_pattern(out)
    if out.parent.is_dir():
        for p in sorted(out.parent.iterdir()):
            m = pat.match(p.name)
            if not m or _alive(int(m.group(2))):
                continue
            if m.group(1) == "old" and not out.exists():
                os.rename(p, out)
                log(f"restored the previous outputs of {out} from {p.name}")
                continue
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            removed.append(p.name)
    if out.is_dir():
        for p in out.iterdir():
            if _TMP_FILE.match(p.name) and p.is_file():
                p.unlink(missing_ok=True)
                removed.append(f"{out.name}/{p.name}")
    if removed:
        log(f"removed leftovers of interrupted runs: {', '.join(removed)}")
    return removed


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two folders (Linux ``renameat2(RENAME_EXCHANGE)``); False if unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _io_error(e: OSError, name: str) -> RecoveryError:
    if e.errno == errno.ENOSPC:
        return RecoveryError(f"no space left on device while writing {name}; earlier outputs are unchanged",
                             rc=1)
    return RecoveryError(f"cannot write {name}: {e.strerror or e}", rc=1)


class _Writing:
    """Context manager turning an ``OSError`` while writing ``name`` into a one-line message."""

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if isinstance(e, OSError):
            raise _io_error(e, self.name) from e
        return False


def _carry_over(src: Path, dst: Path) -> None:
    """Hard-link (or copy) every entry of ``src`` that a run does not write into ``dst``."""
    for p in src.iterdir():
        if p.name in OUTPUT_FILES or _TMP_FILE.match(p.name):
            continue
        target = dst / p.name
        if p.is_dir() and not p.is_symlink():
            shutil.copytree(p, target, symlinks=True, copy_function=_link_or_copy)
        else:
            _link_or_copy(p, target)


def _link_or_copy(a, b) -> None:
    if os.path.islink(a):
        os.symlink(os.readlink(a), b)
        return
    try:
        os.link(a, b)
    except OSError:
        shutil.copy2(a, b)


def commit_outputs(out: Path, write: Callable[[Path], None]) -> None:
    """Run ``write(staging)`` into a fresh folder beside ``out``, then swap it in as a unit.

    Until the swap, ``out`` is untouched; if ``write`` fails the staging folder is removed and
    ``out`` still holds the previous run. Entries of ``out`` a run does not produce (the
    checkpoint, a person's own files) are carried over by hard links.
    """
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-{os.getpid()}-", dir=out.parent))
    try:
        umask = os.umask(0)
        os.umask(umask)
        # The folder's usual mode, not mkdtemp's 0700.
        os.chmod(staging, (out.stat().st_mode & 0o7777) if out.is_dir() else (0o777 & ~umask))
        write(staging)
        if out.is_dir():
            with _Writing(f"{staging.name} (the files of {out.name} carried over)"):
                _carry_over(out, staging)
        fsync_dir(staging)
        if out.exists():
            # Fallback: two renames (a crash between them is repaired by clean_leftovers).
            if not _exchange(staging, out):
                old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-{os.getpid()}-", dir=out.parent))
                os.rmdir(old)
                os.rename(out, old)
                os.rename(staging, out)
                staging = old
        else:
            os.rename(staging, out)
        fsync_dir(out.parent)
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # the new run's leftovers, or the previous outputs


def load_outputs(out: str | os.PathLike) -> RecoveryResult:
    """Read an output folder back, checking it is one consistent run.

    Raises:
        RecoveryError: ``report.json`` is missing or unreadable, or a file differs from the
            SHA-256 the report lists for it.
    """
    out = Path(out)
    try:
        report = json.loads((out / REPORT).read_text())
    except (OSError, ValueError) as e:
        raise RecoveryError(f"{out / REPORT}: missing or unreadable ({e})") from e
    for name, digest in report.get("files", {}).items():
        f = out / name
        if not f.is_file() or _sha256_file(f) != digest:
            raise RecoveryError(f"{f}: does not belong to the run {out / REPORT} describes")
    maps = {n: read_exr(out / f"{n}.exr") for n in MAP_NAMES}
    return RecoveryResult(maps=maps, report=report, out=out)


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


def metallic_preview(metallic: Tensor) -> Tensor:
    """RGB preview ``(3, H, W)`` of ``metallic (1, H, W)``: binary pixels black (0) and white (1),
    fractional ones (0 < m < 1, the soft-metal stage's) coloured from red (m → 0) through
    orange to yellow (m → 1), so they stand out from both classes."""
    m = metallic.clamp(0, 1)
    frac = (m > 0) & (m < 1)
    tint = torch.cat((torch.ones_like(m), 0.15 + 0.85 * m, 0.1 * torch.ones_like(m)), 0)
    return torch.where(frac, tint, m.expand(3, -1, -1))


def write_outputs(folder: Path, cap: Capture, maps: dict, pred: Tensor, report: dict, history: list,
                  plots: bool = True, confidence: Tensor | None = None) -> None:
    """Write one run's files into ``folder`` (the staging folder).

    That is the EXR maps and their PNG previews, ``comparison.png``, ``loss.png`` and, last,
    ``report.json`` with every file's SHA-256. ``maps`` are finite ``(C, H, W)`` at the
    capture's size; ``pred`` the re-rendered images ``(L, 3, H, W)``; ``confidence`` the
    ``(1, H, W)`` confidence map in [0, 1] (what the data measured, 1, vs what the priors
    inferred, 0), written as ``confidence.exr`` and ``confidence.png``. ``plots=False`` (an
    interrupted run, which should exit promptly) skips the two matplotlib figures.
    """
    for name in MAP_NAMES:
        t = maps[name].detach().float().cpu()
        with _Writing(f"{name}.exr"):
            write_exr(folder / f"{name}.exr", t)
        with _Writing(f"{name}.png"):
            if name == "normal":
                write_png(folder / f"{name}.png", t * 0.5 + 0.5, srgb=False)
            elif name == "metallic":
                write_png(folder / f"{name}.png", metallic_preview(t), srgb=False)
            else:
                write_png(folder / f"{name}.png", t, srgb=(name == "base_color"))
    if confidence is not None:
        c = confidence.detach().float().cpu().clamp(0, 1).reshape(1, *confidence.shape[-2:])
        with _Writing("confidence.exr"):
            write_exr(folder / "confidence.exr", c, channels=["Y"])
        with _Writing("confidence.png"):
            write_png(folder / "confidence.png", c, srgb=False)
    if plots:
        with _Writing("comparison.png"):
            _side_by_side(folder / "comparison.png", cap, pred)
        with _Writing("loss.png"):
            _loss_plot(folder / "loss.png", history)
    report["files"] = {p.name: _sha256_file(p) for p in sorted(folder.iterdir()) if p.name in OUTPUT_FILES}
    with _Writing(REPORT), atomic_path(folder / REPORT) as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _side_by_side(path: Path, cap: Capture, pred: Tensor, max_rows: int = 6) -> None:
    """Captured / re-rendered / 10×|difference| for up to ``max_rows`` lights, labelled.

    The panels are composed into one mosaic shown in a single axes at one figure pixel per
    image pixel: 18 separate axes cost most of a second to lay out and draw.
    """
    from torchbrdf.io import to_display

    captured = cap.images.detach().float().cpu()
    pred = pred.detach().float().cpu()
    n, _, h, w = captured.shape
    if max(h, w) > 256:  # panels of at most 256 px: a figure, not a second copy of the images
        h, w = max(1, round(h * 256 / max(h, w))), max(1, round(w * 256 / max(h, w)))
        captured = F.interpolate(captured, size=(h, w), mode="area")
        pred = F.interpolate(pred, size=(h, w), mode="area")
    elif max(h, w) < 200:  # and at least 200 px (pixel-replicated), room for the labels
        k = math.ceil(200 / max(h, w))
        captured = captured.repeat_interleave(k, -1).repeat_interleave(k, -2)
        pred = pred.repeat_interleave(k, -1).repeat_interleave(k, -2)
        h, w = h * k, w * k
    pick = sorted({round(k * (n - 1) / max(1, min(n, max_rows) - 1)) for k in range(min(n, max_rows))})
    scale = float(torch.quantile(captured.flatten()[:: max(1, captured.numel() // 200000)].clamp(min=0), 0.9))
    exposure = -math.log2(max(scale, 1e-6)) - 1.0
    gap = max(2, w // 64)  # white gutter between panels
    mosaic = torch.ones(3, len(pick) * (h + gap) - gap, 3 * (w + gap) - gap)
    for r, k in enumerate(pick):
        a = to_display(captured[k], exposure=exposure, tonemap="aces")
        b = to_display(pred[k], exposure=exposure, tonemap="aces")
        d = ((pred[k] - captured[k]).abs() * 10 * 2**exposure).clamp(0, 1)
        for c, img in enumerate((a, b, d)):
            y, x = r * (h + gap), c * (w + gap)
            mosaic[:, y:y + h, x:x + w] = img
    plt = _pyplot()
    dpi = 100
    margin_l, margin_t, margin_b = 1.1, 0.55, 0.1  # inches: row labels, column titles + title
    iw, ih = mosaic.shape[2] / dpi, mosaic.shape[1] / dpi
    fig = plt.figure(figsize=(iw + margin_l + 0.1, ih + margin_t + margin_b), dpi=dpi)
    ax = fig.add_axes((margin_l / fig.get_figwidth(), margin_b / fig.get_figheight(),
                       iw / fig.get_figwidth(), ih / fig.get_figheight()))
    ax.imshow(mosaic.permute(1, 2, 0).numpy(), interpolation="nearest")
    cols = ("captured", "re-rendered from the maps", "|difference| × 10")
    ax.xaxis.tick_top()
    ax.set_xticks([c * (w + gap) + w / 2 for c in range(3)], cols, fontsize=9)
    ax.set_yticks([r * (h + gap) + h / 2 for r in range(len(pick))],
                  [f"light {k}\n{cap.files[k]}" for k in pick], fontsize=8)
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    fig.suptitle(f"Fit check, {len(pick)} of {n} lights (exposure {exposure:+.1f} EV, ACES tone map; "
                 "difference at the same exposure)", fontsize=8, y=1 - 0.08 / fig.get_figheight(), va="top")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", pil_kwargs={"compress_level": 3})
    plt.close(fig)


_LOSS_LABEL = "fit loss: mean squared log residual\n(per pixel, training light and channel)"


def _loss_plot(path: Path, history: list) -> None:
    """Plot the fit loss per iteration.

    Both hypotheses and each pixel's better one in the dual stages, the chosen class
    afterwards; stage boundaries marked.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.6))
    it = [h["iteration"] for h in history]
    fit = [h.get("fit", {}) for h in history]

    def series(key):
        return [f.get(key, float("nan")) for f in fit]

    best = [f.get("best", f.get("chosen", float("nan"))) for f in fit]
    if any("dielectric" in f for f in fit):
        ax.semilogy(it, series("dielectric"), "--", color="tab:blue",
                    label="dielectric hypothesis (dual stages)")
        ax.semilogy(it, series("metal"), ":", color="tab:orange", label="metal hypothesis (dual stages)")
    ax.semilogy(it, best, "-o", ms=2.5, color="black",
                label="each pixel's better hypothesis (dual) / its chosen class (after)")
    finite = [v for v in series("dielectric") + series("metal") + best if math.isfinite(v) and v > 0]
    k = 0  # the first iteration of each stage run
    for run in stage_seconds(history):
        if k:
            ax.axvline(it[k] - 0.5, color="grey", lw=0.6)
        ax.text(it[k] - 0.3, 0.97, f"{run['stage']} {run['size']}²", fontsize=7, rotation=90,
                va="top", ha="left", transform=ax.get_xaxis_transform(), color="dimgrey", clip_on=True)
        k += run["iterations"]
    if it:
        ax.set_xlim(min(it) - 0.6, max(it) + 0.6)
    if finite:
        ax.set_ylim(min(finite) / 1.5, max(finite) * 3)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("LM iteration (all stages)")
    ax.set_ylabel(_LOSS_LABEL, fontsize=8)
    ax.set_title("SVBRDF recovery: fit loss per iteration (stage and level size marked)", fontsize=9)
    ax.grid(True, which="major", alpha=0.3)
    # Below the axes, where it hides no curve.
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


# --------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------

_STAGE_TEXT = {
    "dual": "both hypotheses side by side (dielectric: metallic 0; metal: metallic 1), LM on base colour, "
            "specular, roughness and normal; each pixel's class is chosen at the end",
    "polish": "each pixel's chosen class only, LM plus neighbour propagation",
    "all": "every light, the held-out validation light included",
}


class _Progress:
    """Stage messages and a bar whose ETA comes from per-stage costs.

    One iteration of a stage costs about (pixels × hypotheses) work units; the bar advances
    in those units, so its average rate (tqdm ``smoothing=0``) predicts the later, larger
    stages instead of jumping when a level four times the size starts.
    """

    def __init__(self, plan, stage: int, it: int, enabled: bool, write: Callable[[str], None]):
        self.plan = plan
        self.units = [s * s * (2 if kind == "dual" else 1) for s, kind, _ in plan]
        self.total_iters = sum(p[2] for p in plan)
        # Where a resumed run starts: by stage and iteration, not by iterations run (a converged
        # stage skipped its rest).
        done = sum(u * p[2] for u, p in zip(self.units[:stage], plan[:stage]))
        done += it * self.units[stage] if stage < len(plan) else 0
        self.done = done  # work units
        self.enabled = enabled
        self.bar = None
        self.write = write
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=sum(u * p[2] for u, p in zip(self.units, plan)), initial=done, smoothing=0,
                            file=sys.stderr, desc="recover", dynamic_ncols=True,
                            bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")
            bar = self.bar
            self.write = lambda msg: bar.write(msg, file=sys.stderr)  # tqdm.write defaults to stdout
            self.write("fit loss (bar and loss.png) = mean squared log residual per pixel, training light "
                       "and channel; in the dual stages, of each pixel's better hypothesis")
        self.stage: int | None = None

    def stage_start(self, stage: int, rec: Recovery) -> None:
        if not self.enabled or stage == self.stage:
            return
        self.stage = stage
        size, kind, n = self.plan[stage]
        extra = ""
        if kind != "dual" and _state(rec).get("metal") is not None:
            extra = f" ({100 * float(_state(rec)['metal'].mean()):.0f}% of pixels metal)"
        start = ("" if kind == "all" else "; its first iteration also propagates neighbours' parameters and "
                 "searches normals, so it takes longer")
        upto = "up to " if size == self.plan[-1][0] and rec.cfg.converge_tol > 0 else ""
        if self.bar is not None:  # the last stage's final iteration first, then this stage's header
            self.bar.refresh()
            self.bar.set_description_str(f"stage {stage + 1}/{len(self.plan)} ({kind} {size}²) starting",
                                         refresh=False)
        self.write(f"stage {stage + 1}/{len(self.plan)}: {size}×{size} px, {upto}{n} iterations — "
                   f"{kind}: {_STAGE_TEXT.get(kind, kind)}{extra}{start}")

    def tick(self, rec: Recovery) -> None:
        if self.bar is None:
            return
        st = _state(rec)
        h = st["history"][-1]
        stage = min(st["stage"], len(self.plan)) - (1 if st["it"] == 0 else 0)
        stage = max(0, min(stage, len(self.plan) - 1))
        fit = h.get("fit", {})
        loss = fit.get("best", fit.get("chosen", h["loss"]))
        self.bar.set_description_str(f"iteration {st['global_it']}/{self.total_iters} "
                                     f"({h['stage']} {h['size']}², fit loss {loss:.3g})", refresh=False)
        self.bar.update(self.units[stage] * (1 + h.get("skipped", 0)))  # a converged stage's rest at once

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _state(rec: Recovery) -> dict[str, Any]:
    """The solver's state dict (set by ``init_state`` or ``load_checkpoint``)."""
    return rec.state


def _fit_losses(rec: Recovery) -> dict:
    """Data-only fit loss of the current state on the training lights.

    The quantity the bar and ``loss.png`` show: per hypothesis and per pixel's better one in a dual stage, the
    chosen class otherwise. Mean over pixels of the squared log residual per light and channel.
    It is the last LM step's (``rec.fit_cost``, no extra render); a state without one is rendered.
    """
    st = _state(rec)
    fc = rec.fit_cost
    if len(fc) == len(st["theta"]) and all(v.shape[0] == st["theta"][0].shape[0] for v in fc.values()):
        return rec.fit_summary()
    size, kind, _ = rec.plan[min(st["stage"], len(rec.plan) - 1)]
    data = rec.data(size)
    n = max(1, len(data.train_idx) * 3)

    def cost(theta, metal):
        r = data.residual(theta, metal, data.train_idx, rec.cfg.model)
        return torch.nan_to_num((r * r).sum(-1), nan=float("inf")) / n

    if len(st["theta"]) == 2:
        ones = torch.ones_like(st["lam"][0])
        cd, cm = cost(st["theta"][0], 0 * ones), cost(st["theta"][1], ones)
        best = float(torch.minimum(cd, cm).mean())  # each pixel's better hypothesis
        return {"dielectric": float(cd.mean()), "metal": float(cm.mean()), "best": best}
    return {"chosen": float(cost(st["theta"][0], st["metal"]).mean())}


class _Interrupt(BaseException):
    """Raised by the signal handler inside an iteration (rolled back by the driver)."""


# --------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------


def recover(capture: PathLike | Capture, config: RecoveryConfig | Settings | None = None, out: PathLike | None = None, *, gt: PathLike | None = None, resume: bool = False,
            force: bool = False, progress: bool = True,
            log: Callable[[str], None] | None = None) -> RecoveryResult:
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

    Returns:
        A :class:`RecoveryResult`: ``maps`` (``(C, H, W)`` tensors at the capture's size),
        ``report`` (``report.json``'s contents), ``confidence`` (``(1, H, W)`` or None).

    Raises:
        RecoveryError: bad settings, capture, ``gt`` or ``out`` (``rc`` 2, nothing created), a
            checkpoint that does not match or is corrupt (2), a full disk or another write
            failure (``rc`` 1; the previous outputs stay intact).
    """
    # Backward compatibility: the old order was recover(capture, out, cfg). (The annotations give
    # only the current order, so the type checker sees this branch as unreachable.)
    if isinstance(config, (str, os.PathLike)) or isinstance(out, (RecoveryConfig, Settings)):
        config, out = out, config
    cfg = settings_of(config or RecoveryConfig())
    log = log or (lambda msg: print(msg, file=sys.stderr))
    check_config(cfg)
    out = check_out(out) if out is not None else None
    if gt is not None:
        gt = check_gt(gt)
    try:
        cap = capture if isinstance(capture, Capture) else load_capture(capture)
    except (OSError, ValueError) as e:
        raise RecoveryError(str(e)) from e
    cap = cap.to(device=cfg.device, dtype=torch.float32)
    if cfg.holdout is not None and not -1 <= cfg.holdout < len(cap):
        raise RecoveryError(f"--holdout {cfg.holdout}: the capture has {len(cap)} lights "
                            f"(0-{len(cap) - 1}, or -1 for none)")
    fingerprint = {"capture": capture_fingerprint(capture, cap), "settings": settings_fingerprint(cfg)}
    if resume and out is None:
        raise RecoveryError("--resume needs --out (the folder holding checkpoint.pt)")
    ck = out / CHECKPOINT if out is not None else None
    if resume and ck is not None and not ck.is_file():
        log(f"--resume: no checkpoint in {out}; starting from scratch")
        resume = False

    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    rec = Recovery(cap, cfg, out, log)
    rec.fingerprint = fingerprint  # type: ignore[attr-defined]  # stored by save_checkpoint
    forced = []
    if resume:
        def check(blob):
            old = blob.get("fingerprint")
            if not old:
                raise RecoveryError(f"{ck}: made by an older version without a fingerprint; it cannot be "
                                    "checked against this capture; delete it to start over")
            cdiff = _capture_differences(old["capture"], fingerprint["capture"])
            if cdiff:
                raise RecoveryError(f"--resume: {ck} belongs to another capture ({'; '.join(cdiff)} differ); "
                                    "use another --out or delete the checkpoint")
            sdiff = _settings_differences(old["settings"], fingerprint["settings"])
            if sdiff and not force:
                raise RecoveryError(f"--resume: {ck} was made with other settings ({', '.join(sdiff)}); "
                                    "pass the same settings, or --force to continue with the new ones")
            if sdiff and blob["plan"] != rec.plan:
                raise RecoveryError(f"--resume --force: {ck} has another schedule ({', '.join(sdiff)}); "
                                    "iterations, size and levels cannot change in a resumed run")
            forced.extend(sdiff)

        try:
            rec.load_checkpoint(cast(Path, ck), check=check)
        except ValueError as e:
            raise RecoveryError(str(e)) from e
        if forced:
            st0 = _state(rec)
            st0["events"].append({"iteration": st0["global_it"], "event": "resumed with --force",
                                  "changed": forced})
            if any(d.startswith("lr ") for d in forced):
                st0["lr"] = float(cfg.lr)  # the step multiplier the run continues with
        log(f"resumed from {ck} at iteration {_state(rec)['global_it']}"
            + (f" with changed settings: {', '.join(forced)}" if forced else ""))
    else:
        with torch.no_grad():
            rec.init_state()

    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RecoveryError(f"--out {out}: cannot create it ({e.strerror or e})") from e
        clean_leftovers(out, log)
    # torch imports torch._dynamo (about 1.4 s) on a process's first custom-op call and in its
    # Python decompositions under torch.func: take that one-time library import before the
    # clock starts, so `seconds` is the fit's own time.
    importlib.import_module("torch._dynamo")

    interrupted, seconds = _run(rec, cfg, ck, progress, log)

    st = _state(rec)
    with torch.no_grad():
        fin = _finite_maps(_resize_maps(rec.current_params(), cap.height, cap.width))
        pred = render_capture(fin, cap, cap.camera_position, backend="compact")
        conf_fn = getattr(rec, "confidence_map", None)  # provided by newer solvers
        confidence = conf_fn() if callable(conf_fn) else None
        if confidence is not None and tuple(confidence.shape[-2:]) != (cap.height, cap.width):
            confidence = F.interpolate(confidence.reshape(1, 1, *confidence.shape[-2:]).float(),
                                       size=(cap.height, cap.width), mode="bilinear", align_corners=False)[0]
    report = {
        "iterations": int(st["global_it"]),
        "seconds": float(seconds),
        "final_loss": float(st["history"][-1]["loss"]) if st["history"] else float("nan"),
        "final_fit_loss": _last_fit(st["history"]),
        "completed": not interrupted,
        "model": cfg.model,
        "schedule": [{"size": s, "stage": k, "iterations": n} for s, k, n in rec.plan],
        "held_out_light": st.get("validation"),
        "metal_fraction": float(st["metal"].mean()) if st["metal"] is not None else None,
        # 0 < metallic < 1 in the written map (the soft-metal stage; the others are exactly 0 or 1)
        "fractional_metallic_fraction": fractional_metallic_fraction(fin["metallic"]),
        "soft_metal": st.get("soft_metal"),
        "events": st["events"],
        "seed": cfg.seed,
        "per_image_psnr": {f: psnr(pred[k], cap.images[k]) for k, f in enumerate(cap.files)},
        "loss_history": [{k: h[k] for k in ("iteration", "stage", "size", "loss", "fit", "skipped", "seconds")
                          if k in h} for h in st["history"]],
        "stage_seconds": stage_seconds(st["history"]),
        "fingerprint": {"capture_sha256": _digest(fingerprint["capture"]),
                        "settings": fingerprint["settings"]},
        "light_intensity_scale": rec.light_corrections(),  # estimated / stated, per image (calibration)
        "light_position_offset": rec.light_position_corrections(),  # estimated − stated, per image
    }
    cpu_maps = {k: v.cpu() for k, v in fin.items()}  # the ground truth and the files live on the CPU
    if gt is not None:
        report["errors"] = map_errors(cpu_maps, gt)
    if out is not None:
        try:
            commit_outputs(out, lambda folder: write_outputs(folder, cap, cpu_maps, pred, report,
                                                             st["history"], plots=not interrupted,
                                                             confidence=None if interrupted else confidence))
        except OSError as e:
            raise _io_error(e, f"the outputs in {out}") from e
        if interrupted:
            log(f"interrupted at iteration {st['global_it']}: checkpoint and partial maps in {out}; "
                "rerun with --resume to continue")
        log(f"outputs written to {out}")
    return RecoveryResult(maps=fin, report=report, confidence=confidence, out=out)


def stage_seconds(history: list) -> list[dict]:
    """Where a run's time went: one entry per stage run, in order.

    ``history``: the solver's per-iteration records (``size``, ``stage`` and, from runs that
    time their iterations, ``seconds``: the iteration with its stage's end work and the next
    stage's setup). Consecutive records of one (size, stage) form an entry. Returns
    ``[{"size", "stage", "iterations", "seconds"}]``; a stage with any iteration without a time
    (one run before a resume from a checkpoint of an older version) has ``seconds`` None.
    """
    out: list[dict] = []
    for h in history:
        if not out or (out[-1]["size"], out[-1]["stage"]) != (h["size"], h["stage"]):
            out.append({"size": h["size"], "stage": h["stage"], "iterations": 0, "seconds": 0.0})
        e = out[-1]
        e["iterations"] += 1
        t = h.get("seconds")
        e["seconds"] = None if t is None or e["seconds"] is None else e["seconds"] + t
    return out


def _last_fit(history: list) -> float | None:
    if not history or "fit" not in history[-1]:
        return None
    f = history[-1]["fit"]
    return float(f.get("best", f.get("chosen", float("nan"))))


def _run(rec: Recovery, cfg: Settings, ck: Path | None, progress: bool, log) -> tuple[bool, float]:
    """Iterate to the end or until a signal; returns ``(interrupted, seconds)``.

    A SIGINT/SIGTERM inside an iteration raises :class:`_Interrupt` at the next Python step
    (between two tensor operations — within one inner step of LM, CG or propagation); the
    iteration is rolled back to its start (state and RNG), so the checkpoint written then
    resumes bit for bit. Outside an iteration the signal only sets ``rec.stop_requested``.
    """
    in_tick = [False]

    def on_signal(signum, frame):
        rec.stop_requested = True
        if in_tick[0]:
            in_tick[0] = False
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
        pending["fit"] = _fit_losses(rec)
        plain_end_stage()

    rec.end_stage = end_stage  # type: ignore[method-assign]
    bar = _Progress(rec.plan, _state(rec)["stage"], _state(rec)["it"], progress, log)
    t0 = time.perf_counter() - _state(rec)["seconds"]
    interrupted = False

    def save():
        try:
            rec.save_checkpoint()
        except OSError as e:
            raise _io_error(e, str(ck)) from e

    try:
        with torch.no_grad():
            while not rec.finished() and not rec.stop_requested:
                bar.stage_start(_state(rec)["stage"], rec)
                snapshot = (copy.deepcopy(_state(rec)), torch.get_rng_state())
                pending.clear()
                t_it = time.perf_counter()  # after the rollback snapshot: the run's bookkeeping
                try:
                    in_tick[0] = True
                    if rec.stop_requested:  # the signal came between two iterations
                        raise _Interrupt()
                    rec.tick()
                    in_tick[0] = False
                    _state(rec)["history"][-1]["fit"] = pending.get("fit") or _fit_losses(rec)
                    # the iteration's own time; a stage's end work (class choice, fusion, soft metal,
                    # the next stage's setup: its level, tie, validation) is in its last iteration
                    _state(rec)["history"][-1]["seconds"] = time.perf_counter() - t_it
                except _Interrupt:
                    rec.state = snapshot[0]
                    torch.set_rng_state(snapshot[1])
                    break
                finally:
                    in_tick[0] = False
                _state(rec)["seconds"] = time.perf_counter() - t0
                bar.tick(rec)
                if cfg.signal_at is not None and _state(rec)["global_it"] == cfg.signal_at:
                    os.kill(os.getpid(), signal.SIGTERM)
                if ck is not None and _state(rec)["global_it"] % cfg.checkpoint_every == 0:
                    save()
        interrupted = not rec.finished()
        if interrupted and ck is not None:
            save()
    finally:
        bar.close()
        del rec.end_stage
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return interrupted, time.perf_counter() - t0


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of the usage block
        self.exit(2, f"error: {message} (see --help)\n")


def _parser() -> argparse.ArgumentParser:
    d = RecoveryConfig()
    p = _Parser(
        prog="torchbrdf-recover",
        description="Recover per-pixel principled BRDF maps (base colour, roughness, metallic, specular, "
                    "normal) from a multi-light capture. Also run as `python -m training.recover_svbrdf`. "
                    "Input format and output layout: docs/capture_format.md. Exit status: 0 done, "
                    "2 refused (bad option, capture, --gt or --out), 1 failed while running "
                    "(e.g. disk full), "
                    "130 interrupted (rerun with --resume).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--capture", type=Path, help="capture folder (capture.json + one EXR per light)")
    src.add_argument("--demo", action="store_true",
                     help="use the built-in synthetic capture (generated on first use, cached; no network)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (replaced as a unit at the end; other files in it are kept)")
    p.add_argument("--gt", type=Path,
                   help="folder of ground-truth maps (base_color.exr, ...) to report errors against")
    p.add_argument("--iters", type=int, default=d.iters,
                   help="total LM iterations planned, spread over the stages (0 = the default schedule, 39); "
                        "converged full-resolution stages end early (--converge-tol)")
    p.add_argument("--lr", type=float, default=d.lr,
                   help="LM step multiplier in (0, 2] (1 = full damped Gauss-Newton step)")
    p.add_argument("--size", type=int, default=d.size,
                   help="working resolution in pixels (default: the capture's; "
                        "maps are written at capture size)")
    p.add_argument("--seed", type=int, default=d.seed,
                   help="random seed (the run is deterministic for a seed)")
    p.add_argument("--device", default=d.device, help="torch device to run on, e.g. cpu or cuda")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt "
                        "(refused if it belongs to another capture or settings)")
    p.add_argument("--force", action="store_true",
                   help="with --resume: continue even if settings differ (never for another capture)")
    p.add_argument("--model", choices=("principled", "svbrdf_ggx"), default=d.model,
                   help="BRDF model fitted (default principled)")
    p.add_argument("--levels", type=int, default=d.levels, help="coarse-to-fine levels (1-12)")
    p.add_argument("--converge-tol", type=float, default=d.converge_tol,
                   help="a full-resolution stage ends once an iteration changes its fit loss by less than this "
                        "fraction (default %(default)s; 0 runs every planned iteration)")
    p.add_argument("--converge-min-iters", type=int, default=d.converge_min_iters,
                   help="... but not before this many of its iterations (default %(default)s)")
    p.add_argument("--prior-roughness", type=float, default=d.prior_roughness,
                   help="weight of the roughness smoothness prior (>= 0)")
    p.add_argument("--prior-specular", type=float, default=d.prior_specular,
                   help="weight of the specular smoothness prior (>= 0)")
    p.add_argument("--prior-metal-base", type=float, default=d.prior_metal_base,
                   help="weight pulling a metal's base colour (F0) toward its metal neighbours (>= 0)")
    p.add_argument("--prior-nonlocal-base", type=float, default=d.prior_nonlocal_base,
                   help="precision of the final non-local fusion of a metal's base colour (0: off)")
    p.add_argument("--no-soft-metal", action="store_true",
                   help="no final continuous-metallic step: every pixel's metallic is exactly 0 or 1")
    p.add_argument("--no-light-calibration", action="store_true",
                   help="trust capture.json's light intensities and positions as stated (default: estimate "
                        "a per-light intensity scale and position offset with the maps)")
    p.add_argument("--no-light-position", action="store_true",
                   help="estimate only the per-light intensity scales, not the position offsets")
    p.add_argument("--holdout", type=int, default=None,
                   help="index of the validation light held out of the fit until the last stage "
                        "(default: light 0 with 5+ lights; -1: none)")
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                   help="write OUT/checkpoint.pt every N iterations (>= 1; also on SIGINT/SIGTERM)")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for torch (default: torch's choice)")
    p.add_argument("--demo-size", type=int, default=128, help="resolution of the --demo capture (16-4096)")
    p.add_argument("--quiet", action="store_true", help="no stage messages or progress bar")
    return p


# The command line's switches that turn a default-on setting off: flag dest -> RecoveryConfig field.
OFF_SWITCHES = {"no_soft_metal": "soft_metal", "no_light_calibration": "light_scale",
                "no_light_position": "light_position"}


def main(argv: Sequence[str] | None = None) -> int:
    """``torchbrdf-recover`` / ``python -m training.recover_svbrdf``; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a malformed option (2, one line already printed)
        return int(e.code or 0)
    try:
        off: dict[str, Any] = {field: not getattr(args, flag) for flag, field in OFF_SWITCHES.items()}
        cfg = RecoveryConfig(
            iters=args.iters, lr=args.lr, size=args.size, seed=args.seed, device=args.device,
            levels=args.levels, prior_roughness=args.prior_roughness, prior_specular=args.prior_specular,
            prior_metal_base=args.prior_metal_base, prior_nonlocal_base=args.prior_nonlocal_base,
            holdout=args.holdout, checkpoint_every=args.checkpoint_every, model=args.model,
            threads=args.threads, converge_tol=args.converge_tol, converge_min_iters=args.converge_min_iters,
            **off,
        )
        check_config(cfg)
        check_out(args.out)
        if args.force and not args.resume:
            raise RecoveryError("--force only applies with --resume")
        gt = args.gt
        if args.demo:
            if not 16 <= args.demo_size <= 4096:
                raise RecoveryError(f"--demo-size must be an integer in [16, 4096], got {args.demo_size}")
            from torchbrdf.capture.synthetic import default_capture

            capture = default_capture(size=args.demo_size)
            gt = gt or capture / "gt"
        else:
            capture = args.capture
        result = recover(capture, cfg, args.out, gt=gt, resume=args.resume, force=args.force,
                         progress=not args.quiet)
    except RecoveryError as e:
        print("error: " + " ".join(str(e).split()), file=sys.stderr)  # one line, whatever the message
        return e.rc
    report = result.report
    summary = {k: report[k] for k in ("iterations", "seconds", "final_loss", "completed")}
    summary["out"] = str(result.out)
    if report.get("held_out_light"):
        summary["held_out_psnr"] = report["held_out_light"]["psnr"]
    if "errors" in report:
        summary["errors"] = report["errors"]
    print(json.dumps(summary, indent=2))
    return 0 if report["completed"] else 130


def keep_freed_memory(limit: int = 32 << 20) -> bool:
    """Let glibc's ``malloc`` reuse freed blocks up to ``limit`` bytes instead of mapping fresh pages.

    A command that owns its process may call this (``torchbrdf-recover`` and
    ``training.evaluate`` do; the library never does). glibc serves a block above its mmap
    threshold with fresh pages, each page-faulted in on first touch, and raises the threshold
    only as such blocks are freed: the fit's many 1-30 MB temporaries at 256² paid that anew
    early in every process (0.2-0.5 s of an 11 s recovery, measured). Fixing the threshold at
    ``limit`` and keeping up to 8 × ``limit`` of freed memory in the heap avoids it. Returns
    whether it applied (False off glibc).
    """
    if not (isinstance(limit, int) and 0 < limit <= 32 << 20):  # glibc's largest mmap threshold on 64 bits
        raise ValueError(f"keep_freed_memory: limit must be an integer in (0, 32 MiB], got {limit!r}")
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
        m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
        return bool(mallopt(m_mmap_threshold, limit)) and bool(mallopt(m_trim_threshold, 8 * limit))
    except (OSError, AttributeError, TypeError, ctypes.ArgumentError):  # not glibc (musl, ...)
        return False


def cli() -> NoReturn:
    """Run :func:`main` as the command line, then end the process without the interpreter's teardown.

    ``torchbrdf-recover`` and ``python -m training.recover_svbrdf`` run this. Freeing torch's
    modules and the fit's objects one by one took ~1 s after a recovery; by then every output
    is written, fsync'd and renamed into place, and nothing else is pending.
    """
    keep_freed_memory()
    rc = main()
    atexit._run_exitfuncs()  # the registered clean-ups still run (e.g. a private kernel folder's removal)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)


if __name__ == "__main__":
    cli()
