"""The recovery's smoothness prior: a quadratic energy on 4-neighbour edges of a square map.

Maps are flat ``(P, C)`` tensors of a ``size × size`` image (row-major, ``P = size²``); edge
weights are ``wx (size, size-1, C)`` between horizontal neighbours and ``wy (size-1, size, C)``
between vertical ones. The energy is ``½ Σ_edges w (θ_p − θ_q)²``; its gradient is the
weighted graph Laplacian ``L θ`` and its Hessian ``L``, which couples pixels — hence
:func:`pcg`, which solves a per-pixel block system plus ``L`` at once.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor


def edge_weights(theta: Tensor, metal: Tensor, size: int, cfg: Any) -> tuple[Tensor, Tensor]:
    """Smoothness-prior weights ``(S, S-1, 7)`` (horizontal edges) and ``(S-1, S, 7)`` (vertical).

    ``theta (P, 7)`` are the recovery's unknowns (base-colour logits first), ``metal (P, 1)``
    the class per pixel, ``cfg`` a ``RecoveryConfig`` (``prior_*`` weights, ``prior_sigma``).

    The prior energy is ``½ Σ_edges w_e,c (θ_p,c − θ_q,c)²`` over 4-neighbour edges ``(p, q)``:

    * roughness and specular: ``prior_* · exp(−|Δbase|²/σ²)`` between pixels of the same
      class (base-colour-guided, so edges between materials are cut);
    * a metal's base colour (its F0, seen only through the specular lobe, like roughness):
      ``prior_metal_base`` between two metal pixels, × the same base-colour guide with
      ``metal_base_guided`` (else class-only). Unguided, a rust island the two-hypothesis
      choice called metal (a dark, red F0 that fits its data) pulled the F0 of the bright
      metal around it down through the chain of ties — the F0 along the GGX tail's valley
      (F0·α² nearly constant) is weakly held by each pixel's own data;
    * a metal's specular does not affect the image at all: weight 1 between metal pixels,
      which keeps it defined.
    """
    c = theta.shape[1]
    img = theta.reshape(size, size, c)
    base = torch.sigmoid(img[..., 0:3])
    m = metal.reshape(size, size, 1)

    def weights(b0, b1, m0, m1):
        same = (m0 == m1).to(theta.dtype)
        both_metal = m0 * m1
        a = torch.exp(-((b1 - b0) ** 2).sum(-1, keepdim=True) / cfg.prior_sigma**2) * same
        w = torch.zeros(*a.shape[:-1], c, dtype=theta.dtype, device=theta.device)
        w[..., 0:3] = cfg.prior_metal_base * both_metal * (a if cfg.metal_base_guided else 1.0)
        w[..., 3:4] = cfg.prior_specular * a + 1.0 * both_metal
        w[..., 4:5] = cfg.prior_roughness * a
        return w

    wx = weights(base[:, :-1], base[:, 1:], m[:, :-1], m[:, 1:])
    wy = weights(base[:-1], base[1:], m[:-1], m[1:])
    return wx, wy


def laplacian(x: Tensor, wx: Tensor, wy: Tensor, size: int) -> Tensor:
    """Weighted graph Laplacian ``L x`` ``(P, C)``: ``(L x)_p = Σ_q w_pq (x_p − x_q)``."""
    img = x.reshape(size, size, -1)
    return _laplacian_image(img, wx, wy, 0, 1).reshape(x.shape)


def _laplacian_image(img: Tensor, wx: Tensor, wy: Tensor, h: int, w: int) -> Tensor:
    """``L x`` of an image whose rows and columns are dims ``h`` and ``w`` of ``img``.

    ``wx``/``wy`` have ``img``'s layout with one column/row fewer: channel-last
    ``(S, S-1, C)``/``(S-1, S, C)`` for ``(S, S, C)`` images (``h, w = 0, 1``), or
    channel-first ``(C, S, S-1)``/``(C, S-1, S)`` for ``(C, S, S)`` (``h, w = 1, 2``, what
    :func:`pcg` iterates on).
    """
    s = img.shape[w]
    out = torch.zeros_like(img)
    fx = wx * (img.narrow(w, 0, s - 1) - img.narrow(w, 1, s - 1))
    out.narrow(w, 0, s - 1).add_(fx)
    out.narrow(w, 1, s - 1).sub_(fx)
    fy = wy * (img.narrow(h, 0, s - 1) - img.narrow(h, 1, s - 1))
    out.narrow(h, 0, s - 1).add_(fy)
    out.narrow(h, 1, s - 1).sub_(fy)
    return out


def laplacian_diag(wx: Tensor, wy: Tensor, size: int) -> Tensor:
    """Diagonal of the weighted Laplacian, ``(P, C)``."""
    d = torch.zeros(size, size, wx.shape[-1], dtype=wx.dtype, device=wx.device)
    d[:, :-1] += wx
    d[:, 1:] += wx
    d[:-1] += wy
    d[1:] += wy
    return d.reshape(-1, wx.shape[-1])


def prior_energy(theta: Tensor, wx: Tensor, wy: Tensor, size: int) -> Tensor:
    """Per-pixel share ``(P, 1)`` of the prior energy, on the scale of the ``|r|²`` data cost.

    The objective is ``½|r|² + ½ Σ_edges w Δθ²``; twice it, split half of each edge to each
    end, gives ``|r|² + ½ Σ_q w_pq Δθ²`` per pixel (summing to the total).
    """
    img = theta.reshape(size, size, -1)
    ex = (wx * (img[:, :-1] - img[:, 1:]) ** 2).sum(-1, keepdim=True)
    ey = (wy * (img[:-1] - img[1:]) ** 2).sum(-1, keepdim=True)
    e = torch.zeros(size, size, 1, dtype=theta.dtype, device=theta.device)
    e[:, :-1] += ex
    e[:, 1:] += ex
    e[:-1] += ey
    e[1:] += ey
    return 0.5 * e.reshape(-1, 1)


def pcg(hess: Tensor, wx: Tensor, wy: Tensor, rhs: Tensor, size: int, iters: int) -> Tensor:
    """Solve ``(blockdiag(hess) + L) x = rhs`` by preconditioned conjugate gradients.

    ``hess (P, C, C)`` is each pixel's damped Gauss–Newton matrix, ``L`` the prior's weighted
    Laplacian (pixels couple only through it), ``rhs (P, C)``; returns ``x (P, C)``. Unlike a
    Jacobi prior (the neighbours frozen within an iteration), CG moves a whole region
    together: a uniform shift costs no prior energy, so a weakly observed region is not held
    at its start value.

    Only the channels the prior joins (``a``: a range with non-zero edge weights somewhere —
    specular and roughness, and a metal's base colour) couple pixels. The others (``u``: the
    normal's slopes, a dielectric's base colour) are eliminated per pixel first, exactly:
    with ``hess = [[A, B], [Bᵀ, D]]`` over ``(a, u)``, CG runs on the Schur complement
    ``(A − B D⁻¹ Bᵀ) + L_a`` (2 of 7 channels on a dielectric map, 5 with metal), and
    ``x_u = D⁻¹ (rhs_u − Bᵀ x_a)`` follows. That is the same solution with cheaper and
    better-conditioned iterations. The preconditioner is the exact inverse of the complement's
    block diagonal (+ the Laplacian's diagonal); the per-pixel algebra runs in float64.

    The iteration runs channel-first (vectors ``(a, P)``, matrices ``(a, a, P)``): a block
    product is then lane-dense multiply-adds over the pixels, much faster on CPU than a
    batched ``einsum`` over ``P`` tiny matrices.
    """
    c = rhs.shape[1]
    joined = ((wx != 0).flatten(0, 1).any(0) | (wy != 0).flatten(0, 1).any(0)).nonzero()[:, 0].tolist()
    if not joined:  # no coupling: each pixel's block alone
        return torch.linalg.solve(hess, rhs[..., None])[..., 0]
    a = list(range(joined[0], joined[-1] + 1))
    u = [k for k in range(c) if k < a[0] or k > a[-1]]
    n, nu, lo = len(a), len(u), a[0]
    # One gather puts the eliminated channels first (blocks are then views); the per-pixel
    # algebra runs in float64: in float32 the elimination's cancellation stalls CG at 1e-2.
    perm = torch.tensor(u + a, device=hess.device)
    flat = (perm[:, None] * c + perm[None, :]).reshape(-1)  # one gather of the 49 entries: 3x faster
    hp = hess.reshape(-1, c * c).index_select(1, flat).view(-1, c, c).double()
    bp = rhs.index_select(1, perm).double()
    s, b = hp[:, nu:, nu:], bp[:, nu:]
    if u:
        d_inv = torch.linalg.inv(hp[:, :nu, :nu])
        bd = hp[:, nu:, :nu] @ d_inv  # B D⁻¹  (P, a, u)
        s = s - bd @ hp[:, :nu, nu:]
        b = b - (bd @ bp[:, :nu, None])[..., 0]
    wxa, wya = wx.narrow(-1, lo, n), wy.narrow(-1, lo, n)
    # The Laplacian's diagonal joins the blocks: the operator is then one block product plus
    # the four neighbour terms, and the preconditioner is the exact inverse of its blocks.
    s = s + torch.diag_embed(laplacian_diag(wxa, wya, size).double())
    pre = torch.linalg.inv(s)
    dt = rhs.dtype
    s_cf, pre = s.to(dt).permute(1, 2, 0).contiguous(), pre.to(dt).permute(1, 2, 0).contiguous()
    wxc, wyc = wxa.permute(2, 0, 1).contiguous(), wya.permute(2, 0, 1).contiguous()

    def block(m, v):  # per-pixel (n, n) @ (n,) on (n, n, P) and (n, P), without an (n, n, P) temporary
        out = m[:, 0] * v[0]
        for j in range(1, n):
            out.addcmul_(m[:, j], v[j])
        return out

    def apply(v):  # (blocks + diag L) v − Σ_q w_pq v_q: every product accumulates in place
        out = block(s_cf, v)
        o, w = out.view(n, size, size), v.view(n, size, size)
        o[:, :, :-1].addcmul_(wxc, w[:, :, 1:], value=-1.0)
        o[:, :, 1:].addcmul_(wxc, w[:, :, :-1], value=-1.0)
        o[:, :-1].addcmul_(wyc, w[:, 1:], value=-1.0)
        o[:, 1:].addcmul_(wyc, w[:, :-1], value=-1.0)
        return out

    def dot(a, b):
        return torch.vdot(a.view(-1), b.view(-1))

    rb = b.to(dt).T.contiguous()
    x = block(pre, rb)
    r = rb - apply(x)
    d = block(pre, r)
    rz = dot(r, d)
    for _ in range(iters):
        ad = apply(d)
        dad = dot(d, ad)
        dad_host = float(dad)  # one host sync per iteration (the stopping test needs it)
        if not math.isfinite(dad_host) or dad_host <= 0:
            break
        alpha = rz / dad  # 0-d tensors: the updates queue without another sync
        x.addcmul_(d, alpha)
        r.addcmul_(ad, alpha, value=-1.0)
        z = block(pre, r)
        rz_new = dot(r, z)
        d = z.addcmul_(d, torch.where(rz != 0, rz_new / rz, torch.zeros_like(rz)))
        rz = rz_new
    out = torch.empty_like(rhs)
    xa = x.T.double()
    out[:, lo:lo + n] = xa.to(dt)
    if u:
        xu = (d_inv @ (bp[:, :nu] - (hp[:, :nu, nu:] @ xa[..., None])[..., 0])[..., None])[..., 0]
        out[:, u] = xu.to(dt)
    return out


def local_prior(cand: Tensor, theta: Tensor, wx: Tensor, wy: Tensor, size: int,
                rows: Tensor | None = None) -> Tensor:
    """``Σ_q w_pq (cand_p − θ_q)²`` over each pixel's 4 neighbours ``q`` ``(*, N, 1)``: the change
    of (twice) the prior energy, up to a constant, if pixel ``p`` alone took ``cand_p``.

    ``cand (*, N, C)``: values for the pixels ``rows (N,)`` (int64; None: all ``P`` pixels in
    order), any number of candidate sets at once along the leading dims; ``theta (P, C)`` the
    map the neighbours keep, ``wx``, ``wy`` its edge weights. The terms are added in one order
    (right, left, lower, upper neighbour) whatever the batch or the rows, so a candidate's
    value does not depend on which others share the call. ``cand``'s dtype and device.
    """
    c = theta.shape[1]
    if size < 2:  # a single pixel has no neighbours
        return cand.new_zeros(*cand.shape[:-1], 1)
    if rows is None:  # every pixel: the edges are slices of the image (no gather)
        a, t = cand.reshape(*cand.shape[:-2], size, size, c), theta.reshape(size, size, c)
        e = torch.zeros(*a.shape[:-1], 1, dtype=cand.dtype, device=cand.device)
        e[..., :, :-1, :] += (wx * (a[..., :, :-1, :] - t[:, 1:]) ** 2).sum(-1, keepdim=True)
        e[..., :, 1:, :] += (wx * (a[..., :, 1:, :] - t[:, :-1]) ** 2).sum(-1, keepdim=True)
        e[..., :-1, :, :] += (wy * (a[..., :-1, :, :] - t[1:]) ** 2).sum(-1, keepdim=True)
        e[..., 1:, :, :] += (wy * (a[..., 1:, :, :] - t[:-1]) ** 2).sum(-1, keepdim=True)
        return e.reshape(*cand.shape[:-1], 1)
    i, j = rows // size, rows % size
    last = size - 1
    # (neighbour, its edge's row in wx or wy, whether it exists): a missing neighbour's indices
    # are clamped into range and its term dropped (not weighted by 0: a non-finite value stays out).
    edges = ((wx, rows + 1, i * last + j, j < last), (wx, rows - 1, i * last + j - 1, j > 0),
             (wy, rows + size, i * size + j, i < last), (wy, rows - size, (i - 1) * size + j, i > 0))
    terms = []
    for w, q, w_row, has in edges:
        wq = w.reshape(-1, c).index_select(0, w_row.clamp(0, size * last - 1))
        term = (wq * (cand - theta.index_select(0, q.clamp(0, size * size - 1))) ** 2).sum(-1, keepdim=True)
        terms.append(torch.where(has[:, None], term, torch.zeros_like(term)))
    return terms[0] + terms[1] + terms[2] + terms[3]
