"""``python -m torchbrdf.bench.silent_profile``: what the data support where a region's roughness is silent.

For one recovery-panel case of the *tuning* split (report seeds are refused: they are run only
to report), the capture is recovered as the panel does, and each region of the truth that is one
material (pixels sharing the truth's specular value, at least :data:`MIN_REGION` of the image:
a tile's glazed face, the grout, a lacquer) gets its pooled roughness profile
(:func:`torchbrdf.recovery.profile.roughness_profile`, summed over the region's pixels): the
truth's roughness, the fitted one (mean), the profile's minimum and how much lower the data cost
is there than at the fit, in noise variances ``σ²`` (the median pixel's cost per residual).
Each pixel's own posterior mean along the profile (a uniform prior over roughness in map units,
each grid value weighing its cell's width, likelihood ``exp(−cost / 2σ²)``) is the per-pixel
estimate of least expected squared error; its region mean is reported too.
Two oracle rows then score the maps again (:func:`score_maps`): *pooled* moves every region whose
pooled minimum fits better than the fit to its refit at that grid value (what a material-level
estimate from the data alone would give, with the truth's segmentation); *posterior* moves each
pixel of every region to its refit at the grid value nearest its own posterior mean.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections.abc import Sequence

import torch

from torchbrdf.bench.recovery_panel import PanelCase, case_seed, render_case, score_maps
from torchbrdf.capture.format import load_capture
from torchbrdf.recovery.classes import residual_variance
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import pixel_cost
from torchbrdf.recovery.params import decode, encode
from torchbrdf.recovery.profile import pooled_minimum, roughness_profile

__all__ = ["GRID", "MIN_REGION", "material_regions", "posterior_mean", "silent_profile", "main"]

#: Roughness values of the profile: dense where glazes live (0.15–0.35), coarse over the rest.
GRID: tuple[float, ...] = (0.1, 0.15, 0.18, 0.2, 0.22, 0.24, 0.26, 0.28, 0.3, 0.35, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)

#: A region's least share of the image: a material's area, not a blend at its border.
MIN_REGION = 1 / 64


def material_regions(specular: torch.Tensor, min_fraction: float = MIN_REGION) -> list[torch.Tensor]:
    """Pixel sets ``(N,)`` (int64, row-major) of a truth specular map ``(1, S, S)`` that share one value
    (to 1e-3) and cover at least ``min_fraction`` of the image, largest first."""
    keys = torch.round(specular.reshape(-1).double() * 1000).long()
    vals, counts = torch.unique(keys, return_counts=True)
    keep = [v for v, c in sorted(zip(vals.tolist(), counts.tolist()), key=lambda x: -x[1])
            if c >= min_fraction * keys.numel()]
    return [torch.nonzero(keys == v)[:, 0] for v in keep]


def posterior_mean(grid: Sequence[float], costs: torch.Tensor, sigma2: float) -> torch.Tensor:
    """Each pixel's posterior mean roughness ``(N,)`` from its profile ``costs (N, K)`` on ``grid``
    (ascending, map units): likelihood ``exp(−cost / 2σ²)``, a uniform prior in map units (each
    grid value weighs the width of its cell, halfway to its neighbours). A pixel with no finite
    cost has no likelihood: its mean is the prior's."""
    g = torch.tensor([float(x) for x in grid], dtype=torch.float64)
    edges = torch.cat((g[:1], (g[1:] + g[:-1]) / 2, g[-1:]))
    c = torch.nan_to_num(costs.double(), nan=float("inf"), posinf=float("inf"), neginf=float("inf"))
    c = torch.where(torch.isfinite(c).any(1, keepdim=True), c, torch.zeros_like(c))
    logw = torch.log(edges[1:] - edges[:-1]) - 0.5 * c / sigma2
    return (torch.softmax(logw, 1) * g).sum(1)


def _flat(x: torch.Tensor) -> torch.Tensor:
    return x.reshape(x.shape[0], -1).T


