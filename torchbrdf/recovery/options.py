"""The ``torchbrdf-recover`` command line's options (``python -m training.recover_svbrdf``).

:func:`build_parser` is the one place a flag is declared; :mod:`~torchbrdf.recovery.checks`
names settings by their flags, :mod:`~torchbrdf.recovery.cli` runs them and
:mod:`~torchbrdf.recovery.batch` reuses them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchbrdf.recovery.config import SCHEDULES, RecoveryConfig

__all__ = ["build_parser", "OFF_SWITCHES", "SCHEDULE_FLAGS"]


class _OneLineErrorParser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of the usage block
        self.exit(2, f"error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``torchbrdf-recover`` command line (every option, its help and default)."""
    d = RecoveryConfig()
    p = _OneLineErrorParser(
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
                   help="output folder, locked while the run uses it; replaced as a unit at the end, so it "
                        "may hold only this recovery's files (see --allow-other-files)")
    p.add_argument("--allow-other-files", action="store_true",
                   help="let --out hold files, folders or mount points this recovery did not write: they "
                        "are left untouched, and the outputs replace the old ones file by file "
                        "(report.json last) instead of as one folder")
    p.add_argument("--gt", type=Path,
                   help="folder of ground-truth maps (base_color.exr, ...) to report errors against")
    p.add_argument("--schedule", choices=tuple(SCHEDULES), default="default",
                   help="how long the fit runs, time against accuracy (docs/recovery.md, Schedules): fast "
                        "(18 iterations planned, stop at a 3%% change), default (39, 1%%) or thorough (78, 0.2%%); "
                        "--iters, --levels, --lr, --converge-tol and --converge-min-iters adjust it")
    p.add_argument("--iters", type=int, default=None,
                   help="total LM iterations planned, spread over the stages (0 = the default plan, 39; "
                        "default: the schedule's); converged full-resolution stages end early (--converge-tol)")
    p.add_argument("--lr", type=float, default=None,
                   help=f"LM step multiplier in (0, 2] (1 = full damped Gauss-Newton step; default {d.lr})")
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
    p.add_argument("--levels", type=int, default=None, help=f"coarse-to-fine levels (1-12; default {d.levels})")
    p.add_argument("--converge-tol", type=float, default=None,
                   help="a full-resolution stage ends once an iteration changes its fit loss by less than this "
                        f"fraction (default: the schedule's, {d.converge_tol} in the default one; 0 runs every "
                        "planned iteration)")
    p.add_argument("--converge-min-iters", type=int, default=None,
                   help="... but not before this many of its iterations (default: the schedule's, "
                        f"{d.converge_min_iters} in the default one)")
    p.add_argument("--prior-roughness", type=float, default=d.prior_roughness,
                   help="weight of the roughness smoothness prior (>= 0)")
    p.add_argument("--prior-specular", type=float, default=d.prior_specular,
                   help="weight of the specular smoothness prior (>= 0)")
    p.add_argument("--prior-metal-base", type=float, default=d.prior_metal_base,
                   help="weight pulling a metal's base colour (F0) toward its metal neighbours (>= 0)")
    p.add_argument("--prior-nonlocal-base", type=float, default=d.prior_nonlocal_base,
                   help="precision of the final non-local fusion of a metal's base colour (0: off)")
    p.add_argument("--prior", metavar="PATH|default",
                   help="a learned estimator as evidence: its metallic weighs the metal/dielectric choice, "
                        "and once each pixel's class is chosen its maps pull where the images are silent (the "
                        "fit starts as without it); a weights file (Prior.save; trained by training/train_estimator.py "
                        "in a checkout) or 'default', the shipped one (default: no learned prior)")
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
                   help="CPU threads for torch (default: the CPUs this process may use, from its affinity and "
                        "cgroup quota, less the load of other processes and the CPUs a hypervisor steals; "
                        "torchbrdf.parallel.default_threads)")
    p.add_argument("--demo-size", type=int, default=128, help="resolution of the --demo capture (16-4096)")
    p.add_argument("--quiet", action="store_true", help="no stage messages or progress bar")
    return p


# The schedule's flags: None (not given) keeps the value of the chosen --schedule.
SCHEDULE_FLAGS = ("iters", "lr", "levels", "converge_tol", "converge_min_iters")

# The command line's switches that turn a default-on setting off: flag dest -> RecoveryConfig field.
OFF_SWITCHES = {"no_soft_metal": "soft_metal", "no_light_calibration": "light_scale",
                "no_light_position": "light_position"}
