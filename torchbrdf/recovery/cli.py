"""The ``torchbrdf-recover`` command (also ``python -m training.recover_svbrdf``).

:func:`main` parses the options (:mod:`~torchbrdf.recovery.options`), runs
:func:`~torchbrdf.recovery.recover` and turns every refusal into one line and an exit
status; :func:`cli` runs it as a process of its own.
"""

from __future__ import annotations

import atexit
import ctypes
import json
import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from torchbrdf.parallel import default_threads
from torchbrdf.recovery.api import recover
from torchbrdf.recovery.checks import RecoveryError, check_config
from torchbrdf.recovery.options import OFF_SWITCHES, SCHEDULE_FLAGS, build_parser
from torchbrdf.recovery.outputs import check_out
from torchbrdf.recovery.config import RecoveryConfig

__all__ = ["main", "cli", "keep_freed_memory"]


def main(argv: Sequence[str] | None = None) -> int:
    """``torchbrdf-recover`` / ``python -m training.recover_svbrdf``; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a malformed option (2, one line already printed)
        return int(e.code or 0)
    try:
        off: dict[str, Any] = {field: not getattr(args, flag) for flag, field in OFF_SWITCHES.items()}
        given = {k: getattr(args, k) for k in SCHEDULE_FLAGS if getattr(args, k) is not None}
        cfg = RecoveryConfig(
            schedule=args.schedule, size=args.size, seed=args.seed, device=args.device,
            prior_roughness=args.prior_roughness, prior_specular=args.prior_specular,
            prior_metal_base=args.prior_metal_base, prior_nonlocal_base=args.prior_nonlocal_base,
            holdout=args.holdout, checkpoint_every=args.checkpoint_every, model=args.model,
            threads=default_threads() if args.threads is None else args.threads,
            **given, **off,
        )
        check_config(cfg)
        check_out(args.out, args.allow_other_files)
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
                         progress=not args.quiet, allow_other_files=args.allow_other_files,
                         prior=args.prior)
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
    only as such blocks are freed: the fit's many 1-30 MB temporaries at 256² pay that anew
    early in every process (measured in docs/fast_path.md, "Threads"). Fixing the threshold at
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
    modules and the fit's objects one by one is slow after a recovery, and by then every output
    is written, fsync'd and renamed into place, and nothing else is pending.
    """
    keep_freed_memory()
    rc = main()
    atexit._run_exitfuncs()  # the registered clean-ups still run (e.g. a private kernel folder's removal)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)
