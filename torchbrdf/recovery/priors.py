"""Non-local priors: a metal's F0 from the metal around it, and the non-local fill of
under-determined roughness / specular from the same material elsewhere.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.lm import marginal_information, newton_step
from torchbrdf.recovery.map_ops import blur, kmeans
from torchbrdf.recovery.params import R_MAX, R_MIN


def nonlocal_prior(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
                   jtj: Tensor | None = None, cost: Tensor | None = None, jtr: Tensor | None = None,
                   rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Confidence-weighted non-local estimate of a metal's base colour (and, optionally, roughness).

    A metal's base colour (F0, logit) gets the average of the metal pixels within a large
    Gaussian window (``cfg.nonlocal_sigma`` × size), weighted by their marginal information;
    with ``cfg.prior_nonlocal > 0`` each pixel's roughness also gets the information-weighted
    average of same-class pixels of similar base colour (bilateral grid over k-means colour
    clusters) — off by default: rough pixels always carry little roughness information, so
    the average is pulled toward nearby glossy pixels (rough grout came out too smooth).
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
            # of its neighbours' F0 (the average came out dark). A non-finite cost weighs 0.
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


def nonlocal_fill(data: LevelData, theta: Tensor, metal: Tensor, cfg: Settings,
                  info: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Targets and precisions ``(P, 7)`` of a unary prior that fills under-determined roughness and
    specular from same-material pixels the captured highlights do constrain.

    Each pixel draws ``cfg.fill_candidates`` pixels of its class from the whole image
    (non-local: a glossy region no highlight reaches borrows from the same material where one
    does) and averages their roughness / specular logits with weights
    ``similarity × reliability``: similarity ``exp(−|Δbase|²/σ_b² − Δtex²/σ_t²)`` in base
    colour and in the local spread of the normal (``_normal_texture``), reliability the
    candidate's own confidence ``1 / (1 + var / tol²)`` from its marginal information
    ``1 / diag((JᵀJ)⁻¹)`` (its posterior variance in map units; ``tol`` = ``cfg.fill_sigma``).
    The prior's precision (logit units) is ``σ² / fill_sigma² · (dvalue/dlogit)²`` × the
    mean reliability of the similar candidates — a value ``fill_sigma`` wide around the
    material's measured one, as strong as the data at a pixel of confidence ½, and nothing
    where no similar pixel was measured. The LM then fuses it with each pixel's data: the
    well-measured pixels keep their own values, the under-determined ones take the material's.
    """
    size = data.size
    if info is None:
        info = marginal_information(data, theta, metal, cfg.model)
    r = data.residual(theta, metal, data.train_idx, cfg.model)
    sigma2 = float(torch.nan_to_num((r * r).mean(-1), nan=0.0).median())
    sr, ss = torch.sigmoid(theta[:, 4:5]), torch.sigmoid(theta[:, 3:4])
    d_r = (R_MAX - R_MIN) * sr * (1 - sr)  # d roughness / d logit
    d_s = ss * (1 - ss)
    tol = cfg.fill_sigma
    rel_r = 1.0 / (1.0 + sigma2 * d_r**2 / (info[:, 4:5].clamp(min=1e-12) * tol**2))
    rel_s = 1.0 / (1.0 + sigma2 * d_s**2 / (info[:, 3:4].clamp(min=1e-12) * tol**2))
    feat = torch.cat((torch.sigmoid(theta[:, 0:3]) / cfg.fill_range,
                      _normal_texture(theta, size) / cfg.fill_texture), -1)  # (P, 4)
    gen = torch.Generator().manual_seed(int(cfg.seed) + 7919)
    tgt = theta.clone()
    prec = torch.zeros_like(theta)
    ism = metal[:, 0] > 0.5
    for cls in (~ism, ism):
        pool = torch.nonzero(cls).flatten()
        if pool.numel() < 2:
            continue
        k = min(cfg.fill_candidates, pool.numel())
        rows = pool
        num = torch.zeros(rows.numel(), 2, dtype=theta.dtype, device=theta.device)
        den = torch.zeros_like(num)
        sim_sum = torch.zeros(rows.numel(), 1, dtype=theta.dtype, device=theta.device)
        chunk = max(1, 2**21 // k)
        for s0 in range(0, rows.numel(), chunk):
            rr = rows[s0:s0 + chunk]
            cand = pool[torch.randint(0, pool.numel(), (rr.numel(), k), generator=gen)]  # (n, K)
            sim = torch.exp(-((feat[cand] - feat[rr][:, None]) ** 2).sum(-1))  # (n, K)
            w = sim[..., None] * torch.stack((rel_s[cand, 0], rel_r[cand, 0]), -1)  # (n, K, 2)
            num[s0:s0 + rr.numel()] = (w * theta[cand][..., 3:5]).sum(1)
            den[s0:s0 + rr.numel()] = w.sum(1)
            sim_sum[s0:s0 + rr.numel()] = sim.sum(1, keepdim=True)
        ok = den > 1e-9
        tgt[rows, 3:5] = torch.where(ok, num / den.clamp(min=1e-12), theta[rows, 3:5])
        support = (den / sim_sum.clamp(min=1e-12)) * (sim_sum >= cfg.fill_min_similar)  # mean reliability
        base_prec = sigma2 / tol**2 * torch.cat((d_s[rows], d_r[rows]), -1) ** 2
        prec[rows, 3:5] = cfg.fill_weight * base_prec * support * ok
    if bool(ism.any()):
        prec[ism, 3] = 0.0  # a metal's specular is invisible and already tied to its neighbours
    return torch.nan_to_num(tgt), torch.nan_to_num(prec)
