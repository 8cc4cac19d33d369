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

from torchbrdf.recovery.pixel_systems import (c_kernels, ldl_factor, ldl_solve, lower_solve, to_lanes,
                                              upper_solve)


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
    channel-first ``(C, S, S-1)``/``(C, S-1, S)`` for ``(C, S, S)`` (``h, w = 1, 2``).
    """
    s = img.shape[w]
    out = torch.zeros_like(img)
    fx = (img.narrow(w, 0, s - 1) - img.narrow(w, 1, s - 1)).mul_(wx)  # (weighted in place)
    out.narrow(w, 0, s - 1).add_(fx)
    out.narrow(w, 1, s - 1).sub_(fx)
    fy = (img.narrow(h, 0, s - 1) - img.narrow(h, 1, s - 1)).mul_(wy)
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


def joined_channels(wx: Tensor, wy: Tensor) -> slice:
    """The channels ``lo:hi`` outside which every edge weight of ``wx``, ``wy`` is 0 (empty: all are).

    Only these channels carry prior terms (a dielectric map's specular and roughness; with
    metals, their base colour too; never the normal's slopes). One host read.
    """
    c = wx.shape[-1]
    # (any over rows, then columns: twice as fast as one reduction of the flattened (S(S-1), C))
    joined = ((wx != 0).any(0).any(0) | (wy != 0).any(0).any(0)).nonzero()[:, 0].tolist()
    return slice(joined[0], joined[-1] + 1) if joined else slice(c, c)


def prior_energy(theta: Tensor, wx: Tensor, wy: Tensor, size: int, channels: slice | None = None) -> Tensor:
    """Per-pixel share ``(P, 1)`` of the prior energy, on the scale of the ``|r|²`` data cost.

    The objective is ``½|r|² + ½ Σ_edges w Δθ²``; twice it, split half of each edge to each
    end, gives ``|r|² + ½ Σ_q w_pq Δθ²`` per pixel (summing to the total). ``channels``:
    :func:`joined_channels` of ``wx``, ``wy`` when the caller has it (else found here).
    """
    ch = joined_channels(wx, wy) if channels is None else channels
    img = theta.reshape(size, size, -1)[..., ch]
    wx, wy = wx[..., ch], wy[..., ch]
    ex = _edge_term(img[:, :-1], img[:, 1:], wx)
    ey = _edge_term(img[:-1], img[1:], wy)
    e = torch.zeros(size, size, 1, dtype=theta.dtype, device=theta.device)
    e[:, :-1] += ex
    e[:, 1:] += ex
    e[:-1] += ey
    e[1:] += ey
    return 0.5 * e.reshape(-1, 1)


def pcg(hess: Tensor, wx: Tensor, wy: Tensor, rhs: Tensor, size: int, iters: int,
        diag: Tensor | None = None) -> Tensor:
    """Solve ``(blockdiag(hess + diag) + L) x = rhs`` by preconditioned conjugate gradients.

    ``hess (P, C, C)`` is each pixel's damped Gauss–Newton matrix (symmetric positive definite;
    ``diag (P, C)``, when given, is added to its diagonal: the damping, without building a
    second ``(P, C, C)``), ``L`` the prior's weighted Laplacian (pixels couple only through it),
    ``rhs (P, C)``; returns ``x (P, C)`` in ``rhs``'s dtype, on its device. Unlike a Jacobi prior
    (the neighbours frozen within an iteration), CG moves a whole region together: a uniform
    shift costs no prior energy, so a weakly observed region is not held at its start value.

    Only the channels the prior joins (``a``: a range with non-zero edge weights somewhere —
    specular and roughness, and a metal's base colour) couple pixels. The others (``u``: the
    normal's slopes, a dielectric's base colour) are eliminated per pixel first, exactly:
    with ``hess = [[A, B], [Bᵀ, D]]`` over ``(a, u)``, CG runs on the Schur complement
    ``S = (A − B D⁻¹ Bᵀ) + L_a`` (2 of 7 channels on a dielectric map, 5 with metal), and
    ``x_u = D⁻¹ (rhs_u − Bᵀ x_a)`` follows. That is the same solution with cheaper and
    better-conditioned iterations. The preconditioner is the exact inverse of the complement's
    block diagonal (+ the Laplacian's diagonal), applied as its ``LDLᵀ`` factors.

    All the per-pixel algebra runs lane-wise (:mod:`~torchbrdf.recovery.pixel_systems`:
    matrices ``(n, n, P)``, vectors ``(n, P)``), each step one multiply-add over all pixels;
    the elimination and the factorisations in float64 (in float32 the elimination's
    cancellation stalls CG at 1e-2), the iterations in ``rhs``'s dtype. The iterations never
    wait for the host (one check of the start's finiteness precedes them): a breakdown
    (``dᵀ A d`` not positive and finite) freezes ``x`` where it is, as stopping would.
    """
    c = rhs.shape[1]
    ch = joined_channels(wx, wy)
    lo, hi = ch.start, ch.stop
    u = [k for k in range(c) if k < lo or k >= hi]
    nu, order = len(u), u + list(range(lo, hi))
    out = torch.empty_like(rhs)
    if lo == hi:  # no coupling: each pixel's block alone
        h = to_lanes(hess, order=order)
        if diag is not None:
            h.diagonal(dim1=0, dim2=1).add_(diag[:, order])  # (a (P, C) view)
        low, d = ldl_factor(h)
        rhs64 = h.new_empty(c, rhs.shape[0]).copy_(rhs[:, order].T)  # (contiguous: the C solves take it)
        out[:, order] = ldl_solve(low, 1.0 / d, rhs64).T.to(rhs.dtype)
        return out
    wxa, wya = wx[..., lo:hi], wy[..., lo:hi]
    # The Laplacian's diagonal joins the blocks: the operator is then the blocks minus the
    # neighbour terms, and the preconditioner the blocks' exact inverse, factored once here.
    lapd = laplacian_diag(wxa, wya, size)
    if c_kernels(hess, diag, rhs, lapd, size=c):
        from torchbrdf.kernels.lane_ops import MAX_SCHUR, lane_schur

        fast = c <= MAX_SCHUR
    else:
        fast = False
    elim = lane_schur if fast else _eliminate
    low_u, d_u, bt, rhs_u, low, d_isqrt, b = elim(hess, diag, rhs, order, nu, lapd)
    dt = rhs.dtype
    x = _cg_iterations(low, d_isqrt, wxa.permute(2, 0, 1).contiguous(), wya.permute(2, 0, 1).contiguous(), b,
                       size, iters)
    out[:, lo:hi] = x.T
    if u:  # x_u = D⁻¹ (rhs_u − Bᵀ x_a)
        t = rhs_u - (bt * x.double()).sum(1)  # (nu, P)
        out[:, u] = ldl_solve(low_u, 1.0 / d_u, t).T.to(dt)
    return out


def _eliminate(hess: Tensor, diag: Tensor | None, rhs: Tensor, order: list[int], nu: int, lapd: Tensor
               ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`pcg`'s per-pixel elimination of the first ``nu`` channels of ``order``, in PyTorch
    operations: :func:`torchbrdf.kernels.lane_ops.lane_schur` (arguments, results) is its one pass."""
    c = rhs.shape[1]
    # Float64 lanes (C, C, P) in the order (u, a): D, Bᵀ, A are views; a fresh copy, updated in place.
    h = to_lanes(hess, order=order)
    rhs64 = h.new_empty(c, rhs.shape[0]).copy_(rhs[:, order].T)  # (C, P)
    if diag is not None:
        h.diagonal(dim1=0, dim2=1).add_(diag[:, order])  # (a (P, C) view)
    s, b = h[nu:, nu:], rhs64[nu:]
    low_u = d_u = h[:0, :0]
    if nu:
        low_u, d_u = ldl_factor(h[:nu, :nu])
        # S = A − B D⁻¹ Bᵀ = A − Σ_k v_k v_kᵀ with v = D^-½ L_u⁻¹ Bᵀ: symmetric as computed
        v = lower_solve(low_u, h[:nu, nu:].clone())  # (nu, n, P)
        y = lower_solve(low_u, rhs64[:nu].clone())  # (nu, P)
        scale = torch.rsqrt(d_u)
        v.mul_(scale[:, None])
        for k in range(nu):
            s.addcmul_(v[k][:, None], v[k][None, :], value=-1.0)
            b.addcmul_(v[k], y[k] * scale[k], value=-1.0)
    s.diagonal(dim1=0, dim2=1).add_(lapd)  # (a (P, n) view)
    low, d = ldl_factor(s)
    dt = rhs.dtype
    return low_u, d_u, h[:nu, nu:], rhs64[:nu], low.to(dt), torch.rsqrt(d).to(dt), b.to(dt)


def reads_host(device: torch.device) -> bool:
    """Whether :func:`pcg` reads its step lengths on the host on ``device`` (CPU: free there)
    rather than masking them on the device (elsewhere: no synchronisation per iteration)."""
    return device.type == "cpu"


def _cg_iterations(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, b: Tensor, size: int,
                   iters: int) -> Tensor:
    """``iters`` CG iterations on ``(M − N) x = b``, preconditioned by ``M``, from ``x₀ = M⁻¹ b``.

    Lane-wise: ``M = L D Lᵀ`` the blocks with the Laplacian's diagonal, given by ``low (n, n, P)``
    (:func:`~torchbrdf.recovery.pixel_systems.ldl_factor`) and ``d_isqrt = D^-½ (n, P)``;
    ``N v = Σ_q w_pq v_q`` the neighbour terms, edge weights ``wx (n, S, S-1)``, ``wy (n, S-1, S)``;
    ``b (n, P)``; all in one dtype. Returns ``x (n, P)``.

    CG runs on the split-preconditioned system ``(I − K) y = G⁻¹ b`` with ``K = G⁻¹ N G⁻ᵀ``,
    ``G = L D^½``, ``x = G⁻ᵀ y``: the same iterates as CG preconditioned by ``M⁻¹`` in exact
    arithmetic, but an iteration needs the two triangular solves and no block product. On the
    CPU the whole loop is one C call (:func:`torchbrdf.kernels.lane_ops.lane_cg`: two passes
    over the vectors an iteration, instead of a dozen small operations and a host read; its dot
    products summed in float64, so its iterates differ from the PyTorch loop below by rounding).
    """
    n = low.shape[0]
    in_c = c_kernels(low, d_isqrt, wx, wy, b, size=n)
    if in_c:
        from torchbrdf.kernels.lane_ops import coupling_operator, lane_cg

        op = coupling_operator(low, d_isqrt, wx, wy)

        def coupling(v):  # K v = G⁻¹ N G⁻ᵀ v
            return op(v, False)
    else:
        coupling, apply = _torch_coupling(low, d_isqrt, wx, wy, size)

    def dot(p, q):
        return torch.vdot(p.view(-1), q.view(-1))

    y = lower_solve(low, b.clone()).mul_(d_isqrt)  # y₀ = G⁻¹ b, i.e. x₀ = M⁻¹ b
    r = coupling(y)  # G⁻¹ b − (I − K) y₀
    # One host synchronisation, before the loop: non-finite data stop CG at its start (every
    # pixel's block solve alone), as a non-finite dᵀAd at the first iteration would.
    if in_c and iters > 0 and bool(torch.isfinite(r).all()):
        y = lane_cg(low, d_isqrt, wx, wy, y, r, iters)
    elif iters > 0 and bool(torch.isfinite(r).all()):
        # On CPU a host read is free and cheaper than the masks' 0-d operations (a small map's
        # iterations are mostly fixed costs); elsewhere it would stall the queue. Both take
        # the same steps: stopping at a breakdown leaves x as freezing it does.
        on_host = reads_host(r.device)
        d = r.clone()
        rr = dot(r, r)
        zero = torch.zeros_like(rr)
        going = torch.ones_like(rr, dtype=torch.bool)  # false from the first breakdown on
        for _ in range(iters):
            ad = apply(d)
            dad = dot(d, ad)
            if on_host:
                if not (math.isfinite(float(dad)) and float(dad) > 0):
                    break
                alpha = rr / dad
            else:
                going = going & torch.isfinite(dad) & (dad > 0)
                alpha = torch.where(going, rr / dad, zero)  # 0-d tensors: the updates queue, no sync
            y.addcmul_(d, alpha)
            r.addcmul_(ad, alpha, value=-1.0)
            rr_new = dot(r, r)
            if on_host:
                beta = rr_new / rr if float(rr) != 0 else zero
            else:
                beta = torch.where(going & (rr != 0), rr_new / rr, zero)
            d = torch.addcmul(r, d, beta)
            rr = rr_new
    return upper_solve(low, y.mul_(d_isqrt))


def _torch_coupling(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, size: int):
    """``(K, I − K)`` of :func:`_cg_iterations` as functions of ``v (n, P)``, in PyTorch operations."""
    n = low.shape[0]

    def neighbours(v):  # N v = Σ_q w_pq v_q (the first term written, not added to zeros)
        out = torch.empty_like(v)
        o, w = out.view(n, size, size), v.view(n, size, size)
        torch.mul(wx, w[:, :, 1:], out=o[:, :, :-1])
        o[:, :, -1] = 0.0
        o[:, :, 1:].addcmul_(wx, w[:, :, :-1])
        o[:, :-1].addcmul_(wy, w[:, 1:])
        o[:, 1:].addcmul_(wy, w[:, :-1])
        return out

    def coupling(v):  # K v = G⁻¹ N G⁻ᵀ v (lower_solve and upper_solve: the PyTorch loops here)
        return lower_solve(low, neighbours(upper_solve(low, v * d_isqrt))).mul_(d_isqrt)

    def apply(v):  # (I − K) v
        k = coupling(v)
        return torch.sub(v, k, out=k)

    return coupling, apply


def local_prior(cand: Tensor, theta: Tensor, wx: Tensor, wy: Tensor, size: int,
                rows: Tensor | None = None, around: tuple | None = None,
                channels: slice | None = None) -> Tensor:
    """``Σ_q w_pq (cand_p − θ_q)²`` over each pixel's 4 neighbours ``q`` ``(*, N, 1)``: the change
    of (twice) the prior energy, up to a constant, if pixel ``p`` alone took ``cand_p``.

    ``cand (*, N, C)``: values for the pixels ``rows (N,)`` (int64; None: all ``P`` pixels in
    order), any number of candidate sets at once along the leading dims; ``theta (P, C)`` the
    map the neighbours keep, ``wx``, ``wy`` its edge weights. The terms are added in one order
    (right, left, lower, upper neighbour) whatever the batch or the rows, so a candidate's
    value does not depend on which others share the call. ``around``: :func:`row_neighbours`
    of these ``rows`` when the caller has them (several calls on the same pixels gather them
    once); ``channels``: :func:`joined_channels` of ``wx``, ``wy`` when the caller has it (else
    found here). Only those channels are summed: elsewhere every weight is 0, and so is each
    term of finite values. ``cand``'s dtype and device.
    """
    c = theta.shape[1]
    if size < 2:  # a single pixel has no neighbours
        return cand.new_zeros(*cand.shape[:-1], 1)
    ch = joined_channels(wx, wy) if channels is None else channels
    if rows is None:  # every pixel: the edges are slices of the image (no gather)
        a, t = cand.reshape(*cand.shape[:-2], size, size, c)[..., ch], theta.reshape(size, size, c)[..., ch]
        wx, wy = wx[..., ch], wy[..., ch]
        e = torch.zeros(*a.shape[:-1], 1, dtype=cand.dtype, device=cand.device)
        e[..., :, :-1, :] += _edge_term(a[..., :, :-1, :], t[:, 1:], wx)
        e[..., :, 1:, :] += _edge_term(a[..., :, 1:, :], t[:, :-1], wx)
        e[..., :-1, :, :] += _edge_term(a[..., :-1, :, :], t[1:], wy)
        e[..., 1:, :, :] += _edge_term(a[..., 1:, :, :], t[:-1], wy)
        return e.reshape(*cand.shape[:-1], 1)
    terms = []
    for tq, wq, has in (around if around is not None else row_neighbours(theta, wx, wy, size, rows)):
        term = _edge_term(cand[..., ch], tq[..., ch], wq[..., ch])
        terms.append(torch.where(has[:, None], term, torch.zeros_like(term)))
    return terms[0] + terms[1] + terms[2] + terms[3]


def row_neighbours(theta: Tensor, wx: Tensor, wy: Tensor, size: int,
                   rows: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor], ...]:
    """The 4 neighbours of pixels ``rows (N,)`` (int64) in :func:`local_prior`'s order (right, left,
    lower, upper): each ``(values (N, C), edge weights (N, C), exists (N,) bool)``, gathered from
    ``theta (P, C)`` and ``wx``, ``wy`` of a ``size²`` map (``size ≥ 2``)."""
    c = theta.shape[1]
    i, j = rows // size, rows % size
    last = size - 1
    # (neighbour, its edge's row in wx or wy, whether it exists): a missing neighbour's indices
    # are clamped into range and its term dropped (not weighted by 0: a non-finite value stays out).
    edges = ((wx, rows + 1, i * last + j, j < last), (wx, rows - 1, i * last + j - 1, j > 0),
             (wy, rows + size, i * size + j, i < last), (wy, rows - size, (i - 1) * size + j, i > 0))
    return tuple((theta.index_select(0, q.clamp(0, size * size - 1)),
                  w.reshape(-1, c).index_select(0, w_row.clamp(0, size * last - 1)), has)
                 for w, q, w_row, has in edges)


def _edge_term(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """``Σ_c w (a − b)²`` over the last dim, keepdim: one temporary, squared and weighted in place
    (the same values as the out-of-place products, in the same order)."""
    d = a - b
    return d.square_().mul_(w).sum(-1, keepdim=True)
