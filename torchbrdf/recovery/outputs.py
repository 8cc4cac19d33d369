"""A recovery's output folder: checking, locking, committing and reading it back.

A run owns the files it writes (:data:`OUTPUT_FILES`, ``checkpoint.pt`` and atomic-write
temporaries) and nothing else in ``--out``. While it runs it holds an advisory lock on the
folder (``flock``, released when the process ends however it ends). Its outputs are
written into a staging folder beside ``--out`` and committed as a unit: when ``--out``
holds only the run's own files, by one atomic folder swap; otherwise (``--allow-other-files``)
file by file, ``report.json`` last, so entries the run did not write (a person's files, a
mount point) are never moved, copied over or deleted.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import Tensor

from torchbrdf.capture.format import Capture
from torchbrdf.capture.synthetic import MAP_NAMES
from torchbrdf.io import atomic_path, fsync_dir, read_exr, write_exr, write_png
from torchbrdf.recovery.checkpoint import sha256_file
from torchbrdf.recovery.checks import RecoveryError
from torchbrdf.recovery.previews import comparison_figure, loss_figure, maps_figure, metallic_preview
from torchbrdf.recovery.engine import CHECKPOINT

__all__ = ["REPORT", "OUTPUT_FILES", "RecoveryResult", "OutputBusyError", "check_out", "foreign_entries",
           "locked_out", "clean_leftovers", "commit_outputs", "write_outputs", "load_outputs", "write_failure",
           "OneLineWriteErrors", "is_own_file"]

REPORT = "report.json"
#: Every file a run writes into OUT besides checkpoint.pt.
OUTPUT_FILES = tuple([f"{n}.exr" for n in MAP_NAMES] + [f"{n}.png" for n in MAP_NAMES]
                     + ["confidence.exr", "confidence.png", "comparison.png", "loss.png", "maps.png", REPORT])
_ATOMIC_TEMPORARY = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")  # atomic_path's temporaries


def is_own_file(name: str) -> bool:
    """Whether an entry named ``name`` in OUT is one a recovery writes."""
    return name in OUTPUT_FILES or name == CHECKPOINT or bool(_ATOMIC_TEMPORARY.match(name))


@dataclass
class RecoveryResult:
    """What :func:`~torchbrdf.recovery.recover` returns.

    Attributes:
        maps: ``{"base_color": (3, H, W), "roughness": (1, H, W), "metallic": (1, H, W),
            "specular": (1, H, W), "normal": (3, H, W)}`` float32 tensors at the capture's
            size, finite (the values written to the EXRs).
        report: the contents of ``report.json`` (iterations, seconds, final_loss, completed,
            fingerprint, per_image_psnr, warnings, ...).
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
# Checking and locking --out
# --------------------------------------------------------------------------------------


def foreign_entries(out: Path) -> list[str]:
    """The entries of ``out`` a recovery did not write, mount points marked (empty: none, or no ``out``)."""
    if not out.is_dir():
        return []
    return [p.name + (" (a mount point)" if os.path.ismount(p) else "")
            for p in sorted(out.iterdir()) if not is_own_file(p.name) or os.path.ismount(p)]


def check_out(out: str | os.PathLike, allow_other_files: bool = False) -> Path:
    """Check that ``out`` can be created and written by a run; creates nothing.

    Refuses an ``out`` holding entries a recovery did not write (files, folders, mount
    points) unless ``allow_other_files``. Returns the folder with symbolic links resolved.
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
    foreign = foreign_entries(out)
    if foreign and not allow_other_files:
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        raise RecoveryError(f"--out {out}: holds entries this recovery did not write "
                            f"({', '.join(foreign[:3])}{more}); name a new or earlier output folder, or pass "
                            "--allow-other-files to leave them untouched")
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


class OutputBusyError(RecoveryError):
    """``--out`` is locked by another process's run."""


def _lock_folder(path: Path) -> int | None:
    """An open descriptor of ``path`` holding its exclusive ``flock``; None when another process holds it."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


@contextlib.contextmanager
def locked_out(out: Path) -> Iterator[None]:
    """Hold the advisory lock of the existing folder ``out`` for the body's duration.

    The lock is an ``flock`` on the folder itself, so it dies with its process. A swap may
    replace the folder between opening and locking it: the lock is then taken again on the
    folder now at ``out``.

    Raises:
        OutputBusyError: another process holds the lock.
    """
    while True:
        fd = _lock_folder(out)
        if fd is None:
            raise OutputBusyError(f"--out {out}: another recovery is writing it (the folder is locked); "
                                "wait for it to finish or name another --out")
        held = os.fstat(fd)
        try:
            now = os.stat(out)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino):
            break
        os.close(fd)
    try:
        yield
    finally:
        os.close(fd)


# --------------------------------------------------------------------------------------
# Leftovers of killed runs
# --------------------------------------------------------------------------------------


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


def _remove_own_folder(folder: Path) -> bool:
    """Delete a run's staging/old ``folder``: its own files, then the folder if that left it empty."""
    for p in folder.iterdir():
        if is_own_file(p.name) and not p.is_dir() and not os.path.ismount(p):
            p.unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:  # it holds something a run did not write: leave it
        return False
    return True


