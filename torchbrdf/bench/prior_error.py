"""The learned prior's own error on recovery-panel materials: the network's maps against the truth.

``python -m torchbrdf.bench.prior_error [--split tuning] [--lights 4] [--json OUT] [--card WEIGHTS]``

Each panel material of the split (one capture per family and seed, rendered as
:func:`~torchbrdf.bench.prior_lights.render_lights_case` renders it under ``--lights`` lights)
is given to the estimator (:meth:`~torchbrdf.recovery.prior.Prior.predict`, the image(s)
nearest the camera) and its maps are compared with the truth: per map, the RMSE over every
pixel of every material, the share of it that is each capture's mean error (a bias shared by
all its pixels), and per material the RMSE and mean error. The normal's mean angle.

These are materials of :mod:`torchbrdf.capture.families`, not the synthetic recipes the
estimator was trained on: its error where a recovery meets it, beside the card's held-out error
on its own training distribution. ``--card WEIGHTS`` writes the measurement (without the
per-material rows) into that weights file's card as ``panel``, which the model card states;
measure it on the tuning split only (``--card`` refuses the report split).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchbrdf.bench.prior_lights import render_lights_case
from torchbrdf.bench.recovery_panel import REPORT_SEEDS, TUNING_SEEDS
from torchbrdf.capture.families import FAMILIES
from torchbrdf.capture.format import load_capture
from torchbrdf.recovery.prior import DEFAULT_WEIGHTS, Prior

__all__ = ["SCALAR_MAPS", "map_errors", "panel_errors", "main"]

#: The maps scored by RMSE (the normal by its mean angle).
SCALAR_MAPS = ("base_color", "roughness", "metallic", "specular")


def map_errors(pred: Mapping[str, Tensor], truth: Mapping[str, Tensor]) -> dict[str, float]:
    """Per map: the sum of squared errors, of the material's mean error squared, and the pixel count.

    Args:
        pred, truth: name -> ``(C, H, W)`` maps of the same shapes.

    Returns:
        ``{name}_sse``, ``{name}_bias`` (the mean error over pixels and channels), ``{name}_n``
        for :data:`SCALAR_MAPS`; ``normal_deg_sum`` and ``normal_n`` (angles in degrees).
    """
    out: dict[str, float] = {}
    for name in SCALAR_MAPS:
        d = (pred[name].float() - truth[name].float()).double()
        out[f"{name}_sse"] = float(d.square().sum())
        out[f"{name}_bias"] = float(d.mean())
        out[f"{name}_n"] = float(d.numel())
    pn, tn = pred["normal"].double(), truth["normal"].double()
    # atan2(|a × b|, a · b): exact near 0°, where acos of a rounded cosine is not
    ang = torch.atan2(torch.linalg.cross(pn, tn, dim=0).norm(dim=0), (pn * tn).sum(0))
    out["normal_deg_sum"] = float(torch.rad2deg(ang).sum())
    out["normal_n"] = float(ang.numel())
    return out


def panel_errors(prior: Prior, split: str = "tuning", lights: int = 4, size: int = 128) -> dict[str, Any]:
    """The estimator's error on the panel materials of ``split`` (``"tuning"`` or ``"report"``).

    Returns:
        ``{"split", "lights", "size", "materials", "{name}_rmse", "{name}_bias_share",
        "normal_mean_deg", "cases": [per material: {name}_rmse, {name}_bias, normal_mean_deg]}``;
        ``bias_share`` is the fraction of the mean squared error that is the captures' mean
        errors (1: each capture's pixels are all off by the same amount).
    """
    if split not in ("tuning", "report"):
        raise ValueError(f"split: expected 'tuning' or 'report', got {split!r}")
    seeds = TUNING_SEEDS if split == "tuning" else REPORT_SEEDS
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        for family in FAMILIES:
            with tempfile.TemporaryDirectory(prefix="prior_error_") as tmp:
                truth = render_lights_case(family, seed, lights, tmp, size)
                cap = load_capture(tmp)
            pred = {k: v[0] for k, v in prior.predict(cap).items()}
            rows.append({"case": f"{family}/{seed}", **map_errors(pred, truth)})
    out: dict[str, Any] = {"split": split, "lights": lights, "size": size, "materials": len(rows)}
    for name in SCALAR_MAPS:
        n = sum(r[f"{name}_n"] for r in rows)
        mse = sum(r[f"{name}_sse"] for r in rows) / n
        bias2 = sum(r[f"{name}_bias"] ** 2 * r[f"{name}_n"] for r in rows) / n
        out[f"{name}_rmse"] = math.sqrt(mse)
        out[f"{name}_bias_share"] = bias2 / mse if mse > 0 else 0.0
    out["normal_mean_deg"] = sum(r["normal_deg_sum"] for r in rows) / sum(r["normal_n"] for r in rows)
    out["cases"] = [{"case": r["case"], **{f"{m}_rmse": math.sqrt(r[f"{m}_sse"] / r[f"{m}_n"]) for m in SCALAR_MAPS},
                     **{f"{m}_bias": r[f"{m}_bias"] for m in SCALAR_MAPS},
                     "normal_mean_deg": r["normal_deg_sum"] / r["normal_n"]} for r in rows]
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.prior_error", description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=("tuning", "report"), default="tuning", help="panel seeds (default tuning)")
    ap.add_argument("--lights", type=int, default=4, help="lights of each capture (default 4)")
    ap.add_argument("--size", type=int, default=128, help="capture size in pixels (default 128)")
    ap.add_argument("--prior", default="default", help="weights file of the prior, or 'default'")
    ap.add_argument("--json", help="write the measurement here")
    ap.add_argument("--card", help="weights file whose card gets the measurement as 'panel' (rewritten in place)")
    args = ap.parse_args(argv)
    if args.card and args.split != "tuning":
        ap.error("--card: the card's panel error is measured on the tuning split only")
    if args.card and args.prior not in ("default", args.card):
        ap.error(f"--card: the card gets its own weights' error; --prior names another file ({args.prior!r})")
    torch.set_num_threads(1)
    if args.card:  # (the card's own weights, whatever Prior.default would pick for --lights)
        prior = Prior.from_file(args.card)
    else:
        prior = Prior.default(args.lights) if args.prior == "default" else Prior.from_file(args.prior)
    res = panel_errors(prior, args.split, args.lights, args.size)
    print(f"| map | RMSE ({res['materials']} {args.split} materials, {args.lights} lights) | mean-error share |")
    print("|---|---|---|")
    for name in SCALAR_MAPS:
        print(f"| {name} | {res[f'{name}_rmse']:.3f} | {res[f'{name}_bias_share']:.2f} |")
    print(f"| normal (mean angle, deg) | {res['normal_mean_deg']:.2f} | |")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    if args.card:
        target = Prior.from_file(args.card)
        words = sys.argv[1:] if argv is None else list(argv)
        target.card["panel"] = {**{k: v for k, v in res.items() if k != "cases"},
                                "command": "python -m torchbrdf.bench.prior_error " + " ".join(words)}
        target.save(args.card)
    return 0


if __name__ == "__main__":
    sys.exit(main())
