"""The batched propagation, normal search and smoothness-prior terms against their per-candidate loops.

The references below are the plain loops (one render per candidate, image-shaped prior
terms); the library evaluates every candidate of a pass in one fused call. Results must be
the same bit for bit: a candidate mapped to the wrong pixel or slot changes them.
"""

import pytest
import torch
import torch.nn.functional as F

from torchbrdf.recovery import classes, lm, map_ops, search, smoothness_prior
from torchbrdf.recovery.config import Settings

from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.params import N_PARAMS, encode

from tests.recovery.recovery_fixtures import flat_level


def reference_local_prior(cand, theta, wx, wy, size):
    """``Σ_q w_pq (cand_p − θ_q)²`` ``(P, 1)`` on image-shaped slices (the loop's form)."""
    c = theta.shape[1]
    a, t = cand.reshape(size, size, c), theta.reshape(size, size, c)
    e = torch.zeros(size, size, 1, dtype=theta.dtype, device=theta.device)
    e[:, :-1] += (wx * (a[:, :-1] - t[:, 1:]) ** 2).sum(-1, keepdim=True)
    e[:, 1:] += (wx * (a[:, 1:] - t[:, :-1]) ** 2).sum(-1, keepdim=True)
    e[:-1] += (wy * (a[:-1] - t[1:]) ** 2).sum(-1, keepdim=True)
    e[1:] += (wy * (a[1:] - t[:-1]) ** 2).sum(-1, keepdim=True)
    return e.reshape(-1, 1)


def reference_propagate(data, theta, metal, cfg, class_sigma2=None, unary=None, active=None):
    """:func:`search.propagate` as a loop over the 8 neighbours, one render each."""
    size, c = data.size, theta.shape[1]
    rows = None if active is None else active.nonzero()[:, 0]

    def sel(x):
        return x if rows is None else x[rows]

    def cost(t, m):
        r = data.residual(t, m, data.train_idx, cfg.model, rows=rows)
        return torch.nan_to_num((r ** 2).sum(-1, keepdim=True), nan=float("inf"))

    un = None if unary is None else (sel(unary[0]), sel(unary[1]))
    wx, wy = smoothness_prior.edge_weights(theta, metal, size, cfg)
    own, own_metal = sel(theta), sel(metal)
    best, best_metal = own, own_metal
    own_cost = cost(own, own_metal)
    own_prior = sel(reference_local_prior(theta, theta, wx, wy, size)) + lm.unary_cost(own, un)
    best_score = own_cost + own_prior
    tau = classes.evidence_threshold(N_PARAMS, cfg.false_metal_rate)
    n_res = 3 * len(data.train_idx)
    pad = F.pad(theta.T.reshape(1, c, size, size), (1, 1, 1, 1), mode="replicate")[0]
    padm = F.pad(metal.T.reshape(1, 1, size, size), (1, 1, 1, 1), mode="replicate")[0]
    for dy, dx in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        cand_all = pad[:, 1 + dy: 1 + dy + size, 1 + dx: 1 + dx + size].reshape(c, -1).T
        cand = sel(cand_all)
        cm = sel(padm[:, 1 + dy: 1 + dy + size, 1 + dx: 1 + dx + size].reshape(1, -1).T)
        same = cm == own_metal
        prior = sel(reference_local_prior(cand_all, theta, wx, wy, size)) + lm.unary_cost(cand, un)
        if class_sigma2 is None:
            score = torch.where(same, cost(cand, own_metal) + prior, float("inf"))
        else:
            data_cost = cost(cand, cm)
            price = tau * classes.pixel_noise_variance(own_cost, data_cost, class_sigma2, n_res)
            score = torch.where(same, data_cost + prior,
                                data_cost + torch.where(cm > 0.5, price, -price) + own_prior)
        better = score < best_score
        best = torch.where(better, cand, best)
        best_metal = torch.where(better, cm, best_metal)
        best_score = torch.where(better, score, best_score)
    if rows is not None:
        best = theta.index_copy(0, rows, best)
        best_metal = metal.index_copy(0, rows, best_metal)
    return best, best_metal, (best != theta).any(-1)


