"""Continuous metallic: the final soft-metal stage, the soft recipes, the report field.

Each test fails on the code before the stage: it had no soft-metal functions, no soft recipes,
no ``fractional_metallic_fraction`` in the report, and its metallic map was only ever 0 or 1.
"""

import dataclasses

import pytest
import torch

from torchbrdf.capture.format import load_capture, write_capture
from torchbrdf.capture.synthetic import (
    RECIPES,
    SOFT_RECIPES,
    light_layout,
    make_material,
    normals_from_height,
    render_capture,
    write_maps,
)
from torchbrdf.recovery import lm, map_ops, soft_metal
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.params import decode, encode
from torchbrdf.recovery.soft_metal import (blend_ends, growth_front, may_be_mixed, soft_metal_candidates, soft_metal_fit,
                                           unmix_metallic)
from torchbrdf.recovery.svbrdf import RecoveryConfig, metallic_preview, recover


def _capture(folder, metallic: torch.Tensor, lights: int = 12, noise: float = 0.01, seed: int = 3):
    """A flat capture of one material whose metallic varies: ``metallic (H, W)``."""
    s = metallic.shape[-1]
    m = metallic[None].float()
    base = torch.tensor([0.75, 0.55, 0.35])[:, None, None] * torch.ones(1, s, s)
    maps = {"base_color": base, "roughness": torch.full((1, s, s), 0.35), "metallic": m,
            "specular": torch.full((1, s, s), 0.5), "normal": normals_from_height(torch.zeros(s, s))}
    pos, inten = light_layout(lights)
    with torch.no_grad():
        img = render_capture(maps, (pos, inten), noise=noise, seed=seed)
    write_maps(folder / "gt", maps, previews=False)
    write_capture(folder, img, (pos, inten), torch.tensor([0.0, 0.0, 3.0]))
    return maps


