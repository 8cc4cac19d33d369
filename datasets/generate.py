"""``python datasets/generate.py``: write synthetic multi-light captures with ground-truth maps.

Example::

    python datasets/generate.py --out cap --recipe tiles --seed 7
"""

from __future__ import annotations

import argparse
import sys

from torchbrdf.capture.synthetic import RECIPES, SOFT_RECIPES, generate_capture


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, generate one capture folder, print where it went."""
    ap = argparse.ArgumentParser(prog="python datasets/generate.py", description=__doc__.split("\n")[0].replace("``", ""))
    ap.add_argument("--out", required=True, help="capture folder to create (capture.json, img_*.exr, gt/)")
    ap.add_argument("--recipe", choices=RECIPES + SOFT_RECIPES, default=None, help="procedural material (default: chosen by --seed)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the material and the noise")
    ap.add_argument("--size", type=int, default=256, help="image width and height in pixels")
    ap.add_argument("--lights", type=int, default=16, help="number of ring lights (plus one beside the camera)")
    ap.add_argument("--noise", type=float, default=0.01, help="relative sensor noise (0.01 = 1 %%)")
    ap.add_argument("--overwrite", action="store_true", help="replace a capture already in --out (refused without it)")
    a = ap.parse_args(argv)
    try:
        path = generate_capture(a.out, recipe=a.recipe, seed=a.seed, size=a.size, lights=a.lights,
                                noise=a.noise, overwrite=a.overwrite)
    except ValueError as e:  # a bad option or an existing capture: one line and exit status 2, no traceback
        ap.error(str(e))
    print(f"wrote {path.parent}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