def silent_profile(case: PanelCase, size: int = 128, grid: Sequence[float] = GRID, iters: int = 10) -> dict:
    """Recover ``case`` and profile each of its truth's material regions (see the module docstring).

    Returns ``{"case", "sigma2", "regions": [{"pixels", "true", "fitted", "pooled", "gain_sigma2",
    "posterior_mean"}], "scores", "oracle_scores", "posterior_scores"}``; ``gain_sigma2`` is the fitted cost minus the cost at the pooled
    grid minimum, summed over the region, in noise variances (> 0: the data prefer the minimum).

    Raises:
        ValueError: a case of the report split.
    """
    if case.split != "tuning":
        raise ValueError(f"case: {case.name} is a report case; profile tuning cases only")
    from torchbrdf.recovery import RecoveryConfig, recover

    with tempfile.TemporaryDirectory(prefix="silent_") as tmp:
        truth, _ = render_case(case, tmp, size)
        # as the panel recovers it: one thread, every captured light in the fit
        res = recover(tmp, RecoveryConfig(threads=1, holdout=-1), progress=False, log=lambda m: None)
        cap = load_capture(tmp)
    maps = res.maps
    data = LevelData(cap, size, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    data.set_light_scale(torch.log(torch.tensor([res.report["light_intensity_scale"][f] for f in cap.files])))
    data.set_light_offset(torch.tensor([res.report["light_position_offset"][f] for f in cap.files]))
    theta = encode({k: _flat(maps[k].float()) for k in ("base_color", "specular", "roughness", "normal")})
    metal = _flat(maps["metallic"].float())
    with torch.no_grad():
        fit_cost = pixel_cost(data.residual(theta, metal, data.train_idx))[:, 0]
        sigma2 = residual_variance(fit_cost[:, None], 3 * len(data.train_idx))
        moved, own = theta.clone(), theta.clone()
        regions = []
        for rows in material_regions(truth["specular"]):
            costs, fits = roughness_profile(data, theta, metal, rows, grid, iters=iters)
            r_min, k = pooled_minimum(grid, costs)
            gain = float((fit_cost[rows].double().sum() - costs[:, k].double().sum()) / sigma2)
            post = posterior_mean(grid, costs, sigma2)
            regions.append({"pixels": int(rows.numel()), "true": float(_flat(truth["roughness"])[rows].mean()),
                            "fitted": float(_flat(maps["roughness"])[rows].mean()), "pooled": r_min,
                            "gain_sigma2": gain, "posterior_mean": float(post.mean())})
            nearest = (post[:, None] - torch.tensor(grid, dtype=torch.float64)).abs().argmin(1)
            own[rows] = fits[torch.arange(rows.numel()), nearest]
            if gain > 0:
                moved[rows] = fits[:, k]
    seed = case_seed(case)
    return {"case": case.name, "sigma2": sigma2, "regions": regions,
            "scores": score_maps(maps, truth, case.model, seed=seed),
            "oracle_scores": score_maps(_maps(moved, metal, size), truth, case.model, seed=seed),
            "posterior_scores": score_maps(_maps(own, metal, size), truth, case.model, seed=seed)}


def _maps(theta: torch.Tensor, metal: torch.Tensor, size: int) -> dict[str, torch.Tensor]:
    """``(C, S, S)`` maps of ``theta (S², 7)``, ``metal (S², 1)``, a metal's specular written as 0.5."""
    out = {k: v.T.reshape(-1, size, size) for k, v in decode(theta, metal).items()}
    out["specular"] = torch.where(out["metallic"] >= 1, 0.5, out["specular"])
    return out


def _case(name: str) -> PanelCase:
    """``family/seed L<lights> <model>[ +cal]`` (a panel case's name) as a case."""
    parts = name.split()
    try:
        fam, seed = parts[0].split("/")
        return PanelCase(fam, int(seed), int(parts[1].lstrip("L")), parts[2], parts[3:] == ["+cal"])
    except (IndexError, ValueError):
        raise ValueError(f"--case: expected 'family/seed L<lights> <model>[ +cal]', got {name!r}") from None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m torchbrdf.bench.silent_profile",
                                description=(__doc__ or "").splitlines()[0])
    p.add_argument("--case", required=True, help="a tuning case, e.g. 'ceramic_tiles/1 L12 exact_fresnel +cal'")
    p.add_argument("--size", type=int, default=128, help="capture size in pixels, square (default 128)")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        out = silent_profile(_case(a.case), a.size)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{out['case']}: σ² = {out['sigma2']:.3g}")
    print("| pixels | true rough | fitted | pooled minimum | data cost lower there (σ²) | per-pixel posterior mean |")
    print("|---|---|---|---|---|---|")
    for r in out["regions"]:
        print(f"| {r['pixels']} | {r['true']:.3f} | {r['fitted']:.3f} | {r['pooled']:.3f} | {r['gain_sigma2']:.0f} "
              f"| {r['posterior_mean']:.3f} |")
    keys = ("base_rmse", "roughness_rmse", "specular_rmse", "heldout_mean_db", "heldout_worst_db")
    for label, s in (("recovered", out["scores"]), ("pooled", out["oracle_scores"]),
                     ("posterior", out["posterior_scores"])):
        print(f"{label:9s} " + "  ".join(f"{k} {s[k]:.4g}" for k in keys if math.isfinite(s[k])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
