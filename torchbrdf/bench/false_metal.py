"""``python -m torchbrdf.bench.false_metal``: how often noise alone calls a dielectric pixel metal.

Every metal/dielectric choice of the recovery is a likelihood-ratio test at the capture's
measured noise level, with a per-pixel false-positive rate (``ClassConfig.false_metal_rate``;
:func:`torchbrdf.recovery.classes.evidence_threshold`). This simulation checks the rate end to
end: dielectric-only materials of several families (:data:`DIELECTRIC_FAMILIES`, seeds outside
the recovery panel's tuning and report splits) are rendered with 1 % sensor noise, the panel's
two forward models alternating, and recovered with the defaults
(:func:`torchbrdf.bench.recovery_panel.run_case`); every pixel recovered with metallic > 0.5 is a
false metal. It prints the count, the rate and its one-sided 95 % upper bound (Poisson: the
χ²(2k + 2) quantile / 2N, ``3 / N`` when none is found).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from torchbrdf.bench.recovery_panel import FORWARD_MODELS, PanelCase, run_case
from torchbrdf.capture.families import DIELECTRIC_FAMILIES
from torchbrdf.recovery.classes import chi2_quantile

__all__ = ["false_metal_rate", "SEEDS", "main"]

#: Material seeds of the simulation: neither the panel's tuning (0, 1) nor its report (2, 3) seeds.
SEEDS: tuple[int, ...] = (10, 11)


def false_metal_rate(families: Sequence[str] = DIELECTRIC_FAMILIES, seeds: Sequence[int] = SEEDS,
                     size: int = 64, lights: int = 12, noise_seed: int = 0) -> dict:
    """Recover dielectric-only captures and count the pixels called metal.

    ``families`` (each one of :data:`DIELECTRIC_FAMILIES`) × ``seeds``, ``size`` pixels square,
    ``lights`` lights (8, 12 or 17), the forward model alternating between the panel's two.
    Returns ``{"pixels", "false_metal", "rate", "upper95", "cases": [per-case rows]}``, the rate
    and its bound as fractions of the pixels.

    Raises:
        ValueError: a family that is not a dielectric one.
    """
    bad = [f for f in families if f not in DIELECTRIC_FAMILIES]
    if bad:
        raise ValueError(f"families: {bad} are not dielectric families {DIELECTRIC_FAMILIES}")
    rows, found, pixels = [], 0, 0
    for k, (fam, seed) in enumerate((f, s) for s in seeds for f in families):
        case = PanelCase(fam, seed, lights, FORWARD_MODELS[k % len(FORWARD_MODELS)], False)
        row = run_case(case, size, noise_seed)
        n = round(row["false_metal"] * size * size)
        rows.append({"case": case.name, "false_metal_pixels": n, "seconds": row["seconds"]})
        found, pixels = found + n, pixels + size * size
    upper = chi2_quantile(2 * found + 2, 0.95) / (2 * pixels)
    return {"pixels": pixels, "false_metal": found, "rate": found / pixels, "upper95": upper, "cases": rows}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.false_metal", description=__doc__.splitlines()[0])
    p.add_argument("--families", default=",".join(DIELECTRIC_FAMILIES), help="comma-separated dielectric families")
    p.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="comma-separated material seeds")
    p.add_argument("--size", type=int, default=64, help="capture size in pixels (square)")
    p.add_argument("--lights", type=int, default=12, choices=(8, 12, 17))
    p.add_argument("--json", help="also write the result to this file")
    a = p.parse_args(argv)
    out = false_metal_rate(a.families.split(","), [int(s) for s in a.seeds.split(",")], a.size, a.lights)
    for r in out["cases"]:
        print(f"  {r['case']:<36} {r['false_metal_pixels']:4d} false-metal pixels  {r['seconds']:6.1f} s")
    print(f"{out['false_metal']} of {out['pixels']} pixels called metal: rate {100 * out['rate']:.4f} %, "
          f"95 % upper bound {100 * out['upper95']:.4f} %")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