def rough_state(size=12, seed=0, dtype=torch.float32, lights=6):
    """A level and a noisy fit of it with a metal patch: every neighbour a different candidate."""
    data, theta, metal = flat_level(size=size, lights=lights)
    gen = torch.Generator().manual_seed(seed)
    theta = theta + 0.6 * torch.randn(theta.shape, generator=gen)
    theta[:, 5:7] *= 0.3
    metal = metal.clone().reshape(size, size)
    metal[2:7, 3:9] = 1.0
    metal[8, 1] = 1.0  # a lone metal pixel
    return data, theta.to(dtype), metal.reshape(-1, 1).to(dtype)


@pytest.mark.parametrize("metal_share, joined", [(0.0, slice(3, 5)), (0.3, slice(0, 5))])
def test_prior_terms_sum_only_the_joined_channels_with_the_same_bits(metal_share, joined):
    """The prior's edge weights join specular and roughness, and a metal's base colour, never the
    normal's slopes: ``joined_channels`` finds them, and ``local_prior`` and ``prior_energy``,
    summing those channels alone, give the bits of the sums over every channel."""
    size = 9
    gen = torch.Generator().manual_seed(3)
    theta = torch.randn(size * size, 7, generator=gen)
    metal = (torch.rand(size * size, 1, generator=gen) < metal_share).to(theta.dtype)
    wx, wy = smoothness_prior.edge_weights(theta, metal, size, Settings())
    assert smoothness_prior.joined_channels(wx, wy) == joined
    cands = torch.randn(8, size * size, 7, generator=gen)
    got = smoothness_prior.local_prior(cands, theta, wx, wy, size)
    for k in range(8):
        assert torch.equal(got[k], reference_local_prior(cands[k], theta, wx, wy, size))
    rows = torch.tensor([80, 0, 8, 40, 72, 3])
    assert torch.equal(smoothness_prior.local_prior(cands[:, rows], theta, wx, wy, size, rows), got[:, rows])
    img = theta.reshape(size, size, 7)
    e = torch.zeros(size, size, 1)
    for w, a, b, at in ((wx, img[:, :-1], img[:, 1:], (slice(None), slice(0, -1))),
                        (wx, img[:, :-1], img[:, 1:], (slice(None), slice(1, None))),
                        (wy, img[:-1], img[1:], (slice(0, -1),)), (wy, img[:-1], img[1:], (slice(1, None),))):
        e[at] += (w * (a - b) ** 2).sum(-1, keepdim=True)
    assert torch.equal(smoothness_prior.prior_energy(theta, wx, wy, size), 0.5 * e.reshape(-1, 1))
    # no weight at all: no term
    zero = torch.zeros_like(wx), torch.zeros_like(wy)
    assert smoothness_prior.joined_channels(*zero) == slice(7, 7)
    assert torch.equal(smoothness_prior.local_prior(cands, theta, *zero, size), torch.zeros(8, size * size, 1))


def test_local_prior_of_stacked_candidates_equals_the_image_form():
    size = 7
    gen = torch.Generator().manual_seed(1)
    wx = torch.rand(size, size - 1, 7, generator=gen)
    wy = torch.rand(size - 1, size, 7, generator=gen)
    theta = torch.randn(size * size, 7, generator=gen)
    cands = torch.randn(3, size * size, 7, generator=gen)
    got = smoothness_prior.local_prior(cands, theta, wx, wy, size)
    assert got.shape == (3, size * size, 1)
    for k in range(3):
        assert torch.equal(got[k], reference_local_prior(cands[k], theta, wx, wy, size))
    rows = torch.tensor([48, 0, 6, 24, 42, 3])  # corners, an edge, the middle, out of order
    at = smoothness_prior.local_prior(cands[:, rows], theta, wx, wy, size, rows)
    assert torch.equal(at, got[:, rows])
    assert torch.equal(smoothness_prior.local_prior(theta[:1], theta[:1], wx[:1, :0], wy[:0, :1], 1),
                       torch.zeros(1, 1))
    around = smoothness_prior.row_neighbours(theta, wx, wy, size, rows)  # gathered once, for both calls
    assert torch.equal(smoothness_prior.local_prior(cands[:, rows], theta, wx, wy, size, rows, around), at)
    assert torch.equal(smoothness_prior.local_prior(theta[rows], theta, wx, wy, size, rows, around),
                       reference_local_prior(theta, theta, wx, wy, size)[rows])


