"""The fill's estimate in blocks of channel-major member tables against the member-by-member
definition: the random-effects EM over ``(N, K, C)`` members and the fill's per-class loop of
advanced-indexed candidates, kept here as written before the fill was batched."""

import math

import pytest
import torch

from torchbrdf.recovery import priors
from torchbrdf.recovery.classes import residual_variance
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.lm import pixel_cost

from tests.recovery.recovery_fixtures import flat_level


def _reference_robust_start(y, v, s, span):
    """The histogram start over ``(N, K, C)`` members (median, interquartile spread)."""
    k = y.shape[1]
    h = span / k
    w = s / (v + h * h / 12)
    v_mean = (w * v).sum(1) / w.sum(1).clamp(min=1e-30)
    lo = y.amin(1, keepdim=True)
    bins = torch.nan_to_num((y - lo) / h).long().clamp_(0, k - 1)
    cw = torch.zeros_like(y).scatter_add_(1, bins, w).cumsum(1).transpose(1, 2).contiguous()
    q = cw[..., -1:] * torch.tensor([0.25, 0.5, 0.75], dtype=cw.dtype)
    at = lo[:, 0, :, None] + (torch.searchsorted(cw, q).clamp_(max=k - 1).to(y.dtype) + 0.5) * h
    return at[..., 1], (((at[..., 2] - at[..., 0]) / 1.349) ** 2 - v_mean).clamp(min=0.0) + h * h / 12


def _reference_material_estimate(y, variances, weights, iters=3, span=None):
    """The random-effects EM member by member along dim 1 of ``(N, K, C)``."""
    s0 = weights.expand_as(y)
    s = s0
    v = torch.nan_to_num(variances, nan=priors.VAR_MAX, posinf=priors.VAR_MAX)
    v = v.clamp(priors.VAR_MIN, priors.VAR_MAX)
    u = v.reciprocal()
    tau2 = torch.zeros_like(y[:, 0])
    pi = torch.full_like(y[:, 0], 0.5)
    d2 = torch.zeros_like(y)
    for it in range(iters + 1):
        if it:
            u = (tau2[:, None] + v).reciprocal()
            if span is not None:
                c = torch.log(pi * span / (1 - pi)) - 0.5 * math.log(2 * math.pi)
                s = s0 * torch.sigmoid(c[:, None] + 0.5 * (torch.log(u) - d2 * u))
                pi = (s.sum(1) / s0.sum(1).clamp(min=1e-30)).clamp(1e-6, 1 - 1e-6)
        su = s * u
        den = su.sum(1)
        if it == 0 and span is not None:
            mu, tau2 = _reference_robust_start(y, v, s, span)
            d2 = (y - mu[:, None]) ** 2
            continue
        mu = (su * y).sum(1) / den.clamp(min=1e-30)
        d2 = (y - mu[:, None]) ** 2
        if it == 0:
            tau2 = (su * d2).sum(1) / den.clamp(min=1e-30)
            continue
        su2 = su * u
        tau2 = ((su2 * (d2 - v)).sum(1) / su2.sum(1).clamp(min=1e-30)).clamp(min=0.0)
    u = (tau2[:, None] + v).reciprocal()
    return mu, tau2, (s * u).sum(1).reciprocal()