def clean_leftovers(out: Path, log: Callable[[str], None] = lambda m: None) -> list[str]:
    """Remove what killed runs left, never anything they did not write.

    That is staging/old folders beside ``out`` (of processes that are gone) and
    atomic-write temporaries inside it. If ``out`` itself is missing because a run died
    between the two renames of a non-atomic swap, the previous outputs are put back. A
    leftover folder holding entries no run writes is kept, with a message.
    """
    removed, kept = [], []
    pattern = _leftover_pattern(out)
    if out.parent.is_dir():
        for p in sorted(out.parent.iterdir()):
            m = pattern.match(p.name)
            if not m or _alive(int(m.group(2))):
                continue
            if m.group(1) == "old" and not out.exists():
                os.rename(p, out)
                log(f"restored the previous outputs of {out} from {p.name}")
                continue
            if not p.is_dir():
                p.unlink(missing_ok=True)
            elif not _remove_own_folder(p):
                kept.append(p.name)
                continue
            removed.append(p.name)
    if out.is_dir():
        for p in out.iterdir():
            if _ATOMIC_TEMPORARY.match(p.name) and p.is_file():
                p.unlink(missing_ok=True)
                removed.append(f"{out.name}/{p.name}")
    if removed:
        log(f"removed leftovers of interrupted runs: {', '.join(removed)}")
    if kept:
        log(f"kept leftover folder(s) {', '.join(kept)}: they hold files no recovery writes")
    return removed


# --------------------------------------------------------------------------------------
# Committing: staged, then swapped in as a unit (or file by file around other files)
# --------------------------------------------------------------------------------------


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


def write_failure(e: OSError, name: str) -> RecoveryError:
    """The one-line :class:`RecoveryError` (``rc`` 1) for an ``OSError`` while writing ``name``."""
    if e.errno == errno.ENOSPC:
        return RecoveryError(f"no space left on device while writing {name}; earlier outputs are unchanged",
                             rc=1)
    return RecoveryError(f"cannot write {name}: {e.strerror or e}", rc=1)


class OneLineWriteErrors:
    """Context manager turning an ``OSError`` while writing ``name`` into :func:`write_failure`'s message."""

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if isinstance(e, OSError):
            raise write_failure(e, self.name) from e
        return False


def _swap_in(staging: Path, out: Path) -> Path:
    """Swap ``staging`` in as ``out``; returns the folder that now holds the previous outputs."""
    if _exchange(staging, out):
        return staging
    # Fallback: two renames (a crash between them is repaired by clean_leftovers).
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-{os.getpid()}-", dir=out.parent))
    os.rmdir(old)
    os.rename(out, old)
    os.rename(staging, out)
    return old


def _replace_file_by_file(staging: Path, out: Path, keep_checkpoint: bool) -> None:
    """Move the run's files from ``staging`` into ``out`` one by one, ``report.json`` last.

    The previous report goes first, so no report ever describes a mix of two runs; the
    previous run's files this run did not write go too. Nothing else in ``out`` is touched.
    """
    (out / REPORT).unlink(missing_ok=True)
    written = {p.name for p in staging.iterdir()}
    for name in OUTPUT_FILES + (() if keep_checkpoint else (CHECKPOINT,)):
        if name not in written and (out / name).is_file() and not (out / name).is_symlink():
            (out / name).unlink()
    for name in sorted(written - {REPORT}) + [REPORT]:
        os.rename(staging / name, out / name)
    fsync_dir(out)


