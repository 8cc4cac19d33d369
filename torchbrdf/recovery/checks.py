"""Refusing bad settings and a bad ``--gt`` up front, before anything is created.

:class:`RecoveryError` carries a one-line message and the command's exit status; every
refusal of :mod:`torchbrdf.recovery` raises it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch

from torchbrdf.capture.synthetic import MAP_NAMES
from torchbrdf.io import read_exr
from torchbrdf.recovery.options import build_parser
from torchbrdf.recovery.config import RecoveryConfig, Settings, settings_of

__all__ = ["RecoveryError", "check_config", "check_gt"]


class RecoveryError(Exception):
    """A refusal or failure with a one-line message for a person.

    ``rc`` is the CLI exit status (2: refused before running — bad settings, capture,
    ``--gt`` or output location; 1: failed while running — e.g. no space left on device).
    """

    def __init__(self, message: str, rc: int = 2):
        super().__init__(message)
        self.rc = rc


def _setting(name: str) -> str:
    """How an error names a setting.

    ``lr (--lr)`` when the command line has the flag, else ``RecoveryConfig.name`` (a setting of
    the Python API only).
    """
    flag = f"--{name.replace('_', '-')}"
    if flag in build_parser()._option_string_actions:
        return f"{name} ({flag})"
    return f"RecoveryConfig.{name}" if hasattr(RecoveryConfig, name) else f"Settings.{name}"


def _finite_in_range(name: str, v, lo: float, hi: float, lo_open: bool = False) -> None:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    ok = ok and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:  # (the name is looked up in the parser only here: building it costs ~1 ms)
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise RecoveryError(f"{_setting(name)} must be a finite number in {rng}, got {v!r}")


def _integer_in_range(name: str, v, lo: int, hi: int, allow_none: bool = False) -> None:
    if v is None and allow_none:
        return
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise RecoveryError(f"{_setting(name)} must be an integer in [{lo}, {hi}], got {v!r}")


def check_config(cfg: RecoveryConfig | Settings) -> None:
    """Refuse settings that cannot give a meaningful result (one-line :class:`RecoveryError`)."""
    cfg = settings_of(cfg)
    _integer_in_range("iters", cfg.iters, 0, 1_000_000)
    _finite_in_range("lr", cfg.lr, 0.0, 2.0, lo_open=True)
    _integer_in_range("size", cfg.size, 8, 16384, allow_none=True)
    _integer_in_range("seed", cfg.seed, 0, 2**63 - 1)
    _integer_in_range("levels", cfg.levels, 1, 12)
    _integer_in_range("checkpoint_every", cfg.checkpoint_every, 1, 1_000_000)
    _integer_in_range("threads", cfg.threads, 1, 4096, allow_none=True)
    _integer_in_range("cg_iters", cfg.cg_iters, 1, 100_000)
    _integer_in_range("propagate_passes", cfg.propagate_passes, 0, 10_000)
    _finite_in_range("converge_tol", cfg.converge_tol, 0.0, 1.0)
    _integer_in_range("converge_min_iters", cfg.converge_min_iters, 1, 1_000_000)
    priors = ("prior_roughness", "prior_specular", "prior_metal_base", "prior_nonlocal_base",
              "prior_nonlocal")
    for name in priors:
        _finite_in_range(name, getattr(cfg, name), 0.0, 1e6)
    _finite_in_range("nonlocal_fit_weight", cfg.nonlocal_fit_weight, 0.0, 1e6)
    for name in ("prior_sigma", "nonlocal_range", "nonlocal_sigma"):
        _finite_in_range(name, getattr(cfg, name), 0.0, 1e6, lo_open=True)
    _finite_in_range("false_metal_rate", cfg.false_metal_rate, 1e-12, 0.1)
    for name in ("soft_metal_factor", "soft_metal_well", "soft_metal_gain", "soft_metal_smooth",
                 "soft_metal_edge", "soft_metal_context", "soft_metal_unmix", "soft_metal_line",
                 "soft_metal_quiet"):
        _finite_in_range(name, getattr(cfg, name), 0.0, 1e6)
    _finite_in_range("soft_metal_max", cfg.soft_metal_max, 0.0, 1.0)
    _integer_in_range("soft_metal_iters", cfg.soft_metal_iters, 0, 10_000)
    _integer_in_range("fuse_refit_iters", cfg.fuse_refit_iters, 0, 10_000)
    _integer_in_range("fuse_rounds", cfg.fuse_rounds, 1, 10_000)
    _integer_in_range("soft_metal_grow", cfg.soft_metal_grow, 0, 10_000)
    _integer_in_range("soft_metal_passes", cfg.soft_metal_passes, 0, 10_000)
    _integer_in_range("soft_metal_band", cfg.soft_metal_band, 0, 10_000)  # a max-pool half width
    _finite_in_range("rough_tie", cfg.rough_tie, 0.0, 1e6)
    _finite_in_range("rough_tie_glossy", cfg.rough_tie_glossy, 0.0, 1.0)
    _finite_in_range("rough_tie_start", cfg.rough_tie_start, 0.03, 1.0)
    _finite_in_range("soft_rough_tie", cfg.soft_rough_tie, 0.0, 1e6)
    # (a fit must stay above twice the threshold to count as rough, and start above that)
    _finite_in_range("soft_rough_tie_glossy", cfg.soft_rough_tie_glossy, 0.0, 0.45)
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


def check_gt(gt: str | os.PathLike, size: tuple[int, int] | None = None) -> Path:
    """The ground-truth folder must exist and hold at least one readable map EXR.

    Each map present must have its map's channel count (3 for ``base_color`` and ``normal``,
    1 for the scalar maps), the capture's ``size = (H, W)`` when given, and finite values: a
    wrong count would broadcast against the recovered map, a truth of another size would be
    resampled into a different truth, and a NaN would make its error NaN in ``report.json``.
    """
    gt = Path(gt)
    if not gt.is_dir():
        raise RecoveryError(f"--gt {gt}: {'not a folder' if gt.exists() else 'does not exist'}")
    found = [n for n in MAP_NAMES if (gt / f"{n}.exr").is_file()]
    if not found:
        raise RecoveryError(f"--gt {gt}: holds none of the maps {', '.join(n + '.exr' for n in MAP_NAMES)}")
    for n in found:
        f = gt / f"{n}.exr"
        try:
            m = read_exr(f)
        except (OSError, ValueError) as e:
            raise RecoveryError(f"--gt {f}: unreadable ({e})") from e
        if m.shape[0] != MAP_NAMES[n]:
            raise RecoveryError(f"--gt {f}: expected {MAP_NAMES[n]} channel(s) for the {n} map, "
                                f"got {m.shape[0]}")
        if size is not None and tuple(m.shape[-2:]) != tuple(size):
            raise RecoveryError(f"--gt {f}: expected the capture's size {size[0]}x{size[1]} (height x width), "
                                f"got {m.shape[-2]}x{m.shape[-1]}")
        bad = ~torch.isfinite(m)
        if bad.any():
            c, i, j = (int(k) for k in bad.nonzero()[0])
            raise RecoveryError(f"--gt {f}: {int(bad.sum())} non-finite value(s) (NaN or inf), first at "
                                f"row {i}, column {j}, channel {c}; a ground-truth map must be finite")
    return gt

