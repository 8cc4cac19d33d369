"""Non-local priors: a metal's F0 from the metal around it, and the non-local fill of
under-determined roughness / specular from the same material elsewhere.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.recovery.classes import residual_variance
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import gauss_newton, marginal_information, newton_step, pixel_cost, unary_cost
from torchbrdf.recovery.map_ops import blur, kmeans
from torchbrdf.recovery.search import BADLY_FITTED
from torchbrdf.recovery.smoothness_prior import edge_weights, laplacian_diag


def nonlocal_prior(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
                   jtj: Tensor | None = None, cost: Tensor | None = None, jtr: Tensor | None = None,
                   rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Confidence-weighted non-local estimate of a metal's base colour (and, optionally, roughness).

    A metal's base colour (F0, logit) gets the average of the metal pixels within a large
    Gaussian window (``cfg.nonlocal_sigma`` × size), weighted by their marginal information;
    with ``cfg.prior_nonlocal > 0`` each pixel's roughness also gets the information-weighted
    average of same-class pixels of similar base colour (bilateral grid over k-means colour
    clusters) — off by default: rough pixels always carry little roughness information, so
    the average is pulled toward nearby glossy pixels (rough grout would end too smooth).
    ``jtj (P, 7, 7)``: the normal matrices at ``theta`` when the caller has them (else computed);
    ``cost (P, 1)``: each pixel's data cost there (its squared residuals' sum; None: not used),
    which scales a metal's weight by ``min(1, cfg.nonlocal_fit_weight × median / cost)`` (the
    median over the metal pixels with a finite cost; a non-finite cost weighs 0);
    ``jtr (P, 7)``: the data gradients there — with ``jtj``, each metal pixel enters the average
    at its own data optimum as one Gauss–Newton step predicts it (:func:`newton_step`), not
    where its fit stopped: in the GGX tail a metal's data pin F0·α², not F0, and the fit
    slides along that valley slowly from its dark start (None: where the fit stopped).
    ``rows (N,)`` (int64): the pixels that ``jtj``, ``cost`` and ``jtr`` (all three given) are
    of, ``(N, 7, 7)``, ``(N, 1)``, ``(N, 7)``; it must hold every metal pixel, and the
    information is then 0 elsewhere. Only without the roughness average, which needs every
    pixel's (None: all P pixels).
    Returns ``(precisions (P, 7), targets (P, 7), information (P, 7))``; the caller fuses
    ``(info θ + w m) / (info + w)``: pixels the data pins down (information ≫ precision)
    keep their value, the under-determined ones take the average.
    """
    size = data.size
    if rows is None:
        info = marginal_information(data, theta, metal, cfg.model, jtj)
    else:
        if cfg.prior_nonlocal > 0 or jtj is None or cost is None or jtr is None:
            raise ValueError("nonlocal_prior: `rows` needs jtj, cost and jtr, and prior_nonlocal = 0")

        def spread(x: Tensor, fill: float) -> Tensor:  # (N, ...) at rows -> (P, ...), fill elsewhere
            out = x.new_full((theta.shape[0], *x.shape[1:]), fill)
            out[rows] = x
            return out

        covered = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
        covered[rows] = True
        if bool(((metal[:, 0] > 0.5) & ~covered).any()):
            raise ValueError("nonlocal_prior: `rows` must hold every metal pixel")
        info = spread(marginal_information(data, theta[rows], metal[rows], cfg.model, jtj), 0.0)
        jtj, cost, jtr = spread(jtj, 0.0), spread(cost, float("inf")), spread(jtr, 0.0)
    sig = cfg.nonlocal_sigma * size
    base = torch.sigmoid(theta[:, 0:3])
    w = torch.zeros_like(theta)
    m = theta.clone()
    ism = metal[:, 0] > 0.5
    ci = info[:, 4:5]
    for cls in (ism, ~ism) if cfg.prior_nonlocal > 0 else ():
        if int(cls.sum()) == 0:
            continue
        # A bilateral grid in base colour: splat into k-means clusters, slice with a
        # Gaussian range weight around each pixel's own colour.
        cent = kmeans(base[cls], cfg.nonlocal_clusters, return_centres=True)
        num = torch.zeros(theta.shape[0], dtype=theta.dtype, device=theta.device)
        den = torch.zeros_like(num)
        lab = torch.cdist(base, cent).argmin(-1)
        g = torch.exp(-((base[:, None, :] - cent[None]) ** 2).sum(-1) / cfg.nonlocal_range**2)  # (P, K)
        for k in range(cent.shape[0]):
            mk = ((lab == k) & cls).to(theta.dtype)[:, None]
            if mk.sum() == 0:
                continue
            b = blur(torch.cat((mk * ci * theta[:, 4:5], mk * ci), -1), size, sig)
            num += g[:, k] * b[:, 0]
            den += g[:, k] * b[:, 1]
        m[cls, 4] = torch.where(den[cls] > 1e-9, num[cls] / den[cls].clamp(min=1e-12), theta[cls, 4])
        w[cls, 4] = cfg.prior_nonlocal
    if bool(ism.any()):
        mm = ism.to(theta.dtype)[:, None]
        # Weights saturate at 1 (the pixel's shrinkage factor info / (info + precision)):
        # a pixel wrongly called metal fits a dielectric's strong diffuse with very high
        # "information" and must not dominate the average.
        cb = info[:, 0:3] / (info[:, 0:3] + max(cfg.prior_nonlocal_base, 1e-12))
        finite = torch.isfinite(cost[:, 0]) & ism if cost is not None else ism[:0]
        if cost is not None and cfg.nonlocal_fit_weight > 0 and bool(finite.any()):
            # ... and by how well the model fits the pixel: one fitted far above the median
            # metal pixel (a rust front called metal, a blend of two materials) is no evidence
            # of its neighbours' F0 (it would darken the average). A non-finite cost weighs 0.
            ref = cfg.nonlocal_fit_weight * cost[finite].median()
            fit = torch.where(cost <= ref, torch.ones_like(cost), ref / cost)
            cb = cb * torch.nan_to_num(fit, nan=0.0, posinf=0.0)
        own = theta[:, 0:3]
        if jtr is not None and jtj is not None:
            # Weights ∝ information, so a pixel the data hardly see moves the average little
            # however far its step goes.
            own = own.clone()
            own[ism] += newton_step(jtj[ism], jtr[ism])[:, 0:3]
        num = blur(torch.cat((mm * cb * own, mm * cb), -1), size, sig)
        mb = torch.where(num[:, 3:6] > 1e-9, num[:, 0:3] / num[:, 3:6].clamp(min=1e-12), theta[:, 0:3])
        m[:, 0:3] = torch.where(ism[:, None], mb, theta[:, 0:3])
        w[:, 0:3] = cfg.prior_nonlocal_base * mm
    m = torch.nan_to_num(m)
    return w, m, info