def reference_choice(scores, own_score, cands, owns):
    """The propagation's choice as a loop over candidates: a strictly lower score replaces the best."""
    best_score, best = own_score, list(owns)
    for k in range(scores.shape[0]):
        better = scores[k] < best_score
        best = [torch.where(better, c[k], b) for c, b in zip(cands, best)]
        best_score = torch.where(better, scores[k], best_score)
    return best


def test_choosing_among_all_candidates_at_once_equals_trying_them_in_order():
    # Scores on a coarse grid tie often (the first of equal scores must win, the pixel's own
    # before any), with NaN (never wins, nor beats a NaN own score) and ±inf among them.
    gen = torch.Generator().manual_seed(11)
    k, n = 8, 4000
    special = torch.tensor([float("nan"), float("inf"), -float("inf")])
    scores = torch.randint(0, 4, (k, n, 1), generator=gen).float()
    pick = torch.rand(k, n, 1, generator=gen) < 0.15
    scores[pick] = special[torch.randint(0, 3, (int(pick.sum()),), generator=gen)]
    own_score = torch.randint(0, 5, (n, 1), generator=gen).float()
    own_score[::37] = float("nan")
    own_score[5::41] = float("inf")
    own_score[7::43] = -float("inf")
    scores[:, 0], own_score[0] = float("inf"), float("inf")  # nothing beats +inf with +inf
    scores[:, 1], scores[3, 1], own_score[1] = float("nan"), float("inf"), float("inf")
    cands = (torch.randn(k, n, 7, generator=gen), torch.arange(k * n, dtype=torch.float32).view(k, n, 1))
    owns = (torch.randn(n, 7, generator=gen), -torch.ones(n, 1))
    got = search.choose_candidate(scores, own_score, cands, owns)
    ref = reference_choice(scores, own_score, cands, owns)
    assert bool((got[1] >= 0).any()) and bool((got[1] < 0).any())
    for a, b in zip(got, ref):
        assert torch.equal(a, b)


