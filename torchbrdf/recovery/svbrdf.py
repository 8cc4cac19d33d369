"""SVBRDF recovery's former single module, kept as the stable import path.

``torchbrdf-recover`` (``torchbrdf.recovery.svbrdf:cli``) and ``python -m
training.recover_svbrdf`` run :func:`cli`. The code lives in one module per concept:
:mod:`~torchbrdf.recovery.api` (:func:`recover`), :mod:`~torchbrdf.recovery.outputs` (the
output folder: checks, lock, commit, :func:`load_outputs`), :mod:`~torchbrdf.recovery.checkpoint`
(fingerprints and checkpoint integrity), :mod:`~torchbrdf.recovery.checks` (settings),
:mod:`~torchbrdf.recovery.previews` (figures), :mod:`~torchbrdf.recovery.progress` (stage
messages and bar), :mod:`~torchbrdf.recovery.options` and :mod:`~torchbrdf.recovery.cli`.
"""

from __future__ import annotations

from torchbrdf.io import write_exr, write_png
from torchbrdf.recovery.api import fractional_metallic_fraction, map_errors, recover
from torchbrdf.recovery.checkpoint import RESULT_INDEPENDENT, capture_fingerprint, settings_fingerprint
from torchbrdf.recovery.checks import RecoveryError, check_config, check_gt
from torchbrdf.recovery.cli import cli, keep_freed_memory, main
from torchbrdf.recovery.options import OFF_SWITCHES, build_parser
from torchbrdf.recovery.outputs import (
    OUTPUT_FILES,
    REPORT,
    RecoveryResult,
    check_out,
    clean_leftovers,
    commit_outputs,
    load_outputs,
    write_outputs,
)
from torchbrdf.recovery.previews import metallic_preview
from torchbrdf.recovery.progress import StageProgress, fit_losses, stage_seconds
from torchbrdf.recovery.config import RecoveryConfig
from torchbrdf.recovery.engine import CHECKPOINT, psnr

__all__ = ["RecoveryConfig", "RecoveryResult", "RecoveryError", "recover", "load_outputs", "main", "cli",
           "psnr", "map_errors", "CHECKPOINT", "REPORT"]

# Former private names, for code written against the single module.
_Progress = StageProgress
_fit_losses = fit_losses
_parser = build_parser

if __name__ == "__main__":
    cli()