def commit_outputs(out: Path, write: Callable[[Path], None], keep_checkpoint: bool = False) -> None:
    """Run ``write(staging)`` into a fresh folder beside ``out``, then commit it.

    Until the commit, ``out`` is untouched; if ``write`` fails the staging folder is removed
    and ``out`` still holds the previous run. When ``out`` holds only a recovery's own files
    the staging folder replaces it by one atomic swap (``checkpoint.pt`` carried over by a
    hard link when ``keep_checkpoint``, e.g. for an interrupted run); otherwise the files
    move in one by one (:func:`_replace_file_by_file`) and nothing else in ``out`` is touched.
    A completed run (``keep_checkpoint`` False) leaves no ``checkpoint.pt``.
    """
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-{os.getpid()}-", dir=out.parent))
    lock = _lock_folder(staging)  # held until the swap is done: the new OUT is never unlocked mid-commit
    try:
        umask = os.umask(0)
        os.umask(umask)
        # The folder's usual mode, not mkdtemp's 0700.
        os.chmod(staging, (out.stat().st_mode & 0o7777) if out.is_dir() else (0o777 & ~umask))
        write(staging)
        if not out.exists():
            fsync_dir(staging)
            os.rename(staging, out)
        elif foreign_entries(out):
            _replace_file_by_file(staging, out, keep_checkpoint)
        else:
            if keep_checkpoint and (out / CHECKPOINT).is_file():
                with OneLineWriteErrors(f"{staging.name}/{CHECKPOINT}"):
                    _link_or_copy(out / CHECKPOINT, staging / CHECKPOINT)
            fsync_dir(staging)
            staging = _swap_in(staging, out)
        fsync_dir(out.parent)
    finally:
        if lock is not None:
            os.close(lock)
        if staging.is_dir():
            _remove_own_folder(staging)  # the new run's leftovers, or the previous outputs


def _link_or_copy(a: Path, b: Path) -> None:
    try:
        os.link(a, b)
    except OSError:
        import shutil

        shutil.copy2(a, b)


# --------------------------------------------------------------------------------------
# Writing and reading one run's files
# --------------------------------------------------------------------------------------


def write_outputs(folder: Path, cap: Capture, maps: dict, pred: Tensor, report: dict, history: list,
                  plots: bool = True, confidence: Tensor | None = None) -> None:
    """Write one run's files into ``folder`` (the staging folder).

    That is the EXR maps and their PNG previews, ``maps.png`` (every map with a colour bar
    and the sample's coordinates), ``comparison.png``, ``loss.png`` and, last,
    ``report.json`` with every file's SHA-256. ``maps`` are finite ``(C, H, W)`` at the
    capture's size; ``pred`` the re-rendered images ``(L, 3, H, W)``; ``confidence`` the
    ``(1, H, W)`` confidence map in [0, 1] (what the data measured, 1, vs what the priors
    inferred, 0), written as ``confidence.exr`` and ``confidence.png``. ``plots=False`` (an
    interrupted run, which should exit promptly) skips the matplotlib figures.
    """
    for name in MAP_NAMES:
        t = maps[name].detach().float().cpu()
        with OneLineWriteErrors(f"{name}.exr"):
            write_exr(folder / f"{name}.exr", t)
        with OneLineWriteErrors(f"{name}.png"):
            if name == "normal":
                write_png(folder / f"{name}.png", t * 0.5 + 0.5, srgb=False)
            elif name == "metallic":
                write_png(folder / f"{name}.png", metallic_preview(t), srgb=False)
            else:
                write_png(folder / f"{name}.png", t, srgb=(name == "base_color"))
    c = None
    if confidence is not None:
        c = confidence.detach().float().cpu().clamp(0, 1).reshape(1, *confidence.shape[-2:])
        with OneLineWriteErrors("confidence.exr"):
            write_exr(folder / "confidence.exr", c, channels=["Y"])
        with OneLineWriteErrors("confidence.png"):
            write_png(folder / "confidence.png", c, srgb=False)
    if plots:
        with OneLineWriteErrors("maps.png"):
            maps_figure(folder / "maps.png", {k: v.detach().float().cpu() for k, v in maps.items()}, c)
        with OneLineWriteErrors("comparison.png"):
            comparison_figure(folder / "comparison.png", cap, pred)
        with OneLineWriteErrors("loss.png"):
            loss_figure(folder / "loss.png", history)
    report["files"] = {p.name: sha256_file(p) for p in sorted(folder.iterdir()) if p.name in OUTPUT_FILES}
    with OneLineWriteErrors(REPORT), atomic_path(folder / REPORT) as tmp:
        tmp.write_text(json.dumps(report, indent=2, allow_nan=True) + "\n")


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
        if not f.is_file() or sha256_file(f) != digest:
            raise RecoveryError(f"{f}: does not belong to the run {out / REPORT} describes")
    maps = {n: read_exr(out / f"{n}.exr") for n in MAP_NAMES}
    return RecoveryResult(maps=maps, report=report, out=out)