def _stripe(size: int = 24) -> torch.Tensor:
    """Dielectric left, metal right, a 4-pixel stripe of 50/50 blend in between."""
    m = torch.zeros(size, size)
    m[:, size // 2 + 2:] = 1.0
    m[:, size // 2 - 2: size // 2 + 2] = 0.5
    return m


def _ramp_capture(folder, cols: dict, diel: tuple, met: tuple, size: int = 24):
    """A flat capture of a dielectric, a metal and a ramp of blends between them.

    The metal from column 14 on; columns ``cols`` ({column: coverage t}) with base colour,
    roughness and metallic blended by t. ``diel`` / ``met``: (base colour (3,), roughness) of
    the two ends. Returns ``(maps, t (S, S))``.
    """
    t = torch.zeros(size, size)
    t[:, 14:] = 1.0
    for c, v in cols.items():
        t[:, c] = v
    lerp = lambda a, b: a * (1 - t) + b * t  # noqa: E731
    base = lerp(diel[0][:, None, None], met[0][:, None, None])
    return _flat_capture(folder, base, lerp(diel[1], met[1])[None], t[None]), t


def _flat_capture(folder, base, rough, metallic):
    """A flat capture (12 ring lights and the flash, 1 % noise) of maps ``(C, S, S)``.

    Specular 0.5, normals straight up. Returns the maps.
    """
    size = base.shape[-1]
    maps = {"base_color": base, "roughness": rough, "metallic": metallic,
            "specular": torch.full((1, size, size), 0.5),
            "normal": normals_from_height(torch.zeros(size, size))}
    pos, inten = light_layout(12)
    with torch.no_grad():
        img = render_capture(maps, (pos, inten), noise=0.01, seed=5)
    write_capture(folder, img, (pos, inten), torch.tensor([0.0, 0.0, 3.0]))
    return maps


def test_double_well_keeps_clear_pixels_binary(tmp_path):
    """At the true parameters of a binary material, refitting every pixel with a free metallic
    (data + double well, the acceptance margin) leaves every pixel exactly 0 or 1."""
    m = torch.zeros(16, 16)
    m[:, 8:] = 1.0
    maps = _capture(tmp_path, m)
    cap = load_capture(tmp_path)
    eps = float(0.01 * cap.images.clamp(min=0).mean())
    data = LevelData(cap, 16, list(range(len(cap))), eps)
    flat = lambda t: t.reshape(t.shape[0], -1).T  # noqa: E731
    theta = encode({k: flat(maps[k]) for k in ("base_color", "specular", "roughness", "normal")})
    metal = flat(maps["metallic"])
    r = data.residual(theta, metal, data.train_idx)
    sigma2 = float((r * r).sum(-1).median()) / r.shape[1]
    rows = torch.arange(256)
    _, m_new, _ = soft_metal_fit(data, theta, metal, rows, data.train_idx, "principled",
                                 32 * sigma2, 8 * sigma2, iters=5)
    assert bool(((m_new == 0) | (m_new == 1)).all()), m_new[(m_new > 0) & (m_new < 1)]
    assert torch.equal(m_new, metal)
    # Without the acceptance margin, the well and the snap, one more unknown fits the noise:
    # fractional values appear (what those three prevent).
    _, m_free, _ = soft_metal_fit(data, theta, metal, rows, data.train_idx, "principled", 0.0, 0.0, iters=5,
                                  snap=0.0)
    assert bool(((m_free > 0) & (m_free < 1)).any())


def test_candidates_are_poor_fits_and_class_boundaries():
    size = 8
    metal = torch.zeros(size * size, 1)
    metal.view(size, size)[:, 6:] = 1.0  # boundary between columns 5 and 6
    cost = torch.ones(size * size, 1)
    cost[0] = 100.0  # a poor fit far from the boundary
    rows = set(soft_metal_candidates(cost, metal, size, factor=8.0, max_frac=1.0, band=1).tolist())
    expect = {0} | {r * size + c for r in range(size) for c in (5, 6)}
    assert rows == expect


def _metal_patch(size: int, span: slice, colour: tuple, patch: tuple):
    """A metal of base ``colour`` with a square patch (rows and columns ``span``) of ``patch``.

    Returns ``(metal (P, 1) all 1, base (P, 3), the patch (S, S) bool, cost (P, 1) all 1)``.
    """
    metal = torch.ones(size * size, 1)
    base = torch.tensor(colour).repeat(size * size, 1)
    mask = torch.zeros(size, size, dtype=torch.bool)
    mask[span, span] = True
    base[mask.reshape(-1)] = torch.tensor(patch)
    return metal, base, mask, torch.ones(size * size, 1)


def test_candidates_include_a_metals_colour_steps():
    """A metal's base-colour step makes candidates; a dielectric's does not.

    A rust island the binary choice called metal (rough rust fits as a rough dark metal) has
    no class boundary and fits at the noise level; its colour step against the bright metal
    around it makes it a candidate (rusted_metal 1: 399 such soft pixels, error 0.32, carried
    69 % of the metallic error).
    """
    size = 10
    metal, base, island, cost = _metal_patch(size, slice(4, 6), (0.95, 0.93, 0.88), (0.45, 0.2, 0.1))
    assert soft_metal_candidates(cost, metal, size, 8.0, 1.0, 1).numel() == 0
    rows = set(soft_metal_candidates(cost, metal, size, 8.0, 1.0, 1, base, edge=0.15).tolist())
    # Each side of every step, grown by the band (1 pixel, 8-neighbourhood).
    step = island.clone()
    step[3, 4:6] = step[6, 4:6] = step[4:6, 3] = step[4:6, 6] = True
    grown = torch.nn.functional.max_pool2d(step[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert rows == set(torch.nonzero(grown.reshape(-1)).flatten().tolist())
    dielectric = torch.zeros_like(metal)
    assert soft_metal_candidates(cost, dielectric, size, 8.0, 1.0, 1, base, edge=0.15).numel() == 0
    # The threshold is the Euclidean RGB step: (0.1, 0.1, 0.1) is 0.17 (a step), (0.08, 0.08, 0)
    # 0.11 (none).
    for d, is_step in (((0.1, 0.1, 0.1), True), ((0.08, 0.08, 0.0), False)):
        b = torch.tensor([0.9, 0.9, 0.9]).repeat(size * size, 1)
        b[island.reshape(-1)] -= torch.tensor(d)
        got = soft_metal_candidates(cost, metal, size, 8.0, 1.0, 1, b, edge=0.15).numel()
        assert (got > 0) == is_step, (d, got)


def test_candidates_include_a_metal_unlike_the_metal_around_it():
    """The inside of a plateau called metal whose colour differs from the metal around it.

    A partly rusted plateau (rusted_metal 122: 186 pixels, 40 % metal, called metal) has a
    colour step only at its rim; with ``context`` its inside is a candidate too, so it is not
    taken as its rim's clear metal end. Bright metal around it, and dielectric pixels, are not.
    """
    size = 32
    metal, base, plateau, cost = _metal_patch(size, slice(10, 20), (0.9, 0.9, 0.88), (0.6, 0.45, 0.35))
    inside = plateau.clone()
    inside[:13] = inside[17:] = False
    inside[:, :13] = inside[:, 17:] = False  # 3 pixels or more from its rim
    args = (cost, metal, size, 8.0, 1.0, 1, base)
    rim = set(soft_metal_candidates(*args, edge=0.15).tolist())
    assert not rim & set(torch.nonzero(inside.reshape(-1)).flatten().tolist())
    rows = set(soft_metal_candidates(*args, edge=0.15, context=8.0).tolist())
    assert rows == rim | set(torch.nonzero(plateau.reshape(-1)).flatten().tolist())
    uniform = torch.tensor([0.9, 0.9, 0.88]).repeat(size * size, 1)
    assert soft_metal_candidates(cost, metal, size, 8.0, 1.0, 1, uniform, edge=0.15, context=8.0).numel() == 0
    diel_plateau = metal.clone()
    diel_plateau[plateau.reshape(-1)] = 0.0  # a dielectric plateau: a class boundary, not this rule
    rows_d = set(soft_metal_candidates(cost, diel_plateau, size, 8.0, 1.0, 1, base, edge=0.15,
                                       context=8.0).tolist())
    assert not rows_d & set(torch.nonzero(inside.reshape(-1)).flatten().tolist())


def test_growth_extends_runs_of_fractional_pixels_only():
    """Growth refits the untried pixels beside a ramp, never beside an isolated fractional pixel.

    A ramp: two fractional 4-neighbours. On a binary material (README example tiles 7) growth
    from one isolated fractional pixel had made five.
    """
    size = 8
    metal = torch.zeros(size * size, 1)
    metal.view(size, size)[:, 5:] = 1.0
    metal.view(size, size)[1, 1] = 0.3  # isolated
    tried = torch.zeros(size * size, dtype=torch.bool)
    assert growth_front(metal, tried, size).numel() == 0
    metal.view(size, size)[2, 2] = 0.4  # a diagonal neighbour only: still not a run
    assert growth_front(metal, tried, size).numel() == 0
    metal.view(size, size)[2, 2] = 0.0
    metal.view(size, size)[5, 3] = metal.view(size, size)[5, 4] = 0.6  # a run into the metal
    tried.view(size, size)[5, 4] = True
    front = set(growth_front(metal, tried, size).tolist())
    near = {r * size + c for r in (4, 5, 6) for c in (2, 3, 4, 5)} - {5 * size + 4}
    assert front == near


def test_unmix_finds_the_coverage_of_a_blend_of_the_clear_neighbours(tmp_path, monkeypatch):
    """A blend's coverage is found from the clear pixels beside it, to within 0.025.

    A stripe of texels blending a rough dielectric (left) and a glossy metal (right) —
    base colour, roughness and metallic all mixed with one coverage t: explained along the
    line between the clear pixels beside it, each column's t is found to within 0.025 (the
    11-value grid alone is off by up to 0.05: the parabola between grid values), from a start
    that knows nothing of it (the stripe fitted as a grey dielectric).

    Fails if an end is taken from the stripe itself, if roughness or base colour is not
    blended, if the metal end's specular (not observed) were used, or without the parabola.
    Evaluated one coverage per call, the answer is the same.
    """
    size = 24
    diel = {"base_color": torch.tensor([0.5, 0.4, 0.3]), "roughness": 0.8, "specular": 0.5}
    met = {"base_color": torch.tensor([0.95, 0.9, 0.8]), "roughness": 0.3, "specular": 0.1}
    maps, t = _ramp_capture(tmp_path, {10: 0.25, 11: 0.43, 12: 0.67, 13: 0.85},
                            (diel["base_color"], diel["roughness"]), (met["base_color"], met["roughness"]),
                            size)
    base = maps["base_color"]
    cap = load_capture(tmp_path)
    data = LevelData(cap, size, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    flat = lambda x: x.reshape(x.shape[0], -1).T  # noqa: E731
    # The metal side's specular is wrong (unobserved under metallic 1), the stripe a grey
    # dielectric: only the clear pixels' base colour and roughness are right.
    stripe = (t > 0) & (t < 1)
    start = dict(maps, metallic=(t == 1).float()[None])
    start["specular"] = torch.where(t == 1, 0.1, 0.5)[None]
    start["base_color"] = torch.where(stripe, 0.7, base)
    start["roughness"] = torch.where(stripe, 0.55, start["roughness"])
    theta = encode({k: flat(start[k]) for k in ("base_color", "specular", "roughness", "normal")})
    metal = flat(start["metallic"])
    rows = torch.nonzero(flat(stripe.float()[None])[:, 0]).flatten()
    with torch.no_grad():
        theta_b, t_b = unmix_metallic(data, theta, metal, rows, data.train_idx, "principled", size)
    truth = flat(t[None])[rows]
    assert float((t_b - truth).abs().max()) < 0.025, (t_b - truth).abs().max()

    monkeypatch.setattr(soft_metal, "UNMIX_PIXELS", 1)  # one coverage per call: the same answer
    with torch.no_grad():
        _, t_1 = unmix_metallic(data, theta, metal, rows, data.train_idx, "principled", size)
    assert torch.equal(t_1, t_b)
    p = decode(theta_b, t_b)  # the blend at the coverage found
    assert torch.allclose(p["roughness"], 0.8 * (1 - t_b) + 0.3 * t_b, atol=1e-3)
    want = diel["base_color"] * (1 - t_b) + met["base_color"] * t_b
    assert torch.allclose(p["base_color"], want, atol=1e-3)
    assert torch.allclose(p["specular"], torch.full_like(t_b, 0.5), atol=1e-3)
    # No blend with a finite cost (a non-finite observation): no blend, NaN, not a guess.
    images = cap.images.clone()
    images[:, :, rows[:3] // size, rows[:3] % size] = float("nan")  # pixel p: row p // size, column p % size
    data = LevelData(dataclasses.replace(cap, images=images), size, data.train_idx, data.eps)
    with torch.no_grad():
        theta_n, t_n = unmix_metallic(data, theta, metal, rows, data.train_idx, "principled", size)
    assert bool(torch.isnan(t_n[:3]).all()) and bool(torch.isnan(theta_n[:3]).all())
    assert bool(torch.isfinite(t_n[3:]).all())


def test_blend_stripe_recovers_fractional_metallic(tmp_path, monkeypatch):
    """A stripe of 50/50 metal/dielectric between a dielectric and a metal region: the old
    recovery could only answer 0 or 1 there (error 0.5); the soft stage recovers ~0.5, and
    the clear pixels away from the stripe stay exactly 0 or 1.

    The stage's glossy/rough tie (``soft_rough_tie``) gets the stage's settings: its candidates
    and grown pixels, the double-well and margin in noise variances, the thresholds, and the
    blend's coverage (NaN off the candidates); with ``soft_rough_tie = 0`` it is not called.
    """

    calls: list = []
    tie = soft_metal.soft_rough_tie

    def spy(*a, **kw):
        calls.append((a, kw))
        return tie(*a, **kw)

    monkeypatch.setattr(soft_metal, "soft_rough_tie", spy)
    gm = _stripe(24)
    _capture(tmp_path, gm)
    cfg = Settings(iters=16, threads=2)
    res = recover(tmp_path, cfg, None, gt=tmp_path / "gt", progress=False)
    assert len(calls) == 1
    (data, theta, metal, rows, idx, model, well, margin, glossy, rough), kw = calls[0]
    assert data.size == 24 and theta.shape == (24 * 24, 7) and rows.dtype == torch.int64
    assert 0 < rows.numel() < 24 * 24
    assert well / margin == pytest.approx(cfg.soft_metal_well / cfg.soft_rough_tie)
    assert (glossy, rough) == (cfg.soft_rough_tie_glossy, cfg.rough_tie_start)
    cov = kw["coverage"]
    assert cov.shape == (24 * 24, 1) and bool(torch.isnan(cov).any())
    assert bool(torch.isfinite(cov[rows]).any())
    calls.clear()
    off = Settings(iters=16, threads=2, soft_rough_tie=0.0)
    recover(tmp_path, off, tmp_path / "off", progress=False)
    assert calls == []
    m = res.maps["metallic"][0]
    stripe = gm == 0.5
    assert float((m[stripe] - 0.5).abs().mean()) < 0.15, m[stripe]
    far = torch.zeros_like(stripe)
    far[:, :8] = True
    far[:, 17:] = True  # three pixels or more from the stripe
    assert bool(((m[far] == 0) | (m[far] == 1)).all())
    assert float((m[far] - gm[far]).abs().max()) == 0.0
    # report.json: the fraction of fractional pixels, as written in metallic.exr
    frac = float(((m > 0) & (m < 1)).float().mean())
    assert res.report["fractional_metallic_fraction"] == frac and frac > 0.05
    assert res.report["soft_metal"]["pixels_refitted"] > 0
    assert res.report["soft_metal"]["glossy_to_rough"] == 0  # no glossy pixel here


def test_blend_line_holds_a_ramps_metallic_and_base_colour(tmp_path):
    """A ramp of five texels between a rough dielectric and a bright metal: both maps held.

    Base colour, roughness and metallic are blended with one coverage (0.15 … 0.88). The
    stage's last refit ties each fractional pixel's base colour to the blend of its clear ends
    at its own metallic (``RecoveryConfig.soft_metal_line``); without that tie the data trade
    metallic for base colour along the ramp (mean metallic error 0.028–0.029 without it,
    0.023–0.024 with it, with the fill on and off; base-colour error 0.0137–0.0141 either way).
    """
    maps, t = _ramp_capture(tmp_path, {9: 0.15, 10: 0.3, 11: 0.5, 12: 0.7, 13: 0.88},
                            (torch.tensor([0.5, 0.3, 0.2]), 0.8), (torch.tensor([0.95, 0.93, 0.88]), 0.25))
    base = maps["base_color"]
    res = recover(tmp_path, RecoveryConfig(iters=16, threads=2), None, progress=False)
    ramp = (t > 0) & (t < 1)
    m, b = res.maps["metallic"][0], res.maps["base_color"]
    assert float((m - t)[ramp].abs().mean()) < 0.026, (m - t)[ramp].abs().mean()
    assert float((b - base)[:, ramp].abs().mean()) < 0.016, (b - base)[:, ramp].abs().mean()
    assert bool((m[:, :7] == 0).all() and (m[:, 16:] == 1).all())  # the clear pixels stay clear


def test_metallic_preview_tints_fractional_pixels():
    m = torch.tensor([[[0.0, 1.0, 0.5, 0.02]]])
    p = metallic_preview(m)
    assert p.shape == (3, 1, 4)
    assert torch.equal(p[:, 0, 0], torch.zeros(3)) and torch.equal(p[:, 0, 1], torch.ones(3))
    for k in (2, 3):  # coloured, not grey: told apart from both classes
        assert float(p[0, 0, k] - p[2, 0, k]) > 0.5


def test_soft_recipes_have_5_to_15_percent_soft_pixels_and_leave_the_default_cycle_alone():
    assert RECIPES == ("tiles", "metal_inlay", "scratched_metal", "painted", "stone", "circuit")
    for recipe in SOFT_RECIPES:
        for seed in (1, 101):
            m = make_material(recipe, seed, 64)["metallic"]
            soft = float(((m >= 0.05) & (m <= 0.95)).float().mean())
            assert 0.05 <= soft <= 0.15, (recipe, seed, soft)
    for seed in range(len(RECIPES)):  # recipe=None still picks RECIPES[seed % 6], same maps
        a, b = make_material(None, seed, 16), make_material(RECIPES[seed % len(RECIPES)], seed, 16)
        assert all(torch.equal(a[k], b[k]) for k in a)
        assert bool(((a["metallic"] == 0) | (a["metallic"] == 1)).all())


def test_reference_refit_only_where_the_result_can_win(tmp_path, monkeypatch):
    """The metallic-held reference fit runs only where the free result can win.

    That is, where it beats the unrefitted reference by the gain (a refit only lowers the
    reference): with a gain no pixel can reach, there is no reference fit at all and every
    pixel keeps its class; with no gain, the pixels the stripe made fractional are refitted.
    """

    gm = _stripe(16)
    maps = _capture(tmp_path, gm)
    cap = load_capture(tmp_path)
    data = LevelData(cap, 16, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    flat = lambda t: t.reshape(t.shape[0], -1).T  # noqa: E731
    theta = encode({k: flat(maps[k]) for k in ("base_color", "specular", "roughness", "normal")})
    metal = (flat(maps["metallic"]) > 0.25).float()  # the stripe called metal
    rows = torch.arange(256)
    held = []
    real_lm = lm.soft_lm

    def spy(fn, cost, x, iters, fix_metal=False, **kw):
        if fix_metal:
            held.append(x.shape[0])
        return real_lm(fn, cost, x, iters, fix_metal=fix_metal, **kw)

    monkeypatch.setattr(soft_metal, "soft_lm", spy)
    with torch.no_grad():
        _, m_new, _ = soft_metal_fit(data, theta, metal, rows, data.train_idx, "principled", 0.0, 1e30, 5)
    assert held == [] and torch.equal(m_new, metal)
    with torch.no_grad():
        _, m_free, _ = soft_metal_fit(data, theta, metal, rows, data.train_idx, "principled", 0.0, 0.0, 5)
    assert len(held) == 1 and 0 < held[0] < 256
    assert bool(((m_free > 0) & (m_free < 1)).any())


def test_clear_candidates_that_fit_at_the_noise_level_leave_the_stage(tmp_path, monkeypatch):
    """Clear candidates that fit at the noise level are left out of the final stage's metallic fits.

    Those whose best blend of their clear neighbours is their own class and whose cost is at most
    ``soft_metal_quiet`` × the median pixel's: no metallic fit of the stage (first pass, second
    pass, growth, blend line) is given them, and growth counts them as tried; every other
    candidate gets the first pass. With ``soft_metal_quiet = 0`` (off) none is left out.
    """
    coverage = torch.tensor([[0.0], [1.0], [0.0], [0.4], [float("nan")], [1.0]])
    metal = torch.tensor([[0.0], [1.0], [0.0], [0.0], [0.0], [0.0]])
    cost = torch.tensor([[1.0], [0.5], [1.5], [0.5], [0.5], [0.5]])
    assert may_be_mixed(coverage, metal, cost, 1.0).tolist() == [False, False, True, True, True, True]
    assert may_be_mixed(coverage, metal, cost, 1.5).tolist() == [False, False, False, True, True, True]

    # In the recovery: a binary boundary's band is all candidates; about half of them fit near
    # the noise level and unmix to their own class (and their neighbours across the boundary
    # would otherwise give them the second pass).

    m = torch.zeros(16, 16)
    m[:, 8:] = 1.0
    _capture(tmp_path, m)
    cand, fit = soft_metal.soft_metal_candidates, soft_metal.soft_metal_fit

    grow = soft_metal.growth_front

    def run(**over):
        seen: dict = {"fits": [], "tried": []}
        monkeypatch.setattr(soft_metal, "soft_metal_candidates",
                            lambda *a, **k: seen.setdefault("cand", cand(*a, **k)))
        monkeypatch.setattr(soft_metal, "growth_front", lambda mt, tried, size: (seen["tried"].append(tried.clone()),
                                                                       grow(mt, tried, size))[1])

        def spy(d, t, mt, rows, *a, **k):
            seen["fits"].append(rows.clone())
            return fit(d, t, mt, rows, *a, **k)

        monkeypatch.setattr(soft_metal, "soft_metal_fit", spy)
        recover(tmp_path, Settings(iters=16, threads=2, **over), None, progress=False)
        tried = [set(t.nonzero()[:, 0].tolist()) for t in seen["tried"]]
        return set(seen["cand"].tolist()), [set(f.tolist()) for f in seen["fits"]], tried

    rows, fits, tried = run()
    first, quiet = fits[0], rows - fits[0]
    assert first < rows and len(first) < 0.8 * len(rows), (len(first), len(rows))
    assert len(fits) > 1 and not any(f & quiet for f in fits[1:])  # no later fit takes them up
    assert tried and all(quiet <= t for t in tried)  # nor does growth (they count as tried)
    rows0, fits0, _ = run(soft_metal_quiet=0.0)
    assert rows0 == rows and fits0[0] == rows


def test_second_pass_rounds_after_the_first_go_on_from_the_round_before(tmp_path, monkeypatch):
    """The second pass's later rounds start from the round before's answers.

    Its first round starts from the neighbours' mean; round 2 from the pixels' own theta and
    metallic, which are round 1's answers, on the same pixels.
    """
    import inspect


    _capture(tmp_path, _stripe(16))
    calls = []
    fit = soft_metal.soft_metal_fit
    sig = inspect.signature(fit)

    def spy(*a, **k):
        out = fit(*a, **k)
        b = sig.bind(*a, **k)
        b.apply_defaults()
        g = b.arguments
        if g["refit_reference"] is False and g["line"] is None:  # the second pass (growth is off)
            rows = g["rows"]
            theta, metal = g["theta"][rows].clone(), g["metal"][rows].clone()
            calls.append((rows.clone(), g["starts"], theta, metal, out))
        return out

    monkeypatch.setattr(soft_metal, "soft_metal_fit", spy)
    cfg = Settings(iters=8, threads=2, soft_metal_passes=2, soft_metal_grow=0, fuse_rounds=1,
                         fit_nonlocal_tie=False, soft_metal_line=0.0)
    recover(tmp_path, cfg, None, progress=False)
    assert len(calls) == 2, len(calls)
    (rows1, starts1, _, _, out1), (rows2, starts2, theta2, metal2, _) = calls
    assert isinstance(starts1[0], tuple) and starts1[0][1] == "target"  # the neighbours' mean
    assert starts2 == (None,) and torch.equal(rows1, rows2)  # the pixels' own ...
    assert torch.equal(theta2, out1[0]) and torch.equal(metal2, out1[1])  # ... = round 1's answers


def test_blend_ends_reach_the_same_class_further_off():
    """With no clear dielectric beside a speck, its dielectric end is the clear one further off.

    A metal with a dielectric strip along its left edge and a 3×3 speck of candidates 47
    pixels away (beyond the reach, 3σ, of widths up to 12 pixels): the speck's dielectric end is
    the strip's values, exactly (they are uniform), and found; with narrower widths alone it is
    not found and falls back to the pixel's own values (a metal's: the blend a guess). The metal
    end, beside the speck, is the metal's. And the nearest width wins: a speck 2 pixels from a
    small dielectric patch of another colour takes the patch's values, not the strip's, also
    when another pixel of the call needs the far width.
    """
    size = 64
    metal = torch.ones(size * size, 1)
    metal.view(size, size)[:, :4] = 0.0
    diel = {"base_color": torch.tensor([0.5, 0.4, 0.3]), "specular": torch.tensor([0.5]),
            "roughness": torch.tensor([0.9])}
    met = {"base_color": torch.tensor([0.9, 0.8, 0.6]), "specular": torch.tensor([0.3]),
           "roughness": torch.tensor([0.3])}
    params = {k: torch.where(metal.bool(), met[k], diel[k]) for k in diel}
    params["normal"] = torch.tensor([0.0, 0.0, 1.0]).expand(size * size, 3)
    theta = encode(params)
    rows = torch.tensor([r * size + c for r in (20, 21, 22) for c in (50, 51, 52)])
    (d, m), found = blend_ends(theta, metal, rows, size)
    want = lambda e: torch.cat((e["base_color"], e["specular"], e["roughness"]))  # noqa: E731
    assert bool(found.all())
    assert torch.allclose(d, want(diel).expand_as(d), atol=1e-4)
    assert torch.allclose(m, want(met).expand_as(m), atol=1e-4)
    (d2, _), found2 = blend_ends(theta, metal, rows, size, sigmas=(2.0, 6.0, 12.0))
    assert not bool(found2[:, 0].any()) and bool(found2[:, 1].all())
    assert torch.allclose(d2, want(met).expand_as(d2), atol=1e-4)  # its own values: a metal's
    # The nearest width wins: a patch of another dielectric 2 pixels from a second speck.
    patch = torch.zeros(size, size, dtype=torch.bool)
    patch[40:43, 30:33] = True
    other = {"base_color": torch.tensor([0.2, 0.6, 0.3]), "specular": torch.tensor([0.4]),
             "roughness": torch.tensor([0.6])}
    metal.view(size, size)[patch] = 0.0
    params = {k: torch.where(patch.reshape(-1, 1), other[k], params[k]) for k in other} | {
        "normal": params["normal"]}
    near = torch.tensor([r * size + c for r in (40, 41, 42) for c in (35, 36, 37)] + [10 * size + 60])
    (d3, _), found3 = blend_ends(encode(params), metal, near, size)  # (the last row needs the far width)
    assert bool(found3.all()) and torch.allclose(d3[:9], want(other).expand_as(d3[:9]), atol=1e-4)


def test_growth_fronts_get_their_blend_coverage(tmp_path, monkeypatch):
    """The growth rounds' pixels are unmixed too, as the candidates are.

    So the blend's coverage pulls them as it pulls the candidates (the core of a speck is
    reached by growth from its rim): the growth fit's metallic target is the weighted mean of
    the neighbours' metallic (``soft_metal_smooth``) and the front's coverage
    (``soft_metal_unmix``). With ``soft_metal_unmix = 0`` no pixel is unmixed.
    """
    import inspect


    _capture(tmp_path, _stripe(16))
    fronts: list = []
    unmixed: list = []
    grown: list = []
    calls = {"n": 0}

    def front(metal, tried, size):  # one fixed front, then none
        calls["n"] += 1
        f = torch.tensor([0, 1, 2, 16]) if calls["n"] == 1 else torch.zeros(0, dtype=torch.int64)
        fronts.append(f)
        return f[~tried[f]]

    un, fit = soft_metal.unmix_metallic, soft_metal.soft_metal_fit
    sig = inspect.signature(fit)

    def spy(data, theta, metal, rows, *a, **k):
        unmixed.append(rows.clone())
        t, u = un(data, theta, metal, rows, *a, **k)
        return (t, torch.full_like(u, 0.37)) if len(unmixed) > 1 else (t, u)  # the front's: 0.37

    def spy_fit(*a, **k):
        g = sig.bind(*a, **k).arguments
        if len(fronts) == 1 and len(unmixed) == 2 and torch.equal(g["rows"], fronts[0]):
            grown.append((map_ops.neighbour_mean(g["metal"], 16)[g["rows"]], g["target"]))
        return fit(*a, **k)

    monkeypatch.setattr(soft_metal, "growth_front", front)
    monkeypatch.setattr(soft_metal, "unmix_metallic", spy)
    monkeypatch.setattr(soft_metal, "soft_metal_fit", spy_fit)
    cfg = Settings(iters=8, threads=2, fuse_rounds=1, fit_nonlocal_tie=False)
    recover(tmp_path, cfg, None, progress=False)
    assert len(unmixed) == 2 and torch.equal(unmixed[1], fronts[0])
    (nb, target), = grown
    w_nb, w_un = cfg.soft_metal_smooth, cfg.soft_metal_unmix
    assert torch.allclose(target, (w_nb * nb + w_un * 0.37) / (w_nb + w_un), atol=1e-5)
    unmixed.clear()
    calls["n"] = 0
    recover(tmp_path, Settings(iters=8, threads=2, fuse_rounds=1, fit_nonlocal_tie=False,
                                     soft_metal_unmix=0.0), None, progress=False)
    assert unmixed == []


def test_an_answer_of_the_other_class_is_taken(tmp_path, monkeypatch):
    """A candidate the stage's passes move to the other class takes it, as a fractional one does.

    One that stays its class keeps the fit it had. (A thin dielectric scratch the binary choice
    called metal: scratched_metal 5's metallic RMSE 0.0136 -> 0.0005 with the far ends, docs.) The passes are
    replaced by one that answers the other class for the first candidate, its own class with
    another base colour for the second, a fraction for the third.
    """

    _capture(tmp_path, _stripe(16))
    seen: dict = {}

    def fit(data, theta, metal, rows, *a, **k):
        t, m = theta[rows].clone(), metal[rows].clone()
        if "rows" not in seen:  # the first pass
            seen["rows"], seen["metal"] = rows.clone(), metal[rows].clone()
            seen["theta"] = theta[rows].clone()
            m[0] = 1.0 - m[0]
            t[1, 0] += 1.0
            m[2] = 0.4
            seen["new"] = t.clone(), m.clone()
        return t, m, torch.ones(rows.numel(), dtype=torch.bool)

    monkeypatch.setattr(soft_metal, "soft_metal_fit", fit)
    cfg = Settings(iters=8, threads=2, soft_metal_passes=0, soft_metal_grow=0, soft_rough_tie=0.0,
                         soft_metal_line=0.0, soft_metal_unmix=0.0)
    res = recover(tmp_path, cfg, None, progress=False)
    rows = seen["rows"]
    m = res.maps["metallic"][0].flatten()
    assert float(m[rows[0]]) == 1.0 - float(seen["metal"][0])
    assert float(m[rows[2]]) == pytest.approx(0.4)
    red = res.maps["base_color"][0].flatten()
    kept = decode(seen["theta"][1:2], seen["metal"][1:2])["base_color"][0, 0]
    assert float(red[rows[1]]) == pytest.approx(float(kept), abs=1e-5)


def test_a_metal_of_another_colour_stays_a_clear_metal(tmp_path, monkeypatch):
    """A brass disc inside silver, wood beside them: the disc is a candidate, and stays metal.

    The disc is a metal unlike the metal around it, but stays exactly metallic 1, as does every
    metal pixel. The candidate rule looks for a partly rusted plateau called metal; a clear metal of another
    colour fits its own class at the noise level, its best blend is its own class, and no
    fractional value wins the gain.
    """

    size = 48
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    disc = ((yy - 24) ** 2 + (xx - 32) ** 2) <= 64
    wood = xx < 12
    base = torch.tensor([0.95, 0.93, 0.88])[:, None, None].expand(3, size, size).clone()
    base[:, disc] = torch.tensor([0.9, 0.72, 0.38])[:, None]
    base[:, wood] = torch.tensor([0.5, 0.35, 0.2])[:, None]
    rough = torch.full((1, size, size), 0.3)
    rough[0, wood] = 0.7
    _flat_capture(tmp_path, base, rough, (~wood).float()[None])
    seen: dict = {}
    cand = soft_metal.soft_metal_candidates
    monkeypatch.setattr(soft_metal, "soft_metal_candidates", lambda *a, **k: seen.setdefault("rows", cand(*a, **k)))
    res = recover(tmp_path, RecoveryConfig(iters=16, threads=2), None, progress=False)
    assert 24 * size + 32 in set(seen["rows"].tolist())  # the disc's centre, 8 pixels from its rim
    m = res.maps["metallic"][0]
    assert bool((m[~wood] == 1).all()) and bool((m[wood] == 0).all())
