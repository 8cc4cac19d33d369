"""The non-local fill: where the data are silent, the same material's measured value.

Each pixel's unary prior is the predictive distribution of the pixels like it (base colour and
normal texture), their values weighed by their own information: the target is their
precision-weighted mean, the width their measured spread, and the fit fuses it with the pixel's
own data by precisions.
"""

import pytest
import torch

from torchbrdf.recovery import params, priors
from torchbrdf.recovery.config import Settings

from tests.recovery.recovery_fixtures import flat_level


def _noise_variance(data, theta, metal):
    """The fill's σ²: the median pixel's mean squared residual."""
    r = data.residual(theta, metal, data.train_idx, "principled")
    return float((r * r).mean(-1).median())


def _material(spread, seed=0, size=16):
    """A flat level whose pixels' roughness logits spread by ``spread`` (std) around 0, measured
    with variance 1e-4 (logit²), except a silent block (variance 1e6, logit drifted to −3);
    returns ``(data, theta, metal, info, silent, sigma2)``."""
    data, theta, metal = flat_level(size=size)
    p = theta.shape[0]
    g = torch.Generator().manual_seed(seed)
    theta = theta.clone()
    theta[:, 4] = spread * torch.randn(p, generator=g)
    silent = torch.zeros(p, dtype=torch.bool)
    silent[:24] = True
    theta[silent, 4] = -3.0
    sigma2 = _noise_variance(data, theta, metal)
    var = torch.full((p, 7), 1e-4)
    var[silent, 3:5] = 1e6
    return data, theta, metal, sigma2 / var, silent, sigma2


def test_material_estimate_is_the_precision_weighted_mean_and_the_ml_spread():
    """Members measured without noise give their mean and variance; a member the data do not see
    moves neither; the weights follow each member's information."""
    g = torch.Generator().manual_seed(1)
    y = 0.5 + 0.3 * torch.randn(1, 4000, 1, generator=g)
    v = torch.full_like(y, 1e-8)
    s = torch.ones_like(y)
    mu, tau2, var_mu = priors.material_estimate(y, v, s)
    assert abs(float(mu) - float(y.mean())) < 1e-6
    assert abs(float(tau2) - float(y.var(unbiased=False))) < 1e-3
    assert abs(float(var_mu) - float(tau2) / 4000) < 1e-6
    y2, v2, s2 = torch.cat((y, torch.full((1, 50, 1), 9.0)), 1), torch.cat((v, torch.full((1, 50, 1), 1e9)), 1), \
        torch.ones(1, 4050, 1)
    mu2, tau22, _ = priors.material_estimate(y2, v2, s2)
    assert abs(float(mu2 - mu)) < 1e-4 and abs(float(tau22 - tau2)) < 1e-3
    # Two groups of one material (no spread): the precise one decides the mean, 100:1.
    y3 = torch.tensor([[[0.0], [0.0], [1.0], [1.0]]])
    v3 = torch.tensor([[[1e-2], [1e-2], [1.0], [1.0]]])
    mu3, tau23, _ = priors.material_estimate(y3, v3, torch.ones_like(y3))
    assert float(tau23) == 0.0 and abs(float(mu3) - 1 / 101) < 1e-6


def test_fill_width_is_the_material_measured_spread():
    """A silent pixel's prior is as wide as the spread of the measured pixels of its material (a
    fixed tolerance would give both materials one width); its centre is their mean."""
    widths = {}
    for spread in (0.1, 0.6):
        data, theta, metal, info, silent, sigma2 = _material(spread)
        tgt, prec = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
        good = ~silent
        variance = sigma2 / prec[silent, 4]  # the prior's variance, logit²
        assert torch.allclose(variance, torch.full_like(variance, float(theta[good, 4].var())), rtol=0.35)
        assert float((tgt[silent, 4] - theta[good, 4].mean()).abs().max()) < 3 * spread / 256**0.5 + 0.02
        widths[spread] = float(variance.median())
    assert 20 < widths[0.6] / widths[0.1] < 60  # (0.6 / 0.1)² = 36