#: Bounds of a member's variance (logit²) in :func:`material_estimate`: below, a value is
#: exact for any use here; above, it weighs nothing (and ``1 / v²`` stays finite in float32).
VAR_MIN, VAR_MAX = 1e-12, 1e12

#: The width of the range a specular or roughness logit lives in (:func:`logit`'s clamp, 1e-4
#: inside each end): where a fit stuck in another basin may sit, for :func:`material_estimate`.
LOGIT_SPAN = 2 * math.log((1 - 1e-4) / 1e-4)


def _normal_texture(theta: Tensor, size: int, radius: int = 2) -> Tensor:
    """Local standard deviation ``(P, 1)`` of the normal slope ``(p, q)`` in a ``(2r+1)²`` window
    (reflect-padded: an edge pixel's window lies inside the image): the geometry statistic
    that tells a smooth glaze from a bumpy stone of the same colour."""
    img = theta[:, 5:7].T.reshape(1, 2, size, size)
    k = 2 * radius + 1
    mode = "reflect" if size > radius else "replicate"
    pad = F.pad(torch.cat((img, img * img), 1), (radius,) * 4, mode=mode)
    mom = F.avg_pool2d(pad, k, 1)
    var = (mom[:, 2:] - mom[:, :2] ** 2).clamp(min=0).sum(1)
    return var.sqrt().reshape(-1, 1)


