"""Compare BRDFs side by side in a one-page HTML report, in the spirit of BRDF Explorer.

Usage::

    python -m torchbrdf.analysis.explore --out report/ \\
        --brdf "principled:roughness=0.3,base_color=0.8/0.2/0.1" \\
        --brdf "microfacet:alpha=0.09,fresnel=dielectric,diffuse=0.8/0.2/0.1" \\
        --brdf merl:path/to/red-plastic.binary

With no ``--brdf`` it compares the principled model at two roughnesses with GGX + exact
dielectric Fresnel over a Lambert base. ``--preset roughness`` shows the principled model
across roughness (Burley's Figure 17), ``--preset g-models`` the albedo of several masking
terms under one GGX D and Schlick F (Figure 12). The report (``index.html`` with PNGs beside it) has
image slices, lit spheres, albedo curves, retro-reflection and specular-peak curves, polar
plots and a table of numbers (albedo, white-furnace and reciprocity checks).

BRDF specs: ``MODEL[:key=value,key=value,...]``

* ``MODEL`` is ``principled``, ``lambert``, ``microfacet``, ``merl`` (whose argument is the
  path of a MERL ``.binary`` file: ``merl:PATH``, optionally ``merl:PATH,label=NAME``) or
  ``fit`` (the ``params.json`` written by ``torchbrdf-fit-merl``: ``fit:PATH``),
  so a fitted model can sit beside the measured data it was fitted to;
* values are numbers, RGB triples written ``r/g/b`` (linear), or words (``fresnel=dielectric``);
* ``label=NAME`` names the column; for ``microfacet``, ``diffuse=r/g/b`` adds a Lambert term;
  for ``principled``, ``lobes=diffuse/specular`` keeps only the named lobes.
"""

from __future__ import annotations

import argparse
import html
import inspect
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import torch

from torchbrdf._types import BRDF
from torchbrdf.analysis import measures as A
from torchbrdf.analysis import plots as P
from torchbrdf.io import file_in_the_way

__all__ = ["BRDFSpec", "parse_spec", "parameter_names", "write_report", "main", "DEFAULT_SPECS"]

DEFAULT_SPECS = (
    "principled:roughness=0.2,base_color=0.8/0.25/0.1,label=principled r=0.2",
    "principled:roughness=0.6,base_color=0.8/0.25/0.1,label=principled r=0.6",
    "microfacet:alpha=0.04,fresnel=dielectric,ior=1.5,diffuse=0.8/0.25/0.1,label=GGX a=0.04 + exact Fresnel + Lambert",
)
#: Named comparisons for ``--preset``.
PRESETS = {
    "default": DEFAULT_SPECS,
    # The principled model across roughness (Burley 2012, Figure 17).
    "roughness": tuple(
        f"principled:roughness={r},base_color=0.8/0.25/0.1,label=principled r={r}" for r in (0.1, 0.3, 0.6, 0.9)
    ),
    # Albedo of several G models with the same GGX D and Schlick F (Burley 2012, Figure 12);
    # "implicit" (G = n·l n·v) is the notes' "no G" model. Use with alpha=0.02 or 0.5.
    "g-models": tuple(
        f"microfacet:alpha=0.5,f0=0.04,masking={m},label={m}"
        for m in ("smith_correlated", "smith_separable", "cook_torrance", "kelemen", "implicit")
    ),
}
MODELS = ("principled", "lambert", "microfacet", "merl", "fit")


def _model_function(model: str) -> Callable[..., Any]:
    if model == "principled":
        from torchbrdf.brdf.principled import principled

        return principled
    if model == "lambert":
        from torchbrdf.brdf.lambert import lambert

        return lambert
    from torchbrdf.brdf.microfacet import microfacet

    return microfacet


def parameter_names(model: str) -> tuple[str, ...]:
    """The ``key=value`` names a ``--brdf`` spec of ``model`` takes (none for ``merl`` and ``fit``).

    Example:
        >>> parameter_names("lambert")
        ('base_color',)
    """
    if model in ("merl", "fit"):
        return ()
    params = inspect.signature(_model_function(model)).parameters.values()
    # keyword-only: the material; lambert's **ignored would otherwise swallow any typo silently
    names = tuple(p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY)
    return names + ("diffuse",) if model == "microfacet" else names