def test_fill_moves_a_pixel_by_its_information():
    """The fit's fusion ``(info θ + prec m) / (info + prec)``: a pixel measured 100× better than
    the material's spread keeps its value, one measured as well as the spread moves halfway,
    and a silent one takes the material's value."""
    data, theta, metal, info, silent, sigma2 = _material(0.6)
    tgt, prec = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
    tau2 = float(theta[~silent, 4].var())
    info = info.clone()
    strong, equal = 100, 101
    theta[strong, 4] = theta[equal, 4] = 1.5
    info[strong, 4] = sigma2 / (tau2 / 100)
    info[equal, 4] = sigma2 / tau2
    fused = (info[:, 4] * theta[:, 4] + prec[:, 4] * tgt[:, 4]) / (info[:, 4] + prec[:, 4])
    moved = (fused - theta[:, 4]) / (tgt[:, 4] - theta[:, 4])
    assert float(moved[strong]) < 0.03
    assert 0.35 < float(moved[equal]) < 0.65
    assert bool((moved[silent] > 0.999).all())


def test_fill_keeps_materials_apart_and_gives_a_metal_no_prior():
    """Another base colour is another material. A metal gets no prior, roughness included: the
    F0 tie already pools the metal's valley, and a second pooled prior on its roughness would
    pull it along the valley away from the F0 its neighbours share."""
    data, theta, metal, info, silent, _ = _material(0.1)
    p = theta.shape[0]
    other = torch.arange(p) >= p // 2
    theta[other, 0:3] = params.logit(torch.tensor([0.1, 0.1, 0.1]))
    theta[other, 4] = 2.0
    tgt, _ = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
    assert float((tgt[silent, 4] - theta[~silent & ~other, 4].mean()).abs().max()) < 0.05
    assert torch.allclose(tgt[other, 4], torch.full((int(other.sum()),), 2.0), atol=1e-4)
    metal = torch.ones_like(metal)
    tgt, prec = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
    assert bool((prec == 0).all()) and torch.equal(tgt, theta)
    # Half metal: the dielectric half keeps its prior, the metal half has none.
    metal[: metal.shape[0] // 2] = 0.0
    _, prec = priors.nonlocal_fill(data, theta, metal, Settings(), info=info)
    diel = metal[:, 0] < 0.5
    assert bool((prec[diel][:, 3:5] > 0).all()) and bool((prec[~diel] == 0).all())


def _island_capture(size=24):
    """A flat glossy dielectric (roughness 0.25, specular 0.5) cut by a rough green strip; every
    light stands on the +x side, so the island left of the strip sees no highlight: its
    roughness and specular are silent, and the strip cuts it off from the neighbours' ties."""
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import render_capture

    cols = torch.arange(size)[None, :].expand(size, size)
    island, strip = cols < int(0.375 * size), (cols >= int(0.375 * size)) & (cols < int(0.54 * size))
    maps = {"base_color": torch.tensor([0.5, 0.3, 0.2])[:, None, None].repeat(1, size, size),
            "roughness": torch.full((1, size, size), 0.25), "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), 0.5),
            "normal": torch.tensor([0.0, 0.0, 1.0])[:, None, None].repeat(1, size, size)}
    maps["base_color"][:, strip] = torch.tensor([0.1, 0.4, 0.1])[:, None]
    maps["roughness"][0, strip] = 0.8
    xy = [(0.5, 0.0), (0.9, 0.4), (0.9, -0.4), (1.3, 0.0), (0.6, 0.6), (0.6, -0.6), (1.4, 0.8), (1.4, -0.8), (2.0, 0.0)]
    pos = torch.tensor([[x, y, 2.0] for x, y in xy])
    inten = torch.full((len(xy), 3), 8.0)
    img = render_capture(maps, (pos, inten), backend="compact")
    img = img * (1 + 0.01 * torch.randn(img.shape, generator=torch.Generator().manual_seed(0)))
    cap = Capture(images=img, light_positions=pos, light_intensities=inten,
                  camera_position=torch.tensor([0.0, 0.0, 3.0]), width=size, height=size,
                  files=tuple(f"{k}.exr" for k in range(len(xy))))
    return cap, island, strip


def test_silent_island_takes_the_measured_roughness_and_specular():
    """End to end, default settings: the island no highlight reaches takes the roughness and
    specular its material shows where highlights land, not the dim, glossy valley's answer
    (specular ~0.26 without the fill); the measured half and the strip keep their own."""
    from torchbrdf.recovery.engine import Recovery
    from torchbrdf.recovery.config import RecoveryConfig

    cap, island, strip = _island_capture()
    rec = Recovery(cap, RecoveryConfig(threads=1, holdout=-1), log=lambda m: None)
    with torch.no_grad():
        rec.init_state()
        while not rec.finished():
            rec.step()
    maps = rec.current_params()
    rough, spec = maps["roughness"][0], maps["specular"][0]
    lit = ~island & ~strip
    assert abs(float(rough[island].mean()) - float(rough[lit].mean())) < 0.02
    assert abs(float(spec[island].mean()) - float(spec[lit].mean())) < 0.04
    assert abs(float(spec[island].mean()) - 0.5) < 0.05 and abs(float(rough[island].mean()) - 0.25) < 0.03
    assert float(rough[strip].mean()) > 0.6  # another material: not pulled toward the glossy one


def _periodic_laplacian(size):
    """The unit-weight 4-neighbour Laplacian ``(size², size²)`` of a periodic lattice, float64."""
    n = size * size
    lap = torch.zeros(n, n, dtype=torch.float64)
    for i in range(size):
        for j in range(size):
            p = i * size + j
            for di, dj in ((0, 1), (1, 0), (0, -1), (-1, 0)):
                q = ((i + di) % size) * size + (j + dj) % size
                lap[p, p] += 1.0
                lap[p, q] -= 1.0
    return lap


def test_tie_information_is_the_lattice_marginal():
    """What the ties add is ``1 / diag((d I + λ L)⁻¹) − d`` on the lattice (exact, dense inverse):
    ``4 λ`` (the neighbours held) where the data dominate, little where the data are silent
    (a silent region floats as a whole), not the ``4 λ`` of neighbours known exactly."""
    size, lam = 8, 0.002
    lap = _periodic_laplacian(size)
    for d in (1e-6, 1e-4, 2e-3, 0.02, 2.0):
        exact = 1.0 / torch.linalg.inv(d * torch.eye(size * size, dtype=torch.float64) + lam * lap)[0, 0] - d
        got = priors.tie_information(torch.tensor([[d]]), torch.tensor([[lam]]), size)
        assert abs(float(got) - float(exact)) <= 1e-3 * float(exact) + 1e-12, (d, float(got), float(exact))
    strong = float(priors.tie_information(torch.tensor([[1e3 * lam]]), torch.tensor([[lam]]), size))
    silent = float(priors.tie_information(torch.tensor([[1e-6 * lam]]), torch.tensor([[lam]]), size))
    assert abs(strong - 4 * lam) < 0.01 * lam and silent < 1e-3 * lam
    assert float(priors.tie_information(torch.tensor([[1e-3]]), torch.tensor([[0.0]]), size)) == 0.0


def test_fit_information_counts_the_ties_between_the_data_and_the_neighbours_held():
    """A fitted value's information lies between its data's alone (the neighbours unknown) and
    its data plus ``4 λ`` (the neighbours known), and exceeds the data's where ties act."""
    from torchbrdf.recovery.lm import gauss_newton, marginal_information
    from torchbrdf.recovery.smoothness_prior import edge_weights, laplacian_diag

    data, theta, metal = flat_level()
    cfg = Settings()
    jtj = gauss_newton(data, theta, metal, data.train_idx, "principled")[1]
    fit = priors.fit_information(data, theta, metal, cfg, jtj)
    alone = marginal_information(data, theta, metal, "principled", jtj)
    wx, wy = edge_weights(theta, metal, data.size, cfg)
    neighbours = torch.diag_embed(laplacian_diag(wx, wy, data.size))
    held = marginal_information(data, theta, metal, "principled", jtj + neighbours)
    assert bool((fit[:, 3:5] > alone[:, 3:5] * 1.01).all())
    assert bool((fit <= held * (1 + 1e-4)).all()) and bool((fit >= alone * (1 - 1e-4)).all())


def test_material_estimate_sets_stuck_members_aside():
    """Members stuck in another basin (8 % of them, anywhere in the logit range, their variances
    claimed small) are an outlier component: with ``span`` the spread and the mean are the
    material's; without, the stuck members inflate the spread many times over."""
    g = torch.Generator().manual_seed(3)
    k = 2000
    y = 0.4 + 0.05 * torch.randn(1, k, 1, generator=g)  # τ² = 2.5e-3
    stuck = torch.rand(1, k, 1, generator=g) < 0.08
    y = torch.where(stuck, -9 + 18 * torch.rand(1, k, 1, generator=g), y)
    v = torch.full_like(y, 1e-4)
    s = torch.ones_like(y)
    mu, tau2, _ = priors.material_estimate(y, v, s, span=priors.LOGIT_SPAN)
    assert abs(float(tau2) - 2.5e-3) < 0.4e-3 and abs(float(mu) - 0.4) < 0.01
    _, tau2_all, _ = priors.material_estimate(y, v, s)
    assert float(tau2_all) > 100 * 2.5e-3
    # No stuck member: the same estimate as without the outlier component.
    y0 = 0.4 + 0.05 * torch.randn(1, k, 1, generator=g)
    a, b = priors.material_estimate(y0, v, s, span=priors.LOGIT_SPAN), priors.material_estimate(y0, v, s)
    assert all(torch.allclose(p, q, rtol=1e-3) for p, q in zip(a, b))



def test_material_estimate_spread_with_stuck_members_from_a_robust_start():
    """Groups of one material measured precisely, 5–10 % of the members stuck anywhere in the
    logit range: a material without spread gets none (a start from every member's spread would
    leave the stuck ones in it after the few EM rounds), one with spread gets its own."""
    g = torch.Generator().manual_seed(5)
    n, k = 200, 256
    for tau in (0.0, 0.05):
        v = 1e-6 * torch.exp(torch.randn(n, k, 1, generator=g))
        y = 0.4 + tau * torch.randn(n, k, 1, generator=g) + v.sqrt() * torch.randn(n, k, 1, generator=g)
        frac = 0.05 + 0.05 * torch.rand(n, 1, 1, generator=g)
        stuck = torch.rand(n, k, 1, generator=g) < frac
        y = torch.where(stuck, -0.5 * priors.LOGIT_SPAN + priors.LOGIT_SPAN * torch.rand(n, k, 1, generator=g), y)
        s = 0.2 + 0.8 * torch.rand(n, k, 1, generator=g)
        mu, tau2, _ = priors.material_estimate(y, v, s, span=priors.LOGIT_SPAN)
        assert float((mu - 0.4).abs().max()) < 0.03
        if tau == 0.0:
            assert float(tau2.max()) < 1e-5  # the fit's own noise, 1e-6, is the scale of "none"
            _, tau2_fill, _ = priors.material_estimate(y, v, s, iters=2, span=priors.LOGIT_SPAN)
            assert float(tau2_fill.max()) < 1e-5  # the fill's two rounds
        else:
            assert float(tau2.median()) == pytest.approx(tau**2, rel=0.1)
            assert float(tau2.max()) < 2.0 * tau**2


def _dim_extreme(size=24):
    """A silent island held at a dim, rough extreme that fits its images (base colour and normal
    refitted there) and a fill prior at the truth: ``(data, x, metal, unary, truth, island,
    sigma2)``."""
    from torchbrdf.recovery.classes import residual_variance
    from torchbrdf.recovery.levels import LevelData
    from torchbrdf.recovery.lm import gauss_newton, newton_step, pixel_cost

    cap, island, strip = _island_capture(size)
    data = LevelData(cap, size, list(range(len(cap.files))), float(0.01 * cap.images.mean()))
    isl, st = island.flatten(), strip.flatten()
    n = size * size
    maps = {"base_color": torch.tensor([0.5, 0.3, 0.2]).repeat(n, 1), "roughness": torch.full((n, 1), 0.25),
            "specular": torch.full((n, 1), 0.5), "normal": torch.tensor([0.0, 0.0, 1.0]).repeat(n, 1)}
    maps["base_color"][st] = torch.tensor([0.1, 0.4, 0.1])
    maps["roughness"][st] = 0.8
    truth, metal = params.encode(maps), torch.zeros(n, 1)
    x = truth.clone()
    x[isl, 3] = params.logit(torch.tensor(0.1))
    x[isl, 4] = params.logit(torch.tensor(0.5), params.R_MIN, params.R_MAX)
    free = torch.tensor([1.0, 1, 1, 0, 0, 1, 1])  # the dim extreme's best base colour and normal
    idx = data.train_idx
    for _ in range(10):
        r, jtj, jtr = gauss_newton(data, x, metal, idx, "principled")
        cand = x + newton_step(jtj * free[:, None] * free + torch.diag(1 - free), jtr * free)
        x = torch.where(pixel_cost(data.residual(cand, metal, idx, "principled")) < pixel_cost(r), cand, x)
    r = data.residual(x, metal, idx, "principled")
    sigma2 = residual_variance(pixel_cost(r), r.shape[-1])
    prec = torch.zeros_like(x)
    prec[:, 3:5] = sigma2 / 0.5**2  # the material's spread: 0.5 in logit
    return data, x, metal, (truth, prec), truth, isl, sigma2


def test_fuse_walks_a_silent_pixel_out_of_the_dim_rough_extreme():
    """A silent island held at a dim, rough extreme that fits its images and a fill prior at the
    truth (:func:`_dim_extreme`): a full Gauss–Newton step overshoots the curved valley and
    raises the energy, the backtracked rounds reach the prior's value."""
    from torchbrdf.recovery.lm import gauss_newton, newton_step, pixel_cost, unary_cost

    data, x, metal, unary, truth, isl, sigma2 = _dim_extreme()
    prec, idx = unary[1], data.train_idx

    def energy(y):
        return (pixel_cost(data.residual(y, metal, idx, "principled")) + unary_cost(y, unary))[:, 0] / sigma2

    fused = priors.fuse_fill(data, x, metal, unary, "principled")
    # A metal walks no valley: the same pixels as metal take the two full steps only.
    as_metal = priors.fuse_fill(data, x, torch.ones_like(metal), unary, "principled")
    full = x
    for _ in range(2):
        r, jtj, jtr = gauss_newton(data, full, torch.ones_like(metal), idx, "principled")
        cand = full + newton_step(jtj + torch.diag_embed(prec), jtr + prec * (full - truth))
        e0 = pixel_cost(r) + unary_cost(full, unary)
        e1 = pixel_cost(data.residual(cand, torch.ones_like(metal), idx, "principled")) + unary_cost(cand, unary)
        full = torch.where(e1 < e0, cand, full)
    torch.testing.assert_close(as_metal, full)
    spec = torch.sigmoid(fused[isl, 3])
    # (a few pixels beside the strip sit in a local minimum of their own: 4 of 216)
    assert float(((spec - 0.5).abs() < 0.05).float().mean()) > 0.95 and abs(float(spec.median()) - 0.5) < 0.01
    assert bool((energy(fused) <= energy(x)).all()) and float((energy(fused) - energy(x))[isl].median()) < -10


def _fuse_fill_rendering_all(data, theta, metal, unary, rounds=2):
    """:func:`priors.fuse_fill` as it reads, every round's pixels rendered at every halving: the
    reference of the one that renders only the walkers a halving can still move."""
    from torchbrdf.recovery.classes import residual_variance
    from torchbrdf.recovery.lm import gauss_newton, newton_step, pixel_cost, unary_cost
    from torchbrdf.recovery.search import BADLY_FITTED

    tgt, prec = unary
    idx, model = data.train_idx, "principled"
    x = theta.clone()
    rows = torch.arange(theta.shape[0])
    for k in range(max(rounds, priors.FUSE_ROUNDS)):
        sub = data if k == 0 else data.subset(rows)
        xr, mr, un = x[rows], metal[rows], (tgt[rows], prec[rows])
        r0, jtj, jtr = gauss_newton(sub, xr, mr, idx, model)
        e_data = pixel_cost(r0)
        if k == 0:
            sigma2 = residual_variance(e_data, r0.shape[-1])
            noise = float(e_data[torch.isfinite(e_data[:, 0]), 0].median())
            walk = (metal[:, 0] < 0.5) & (e_data[:, 0] <= BADLY_FITTED * noise)
        step = newton_step(jtj + torch.diag_embed(un[1]), jtr + un[1] * (xr - un[0]))
        e0 = e_data + unary_cost(xr, un)
        best, e_best, todo, t = xr, e0, torch.ones_like(e0, dtype=torch.bool), 1.0
        for _ in range(priors.FUSE_HALVINGS + 1):
            cand = xr + t * step
            e1 = pixel_cost(sub.residual(cand, mr, idx, model)) + unary_cost(cand, un)
            ok = todo & (e1 < e0)
            best, e_best = torch.where(ok, cand, best), torch.where(ok, e1, e_best)
            todo &= ~ok & walk[rows, None]
            if not bool(todo.any()):
                break
            t *= 0.5
        x[rows] = best
        keep = ((e0 - e_best)[:, 0] >= sigma2) & walk[rows] if k + 1 >= rounds else torch.ones_like(walk[rows])
        rows = rows[keep]
        if rows.numel() == 0:
            break
    return x


def test_fuse_halvings_render_only_the_walkers_they_can_still_move(monkeypatch):
    """A round's halvings render only its walking pixels that no earlier step of the round
    lowered, each fewer than the round's full step; the result is bit for bit that of rendering
    every pixel at every halving."""
    from torchbrdf.recovery.levels import LevelData

    data, x, metal, unary, *_ = _dim_extreme()
    reference = _fuse_fill_rendering_all(data, x, metal, unary)
    log = []
    residual, gauss_newton = LevelData.residual, priors.gauss_newton

    def spy_residual(self, theta, *args, **kwargs):
        log[-1].append(theta.shape[0])
        return residual(self, theta, *args, **kwargs)

    def spy_gauss_newton(*args, **kwargs):  # a round's start
        log.append([])
        return gauss_newton(*args, **kwargs)

    monkeypatch.setattr(LevelData, "residual", spy_residual)
    monkeypatch.setattr(priors, "gauss_newton", spy_gauss_newton)
    fused = priors.fuse_fill(data, x, metal, unary, "principled")
    monkeypatch.undo()
    assert torch.equal(fused, reference)
    halvings = [n for full, *rest in log for n in rest]
    assert halvings, "the island's full steps overshoot: some pixels halve their step"
    assert all(n < full for full, *rest in log for n in rest), log