def _robust_start(y: Tensor, v: Tensor, s: Tensor, span: float) -> tuple[Tensor, Tensor]:
    """Centre and spread ``(...)`` of members ``y (..., K)`` along the last dim (variances ``v``
    alike, memberships ``s`` broadcast to them) that a minority anywhere in a range of width
    ``span`` moves neither: the median and the interquartile range (``/ 1.349``, a normal's) of a
    histogram of ``K`` bins of width ``h`` over the range (no sort), each member weighted
    ``s / (v + h²/12)`` (members more precise than a bin count alike), the spread less their
    mean variance plus a bin's own variance ``h²/12``."""
    k = y.shape[-1]
    h = span / k
    w = (v + h * h / 12).reciprocal_().mul_(s)
    v_mean = torch.linalg.vecdot(w, v) / w.sum(-1).clamp_(min=1e-30)
    lo = y.amin(-1, keepdim=True)
    # (clamped as floats: a bin beyond the range is the last, a NaN member's the first)
    bins = torch.nan_to_num_((y - lo).div_(h)).clamp_(0, k - 1).long()
    cw = torch.zeros_like(y).scatter_add_(-1, bins, w).cumsum_(-1)  # (..., K)
    q = cw[..., -1:] * torch.tensor([0.25, 0.5, 0.75], dtype=cw.dtype, device=cw.device)
    at = lo + (torch.searchsorted(cw, q).clamp_(max=k - 1).to(y.dtype) + 0.5) * h
    return at[..., 1], (((at[..., 2] - at[..., 0]) / 1.349) ** 2 - v_mean).clamp_(min=0.0) + h * h / 12