@dataclass
class BRDFSpec:
    """A parsed ``--brdf`` argument.

    Attributes:
        model: one of :data:`MODELS`.
        params: material parameters (floats, ``(3,)`` float64 tensors, strings).
        label: column title.
        path: MERL file for ``model == "merl"``.
    """

    model: str
    params: dict[str, Any] = field(default_factory=dict)
    label: str = ""
    path: str | None = None
    _loaded: Any = field(default=None, init=False, repr=False, compare=False)

    def brdf(self) -> BRDF:
        """The parameter-free callable ``f(l, v, n, x=None, y=None) -> (*, 3)``, loaded once.

        Raises:
            OSError: the MERL or params file does not exist or cannot be read.
            ValueError: the file is not a MERL file or a ``torchbrdf-fit-merl`` params.json.
        """
        if self._loaded is None:
            self._loaded = self._load()
        return self._loaded

    def _load(self) -> BRDF:
        if self.model == "principled":
            return A.bind_brdf(_model_function("principled"), **self.params)
        if self.model == "lambert":
            return A.bind_brdf(_model_function("lambert"), **{"base_color": 0.8, **self.params})
        if self.model == "microfacet":
            params = dict(self.params)
            diffuse = params.pop("diffuse", None)
            spec = A.bind_brdf(_model_function("microfacet"), **params)
            if diffuse is None:
                return spec
            kd = torch.as_tensor(diffuse, dtype=torch.float64) / math.pi

            def with_diffuse(l, v, n, x=None, y=None):
                ok = ((l * n).sum(-1, keepdim=True) > 0) & ((v * n).sum(-1, keepdim=True) > 0)
                return spec(l, v, n, x, y) + torch.where(ok, kd.to(l.dtype), torch.zeros((), dtype=l.dtype))

            with_diffuse.params = spec.params  # type: ignore[attr-defined]
            return with_diffuse
        path = cast(str, self.path)  # merl and fit specs carry a path (parse_spec requires one)
        if self.model == "fit":
            return _fitted_brdf(path)
        from torchbrdf.brdf.measured import MERLBRDF

        return MERLBRDF.from_file(path)


def _fitted_brdf(path: str):
    """The BRDF described by a ``training.fit_measured`` ``params.json``."""
    from torchbrdf.brdf.microfacet import microfacet
    from torchbrdf.brdf.principled import principled

    try:
        fitted = json.loads(Path(path).read_text())["params"]
    except FileNotFoundError as e:
        raise FileNotFoundError(f"params file '{path}' not found (no such file)") from e
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"'{path}' is not a params.json of torchbrdf-fit-merl (a JSON object with "
                         f"'params'): {e!r}") from e
    lobe2 = {k: fitted.pop(k) for k in ("roughness2", "spec2_f0", "spec2_f90") if k in fitted}
    params = {k: (torch.tensor(v, dtype=torch.float64) if isinstance(v, list) else float(v)) for k, v in fitted.items()}
    base = A.bind_brdf(principled, **params)
    if not lobe2:
        return base
    second = A.bind_brdf(
        microfacet,
        alpha=float(lobe2["roughness2"]) ** 2,
        f0=torch.tensor(lobe2["spec2_f0"], dtype=torch.float64),
        f90=float(lobe2["spec2_f90"]),
    )

    def two_lobes(l, v, n, x=None, y=None):
        return base(l, v, n, x, y) + second(l, v, n, x, y)

    two_lobes.params = params  # type: ignore[attr-defined]
    return two_lobes


def _value(text: str):
    if "/" in text:
        parts = text.split("/")
        try:
            return torch.tensor([float(p) for p in parts], dtype=torch.float64)
        except ValueError:
            return text
    try:
        return float(text)
    except ValueError:
        return text


