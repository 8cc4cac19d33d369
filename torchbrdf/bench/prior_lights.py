"""The learned prior against the light count: accuracy and time with and without it.

``python -m torchbrdf.bench.prior_lights [--cases rusted_metal/2,lacquer/3] [--lights 1,2,4,8,17]``

Each case is a recovery-panel material (:func:`~torchbrdf.capture.families.make_family_material`,
a *report* seed by default) rendered under the panel's forward model and calibration error for
its family and seed, with ``L`` lights: a ring of ``L − 1`` and the flash
(:func:`~torchbrdf.capture.synthetic.light_layout`; ``L = 1`` is the flash alone), 1 % noise.
Each capture is recovered twice through :func:`torchbrdf.recovery.recover`, without and with
the learned prior (``prior="default"`` unless ``--prior``), every light in the fit, one thread,
and scored by the panel's :func:`~torchbrdf.bench.recovery_panel.score_maps`: maps RMSE,
held-out worst of 8 random lights, and the recovery's wall time. Any panel seed is accepted:
choose settings on its tuning seeds (``--cases lacquer/0,rusted_metal/0``), report on its report
seeds (the default cases).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from torchbrdf.bench.recovery_panel import (FORWARD_MODELS, NOISE, REPORT_SEEDS, calibration_error,
                                            exact_fresnel_brdf, panel_cases, score_maps)
from torchbrdf.capture import synthetic
from torchbrdf.capture.families import FAMILIES, make_family_material
from torchbrdf.capture.format import write_capture

__all__ = ["LIGHT_COUNTS", "DEFAULT_CASES", "case_model", "render_lights_case", "run_lights_case", "main"]

#: Light counts of the study: the flash alone, then rings of 1, 3, 7 and 16 lights plus the flash.
LIGHT_COUNTS = (1, 2, 4, 8, 17)
#: Default cases ``family/seed`` (report seeds): a mixed metal/dielectric and a glossy dielectric.
DEFAULT_CASES = (f"rusted_metal/{REPORT_SEEDS[0]}", f"lacquer/{REPORT_SEEDS[1]}")


def case_model(family: str, seed: int) -> tuple[str, bool]:
    """The forward model and calibration error the recovery panel gives ``family``/``seed``."""
    case = next(c for c in panel_cases("all") if c.family == family and c.seed == seed)
    return case.model, case.calibration_error


def render_lights_case(family: str, seed: int, lights: int, folder: str | Path, size: int = 128) -> dict:
    """Write the capture of ``family``/``seed`` under ``lights`` lights into ``folder``; returns the truth maps."""
    if lights < 1:
        raise ValueError(f"lights: need at least 1 (the flash), got {lights}")
    model, cal = case_model(family, seed)
    maps = make_family_material(family, seed, size)
    pos, inten = synthetic.light_layout(lights - 1)
    case_seed = 1000 * FAMILIES.index(family) + 10 * seed + lights
    with torch.no_grad():
        img = synthetic.render_capture(maps, (pos, inten), synthetic.DEFAULT_CAMERA,
                                       brdf=exact_fresnel_brdf if model == FORWARD_MODELS[1] else None,
                                       noise=NOISE, seed=case_seed)
    stated = calibration_error(pos, inten, case_seed) if cal else (pos, inten)
    write_capture(folder, img, stated, synthetic.DEFAULT_CAMERA)
    return maps


def run_lights_case(family: str, seed: int, lights: int, prior: str | None, size: int = 128) -> dict:
    """Render, recover (with ``prior`` or none) and score one case; returns its row."""
    from torchbrdf.recovery import RecoveryConfig, recover

    model, cal = case_model(family, seed)
    with tempfile.TemporaryDirectory(prefix="prior_lights_") as tmp:
        truth = render_lights_case(family, seed, lights, tmp, size)
        t0 = time.perf_counter()
        maps = recover(tmp, RecoveryConfig(threads=1, holdout=-1), progress=False, log=lambda m: None,
                       prior=prior).maps
        seconds = time.perf_counter() - t0
    row = {"case": f"{family}/{seed}", "lights": lights, "prior": prior is not None, "model": model,
           "calibration_error": cal}
    row.update(score_maps(maps, truth, model, seed=1000 * FAMILIES.index(family) + 10 * seed + lights))
    row["seconds"] = seconds
    return row


def _line(r: dict) -> str:
    return (f"| {r['case']} | {r['lights']} | {'yes' if r['prior'] else 'no'} | {r['base_rmse']:.3f} | "
            f"{r['roughness_rmse']:.3f} | {r['metallic_rmse']:.3f} | {r['heldout_worst_db']:.1f} | "
            f"{r['seconds']:.0f} |")


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.prior_lights", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES), help="comma-separated family/seed")
    ap.add_argument("--lights", default=",".join(map(str, LIGHT_COUNTS)), help="comma-separated light counts")
    ap.add_argument("--size", type=int, default=128, help="capture size in pixels (default 128)")
    ap.add_argument("--prior", default="default", help="weights file of the prior, or 'default'")
    ap.add_argument("--json", help="write the rows here (after each row)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cases = []
    for c in args.cases.split(","):
        family, _, seed = c.partition("/")
        if family not in FAMILIES or not seed.isdigit():
            ap.error(f"--cases: expected family/seed with a family of {FAMILIES}, got {c!r}")
        cases.append((family, int(seed)))
    lights = [int(n) for n in args.lights.split(",")]
    rows: list[dict] = []
    print("| case | lights | prior | base | rough | metal | worst dB | s |\n|---|---|---|---|---|---|---|---|")
    for family, seed in cases:
        for n in lights:
            for prior in (None, args.prior):
                rows.append(run_lights_case(family, seed, n, prior, args.size))
                print(_line(rows[-1]), flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
