"""Levenberg–Marquardt on the per-pixel unknowns: Jacobians, normal equations and steps.

The coupled step with the smoothness prior (:func:`lm_step`), the per-pixel data-only refit
(:func:`refit_pixels`), the 8-unknown projected LM of the continuous-metallic stage
(:func:`soft_lm`), and the Gauss–Newton algebra they share (:func:`newton_step`,
:func:`conditional_shift`, :func:`marginal_information`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.params import N_PARAMS
from torchbrdf.recovery.pixel_systems import inverse_diagonal, to_lanes
from torchbrdf.recovery.smoothness_prior import (edge_weights, joined_channels, laplacian, laplacian_diag, pcg,
                                                 prior_energy)


def fit_jacobian(jvp: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]], x: Tensor, n_t: int
                 ) -> tuple[Tensor, Tensor]:
    """Residuals and their per-pixel Jacobian by forward mode, the base colour in one direction.

    ``jvp(x, tangents (K, N, K')) -> (r (N, M), derivatives (K, N, M))``: the residuals at
    ``x (N, K')`` and their derivatives along ``K`` directions of ``x`` at once
    (:meth:`LevelData.residual_jvp`, or :func:`vmapped_jvp` of a residual function). Returns
    ``r`` and its Jacobian ``(N, n_t, M)`` w.r.t. the first ``n_t`` (≥ 3) columns of ``x`` —
    the unknowns of :func:`decode`, base-colour logits first.

    The fit's models act on each colour channel with that channel's base colour alone (no tint:
    :func:`decode` sets none), and ``M`` interleaves the channels (light-major, ``3 l + c``), so
    one direction along all three base-colour logits gives their three columns at once, each on
    its own channel's residuals: ``n_t − 2`` directions instead of ``n_t``. Non-finite Jacobian
    entries are 0; the residuals are as they come. Both on ``x``'s device, in its dtype.
    """
    k = n_t - 2
    tan = torch.zeros(k, x.shape[1], dtype=x.dtype, device=x.device)
    tan[0, 0:3] = 1.0
    tan[1:, 3:n_t] = torch.eye(n_t - 3, dtype=x.dtype, device=x.device)
    r, cols = jvp(x, tan[:, None, :].expand(k, *x.shape))
    cols = cols.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)  # (k, N, M), a fresh tensor: in place
    channel = torch.arange(cols.shape[-1], device=x.device) % 3
    own = (channel == torch.arange(3, device=x.device)[:, None]).to(cols.dtype)  # (3, M)
    # (one buffer: torch.cat of the transposed directions copied element by element)
    jac = cols.new_empty(x.shape[0], n_t, cols.shape[-1])
    jac[:, :3] = cols[0][:, None, :] * own  # (an assignment, not out=: autograd may run through it)
    jac[:, 3:] = cols[1:].transpose(0, 1)
    return r, jac


def gauss_newton(data: LevelData, theta: Tensor, metal: Tensor, idx: list[int], model: str,
                 chunk: int = 16384, fused: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals and the per-pixel normal equations of the log residuals on lights ``idx``.

    Returns ``r (P, M)`` (the residuals at ``theta``, non-finite entries as they come),
    ``JᵀJ (P, 7, 7)`` and ``Jᵀr (P, 7)`` w.r.t. each pixel's 7 unknowns (non-finite Jacobian
    entries and residuals count as 0 there). Where the fused normal-equations kernel applies
    (either model in float32/float64 with the fused path on:
    :meth:`LevelData.normal_equations`; ``fused=False`` skips it, to compare) one pass over
    the lights writes all three, with no Jacobian in memory. Otherwise, pixels being
    independent, forward mode (:func:`fit_jacobian`: five directions for the seven unknowns,
    in one call of the fused operators, the residual as their primal output) gives every
    pixel's Jacobian. It runs over blocks of ``chunk`` pixels and reduces each block to its 7×7 products at once, so the
    ``7 × lights × pixels`` Jacobian never exists whole: its blocks stay in cache and below
    the allocator's mmap threshold (a whole 256² Jacobian is 88 MB, and every fresh
    allocation that size is page-faulted in anew).
    """
    one_pass = data.normal_equations(theta, metal, idx, model, N_PARAMS) if fused else None
    if one_pass is not None:
        return one_pass[0], one_pass[2], one_pass[3]
    P = theta.shape[0]
    r_out = theta.new_empty(P, 3 * len(idx))
    jtj = theta.new_empty(P, N_PARAMS, N_PARAMS)
    jtr = theta.new_empty(P, N_PARAMS)
    for s0 in range(0, P, chunk):
        rows = slice(s0, min(s0 + chunk, P))
        t, m = theta[rows], metal[rows]
        r, jt = fit_jacobian(lambda x, tg: data.residual_jvp(x, m, idx, model, tg, rows=rows),  # noqa: B023
                             t, N_PARAMS)
        r_out[rows] = r
        torch.bmm(jt, jt.transpose(1, 2), out=jtj[rows])
        torch.bmm(jt, torch.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0)[..., None], out=jtr[rows, :, None])
    return r_out, jtj, jtr


def marginal_information(data: LevelData, theta: Tensor, metal: Tensor, model: str,
                         jtj: Tensor | None = None) -> Tensor:
    """Per-parameter marginal information ``1 / diag((JᵀJ)⁻¹)`` ``(P, 7)`` of the data term.

    It is what the captured images say about each parameter once the others are free to
    trade off against it (Gauss–Newton posterior precision): small for a glossy pixel's
    roughness when no highlight reaches it, and for a metal's F0 far from every highlight.
    """
    if jtj is None:  # the normal matrices ``(P, 7, 7)`` at theta, when the caller has none
        jtj = gauss_newton(data, theta, metal, data.train_idx, model)[1]
    # Only the inverse's diagonal is needed: one lane-wise LDLᵀ, in float64.
    lanes = to_lanes(jtj)
    lanes.diagonal(dim1=0, dim2=1).add_(1e-6)
    cov_diag = inverse_diagonal(lanes).T  # (P, 7)
    return (1.0 / cov_diag.clamp(min=1e-12)).to(theta.dtype)


def prior_gradient(theta: Tensor, wx: Tensor, wy: Tensor, size: int,
                   unary: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Gradient ``(P, 7)`` of the maps' prior energy at ``theta``.

    The smoothness prior's weighted Laplacian (:func:`edge_weights` ``wx``, ``wy``) plus the
    unary fill's pull.
    """
    g = laplacian(theta, wx, wy, size)
    if unary is not None:
        g = g + unary[1] * (theta - unary[0])
    return g


def map_prior_terms(theta: Tensor, metal: Tensor, size: int, cfg: Settings,
                    unary: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Gradient and Hessian diagonal ``(P, 7)`` each of the maps' prior energy at ``theta``.

    ``theta (P, 7)``, ``metal (P, 1)`` of a ``size × size`` map; ``unary`` as in :func:`lm_step`.
    The results have ``theta``'s dtype and device.
    """
    wx, wy = edge_weights(theta, metal, size, cfg)
    hdiag = laplacian_diag(wx, wy, size)
    return prior_gradient(theta, wx, wy, size, unary), hdiag if unary is None else hdiag + unary[1]


def lm_step(data: LevelData, theta: Tensor, metal: Tensor, lam: Tensor, cfg: Settings, lr: float,
            extra: dict | None = None, unary: tuple[Tensor, Tensor] | None = None,
            gn: tuple[Tensor, Tensor, Tensor] | None = None, residual: bool = True
            ) -> tuple[Tensor, Tensor, Tensor, int]:
    """One Levenberg–Marquardt iteration with the coupled smoothness prior.

    ``theta (P, 7)`` unknowns, ``metal (P, 1)`` classes, ``lam (P, 1)`` per-pixel damping;
    ``lr`` scales the step. Returns ``(theta, lam, cost (P, 1), n_nonfinite)``; when ``extra``
    (a dict) is given, ``extra["data_cost"]`` receives each pixel's summed squared residuals
    ``(P, 1)`` and, unless ``residual`` is false, ``extra["residual"]`` the residuals ``(P, M)``,
    both at the returned ``theta`` (for the light-scale update and the fit loss, without
    another render; the summed squares are those of the residuals). ``unary = (target, precision)``
    ``(P, 7)`` each adds ``½ Σ precision (θ − target)²`` (the non-local fill, :func:`nonlocal_fill`,
    and the metals' F0 tie, :func:`nonlocal_prior`). ``gn``: :func:`gauss_newton`'s result at
    ``theta`` on these lights when the caller has it (else computed).
    """
    idx, size = data.train_idx, data.size
    wx, wy = edge_weights(theta, metal, size, cfg)
    fn = lambda t: data.residual(t, metal, idx, cfg.model)  # noqa: E731
    r0, jtj, jtr = gn if gn is not None else gauss_newton(data, theta, metal, idx, cfg.model)
    g = jtr + prior_gradient(theta, wx, wy, size, unary)
    # The blocks are JᵀJ + diag(unary precision + per-pixel Marquardt damping); pcg adds the
    # diagonal itself, so no second (P, 7, 7) is built.
    hd = torch.diagonal(jtj, dim1=-2, dim2=-1) + laplacian_diag(wx, wy, size)
    if unary is not None:
        hd = hd + unary[1]
    damp = lam * (hd + 1e-6)
    step = pcg(jtj, wx, wy, -g, size, cfg.cg_iters, diag=damp if unary is None else damp + unary[1])
    step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0).clamp(-3, 3)
    inf = float("inf")  # (a non-finite cost is +inf: it never wins, and n_nonfinite counts it)
    ch = joined_channels(wx, wy)
    d0 = (r0 * r0).sum(-1, keepdim=True)
    c0 = d0 + prior_energy(theta, wx, wy, size, ch) + unary_cost(theta, unary)
    c0 = torch.nan_to_num(c0, nan=inf, posinf=inf, neginf=inf)
    cand = theta + lr * step
    r1 = fn(cand)
    d1 = (r1 * r1).sum(-1, keepdim=True)
    c1 = d1 + prior_energy(cand, wx, wy, size, ch) + unary_cost(cand, unary)
    c1 = torch.nan_to_num(c1, nan=inf, posinf=inf, neginf=inf)
    better = c1 < c0
    theta = torch.where(better, cand, theta)
    lam = torch.where(better, (lam * 0.3).clamp(min=1e-5), (lam * 10).clamp(max=1e6))
    cost = torch.where(better, c1, c0)
    if extra is not None:
        extra["data_cost"] = torch.where(better, d1, d0)
        if residual:
            extra["residual"] = torch.where(better, r1, r0)
    return theta, lam, cost, int((c1 == inf).sum())


def newton_step(jtj: Tensor, g: Tensor, held: Tensor | None = None, chunk: int = 65536) -> Tensor:
    """Each pixel's Gauss–Newton step ``−H_ff⁻¹ g_f`` ``(P, 7)`` on its free unknowns (0 on the held).

    ``jtj (P, 7, 7)`` the normal matrices ``H``, ``g (P, 7)`` the gradients, ``held (P, 7)`` the
    unknowns kept fixed (None: none). ``H_ff`` gets a relative 1e-6 (plus 1e-9) on its diagonal,
    so a direction the data do not see takes a bounded step; steps are clamped to ±3 (logit /
    slope units). The float64 algebra runs over blocks of ``chunk`` pixels (a 1024² map's 7×7
    blocks are 0.4 GB each); the result has ``g``'s dtype and device.
    """
    out = torch.empty_like(g)
    for s0 in range(0, g.shape[0], chunk):
        rows = slice(s0, s0 + chunk)
        # float64 copies, damped in place (copy=True: a float64 caller's own blocks stay as they are)
        h, rhs = jtj[rows].to(torch.float64, copy=True), -g[rows].double()
        if held is not None:  # (a held row becomes the identity's, its rhs 0: its step is 0)
            hold_unknowns(h, rhs, held[rows])
        diag = torch.diagonal(h, dim1=-2, dim2=-1)
        diag.add_(1e-6 * diag + 1e-9)
        x = torch.linalg.solve(h, rhs[..., None])[..., 0]
        out[rows] = torch.nan_to_num(x).clamp(-3, 3).to(g.dtype)
    return out


def conditional_shift(jtj: Tensor, delta: Tensor, moved: Tensor, chunk: int = 65536) -> Tensor:
    """The other unknowns' first-order response ``(P, 7)`` to moving some of a pixel's unknowns.

    ``jtj (P, 7, 7)`` each pixel's normal matrix, ``delta (P, 7)`` the change imposed on the
    unknowns where ``moved (P, 7)`` is true (per pixel). Returns ``−H_oo⁻¹ H_om δ_m`` on the
    others (zero on the moved ones): how the data optimum of the free unknowns moves with the
    moved ones under the Gauss–Newton model — exactly the least-squares response where the
    data gradient on the free unknowns is zero, as at a converged fit: the Newton step from
    the gradient ``H δ_m`` that the move creates (:func:`newton_step`). After a prior moves a
    metal's F0 along the F0–roughness valley, its roughness and normal follow. Callers keep a
    shift only where it helps (a curved valley bends away from the linear response). ``chunk``:
    as in :func:`newton_step`.
    """
    g = torch.empty_like(delta)
    for s0 in range(0, delta.shape[0], chunk):  # H δ_m in float64, block by block (as the solve)
        rows = slice(s0, s0 + chunk)
        dm = (delta[rows] * moved[rows]).double()
        g[rows] = (jtj[rows].double() @ dm[..., None])[..., 0].to(delta.dtype)
    return newton_step(jtj, g, moved, chunk)


def sum_unary(a: tuple[Tensor, Tensor] | None, b: tuple[Tensor, Tensor] | None
               ) -> tuple[Tensor, Tensor] | None:
    """The sum of two unary priors ``(target, precision)`` ``(P, 7)`` each (None: absent), as one."""
    if a is None or b is None:
        return a if b is None else b
    prec = a[1] + b[1]
    target = torch.where(prec > 0, (a[1] * a[0] + b[1] * b[0]) / prec.clamp(min=1e-30), a[0])
    return target, prec


def unary_cost(theta: Tensor, unary: tuple[Tensor, Tensor] | None) -> Tensor | float:
    """Per-pixel share ``(P, 1)`` (on the ``|r|²`` scale) of the unary prior, or 0."""
    if unary is None:
        return 0.0
    return (unary[1] * (theta - unary[0]) ** 2).sum(-1, keepdim=True)


def keep_better(best: Tensor | None, best_c: Tensor | None, x: Tensor, c: Tensor
                 ) -> tuple[Tensor, Tensor]:
    """Per pixel, the better of ``(best, best_c)`` and ``(x, c)`` (lower cost ``(N, 1)``; the
    first start when ``best`` is None)."""
    if best is None or best_c is None:
        return x, c
    better = c < best_c
    return torch.where(better, x, best), torch.where(better, c, best_c)


def pixel_cost(r: Tensor) -> Tensor:
    """Each pixel's data cost ``(N, 1)``: the sum of its squared residuals ``r (N, M)``.

    A non-finite sum is +inf, so it never wins a comparison and drops out of finite medians;
    ``r``'s dtype and device.
    """
    inf = float("inf")
    return torch.nan_to_num((r * r).sum(-1, keepdim=True), nan=inf, posinf=inf)


def hold_unknowns(jtj: Tensor, g: Tensor, held: Tensor) -> tuple[Tensor, Tensor]:
    """Per-pixel normal equations ``jtj (N, K, K)``, ``g (N, K)`` with ``held (N, K)`` unknowns decoupled.

    A held unknown's row and column are the identity's and its gradient is 0, so an LM step leaves
    it at its value. In place: ``jtj`` and ``g`` must be the caller's own (fresh) tensors.
    Returns them, in their dtype, on their device.
    """
    free = (~held).to(jtj.dtype)
    jtj.mul_(free[:, :, None] * free[:, None, :])
    torch.diagonal(jtj, dim1=-2, dim2=-1).add_(1 - free)
    return jtj, g.mul_(free)


def refit_pixels(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, starts: list[Tensor],
                 idx: list[int], model: str, iters: int = 10, held: Tensor | None = None
                 ) -> tuple[Tensor, Tensor]:
    """Per-pixel Levenberg–Marquardt (data term only) on the listed pixels from several starts.

    ``theta (P, 7)``, ``metal (P, 1)``, ``rows (N,)`` pixel indices, ``starts``: ``(N, 7)``
    starting points; ``idx`` the lights; ``held (N, 7)``: unknowns kept at their start (None:
    all free). Cheap — a few thousand pixels, no prior coupling.
    Returns the best ``(theta rows (N, 7), data cost (N, 1))`` over the starts.
    """
    m = metal[rows]
    sub = data.subset(rows)

    def cost(t):
        return pixel_cost(sub.residual(t, m, idx, model))

    best: Tensor | None = None
    best_c: Tensor | None = None
    for t in starts:
        t = t.clone()
        lam = torch.full((t.shape[0], 1), 1e-2, dtype=t.dtype, device=t.device)
        c = cost(t)
        for _ in range(iters):
            _, jtj, g = gauss_newton(sub, t, m, idx, model)
            if held is not None:
                jtj, g = hold_unknowns(jtj, g, held)
            h = jtj + torch.diag_embed(lam * (torch.diagonal(jtj, dim1=-2, dim2=-1) + 1e-6))
            step = torch.nan_to_num(torch.linalg.solve(h, -g[..., None])[..., 0]).clamp(-3, 3)
            cand = t + step
            c1 = cost(cand)
            better = c1 < c
            t = torch.where(better, cand, t)
            c = torch.where(better, c1, c)
            lam = torch.where(better, (lam * 0.3).clamp(min=1e-5), (lam * 10).clamp(max=1e6))
        best, best_c = keep_better(best, best_c, t, c)
    assert best is not None and best_c is not None, "refit_pixels: `starts` must not be empty"
    return best, best_c


PixelRows = Tensor | None  # pixel indices into an LM call's N pixels; None: all of them


def at_rows(v: Any, r: PixelRows) -> Any:
    """A per-pixel tensor (or a tuple or dict of them) at rows ``r``; None rows or a float: as is."""
    if isinstance(v, tuple):
        return tuple(at_rows(x, r) for x in v)
    if isinstance(v, dict):
        return {k: at_rows(x, r) for k, x in v.items()}
    return v[r] if isinstance(v, Tensor) and r is not None else v


def soft_lm(jvp: Callable[[Tensor, Tensor, PixelRows], tuple[Tensor, Tensor]],
             cost: Callable[[Tensor, PixelRows], Tensor], x: Tensor, iters: int, fix_metal: bool = False,
             prior: Callable[[Tensor, PixelRows], tuple[Tensor, Tensor]] | None = None, tol: float = 1e-3,
             held: Tensor | None = None,
             normal_eq: Callable[[Tensor, PixelRows, int], tuple[Tensor, Tensor, Tensor] | None] | None = None
             ) -> tuple[Tensor, Tensor]:
    """``iters`` per-pixel LM iterations on ``x (N, 8)`` (the data residuals and their
    derivatives along K directions from ``jvp``, as :meth:`LevelData.residual_jvp`; metallic —
    the last column — clamped to [0, 1] after each step; held fixed with ``fix_metal``, which
    then has no tangent: 5 instead of 6 per Jacobian, :func:`fit_jacobian`). ``prior``: the
    prior residuals and their Jacobian (``x`` → ``(N, k)``, ``(N, k, 8)``, as
    :func:`soft_prior`), added to the normal equations by hand (they are not part of the data
    residuals' forward-mode Jacobian, which would copy them once per tangent); ``cost`` must
    be the summed squares of both (a linearised candidate's cost is taken from them: only the
    last iteration's candidates are costed by ``cost``). ``jvp``, ``cost`` and ``prior`` take
    the unknowns of some of the pixels and their indices (``None``: all N, in order); the
    base-colour unknowns act each on its own channel's residuals (:func:`fit_jacobian`).
    ``held (N, 8)`` bool: unknowns kept at their start (None: none held but metallic with
    ``fix_metal``, which ignores its column 7; a held metallic is still clamped to [0, 1]).
    ``normal_eq(x, rows, n_t)``: the data term's summed squares ``(n,)``, ``JᵀJ (n, n_t, n_t)``
    and ``Jᵀr (n, n_t)`` w.r.t. the first ``n_t`` unknowns in one fused pass
    (:meth:`LevelData.normal_equations`), or None where that does not apply: then (and with
    ``normal_eq`` None) they come from ``jvp`` by :func:`fit_jacobian`.

    A pixel whose accepted step (at no more than the starting damping) lowered its finite cost by
    less than ``tol`` of it has converged and leaves the iterations (0: every pixel runs every
    iteration): most of a warm-started refit's pixels settle in two or three (in the soft-metal
    stage most of its LM work is saved, with the maps within measurement noise).
    Returns ``(x, cost (N, 1))``, on ``x``'s device and in its dtype."""
    n_t = x.shape[1] - 1 if fix_metal else x.shape[1]  # the unknowns that move
    lam0 = 1e-2  # the starting damping
    lam = torch.full((x.shape[0], 1), lam0, dtype=x.dtype, device=x.device)

    def linearise(v: Tensor, rows: PixelRows) -> tuple[Tensor, Tensor, Tensor]:
        # The cost (n, 1) at v and its normal equations (n, n_t, n_t), (n, n_t): the residuals
        # come with the Jacobian (the same values `cost` gives).
        fused = normal_eq(v, rows, n_t) if normal_eq is not None else None
        if fused is not None:
            data_cost, jtj, g = fused
            pr, pj = prior(v, rows) if prior is not None else (v[:, :0], None)
            inf = float("inf")
            c = torch.nan_to_num(data_cost[:, None] + (pr * pr).sum(-1, keepdim=True), nan=inf, posinf=inf)
        else:
            r, jac = fit_jacobian(lambda u, tg: jvp(u, tg, rows), v, n_t)  # (n, M), (n, n_t, M)
            pr, pj = prior(v, rows) if prior is not None else (r[:, :0], None)
            c = pixel_cost(torch.cat((r, pr), -1))
            r = r.nan_to_num_()  # (a fresh tensor of the jvp: cleaned in place)
            # (the gradients, and the priors' few rows, as products and sums: a batch of small
            # matrix-vector products is slower)
            jtj = torch.bmm(jac, jac.transpose(1, 2))
            g = (jac * r[:, None, :]).sum(-1)
        if pj is not None:
            pj = pj[..., :n_t]  # (n, k, n_t)
            jtj = jtj + (pj[..., :, None] * pj[..., None, :]).sum(1)
            g = g + (pj * pr[..., None]).sum(1)
        if held is not None:
            jtj, g = hold_unknowns(jtj, g, at_rows(held, rows)[:, :n_t])
        return c, jtj, g

    # Each candidate step is judged by its cost, which its linearisation gives too: an accepted
    # step's normal equations are the next iteration's, a rejected one keeps the pixel's own,
    # and only the last iteration's candidates are evaluated without their Jacobian (one
    # residual evaluation per iteration less than linearising each accepted point anew).
    # (the first iteration runs on every pixel and replaces x, c, lam, jtj, g with new tensors:
    # the caller's x is never written to)
    c, jtj, g = linearise(x, None)
    active = torch.arange(x.shape[0], device=x.device)
    for it in range(iters):
        if active.numel() == 0:
            break
        rows: PixelRows = None if active.numel() == x.shape[0] else active
        if rows is None:
            xa, ca, la, ja, ga = x, c, lam, jtj, g
        else:
            xa, ca, la, ja, ga = x[rows], c[rows], lam[rows], jtj[rows], g[rows]
        h = ja + torch.diag_embed(la * (torch.diagonal(ja, dim1=-2, dim2=-1) + 1e-6))
        step = torch.nan_to_num(torch.linalg.solve(h, -ga[..., None])[..., 0]).clamp(-3, 3)
        cand = xa + torch.nn.functional.pad(step, (0, x.shape[1] - n_t))
        cand = torch.cat((cand[:, :-1], cand[:, -1:].clamp(0.0, 1.0)), -1)
        last = it == iters - 1
        if last:
            c1 = cost(cand, rows)
        else:
            c1, j1, g1 = linearise(cand, rows)
        better = c1 < ca
        new_x, new_c = torch.where(better, cand, xa), torch.where(better, c1, ca)
        new_l = torch.where(better, (la * 0.3).clamp(min=1e-5), (la * 10).clamp(max=1e6))
        if rows is None:
            x, c, lam = new_x, new_c, new_l
        else:
            x[rows], c[rows], lam[rows] = new_x, new_c, new_l
        if not last:
            new_j, new_g = torch.where(better[..., None], j1, ja), torch.where(better, g1, ga)
            if rows is None:
                jtj, g = new_j, new_g
            else:
                jtj[rows], g[rows] = new_j, new_g
        # Converged: an accepted step that gained less than tol of a finite cost, taken at no more
        # than the starting damping (after rejected steps a step is short because of the
        # damping, not because the pixel is done; a rejected step is not convergence either).
        done = (better & (la <= lam0) & torch.isfinite(ca) & (ca - c1 <= tol * ca))[:, 0]
        active = active[~done]
    return x, c