def test_rows_equal_compares_every_channel_as_floats():
    a = torch.tensor([[1.0, 2.0, 3.0], [0.0, 2.0, float("nan")], [-0.0, 5.0, 6.0], [1.0, 2.0, 4.0]])
    b = torch.tensor([[1.0, 2.0, 3.0], [0.0, 2.0, float("nan")], [0.0, 5.0, 6.0], [1.0, 2.0, 3.0]])
    assert search.rows_equal(a, b)[:, 0].tolist() == [True, False, True, False]
    stacked = torch.stack((a, b, a.flip(0)))  # (3, 4, 3) against (4, 3): broadcast over the sets
    assert torch.equal(search.rows_equal(stacked, b), (stacked == b).all(-1, keepdim=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cross", [None, 1e-3])
def test_batched_propagation_equals_the_per_candidate_loop(dtype, cross):
    data, theta, metal = rough_state(dtype=dtype)
    data.points, data.camera = data.points.to(dtype), data.camera.to(dtype)
    data.pos, data.inten, data._log_obs = data.pos.to(dtype), data.inten.to(dtype), data._log_obs.to(dtype)
    cfg = Settings()
    got = search.propagate(data, theta, metal, cfg, class_sigma2=cross)
    ref = reference_propagate(data, theta, metal, cfg, class_sigma2=cross)
    assert bool(ref[2].any()) and not bool(ref[2].all())  # some pixels move, not all
    if cross is not None:
        assert not torch.equal(ref[1], metal)  # ... and some change class
    for a, b in zip(got, ref):
        # (the layout too: the fit's later float sums over a pixel's unknowns round by it)
        assert torch.equal(a, b) and a.stride() == b.stride()


def test_batched_propagation_with_a_unary_prior_and_active_pixels_equals_the_loop():
    data, theta, metal = rough_state(seed=3)
    gen = torch.Generator().manual_seed(4)
    unary = (theta + 0.3 * torch.randn(theta.shape, generator=gen), torch.rand(theta.shape, generator=gen))
    cfg = Settings()
    changed = reference_propagate(data, theta, metal, cfg)[2]
    active = map_ops.dilate(changed, data.size) & (torch.rand(theta.shape[0], generator=gen) < 0.7)
    for cross in (None, 1e-3):
        got = search.propagate(data, theta, metal, cfg, class_sigma2=cross, unary=unary, active=active)
        ref = reference_propagate(data, theta, metal, cfg, class_sigma2=cross, unary=unary, active=active)
        assert bool(ref[2].any())
        for a, b in zip(got, ref):
            assert torch.equal(a, b) and a.stride() == b.stride()
    none = search.propagate(data, theta, metal, cfg, active=torch.zeros_like(active))
    assert none[0] is theta and not bool(none[2].any())


def reference_passes(data, theta, metal, cfg, passes, class_sigma2=None, unary=None):
    """Passes of the per-candidate loop, each after the first on the pixels near the last one's changes."""
    active = None
    for _ in range(passes):
        theta, metal, changed = reference_propagate(data, theta, metal, cfg, class_sigma2, unary, active)
        if not bool(changed.any()):
            break
        active = map_ops.dilate(changed, data.size)
    return theta, metal


def count_rendered(monkeypatch):
    """Patch :func:`search._data_cost` to count the pixels it renders; returns the running count (a list)."""
    seen = [0]
    original = search._data_cost

    def counting(data, theta, metal, model, rows):
        seen[0] += theta.shape[0]
        return original(data, theta, metal, model, rows)

    monkeypatch.setattr(search, "_data_cost", counting)
    return seen


@pytest.mark.parametrize("cross", [None, 1e-3])
def test_passes_reusing_earlier_costs_equal_the_loop_of_passes(monkeypatch, cross):
    # A wrong block over a rough map with a metal patch, repaired one ring per pass: from the
    # third pass on, some of a pixel's neighbours are unchanged since a pass that rendered
    # them at it (their costs reused) and some are new.
    size = 16
    data, theta, metal = rough_state(size=size, seed=7)
    img = theta.view(size, size, 7)
    img[4:12, 4:12, :5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])
    gen = torch.Generator().manual_seed(8)
    unary = (theta + 0.3 * torch.randn(theta.shape, generator=gen), torch.rand(theta.shape, generator=gen))
    cfg = Settings()
    ref = reference_passes(data, theta, metal, cfg, 6, cross, unary)
    monkeypatch.setattr(search, "FULL_PASS_SHARE", 1.0)  # (every pass after the first on some pixels)
    rendered = count_rendered(monkeypatch)
    got = search.propagate_passes(data, theta, metal, cfg, 6, class_sigma2=cross, unary=unary)
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
    reused, rendered[0] = rendered[0], 0
    t, m, active = theta, metal, None  # the same passes, each rendering all its candidates
    for _ in range(6):
        t, m, changed = search.propagate(data, t, m, cfg, class_sigma2=cross, unary=unary, active=active)
        if not bool(changed.any()):
            break
        active = map_ops.dilate(changed, size)
    assert reused < 0.75 * rendered[0]


def fitted_state(size=24, lights=8, dtype=torch.float32):
    """A level of bumpy normals and varying roughness, its exact maps with a few pixels broken and a metal patch.

    Most pixels hold their own exact parameters, so most neighbours' explain them worse; the
    broken ones take a neighbour's. Training lights: all but 0 and 3 (not the first L lights).
    """
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import light_layout, render_capture

    y, x = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    n = torch.stack((0.3 * torch.sin(5 * x), 0.3 * torch.cos(4 * y), torch.ones_like(x)))
    maps = {"base_color": torch.stack((0.5 + 0.2 * x, 0.3 + 0.1 * y, 0.2 + 0 * x)),
            "roughness": (0.3 + 0.15 * x * y)[None], "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), 0.5), "normal": n / n.norm(dim=0)}
    pos, inten = light_layout(lights)
    imgs = render_capture(maps, (pos, inten), backend="compact")
    cap = Capture(images=imgs, light_positions=pos, light_intensities=inten,
                  camera_position=torch.tensor([0.0, 0.0, 3.0]), width=size, height=size,
                  files=tuple(f"{k}.exr" for k in range(len(pos))))
    data = LevelData(cap, size, [k for k in range(lights) if k not in (0, 3)], float(0.01 * imgs.mean()))
    p = {k: v.reshape(v.shape[0], -1).T.contiguous() for k, v in maps.items()}
    metal = p.pop("metallic").reshape(size, size)
    metal[3:8, 10:16] = 1.0
    theta = encode(p)
    theta[::29] += 1.5 * torch.randn(theta[::29].shape, generator=torch.Generator().manual_seed(9))
    data.points, data.camera = data.points.to(dtype), data.camera.to(dtype)
    data.pos, data.inten, data._log_obs = data.pos.to(dtype), data.inten.to(dtype), data._log_obs.to(dtype)
    return data, theta.to(dtype), metal.reshape(-1, 1).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cross", [None, 1e-3])
def test_a_full_pass_bounded_on_a_few_lights_equals_rendering_every_candidate(monkeypatch, dtype, cross):
    # (a bound rendered on the wrong lights, or too tight, rules out candidates that win)
    data, theta, metal = fitted_state(dtype=dtype)
    chosen = []
    original = search.pruning_lights
    monkeypatch.setattr(search, "pruning_lights", lambda *a, **k: chosen.append(original(*a, **k)) or chosen[-1])
    rendered = count_rendered(monkeypatch)
    cfg = Settings()
    got = search.propagate(data, theta, metal, cfg, class_sigma2=cross)
    ref = reference_propagate(data, theta, metal, cfg, class_sigma2=cross)
    assert chosen[0] is not None and set(chosen[0]) < set(data.train_idx)
    assert rendered[0] < 0.6 * 9 * theta.shape[0]  # most candidates ruled out on those lights
    assert bool(ref[2].any())
    for a, b in zip(got, ref):
        assert torch.equal(a, b) and a.stride() == b.stride()


@pytest.mark.parametrize("cross", [None, 1e-3])
def test_an_active_pass_over_repeated_values_equals_the_loop(cross):
    # Exact pixels with a few broken ones, a metal patch and a block of one value: the block's
    # neighbours repeat each other, across the class boundary too. (A candidate's cost given
    # to another pixel or neighbour changes the maps.)
    size = 24
    data, theta, metal = fitted_state(size=size)
    img, metal_img = theta.view(size, size, 7), metal.view(size, size)
    img[1:9, 8:14] = img[5, 11]  # one value over metal and dielectric pixels
    img[14:20, 2:9] = img[16, 5]
    cfg = Settings()
    changed = reference_propagate(data, theta, metal, cfg, class_sigma2=cross)[2]
    active = map_ops.dilate(changed, size)
    active.view(size, size)[0:10, 7:15] = True
    got = search.propagate(data, theta, metal, cfg, class_sigma2=cross, active=active)
    ref = reference_propagate(data, theta, metal, cfg, class_sigma2=cross, active=active)
    assert bool(ref[2].any()) and not bool(ref[2].all()) and bool((metal_img[1:9, 8:14] > 0.5).any())
    for a, b in zip(got, ref):
        assert torch.equal(a, b) and a.stride() == b.stride()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_subset_cost_bound_stays_below_the_cost_of_any_rounding(dtype):
    gen = torch.Generator().manual_seed(10)
    r = (torch.randn(500, 12, generator=gen) * torch.logspace(-6, 1, 500)[:, None]).to(dtype)
    tol = search.BOUND_ULPS * torch.finfo(dtype).eps
    bound = search.subset_cost_bound(r, tol)
    worst = r.abs() - tol * (1 + r.abs())  # every residual rounded as far towards 0 as allowed
    assert bool((bound[:, 0] <= (worst.clamp(min=0) ** 2).sum(-1)).all())
    big = (r * r).sum(-1) > 1e-3  # (residuals of 1 % noise and more: not much looser than the cost)
    assert bool(big.any()) and bool((bound[big, 0] >= 0.99 * (r[big] * r[big]).sum(-1)).all())
    r[3, 4] = float("nan")
    assert search.subset_cost_bound(r, tol)[3, 0] == float("inf")


def test_neighbour_rows_replicate_the_border():
    rows = torch.tensor([0, 2, 5, 15])  # corners, a top-edge pixel, an inside one of a 4x4 map
    assert search.neighbour_rows(rows, 4).T.tolist() == [[0, 0, 1, 0, 1, 4, 4, 5], [1, 2, 3, 1, 3, 5, 6, 7],
                                                         [0, 1, 2, 4, 6, 8, 9, 10],
                                                         [10, 11, 11, 14, 15, 14, 15, 15]]


def reference_normal_search(data, theta, metal, model, factor=10.0, max_pixels=4096):
    """:func:`search.normal_search` rendering every candidate of every base, blocks of whole pixels."""
    found = search.search_bases(data, theta, metal, model, factor, max_pixels)
    if found is None:
        return theta, 0
    cost, bad, bases, valid = found
    c, idx = theta.shape[1], data.train_idx
    slopes = search.candidate_slopes(theta.dtype, theta.device)
    nb, nbase, k = bad.numel(), bases.shape[1], slopes.shape[0]
    cand = bases[:, :, None, :].expand(nb, nbase, k + 1, c).clone()
    cand[:, :, 1:, 5:7] = slopes[None, None]
    cand = cand.reshape(nb, -1, c)
    ccost = torch.empty(cand.shape[:2], dtype=theta.dtype, device=theta.device)
    chunk = max(1, 65536 // cand.shape[1])
    for s0 in range(0, nb, chunk):
        sl = slice(s0, s0 + chunk)
        n = cand[sl].shape[0]
        rows = bad[sl].repeat_interleave(cand.shape[1])
        rr = data.residual(cand[sl].reshape(-1, c), metal[rows], idx, model, rows=rows)
        ccost[sl] = torch.nan_to_num((rr * rr).sum(-1), nan=float("inf")).reshape(n, -1)
    ccost = torch.where(valid[:, :, None].expand(nb, nbase, k + 1).reshape(nb, -1), ccost, float("inf"))
    best_cost, best = ccost.min(1)
    better = best_cost < cost[bad]
    theta = theta.clone()
    theta[bad[better]] = cand[better, best[better]]
    return theta, int(better.sum())


def test_normal_search_without_repeated_candidates_equals_rendering_all():
    # Bad pixels among neighbours that repeat each other's parameters (a region one value
    # spread over) or only their material (the normal grid's candidates repeat), across a
    # class boundary (the other class's bases are no candidates).
    data, theta, metal = rough_state(size=12, seed=5)
    img = theta.view(12, 12, 7)
    img[4:8, 0:6] = img[5, 2]  # one value over a block, metal and dielectric pixels
    img[0:4, 6:12, :5] = img[1, 8, :5]  # one material, the normals left as they were
    img[0:4, 6:12, 5:7] *= 0.5
    got = search.normal_search(data, theta, metal, "principled", factor=1.0)
    ref = reference_normal_search(data, theta, metal, "principled", factor=1.0)
    assert ref[1] > 10 and got[1] == ref[1] and torch.equal(got[0], ref[0])
    few = search.normal_search(data, theta, metal, "principled", factor=1.0, max_pixels=7)
    assert few[1] == reference_normal_search(data, theta, metal, "principled", factor=1.0, max_pixels=7)[1]


def test_normal_search_bounded_on_a_few_lights_equals_rendering_all(monkeypatch):
    # Broken normals among exact pixels: most grid normals cost more than a broken pixel's own.
    data, theta, metal = fitted_state(size=24, lights=16)
    theta[::7, 5:7] = torch.tensor([0.6, -0.5])
    chosen = []
    original = search.pruning_lights
    monkeypatch.setattr(search, "pruning_lights", lambda *a, **k: chosen.append(original(*a, **k)) or chosen[-1])
    got = search.normal_search(data, theta, metal, "principled", factor=1.5)
    ref = reference_normal_search(data, theta, metal, "principled", factor=1.5)
    assert chosen[0] is not None and set(chosen[0]) < set(data.train_idx)
    assert ref[1] > 10 and got[1] == ref[1] and torch.equal(got[0], ref[0])


def test_lm_step_counts_and_rejects_non_finite_costs():
    data, theta, metal = rough_state(size=12, seed=6)
    theta[[3, 100], 4] = float("nan")  # NaN costs there and, through the prior, at their 4-neighbours
    lam = torch.full((theta.shape[0], 1), 1e-2)
    new, lam1, cost, n_bad = lm.lm_step(data, theta, metal, lam, Settings(), 1.0)
    bad = torch.isinf(cost[:, 0])
    assert n_bad == int(bad.sum()) == 9 and bool(bad[[2, 3, 4, 15, 88, 99, 100, 101, 112]].all())
    assert bool(torch.isnan(new[[3, 100], 4]).all()) and bool((lam1[bad] > lam[bad]).all())
    assert bool(torch.isfinite(new[~bad]).all()) and bool(torch.isfinite(cost[~bad]).all())


def test_normal_search_survives_a_chunk_the_bound_rules_out_entirely(monkeypatch):
    # (every candidate of a chunk above its pixel's cost on the few lights: no pixel left to render)
    data, theta, metal = fitted_state(size=24, lights=16)
    empty = torch.zeros(0, dtype=torch.long)
    assert data.residual(theta[empty], metal[empty], data.train_idx, "principled", rows=empty).shape == \
        (0, 3 * len(data.train_idx))
    theta[::7, 5:7] = torch.tensor([0.6, -0.5])
    monkeypatch.setattr(search, "pruning_lights", lambda data, *a, **k: data.train_idx[:2])
    monkeypatch.setattr(search, "subset_cost_bound", lambda r, tol, m=None: torch.full_like(r[:, :1], float("inf")))
    got, changed = search.normal_search(data, theta, metal, "principled", factor=1.5)
    assert changed == 0 and torch.equal(got, theta)


def test_a_pass_on_most_of_the_map_runs_as_a_full_pass(monkeypatch):
    # A pass on some pixels renders every candidate of theirs; beyond FULL_PASS_SHARE of the
    # map the full pass (its candidates bounded on a few lights) is the faster, and its maps
    # are the full pass's own.
    size = 16
    data, theta, metal = rough_state(size=size, seed=7)
    img = theta.view(size, size, 7)
    img[2:14, 2:14, :5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])
    seen = []
    plain = search._pass

    def recording(data, theta, metal, cfg, class_sigma2, unary, active, known):
        seen.append(None if active is None else int(active.sum()))
        return plain(data, theta, metal, cfg, class_sigma2, unary, active, known)

    monkeypatch.setattr(search, "_pass", recording)
    most = torch.zeros(size * size, dtype=torch.bool)
    most[: int(search.FULL_PASS_SHARE * size * size) + 1] = True
    got = search.propagate_passes(data, theta, metal, Settings(), 1, active=most)
    assert seen == [None]
    full = search.propagate(data, theta, metal, Settings())
    assert torch.equal(got[0], full[0]) and torch.equal(got[1], full[1])
    seen.clear()
    few = torch.zeros(size * size, dtype=torch.bool)
    few[: int(search.FULL_PASS_SHARE * size * size)] = True  # (at most the share: a pass on some pixels)
    search.propagate_passes(data, theta, metal, Settings(), 1, active=few)
    assert seen == [int(few.sum())]
