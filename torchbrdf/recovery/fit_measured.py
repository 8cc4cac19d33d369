"""Fit the principled BRDF (optionally plus a second specular lobe) to a measured MERL BRDF.

Usage::

    torchbrdf-fit-merl --merl red-plastic.binary --out fit_red_plastic/ [--two-lobes]
    torchbrdf-fit-merl --demo --out fit_demo/      # no data needed: a known material, tabulated

Measured files come from the MERL BRDF database (not shipped); ``--demo`` writes a MERL file
of :data:`DEMO_MATERIAL` into ``--out`` and fits it, so the fit's error against a known truth
is in ``params.json`` (``truth_error``).

What is fitted
    The principled parameters ``base_color`` (RGB), ``metallic``, ``specular`` and
    ``roughness`` by default (``--extra subsurface,sheen,...`` adds more). Each is an
    unconstrained variable mapped by a sigmoid into its range (:data:`RANGES`), so the
    optimiser never leaves the plausible domain. ``--two-lobes`` adds a second GGX lobe with
    its own roughness and Schlick Fresnel ``(spec2_f0 RGB, spec2_f90)`` — Ngan et al.'s
    remedy for the long specular tails Burley shows in Figure 9; both Fresnel ends start
    near 0, so the second lobe is off unless the data ask for it.

Data and loss
    The samples are MERL grid nodes ``(θh, θd, φd)`` (a seeded random subset), converted to
    directions with :func:`torchbrdf.measured.merl_directions`; nodes with the light or the
    view at or below the horizon, or with missing (negative) data, are dropped. The table
    values are used as stored, so no interpolation error enters. The loss is the mean over
    samples and channels of

        ``(log(ε + c · f_model) - log(ε + c · f_measured))²``,  ``c = cos θl · cos θv``,

    a log-space error (peaks and diffuse weigh alike, as Burley's log plots suggest) of
    cosine-weighted values: the product of cosines keeps the loss symmetric in ``l`` and
    ``v`` and fades out the near-horizon data, which MERL extrapolates. ``ε = 1e-3``
    (``--eps``) sets the value below which differences stop mattering.

Optimisation
    Short Adam runs from six starting points (three roughnesses, dielectric or metal: the
    loss is not convex in either), the best continued with Adam, then polished with L-BFGS.

Outputs in ``--out``
    ``params.json`` (fitted parameters, loss, per-channel errors, settings),
    ``slices.png`` (measured vs fitted image slices and their log ratio), ``spheres.png``
    (measured vs fitted lit spheres through the shader).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import torch
from torch import Tensor, nn

from torchbrdf.brdf.measured import MERL_RES, MERLBRDF, merl_directions, merl_grid
from torchbrdf.brdf.microfacet import microfacet
from torchbrdf.brdf.principled import principled
from torchbrdf.io import file_in_the_way

__all__ = ["RANGES", "DEFAULT_PARAMS", "MeasuredSamples", "PrincipledFit", "sample_merl", "fit", "fit_errors", "main"]

F64 = torch.float64

#: Range of each fitted parameter (the sigmoid maps onto it). Roughness stops at 0.0316,
#: where the principled model floors α = roughness² at 0.001.
RANGES = {
    "base_color": (0.0, 1.0),
    "metallic": (0.0, 1.0),
    "specular": (0.0, 1.0),
    "roughness": (0.0316, 1.0),
    "subsurface": (0.0, 1.0),
    "specular_tint": (0.0, 1.0),
    "sheen": (0.0, 1.0),
    "sheen_tint": (0.0, 1.0),
    "clearcoat": (0.0, 1.0),
    "clearcoat_gloss": (0.0, 1.0),
    "roughness2": (0.0316, 1.0),
    "spec2_f0": (0.0, 1.0),
    "spec2_f90": (0.0, 1.0),
}
DEFAULT_PARAMS = ("base_color", "metallic", "specular", "roughness")
_INIT = {
    "metallic": 0.1,
    "specular": 0.5,
    "roughness": 0.5,
    "subsurface": 0.1,
    "specular_tint": 0.1,
    "sheen": 0.05,
    "sheen_tint": 0.5,
    "clearcoat": 0.05,
    "clearcoat_gloss": 0.5,
    "roughness2": 0.6,
    "spec2_f0": 0.01,
    "spec2_f90": 0.01,
}
# Keeps logit() finite for initial values at the ends of a range.
_LOGIT_MARGIN = 1e-3


class MeasuredSamples:
    """Directions and measured values at a subset of MERL nodes.

    Attributes:
        l, v: ``(N, 3)`` unit directions in the local frame (n = +Z).
        value: ``(N, 3)`` measured BRDF values.
        cos: ``(N, 1)`` ``cos θl · cos θv``.
    """

    def __init__(self, l: Tensor, v: Tensor, value: Tensor):
        self.l, self.v, self.value = l, v, value
        self.cos = l[:, 2:3] * v[:, 2:3]

    def __len__(self) -> int:
        return self.l.shape[0]


def sample_merl(
    merl: MERLBRDF, n_samples: int | None = 100_000, seed: int = 0, max_theta_deg: float | None = None
) -> MeasuredSamples:
    """Pick ``n_samples`` valid MERL nodes at random (all valid nodes when ``None``).

    Args:
        merl: the measured BRDF.
        n_samples: how many nodes to keep.
        seed: selection seed.
        max_theta_deg: drop nodes whose ``θl`` or ``θv`` exceeds this (MERL extrapolates
            beyond ~75°, Burley 2012 §4.7); default keep all and let the loss's cosine
            weight fade them.

    Returns:
        :class:`MeasuredSamples` in float64.
    """
    th, td, tp = merl_grid(F64)
    ih, idd, ip = torch.meshgrid(
        torch.arange(MERL_RES[0]), torch.arange(MERL_RES[1]), torch.arange(MERL_RES[2]), indexing="ij"
    )
    ih, idd, ip = ih.reshape(-1), idd.reshape(-1), ip.reshape(-1)
    l, v = merl_directions(th[ih], td[idd], tp[ip])
    table = merl.table.detach().to("cpu", F64).reshape(3, -1).t()
    min_cos = 1e-3 if max_theta_deg is None else max(math.cos(math.radians(max_theta_deg)), 1e-3)
    ok = (l[:, 2] > min_cos) & (v[:, 2] > min_cos) & (table >= 0).all(-1)
    idx = torch.nonzero(ok).squeeze(-1)
    if n_samples is not None and n_samples < idx.numel():
        gen = torch.Generator().manual_seed(seed)
        idx = idx[torch.randperm(idx.numel(), generator=gen)[:n_samples]]
    return MeasuredSamples(l[idx], v[idx], table[idx])


def _logit(p: float, lo: float, hi: float) -> float:
    t = min(max((p - lo) / (hi - lo), _LOGIT_MARGIN), 1 - _LOGIT_MARGIN)
    return math.log(t / (1 - t))


class PrincipledFit(nn.Module):
    """Principled parameters (plus an optional second GGX lobe) as sigmoid-mapped variables.

    Args:
        names: principled parameters to fit (others keep the model's defaults, except
            ``sheen``/``clearcoat``, which stay 0 unless fitted).
        two_lobes: add the second specular lobe (``roughness2``, ``spec2_f0``, ``spec2_f90``).
        init: starting values (floats; ``base_color`` a float or 3 floats).

    Shape:
        ``forward(l, v, n)``: ``(N, 3)`` directions → ``(N, 3)`` BRDF values.
    """

    def __init__(self, names: Iterable[str] = DEFAULT_PARAMS, two_lobes: bool = False,
                 init: dict | None = None) -> None:
        super().__init__()
        names = list(names)
        if "base_color" not in names:
            names.insert(0, "base_color")
        if two_lobes:
            names += ["roughness2", "spec2_f0", "spec2_f90"]
        unknown = [n for n in names if n not in RANGES]
        if unknown:
            raise ValueError(f"cannot fit {unknown}; fittable: {sorted(RANGES)}")
        self.names = names
        self.two_lobes = two_lobes
        init = {**_INIT, "base_color": 0.5, **(init or {})}
        self.raw = nn.ParameterDict()
        for name in names:
            lo, hi = RANGES[name]
            width = 3 if name in ("base_color", "spec2_f0") else 1
            val = init[name]
            vals = [float(x) for x in (val if isinstance(val, (list, tuple, Tensor)) else [val] * width)]
            self.raw[name] = nn.Parameter(torch.tensor([_logit(x, lo, hi) for x in vals], dtype=F64))

    def values(self) -> dict[str, Tensor]:
        """The constrained parameters, ``(3,)`` or ``(1,)`` tensors."""
        out = {}
        for name, raw in self.raw.items():
            lo, hi = RANGES[name]
            out[name] = lo + (hi - lo) * torch.sigmoid(raw)
        return out

    def principled_params(self) -> dict[str, Tensor]:
        """The principled keyword arguments (without the second lobe)."""
        return {k: t for k, t in self.values().items() if k not in ("roughness2", "spec2_f0", "spec2_f90")}

    def forward(self, l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None) -> Tensor:
        """BRDF value ``(N, 3)`` at directions ``(N, 3)``."""
        p = self.values()
        f = principled(l, v, n, x, y, **self.principled_params())
        if self.two_lobes:
            alpha2 = p["roughness2"] * p["roughness2"]
            f = f + microfacet(
                l, v, n, x, y, alpha=alpha2, fresnel="schlick", f0=p["spec2_f0"], f90=p["spec2_f90"]
            ).expand_as(f)
        return f

    def to_json(self) -> dict:
        """Parameters as plain floats / lists."""
        with torch.no_grad():
            vals = self.values()
        return {k: (t.tolist() if t.numel() > 1 else t.item()) for k, t in vals.items()}


def _loss_terms(model: nn.Module, s: MeasuredSamples, eps: float) -> Tensor:
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(s.l)
    pred = model(s.l, s.v, n)
    return (torch.log(eps + s.cos * pred) - torch.log(eps + s.cos * s.value)) ** 2


def fit_errors(model: nn.Module, s: MeasuredSamples, eps: float = 1e-3) -> dict:
    """Per-channel fit errors of ``model`` on samples ``s``.

    Returns:
        ``{"log_rmse": [r, g, b], "rel_rmse": [r, g, b], "loss": float}``: the RMS of the
        loss residual per channel, and the relative RMS error of the cosine-weighted values
        ``sqrt(Σ (c f̂ - c f)² / Σ (c f)²)`` per channel.
    """
    with torch.no_grad():
        n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(s.l)
        pred = model(s.l, s.v, n)
        r = torch.log(eps + s.cos * pred) - torch.log(eps + s.cos * s.value)
        a, b = s.cos * pred, s.cos * s.value
        rel = torch.sqrt(((a - b) ** 2).sum(0) / (b**2).sum(0).clamp(min=1e-30))
        return {
            "log_rmse": r.pow(2).mean(0).sqrt().tolist(),
            "rel_rmse": rel.tolist(),
            "loss": float(r.pow(2).mean()),
        }


def _initial_base_color(s: MeasuredSamples) -> list[float]:
    """Diffuse-region estimate: median of ``π f`` away from the specular peak and grazing angles."""
    h = torch.nn.functional.normalize(s.l + s.v, dim=-1)
    away = (h[:, 2] < math.cos(math.radians(25))) & (s.l[:, 2] > 0.5) & (s.v[:, 2] > 0.5)
    vals = s.value[away] if int(away.sum()) >= 16 else s.value
    return (vals.median(0).values * math.pi).clamp(0.02, 0.98).tolist()


def _adam(model, s, eps, iters, lr, log=None, tag=""):
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    loss = None
    for i in range(iters):
        opt.zero_grad()
        loss = _loss_terms(model, s, eps).mean()
        loss.backward()
        opt.step()
        if log and (i % max(iters // 5, 1) == 0 or i == iters - 1):
            log(f"  {tag}adam {i:4d}  loss {loss.item():.5f}")
    return loss.item() if loss is not None else float("nan")


def fit(
    samples: MeasuredSamples,
    *,
    names: Iterable[str] = DEFAULT_PARAMS,
    two_lobes: bool = False,
    iters: int = 300,
    lbfgs_iters: int = 30,
    restarts: Sequence[tuple[float, float]] = ((0.15, 0.05), (0.4, 0.05), (0.75, 0.05), (0.15, 0.9), (0.4, 0.9), (0.75, 0.9)),
    restart_iters: int | None = None,
    lr: float = 0.05,
    eps: float = 1e-3,
    log: Callable[[str], object] | None = print,
) -> PrincipledFit:
    """Fit principled parameters to measured samples.

    Args:
        samples: from :func:`sample_merl`.
        names: principled parameters to fit (``base_color`` always is).
        two_lobes: add the second GGX lobe.
        iters: Adam iterations after the restarts.
        lbfgs_iters: L-BFGS iterations (strong-Wolfe line search) at the end; 0 to skip.
        restarts: ``(roughness, metallic)`` starting points tried with short Adam runs; the
            best is continued. Dielectric starts take the base colour from the diffuse
            region of the data, metallic ones a light grey (a metal's colour is in its
            specular peak), since starting a metal from a dark diffuse estimate gets stuck
            at metallic = 0.
        restart_iters: Adam iterations per restart (default ``max(iters // 5, 10)``).
        lr: Adam learning rate (on the sigmoid logits).
        eps: the loss's ε.
        log: progress printer (``None`` for silence).

    Returns:
        The fitted :class:`PrincipledFit`.
    """
    base = _initial_base_color(samples)
    restart_iters = max(iters // 5, 10) if restart_iters is None else restart_iters
    best, best_loss = None, math.inf
    for r0, m0 in restarts:
        init = {"base_color": base if m0 < 0.5 else 0.7, "roughness": r0}
        if "metallic" in names:
            init["metallic"] = m0
        elif m0 >= 0.5:
            continue  # metallic is not fitted: the metal starts make no sense
        model = PrincipledFit(names, two_lobes, init=init)
        loss = _adam(model, samples, eps, restart_iters, lr, log, tag=f"r0={r0:g} m0={m0:g} ")
        if loss < best_loss:
            best, best_loss = model, loss
    assert best is not None
    _adam(best, samples, eps, iters, lr, log)
    if lbfgs_iters > 0:
        opt = torch.optim.LBFGS(best.parameters(), lr=1.0, max_iter=lbfgs_iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = _loss_terms(best, samples, eps).mean()
            loss.backward()
            return loss

        opt.step(closure)
        if log:
            log(f"  lbfgs       loss {float(_loss_terms(best, samples, eps).mean().detach()):.5f}")
    return best


def write_outputs(out: Path, merl: MERLBRDF, model: PrincipledFit, report: dict, figures: bool = True) -> None:
    """Write ``params.json`` and (when ``figures``) ``slices.png`` and ``spheres.png`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "params.json").write_text(json.dumps(report, indent=2))
    if not figures:
        return
    from torchbrdf.recovery.fit_figures import slice_comparison_figure, spheres_figure

    fitted = _frozen(model)
    fig = slice_comparison_figure(merl, fitted, labels=(merl.name or "measured", "fitted"))
    fig.savefig(out / "slices.png")
    fig = spheres_figure([(merl.name or "measured", merl), ("fitted", fitted)], resolution=128)
    fig.savefig(out / "spheres.png")


def _demo_errors(params: dict) -> dict:
    """Absolute error of each fitted value of :data:`DEMO_MATERIAL` (the largest over channels)."""
    out = {}
    for k, want in DEMO_MATERIAL.items():
        if k in params:
            got = torch.as_tensor(params[k], dtype=F64)
            out[k] = float((got - torch.as_tensor(want, dtype=F64)).abs().max())
    return out


def _frozen(model: PrincipledFit):
    """A parameter-free, no-grad BRDF callable of the fitted model."""

    def f(l, v, n, x=None, y=None):
        with torch.no_grad():
            return model(l.to(F64), v.to(F64), n.to(F64), None, None).to(l.dtype)

    return f


#: The known material of ``--demo``: a partly metallic copper-coloured principled BRDF, so base
#: colour, roughness and metallic all shape the data.
DEMO_MATERIAL = {"base_color": (0.7, 0.35, 0.15), "roughness": 0.3, "metallic": 0.4, "specular": 0.5}
DEMO_FILE = "demo_principled.binary"


def write_demo_merl(folder: Path) -> Path:
    """Tabulate :data:`DEMO_MATERIAL` into ``folder``/:data:`DEMO_FILE` (MERL binary layout); its path."""
    from torchbrdf.brdf.measured import write_merl

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / DEMO_FILE
    params = {k: torch.tensor(v, dtype=F64) if isinstance(v, tuple) else v for k, v in DEMO_MATERIAL.items()}
    write_merl(path, principled, **params)
    return path


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(
        prog="torchbrdf-fit-merl", description=__doc__.split("\n\n")[0],
        epilog="Measured data: the MERL BRDF database (Matusik et al. 2003, 100 isotropic materials as "
               "*.binary files) is not shipped with torchbrdf; download it from MERL's BRDF database page "
               "and pass one file with --merl. --demo needs no data: it writes a MERL file from a known "
               "principled material (DEMO_MATERIAL) into --out and fits it, reporting the fit's error "
               "against that truth.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--merl", help="MERL .binary file")
    src.add_argument("--demo", action="store_true",
                     help=f"fit a synthetic MERL file ({DEMO_FILE}, written into --out) of a known material")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--two-lobes", action="store_true", help="add a second GGX specular lobe")
    ap.add_argument("--extra", default="", help="more principled parameters to fit, comma separated "
                    "(subsurface, specular_tint, sheen, sheen_tint, clearcoat, clearcoat_gloss)")
    ap.add_argument("--samples", type=int, default=100_000, help="MERL nodes used (random subset)")
    ap.add_argument("--iters", type=int, default=200, help="Adam iterations after the restarts")
    ap.add_argument("--lbfgs", type=int, default=100, help="L-BFGS iterations at the end (0: none)")
    ap.add_argument("--eps", type=float, default=1e-3, help="ε of the log loss")
    ap.add_argument("--max-theta", type=float, default=None, help="ignore data with θl or θv above this (degrees)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random subset of MERL nodes (--samples)")
    ap.add_argument("--no-figures", action="store_true", help="write params.json only")
    args = ap.parse_args(argv)
    # refused before the MERL file (35 MB) is read or written, in one line each
    names = list(DEFAULT_PARAMS) + [n.strip() for n in args.extra.split(",") if n.strip()]
    extra = sorted(set(RANGES) - set(DEFAULT_PARAMS) - {"roughness2", "spec2_f0", "spec2_f90"})
    # (the second lobe's names are --two-lobes's: fitted alone they would not enter the model)
    if [n for n in names if n not in (*DEFAULT_PARAMS, *extra)] or len(set(names)) < len(names):
        ap.error(f"--extra {args.extra!r}: expected distinct names among {', '.join(extra)} (comma separated)")
    for flag, value, least in (("--samples", args.samples, 1), ("--iters", args.iters, 0), ("--lbfgs", args.lbfgs, 0)):
        if value < least:
            ap.error(f"{flag} must be at least {least}, got {value}")
    if (blocked := file_in_the_way(args.out)) is not None:
        ap.error(f"--out {args.out}: {blocked} is a file, not a folder")

    t0 = time.perf_counter()
    if args.demo:
        args.merl = str(write_demo_merl(Path(args.out)))
        print(f"fit_measured: --demo wrote {args.merl} from {DEMO_MATERIAL}")
    try:
        merl = MERLBRDF.from_file(args.merl)
    except (OSError, ValueError) as e:
        ap.error(f"--merl: {e}")
    samples = sample_merl(merl, args.samples, args.seed, args.max_theta)
    print(f"fit_measured: {merl.name}, {len(samples)} samples, fitting {names}{' + second lobe' if args.two_lobes else ''}")
    model = fit(samples, names=names, two_lobes=args.two_lobes, iters=args.iters, lbfgs_iters=args.lbfgs, eps=args.eps)
    errors = fit_errors(model, samples, args.eps)
    seconds = time.perf_counter() - t0
    report = {
        "merl": str(args.merl),
        "params": model.to_json(),
        "two_lobes": args.two_lobes,
        "fitted": model.names,
        "errors": errors,
        "loss": errors["loss"],
        "samples": len(samples),
        "eps": args.eps,
        "max_theta_deg": args.max_theta,
        "seconds": seconds,
    }
    if args.demo:
        report["truth"] = DEMO_MATERIAL
        report["truth_error"] = _demo_errors(model.to_json())
    write_outputs(Path(args.out), merl, model, report, figures=not args.no_figures)
    print(json.dumps({"params": report["params"], "errors": errors}, indent=2))
    print(f"wrote {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