def parse_spec(spec: str) -> BRDFSpec:
    """Parse ``MODEL[:key=value,...]`` (see the module docstring).

    Example:
        >>> s = parse_spec("principled:roughness=0.3,base_color=0.8/0.2/0.1")
        >>> s.model, s.params["roughness"], s.label
        ('principled', 0.3, 'principled roughness=0.3 base_color=0.8/0.2/0.1')
    """
    model, _, rest = spec.partition(":")
    model = model.strip().lower()
    if model not in MODELS:
        raise ValueError(f"--brdf {spec!r}: unknown model {model!r}; expected one of {MODELS}")
    out = BRDFSpec(model)
    items = [p for p in rest.split(",") if p.strip()] if rest else []
    if model in ("merl", "fit"):
        if not items or "=" in items[0]:
            raise ValueError(f"--brdf {spec!r}: {model} needs a file, e.g. {model}:path/to/file")
        out.path = items[0].strip()
        items = items[1:]
    for item in items:
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"--brdf {spec!r}: expected key=value, got {item!r}")
        key, val = key.strip(), val.strip()
        if key == "label":
            out.label = val
        elif key not in parameter_names(model):
            raise ValueError(f"--brdf {spec!r}: {model} has no parameter {key!r}; it takes "
                             f"{', '.join(parameter_names(model)) or 'only a file'} (and label)")
        elif key == "lobes":  # names, not a colour: lobes=diffuse/specular
            out.params[key] = tuple(w.strip() for w in val.split("/"))
        else:
            out.params[key] = _value(val)
    if model == "principled":
        out.params.setdefault("base_color", torch.tensor([0.8, 0.8, 0.8], dtype=torch.float64))
    if not out.label:
        # (the casts: merl and fit specs always have a path, set above)
        if model == "merl":
            out.label = Path(cast(str, out.path)).stem
        elif model == "fit":
            out.label = f"fit {Path(cast(str, out.path)).parent.name}"
        else:
            shown = " ".join(f"{k}={v}" for k, v in _readable(out.params).items())
            out.label = f"{model} {shown}".strip()
    return out


def _readable(params: dict) -> dict:
    return {
        k: ("/".join(f"{x:g}" for x in v.tolist()) if isinstance(v, torch.Tensor) else
            "/".join(v) if isinstance(v, tuple) else v) for k, v in params.items()
    }


def _white(spec: BRDFSpec) -> dict | None:
    """Parameters of the same model with white colours (for the furnace), or None for data."""
    if spec.model in ("merl", "fit"):
        return None
    p = dict(spec.params)
    if spec.model in ("principled", "lambert"):
        p["base_color"] = 1.0
    if spec.model == "microfacet" and "diffuse" in p:
        p["diffuse"] = torch.ones(3, dtype=torch.float64)
    return p