def _reference_fill(data, theta, metal, cfg, info):
    """The fill of the dielectric pixels (metals get none), each pixel's candidates gathered as
    ``(n, K, C)`` members."""
    r = data.residual(theta, metal, data.train_idx, cfg.model)
    sigma2 = residual_variance(pixel_cost(r), r.shape[-1])
    var = sigma2 / info[:, 3:5].clamp(min=1e-30)
    sr = theta[:, 3:5].contiguous()
    img = theta[:, 5:7].T.reshape(1, 2, data.size, data.size)
    pad = torch.nn.functional.pad(torch.cat((img, img * img), 1), (2,) * 4, mode="reflect")
    mom = torch.nn.functional.avg_pool2d(pad, 5, 1)
    tex = (mom[:, 2:] - mom[:, :2] ** 2).clamp(min=0).sum(1).sqrt().reshape(-1, 1)
    feat = torch.cat((torch.sigmoid(theta[:, 0:3]) / cfg.fill_range, tex / cfg.fill_texture), -1)
    gen = torch.Generator().manual_seed(int(cfg.seed) + 7919)
    tgt, prec = theta.clone(), torch.zeros_like(theta)
    ism = metal[:, 0] > 0.5
    for cls in (~ism,):
        pool = torch.nonzero(cls).flatten()
        k = min(cfg.fill_candidates, pool.numel())
        chunk = max(1, 2**20 // k)
        for s0 in range(0, pool.numel(), chunk):
            rr = pool[s0:s0 + chunk]
            cand = pool[torch.randint(0, pool.numel(), (rr.numel(), k), generator=gen)]
            sim = torch.exp(-((feat[cand] - feat[rr][:, None]) ** 2).sum(-1)) * (cand != rr[:, None])
            mu, tau2, var_mu = _reference_material_estimate(sr[cand], var[cand], sim[..., None], 2,
                                                            priors.LOGIT_SPAN)
            ok = torch.isfinite(mu) & (var_mu < priors.VAR_MAX)
            tgt[rr, 3:5] = torch.where(ok, mu, theta[rr, 3:5])
            prec[rr, 3:5] = torch.where(ok, sigma2 / (tau2 + var_mu), 0.0)
    return torch.nan_to_num(tgt), torch.nan_to_num(prec, posinf=0.0)


def _members(n, k, c, seed, dtype):
    """Members of ``n`` materials whose ``c`` quantities differ in centre and spread, a tenth
    stuck anywhere in the logit range, variances from exact to silent (some non-finite)."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    centre = torch.linspace(-2, 2, c, dtype=f64)[None, None] + torch.randn(n, 1, 1, generator=g, dtype=f64)
    spread = torch.linspace(0.02, 0.5, c, dtype=torch.float64)[None, None]
    y = centre + spread * torch.randn(n, k, c, generator=g, dtype=torch.float64)
    stuck = torch.rand(n, k, c, generator=g) < 0.1
    y = torch.where(stuck, priors.LOGIT_SPAN * (torch.rand(n, k, c, generator=g, dtype=f64) - 0.5), y)
    v = 10 ** (-8 + 10 * torch.rand(n, k, c, generator=g, dtype=torch.float64))
    v[:, :3, 0] = float("inf")
    v[:, 3, -1] = float("nan")
    s = torch.rand(n, k, 1, generator=g, dtype=torch.float64)
    return y.to(dtype), v.to(dtype), s.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("span", [None, priors.LOGIT_SPAN])
@pytest.mark.parametrize("iters", [0, 2, 3])
def test_material_estimate_matches_the_member_by_member_definition(dtype, span, iters):
    """Each material's and each quantity's estimate is its own: a swapped member order, a
    weight broadcast over the wrong dim or quantities mixed in one histogram all differ."""
    y, v, s = _members(7, 300, 3, seed=11, dtype=dtype)
    tol = {"rtol": 1e-9, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 2e-4, "atol": 1e-6}
    for weights in (s, s.expand(-1, -1, 3) * torch.tensor([1.0, 0.3, 0.7], dtype=dtype)):
        got = priors.material_estimate(y, v, weights, iters=iters, span=span)
        want = _reference_material_estimate(y, v, weights, iters=iters, span=span)
        for a, b in zip(got, want):
            assert a.shape == (7, 3) and a.dtype == dtype
            torch.testing.assert_close(a, b, **tol)
    # The check sees a batching error: the materials' quantities are far apart.
    swapped = _reference_material_estimate(y.flip(2), v.flip(2), s, iters=iters, span=span)
    assert not torch.allclose(swapped[0], want[0], rtol=1e-2)


def _two_class_level(size=80, seed=4):
    """A level of three dielectric looks and one metal block, their specular and roughness
    logits apart (and apart from each other), the normals bumpy on one look; a few pixels
    stuck elsewhere and a silent patch. Returns ``(data, theta, metal, info)``."""
    data, theta, metal = flat_level(size=size)
    p = theta.shape[0]
    g = torch.Generator().manual_seed(seed)
    look = torch.randint(0, 3, (p,), generator=g)
    theta = theta.clone()
    theta[:, 0:3] = torch.tensor([[0.0, -1.0, -2.0], [-2.0, 0.5, 0.0], [1.0, 1.0, -0.5]])[look]
    theta[:, 3] = torch.tensor([-1.0, 0.5, 1.5])[look] + 0.1 * torch.randn(p, generator=g)
    theta[:, 4] = torch.tensor([0.8, -1.5, -0.2])[look] + 0.3 * torch.randn(p, generator=g)
    theta[:, 5:7] = 0.05 * torch.randn(p, 2, generator=g) * (look == 2)[:, None]
    stuck = torch.rand(p, generator=g) < 0.05
    theta[stuck, 3:5] = -4.0
    rows = torch.arange(p) // size
    metal = (rows < size // 4).to(theta.dtype)[:, None]
    info = 10 ** (2 + 2 * torch.rand(p, 7, generator=g))
    info[torch.arange(p) % size < 6] = 1e-3  # a silent strip
    return data, theta, metal, info


def test_fill_matches_the_per_class_loop():
    """Candidates drawn as before (the same random stream), each pixel's estimate from its own:
    more pixels than one block of candidates and one draw, two classes, silent pixels."""
    data, theta, metal, info = _two_class_level()
    cfg = Settings()
    got = priors.nonlocal_fill(data, theta, metal, cfg, info=info)
    want = _reference_fill(data, theta, metal, cfg, info)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=2e-4, atol=1e-6)
    diel = metal[:, 0] < 0.5
    assert float(want[1][diel, 3:5].min()) > 0 and bool((got[1][~diel] == 0).all())
    # A pixel estimated from another's candidates (rows shifted by one) fails the check.
    shifted = torch.roll(want[0][:, 4], 1)
    assert not torch.allclose(shifted, want[0][:, 4], rtol=1e-2)


def test_fill_takes_the_callers_residuals():
    """The residuals the caller has at ``theta`` (Gauss–Newton's) give the same prior as those
    the fill computes, and they are the ones used: residuals twice as large, a 4× noise variance."""
    from torchbrdf.recovery.lm import gauss_newton

    data, theta, metal, info = _two_class_level(size=24)
    cfg = Settings()
    r = gauss_newton(data, theta, metal, data.train_idx, cfg.model)[0]
    own = priors.nonlocal_fill(data, theta, metal, cfg, info=info)
    given = priors.nonlocal_fill(data, theta, metal, cfg, info=info, residual=r)
    assert all(torch.equal(a, b) for a, b in zip(own, given))
    doubled = priors.nonlocal_fill(data, theta, metal, cfg, info=info, residual=2 * r)
    assert not torch.allclose(doubled[1], own[1], rtol=0.5)


@pytest.mark.parametrize("block", [1, 700, 2**20])
def test_fill_block_changes_no_bit(monkeypatch, block):
    """The block of candidates an estimate takes at once is a cache size only: blocks of one
    pixel, of a pixel count that splits a draw unevenly and of all pixels give the same bits
    as the default's. A pixel of a colour no other has (every candidate weighs 0, no member)
    gets no prior and keeps its value; its estimate is not borrowed from its block."""
    data, theta, metal, info = _two_class_level(size=40)
    lone = int(torch.nonzero(metal[:, 0] < 0.5)[7])
    theta[lone, 0:3] = torch.tensor([6.0, -6.0, 6.0])
    cfg = Settings(fill_candidates=64)
    want = priors.nonlocal_fill(data, theta, metal, cfg, info=info)
    monkeypatch.setattr(priors, "FILL_BLOCK", block)
    got = priors.nonlocal_fill(data, theta, metal, cfg, info=info)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    assert float(got[1][lone, 3:5].abs().max()) == 0.0
    assert torch.equal(got[0][lone, 3:5], theta[lone, 3:5])
    ref = _reference_fill(data, theta, metal, cfg, info)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=2e-4, atol=1e-6)