def _random_effects(y: Tensor, v: Tensor, s0: Tensor, iters: int,
                    span: float | None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`material_estimate` with the members along the last dim: ``y``, ``v (..., K)``
    (``v`` already clamped, overwritten), ``s0`` broadcast to them; returns ``(μ, τ², var(μ))``,
    each ``(...)``. Products go in place where they can: a fill's member tables are large."""
    s = s0
    if span is None:  # the start: the fixed-effects mean and spread of the members
        su = s * v.reciprocal()
        den = su.sum(-1).clamp_(min=1e-30)
        mu = torch.linalg.vecdot(su, y) / den
        d2 = (y - mu[..., None]).square_()
        tau2 = torch.linalg.vecdot(su, d2) / den
    else:  # the start, with stuck members: their robust centre and spread
        mu, tau2 = _robust_start(y, v, s, span)
        d2 = (y - mu[..., None]).square_()
        pi = torch.full_like(mu, 0.5)
        s_total = s0.sum(-1).clamp(min=1e-30)
    for _ in range(iters):
        spread = v + tau2[..., None]
        u = spread.reciprocal()
        if span is not None:  # E step: each member's responsibility of the material,
            # π N / (π N + (1 − π) / span) = 1 / (1 + odds · √(τ² + v) · exp(d² u / 2)): each
            # factor positive and at worst +inf (a member far off: responsibility 0), never NaN
            log2_odds = torch.log2((1 - pi) / (pi * span) * math.sqrt(2 * math.pi))
            odds_n = torch.addcmul(log2_odds[..., None], d2, u, value=0.5 / math.log(2), out=d2).exp2_()
            s = torch.div(s0, odds_n.mul_(spread.sqrt_()).add_(1), out=odds_n)
            pi = (s.sum(-1) / s_total).clamp_(1e-6, 1 - 1e-6)
        su = s * u
        den = su.sum(-1)
        mu = torch.linalg.vecdot(su, y) / den.clamp_(min=1e-30)
        d2 = (y - mu[..., None]).square_()
        su2 = su.mul_(u)
        tau2 = (torch.linalg.vecdot(su2, d2 - v) / su2.sum(-1).clamp_(min=1e-30)).clamp_(min=0.0)
    return mu, tau2, torch.linalg.vecdot(s, v.add_(tau2[..., None]).reciprocal_()).reciprocal_()


def material_estimate(values: Tensor, variances: Tensor, weights: Tensor, iters: int = 3,
                      span: float | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """A material's mean, spread and the mean's variance from noisy, softly weighted members.

    The random-effects model: each member's true value ``θ_j ~ N(μ, τ²)``, measured as
    ``y_j = θ_j + e_j`` with ``e_j ~ N(0, v_j)``; ``weights`` ``s_j`` in [0, 1] are soft
    memberships (each member's log-likelihood counted ``s_j`` times). ``μ`` is the weighted mean
    with weights ``s_j / (τ² + v_j)``; ``τ²`` the maximum-likelihood spread, by the fixed point
    ``τ² = Σ s u² ((y − μ)² − v) / Σ s u²`` with ``u = 1 / (τ² + v)`` (``iters`` rounds from
    the fixed-effects spread), so a member the data hardly see (``v`` large) counts neither in
    the mean nor in the spread. With ``span``, a member is instead, with a probability
    ``1 − π`` estimated with the rest (EM, one update per round from ``π = ½`` and from the
    members' median and interquartile spread in a histogram over ``span``, a start the stuck
    members move neither, so ``iters`` rounds suffice), a fit stuck
    anywhere in a range of that width (density ``1 / span``; a pixel in another basin, whose
    linearised ``v`` does not hold): its weight is multiplied by its responsibility
    ``π N(y; μ, τ² + v) / (π N(y; μ, τ² + v) + (1 − π) / span)``, so it widens neither the
    spread nor moves the mean (None: every member measures the material).
    ``values``, ``variances``: ``(N, K, C)`` (``K`` members, ``C`` independent quantities);
    ``weights`` ``(N, K, 1)`` or ``(N, K, C)``. Variances are clamped to ``[VAR_MIN, VAR_MAX]``
    (a non-finite one is ``VAR_MAX``: the member weighs nothing), so the powers stay finite in
    float32.
    Returns ``(μ, τ², var(μ) = 1 / Σ s u)`` of the material, each ``(N, C)`` in ``values``'
    dtype (``var(μ)`` is +inf where no member carries weight).
    """
    s = weights.expand_as(values).transpose(1, 2)
    v = _clamped_variance(variances.transpose(1, 2))
    return _random_effects(values.transpose(1, 2).contiguous(), v, s.contiguous(), iters, span)


def _clamped_variance(v: Tensor) -> Tensor:
    """Variances in ``[VAR_MIN, VAR_MAX]``, a non-finite one ``VAR_MAX`` (a new, contiguous tensor)."""
    return torch.nan_to_num(v, nan=VAR_MAX, posinf=VAR_MAX).clamp_(VAR_MIN, VAR_MAX).contiguous()


@functools.lru_cache(maxsize=8)
def _lattice_green_table(size: int) -> tuple[Tensor, Tensor]:
    """``(t (T,), g(t) (T,))`` float64: the diagonal of ``(t I + L)⁻¹`` for the unit-weight
    4-neighbour Laplacian ``L`` of a periodic ``size × size`` lattice, on a log grid of ``t``."""
    k = 2 * math.pi * torch.arange(size, dtype=torch.float64) / size
    s = (4 - 2 * torch.cos(k)[:, None] - 2 * torch.cos(k)[None, :]).flatten()  # L's eigenvalues
    t = torch.logspace(-9, 8, 341, dtype=torch.float64)
    g = torch.cat([(1.0 / (tc[:, None] + s[None, :])).mean(-1) for tc in t.split(32)])
    return t, g


def tie_information(data_info: Tensor, tie_weight: Tensor, size: int) -> Tensor:
    """The information ``(P, C)`` a pixel's smoothness ties add to each of its unknowns.

    A Gaussian Markov random field on the image: each unknown has data information ``d``
    (``data_info (P, C)``, the |r|² scale) and each of its 4 edges the weight ``λ``
    (``tie_weight (P, C)``: the pixel's mean edge weight). Its marginal variance (∝) is
    ``G = g(d / λ) / λ`` with ``g(t) = diag((t I + L)⁻¹)`` of the unit lattice Laplacian ``L``
    (exact on a periodic lattice of constant ``d`` and ``λ``; evaluated over ``L``'s
    eigenvalues on the ``size × size`` lattice), so the ties add ``1 / G − d``. Where the data
    dominate (``d ≫ λ``) that is ``4 λ``, the neighbours held; where the data are silent it
    falls to 0 (on the image's lattice logarithmically, a silent region floats as a whole):
    the neighbours are not known either. Returns ``data_info``'s dtype and device.
    """
    t_grid, g_grid = (x.to(data_info.device) for x in _lattice_green_table(int(size)))
    lam = tie_weight.double()
    t = (data_info.double() / lam.clamp(min=1e-300)).clamp(float(t_grid[0]), float(t_grid[-1]))
    pos = torch.log(t / t_grid[0]) / math.log(float(t_grid[-1] / t_grid[0])) * (t_grid.numel() - 1)
    i0 = pos.floor().long().clamp(0, t_grid.numel() - 2)
    f = pos - i0
    g = torch.exp(torch.lerp(torch.log(g_grid[i0]), torch.log(g_grid[i0 + 1]), f))  # log–log interpolation
    add = torch.where(lam > 0, (lam / g - data_info.double()).clamp(min=0.0), torch.zeros_like(lam))
    return add.to(data_info.dtype)


def fit_information(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
                    jtj: Tensor | None = None) -> Tensor:
    """Per-parameter marginal information ``(P, 7)`` of each pixel's fitted value: its data
    normal matrix ``JᵀJ`` plus what its smoothness ties (:func:`edge_weights`) add to each
    unknown (:func:`tie_information`), the other unknowns free.

    Why not the data's alone (:func:`marginal_information`): the fitted values the fill measures
    a material from were fitted with the ties, and a tie that pins one unknown (a constant
    specular, tied across the image) also pins those its data trade against it (roughness).
    The data-only information understates the fitted values' precision, and so the material's
    spread ``τ²`` (measured in docs/recovery_measurements.md, "The fill's measured spread").
    ``jtj (P, 7, 7)``: the data normal matrices at ``theta`` when the caller has them (else
    computed); the result has ``theta``'s dtype and device.
    """
    if jtj is None:
        jtj = gauss_newton(data, theta, metal, data.train_idx, cfg.model)[1]
    wx, wy = edge_weights(theta, metal, data.size, cfg)
    ties = tie_information(marginal_information(data, theta, metal, cfg.model, jtj),
                           laplacian_diag(wx, wy, data.size) / 4, data.size)
    return marginal_information(data, theta, metal, cfg.model, jtj + torch.diag_embed(ties))


#: Candidates (pixels × ``fill_candidates``) per block of :func:`nonlocal_fill`'s estimate: a
#: bound on its member tables' memory (each up to 1 MiB in float32). Each pixel's estimate is its own,
#: so the block changes no bit of the result; with the CLI's malloc settings 2¹⁶ takes the same
#: time (docs/recovery_measurements.md, "Variants measured and not kept").
FILL_BLOCK = 2**18


def _member_estimate(feat: Tensor, members: Tensor, rows: Tensor,
                     cand: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`material_estimate` of each pixel ``rows (n,)`` from its candidates ``cand (n, K)``
    (pixel indices; a pixel is not its own), weighted by ``exp(−|Δfeat|²)``: ``feat (F, P)`` the
    similarity features, ``members (4, P)`` the specular / roughness logits and their clamped
    variances, channel-major. Returns ``(μ, τ², var(μ))``, each ``(n, 2)``."""
    n, k = cand.shape
    flat = cand.flatten()
    diff = feat.index_select(1, flat).view(-1, n, k).sub_(feat[:, rows, None])
    # exp(−x) as 2^(−x / ln 2): exp2 takes half exp's time here
    sim = diff.square_().sum(0).mul_(-1 / math.log(2)).exp2_().mul_(cand != rows[:, None])  # (n, K)
    m = members.index_select(1, flat).view(4, n, k)
    mu, tau2, var_mu = _random_effects(m[:2], m[2:], sim, iters=2, span=LOGIT_SPAN)
    return mu.T, tau2.T, var_mu.T


def nonlocal_fill(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
                  info: Tensor | None = None, residual: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Targets and precisions ``(P, 7)`` of a unary prior that fills under-determined roughness and
    specular from same-material pixels the captured highlights do constrain: each pixel's
    Gaussian prior is what the pixels like it measured.

    Each pixel draws ``cfg.fill_candidates`` pixels of its class from the whole image
    (non-local: a glossy region no highlight reaches borrows from the same material where one
    does), weighted by their similarity ``exp(−|Δbase|²/fill_range² − Δtex²/fill_texture²)`` in
    base colour and in the local spread of the normal (``_normal_texture``). Each candidate's
    roughness / specular logit is a measurement of variance ``v = σ² / info`` (the marginal
    information of its fit's energy, data and smoothness ties, :func:`fit_information`, and the
    noise variance ``σ²``, the median pixel's cost per residual); :func:`material_estimate`
    gives the material's mean ``μ``, its spread ``τ²`` and the mean's variance, a member stuck
    in another basin set aside (an outlier component over :data:`LOGIT_SPAN`). The prior is
    ``N(μ, τ² + var(μ))`` — the predictive distribution of one more pixel of the material — so
    its precision on the fit's ``|r|²`` scale is ``σ² / (τ² + var(μ))``. The LM then fuses it
    with each pixel's data (precision ``info``): a pixel whose data pin it (``σ²/info ≪ τ²``)
    keeps its value, one the data leave free takes the material's, and where no similar pixel
    was measured the prior vanishes.
    A pixel is not its own candidate. Metals get no prior (precision 0, target their own
    value): a metal's silent direction is its F0–roughness valley (the GGX tail pins
    F0·α²), whose F0 end the non-local F0 tie (:func:`nonlocal_prior`) already pools from the
    same metal pixels; a second pooled prior on its roughness end would count those pixels
    twice, and where a metal's roughness varies across the image while its F0 does not, it
    pulls the pixel along the valley away from the F0 its metal neighbours share.
    ``theta (P, 7)``, ``metal (P, 1)``, ``info (P, 7)`` (:func:`fit_information`; None:
    computed), ``residual (P, M)``: the residuals at ``theta`` on ``data.train_idx`` when the
    caller has them (:func:`gauss_newton`'s first result; None: computed); results in
    ``theta``'s dtype, on its device.
    """
    size = data.size
    if info is None:
        info = fit_information(data, theta, metal, cfg)
    r = data.residual(theta, metal, data.train_idx, cfg.model) if residual is None else residual
    sigma2 = residual_variance(pixel_cost(r), r.shape[-1])
    var = sigma2 / info[:, 3:5].clamp(min=1e-30)  # (P, 2): specular, roughness logits
    # Channel-major tables: a block of candidates is one index_select per table, and the
    # estimate's sums run along contiguous members.
    members = torch.cat((theta[:, 3:5], _clamped_variance(var)), -1).T.contiguous()  # (4, P): logits, vars
    feat = torch.cat((torch.sigmoid(theta[:, 0:3]) / cfg.fill_range,
                      _normal_texture(theta, size) / cfg.fill_texture), -1).T.contiguous()  # (4, P)
    gen = torch.Generator().manual_seed(int(cfg.seed) + 7919)
    tgt = theta.clone()
    prec = torch.zeros_like(theta)
    pool = torch.nonzero(metal[:, 0] <= 0.5).flatten()  # dielectrics only (see above)
    if pool.numel() < 2 or sigma2 <= 0:
        return torch.nan_to_num(tgt), prec
    k = min(cfg.fill_candidates, pool.numel())
    draw = max(1, 2**20 // k)  # pixels per draw of candidates (the random stream's blocks)
    block = max(1, FILL_BLOCK // k)  # ... per estimate
    for s0 in range(0, pool.numel(), draw):
        rows = pool[s0:s0 + draw]
        draws = torch.randint(0, pool.numel(), (rows.numel() * k,), generator=gen)  # on the CPU
        drawn = pool.index_select(0, draws.to(pool.device))
        for b0 in range(0, rows.numel(), block):
            rr = rows[b0:b0 + block]
            cand = drawn[b0 * k:(b0 + rr.numel()) * k]  # (n K,)
            mu, tau2, var_mu = _member_estimate(feat, members, rr, cand.view(-1, k))
            ok = torch.isfinite(mu) & (var_mu < VAR_MAX)
            tgt[rr, 3:5] = torch.where(ok, mu, theta[rr, 3:5])
            prec[rr, 3:5] = torch.where(ok, sigma2 / (tau2 + var_mu), 0.0)
    return torch.nan_to_num(tgt), torch.nan_to_num(prec, posinf=0.0)


#: Most Gauss–Newton rounds of :func:`fuse_fill` for the pixels that walk the valley, and the
#: most halvings of a round's step: a bound on the cost; on glossy captures the silent pixels
#: settle within them (docs/recovery_measurements.md, "The fill's walk along the valley").
FUSE_ROUNDS, FUSE_HALVINGS = 16, 4


def fuse_fill(data: LevelData, theta: Tensor, metal: Tensor, unary: tuple[Tensor, Tensor], model: str,
              rounds: int = 2, gn: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """Each pixel moved to the mode of its data and a unary prior (the fill), all its unknowns
    following: Gauss–Newton rounds on ``|r|² + Σ precision (θ − target)²``.

    Where the data are silent the steps take roughness / specular to the prior's target and
    the other unknowns to their conditional optimum there (along the specular–roughness valley,
    which the damped LM steps of the last stage descend only slowly); where the data pin a
    value they keep it. A pixel takes a step only where it lowers that energy.

    Every pixel takes ``rounds`` full steps. The valley is curved: from a silent dielectric's
    dim, rough extreme a full step overshoots and raises the energy, so a dielectric fitted at
    the noise level (data cost at most :data:`~torchbrdf.recovery.search.BADLY_FITTED` × the
    median pixel's) instead walks: each round halves its step (at most :data:`FUSE_HALVINGS`
    times) until the energy falls, and it takes further rounds (at most :data:`FUSE_ROUNDS`)
    while its last one lowered the energy by at least the noise variance ``σ²`` (the median
    pixel's data cost per residual; a smaller gain is below what the data resolve). A badly
    fitted pixel is not silent, its data reject the model there: a walk toward the prior
    would move its normal instead (a glint on a steep bump).
    ``theta (P, 7)``, ``metal (P, 1)``, ``unary = (target, precision)`` ``(P, 7)`` each;
    ``gn``: :func:`gauss_newton`'s result at ``theta`` on ``data.train_idx`` when the caller has
    it. Returns the new ``theta (P, 7)`` (same dtype and device).
    """
    if rounds < 0:
        raise ValueError(f"fuse_fill: rounds must be >= 0, got {rounds}")
    tgt, prec = unary
    idx = data.train_idx
    x = theta.clone()
    rows = torch.arange(theta.shape[0], device=theta.device)
    walk = torch.zeros(0, dtype=torch.bool)
    sigma2 = 0.0
    for k in range(max(rounds, FUSE_ROUNDS)):
        sub = data if k == 0 else data.subset(rows)
        xr, mr, un = x[rows], metal[rows], (tgt[rows], prec[rows])
        r0, jtj, jtr = gn if (k == 0 and gn is not None) else gauss_newton(sub, xr, mr, idx, model)
        e_data = pixel_cost(r0)
        if k == 0:
            sigma2 = residual_variance(e_data, r0.shape[-1])
            finite = torch.isfinite(e_data[:, 0])
            noise = float(e_data[finite, 0].median()) if bool(finite.any()) else 0.0
            walk = (metal[:, 0] < 0.5) & (e_data[:, 0] <= BADLY_FITTED * noise)
        step = newton_step(jtj + torch.diag_embed(un[1]), jtr + un[1] * (xr - un[0]))
        e0 = e_data + unary_cost(xr, un)
        # The full step on every pixel; each halving only on the walkers it has not yet lowered
        # (the others' values are final: rendering them again changed nothing).
        cand = xr + step
        e1 = pixel_cost(sub.residual(cand, mr, idx, model)) + unary_cost(cand, un)
        ok = e1 < e0
        best, e_best = torch.where(ok, cand, xr), torch.where(ok, e1, e0)
        at = (~ok[:, 0] & walk[rows]).nonzero()[:, 0]  # (of this round's rows)
        t = 1.0
        for _ in range(FUSE_HALVINGS):
            if at.numel() == 0:
                break
            t *= 0.5
            cand = xr[at] + t * step[at]
            e1 = (pixel_cost(sub.residual(cand, mr[at], idx, model, rows=at))
                  + unary_cost(cand, (un[0][at], un[1][at])))
            ok = e1 < e0[at]
            best[at] = torch.where(ok, cand, best[at])
            e_best[at] = torch.where(ok, e1, e_best[at])
            at = at[~ok[:, 0]]
        x[rows] = best
        # the next round: every pixel while its full steps last, then those walking on
        keep = ((e0 - e_best)[:, 0] >= sigma2) & walk[rows] if k + 1 >= rounds else torch.ones_like(walk[rows])
        rows = rows[keep]
        if rows.numel() == 0:
            break
    return x