def write_report(
    specs: list[BRDFSpec], out: str | Path, *, quick: bool = False, log: Callable[[str], object] = print
) -> Path:
    """Compute every view for ``specs`` and write ``out/index.html`` with its PNGs.

    Args:
        specs: parsed BRDF specs (two or more for a comparison; one works too).
        out: output folder (created).
        quick: smaller images and grids (for tests and previews).
        log: progress printer.

    Returns:
        Path of ``index.html``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    entries = [(s.label, s.brdf()) for s in specs]
    res = 48 if quick else 128
    sphere_res = 48 if quick else 160
    theta_curve = torch.deg2rad(torch.arange(0.0, 90.0, 10.0 if quick else 2.0, dtype=torch.float64))
    samples = (8, 32) if quick else None

    figures = {
        "slices.png": ("Image slices (φd = 90°)", lambda: P.plot_image_slices(entries, res)),
        "slices_phid45.png": ("Image slices (φd = 45°)", lambda: P.plot_image_slices(entries, res, math.radians(45))),
        "spheres.png": ("Lit spheres", lambda: P.plot_spheres(entries, sphere_res)),
        "albedo.png": ("Albedo vs view angle", lambda: P.plot_albedo_curves(entries, theta_curve, samples=samples)),
        "retro.png": ("Retro-reflection", lambda: P.plot_retro_reflection(entries)),
        "peak.png": ("Specular peak", lambda: P.plot_specular_peaks(entries)),
        "polar.png": ("Polar lobes", lambda: P.plot_polar_lobes(entries)),
    }
    for name, (title, make) in figures.items():
        t0 = time.perf_counter()
        fig = make()
        fig.savefig(out / name)
        log(f"  {name:18s} {time.perf_counter() - t0:5.1f} s")

    rows = []
    summary = []
    check_angles = torch.deg2rad(torch.tensor([0.0, 60.0, 85.0], dtype=torch.float64))
    for spec, (label, f) in zip(specs, entries):
        alb = A.directional_albedo(f, check_angles, samples=samples)
        rec = A.reciprocity_error(f, 512 if quick else 4096)
        white = _white(spec)
        furnace = None
        if white is not None:
            wf = A.white_furnace(BRDFSpec(spec.model, white).brdf(), samples=samples)
            furnace = (wf.max_albedo, wf.passed)
        lum = P.luminance(alb.value)
        summary.append(
            {
                "label": label,
                "model": spec.model,
                "params": {k: (v.tolist() if isinstance(v, torch.Tensor) else v) for k, v in spec.params.items()},
                "path": spec.path,
                "albedo_luminance_0_60_85": [round(float(x), 4) for x in lum],
                "reciprocity_max_rel": rec.max_rel,
                "white_furnace_max": None if furnace is None else furnace[0],
            }
        )
        furnace_txt = "—" if furnace is None else f"{furnace[0]:.3f} ({'≤ 1' if furnace[1] else '> 1: gains energy'})"
        rows.append(
            "<tr>"
            f"<td>{html.escape(label)}</td><td>{html.escape(spec.model)}</td>"
            f"<td><code>{html.escape(', '.join(f'{k}={v}' for k, v in _readable(spec.params).items()) or (spec.path or ''))}</code></td>"
            f"<td>{' / '.join(f'{x:.3f}' for x in lum)}</td>"
            f"<td>{furnace_txt}</td><td>{rec.max_rel:.1e}</td>"
            "</tr>"
        )
    (out / "summary.json").write_text(json.dumps(summary, indent=2))

    def img(name):
        title = figures[name][0]
        return f'<figure><img src="{name}" alt="{html.escape(title)}"><figcaption>{html.escape(title)}</figcaption></figure>'

    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>torchbrdf explore</title>
<style>
body {{ font-family: sans-serif; max-width: 1400px; margin: 1em auto; color: #222; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.9em; }}
td, th {{ border: 1px solid #ccc; padding: 3px 8px; text-align: left; }}
figure {{ display: inline-block; margin: 0.3em; vertical-align: top; }}
img {{ max-width: 100%; }}
figcaption {{ font-size: 0.8em; color: #555; }}
p.note {{ font-size: 0.85em; color: #444; max-width: 60em; }}
</style></head><body>
<h1>BRDF comparison</h1>
<table><tr><th>BRDF</th><th>model</th><th>parameters</th><th>albedo (lum.) at θv = 0° / 60° / 85°</th>
<th>white furnace: max albedo with white colours</th><th>reciprocity: max rel. error</th></tr>
{''.join(rows)}
</table>
<p class="note">Image slices follow Burley 2012, Figure 3: θh to the right, θd upward; the left edge is the
specular peak, the bottom edge retro-reflection (l = v), the top edge the Fresnel peak. Slices show π·f
clipped at 1 (a white Lambert surface is white). Spheres: one directional light of irradiance π from the upper
left. Albedo is the directional–hemispherical reflectance by half-vector Gauss–Legendre quadrature (band:
error estimate; dotted: R, G, B).</p>
<h2>Slices and spheres</h2>
{img('slices.png')}<br>{img('slices_phid45.png')}<br>{img('spheres.png')}
<h2>Curves</h2>
{img('albedo.png')}{img('retro.png')}{img('peak.png')}
<h2>Lobes</h2>
{img('polar.png')}
</body></html>
"""
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    return index


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(
        prog="torchbrdf-explore", description=__doc__.split("\n\n")[0],
        epilog=__doc__[__doc__.index("BRDF specs:"):].replace("``", "") + "\nParameters per model: " + "; ".join(
            f"{m}: {', '.join(parameter_names(m))}" for m in ("principled", "lambert", "microfacet")) + ".",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="explore_report", help="output folder (default: explore_report)")
    ap.add_argument("--brdf", action="append", default=[], metavar="SPEC", help="MODEL[:key=value,...]; repeat to compare")
    ap.add_argument("--preset", choices=sorted(PRESETS), help="a named comparison (added before any --brdf)")
    ap.add_argument("--quick", action="store_true", help="small images and grids (fast preview)")
    args = ap.parse_args(argv)
    texts = list(PRESETS[args.preset]) if args.preset else []
    texts += args.brdf
    try:
        specs = [parse_spec(s) for s in (texts or DEFAULT_SPECS)]
    except ValueError as e:
        ap.error(str(e))
    # Load every file and evaluate each BRDF once before --out is touched, so that a missing
    # file or a value the model refuses is one line, not a traceback in a half-written report.
    unit = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    for text, spec in zip(texts or DEFAULT_SPECS, specs):
        try:
            spec.brdf()(unit, unit, unit)
        except (OSError, ValueError, TypeError, KeyError, RuntimeError) as e:
            ap.error(f"--brdf {text!r}: {e}")
    if (blocked := file_in_the_way(args.out)) is not None:
        ap.error(f"--out {args.out}: {blocked} is a file, not a folder")
    try:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--out {args.out}: cannot create the folder ({e.strerror or e})")
    t0 = time.perf_counter()
    print(f"explore: {len(specs)} BRDF(s) -> {args.out}")
    index = write_report(specs, args.out, quick=args.quick)
    print(f"wrote {index} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
