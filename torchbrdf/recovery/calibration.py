"""Light calibration: per-light intensity scales and position offsets estimated with the maps.

Alternating steps (:func:`light_scale_step`, :func:`light_position_step`) and the joint step
with the maps eliminated (:func:`light_joint_step`); the rig's placement and a flash beside the
camera are held (:func:`rig_free_directions`, :func:`camera_lights`).
"""

from __future__ import annotations

import math
import sys

import numpy as np
import torch
from torch import Tensor

from torchbrdf.brdf import capture_residual
from torchbrdf.capture.synthetic import log_residual_points_jvp
from torchbrdf.recovery.classes import chi2_quantile
from torchbrdf.recovery.levels import LevelData, log_residual
from torchbrdf.recovery.params import N_PARAMS, decode, decode_directions
from torchbrdf.recovery.pixel_systems import cholesky_factor


#: The median of χ² with one degree of freedom: median(r²) = 0.455 σ² for Gaussian residuals.
_CHI2_1_MEDIAN = chi2_quantile(1, 0.5)


def light_position_step(data: LevelData, theta: Tensor, metal: Tensor, offset: Tensor, model: str,
                        prior_sigma: float = 0.01, stride: int = 4, at_camera: bool = True) -> Tensor:
    """One Gauss–Newton update of the per-light position offsets ``(L, 3)`` (world units).

    Each light's residuals depend only on its own position, so three forward-mode passes (one
    per axis, every light at once) give every light's ``(pixels, 3)`` Jacobian; the step solves
    each light's 3×3 normal equations with a Gaussian prior of ``prior_sigma`` (1 cm) on the
    offset, over every ``stride``-th pixel (cheap; the offset is 3 numbers per light against
    thousands of pixels). Lights not in ``data.train_idx`` keep their offsets, and so, with
    ``at_camera=False``, does a light beside the camera (:func:`camera_lights`).
    """
    idx = data.train_idx
    rows = torch.arange(0, theta.shape[0], stride, device=theta.device)
    p = decode(theta[rows], metal[rows])
    pts, cam = data.points[rows], data.camera
    log_obs = data.log_obs[idx][:, rows]
    inten = data.inten[idx]
    base = data.pos_stated[idx] + offset[idx]

    def res(pos):  # (L, N, 3)
        r = log_residual(p, pts, cam, pos, inten, log_obs.permute(1, 0, 2), data.eps, model)
        return r.permute(1, 0, 2)

    r = torch.nan_to_num(res(base))
    cols = []
    for k in range(3):
        tg = torch.zeros_like(base)
        tg[:, k] = 1.0
        cols.append(torch.nan_to_num(torch.func.jvp(res, (base,), (tg,))[1]))
    jac = torch.stack(cols, -1).reshape(len(idx), -1, 3)  # (L, N*3, 3)
    r = r.reshape(len(idx), -1)
    sigma2 = float(r.pow(2).median()) + 1e-12  # robust per-residual noise variance
    # Huber weights: a residual beyond 3 noise deviations counts linearly, not quadratically, so
    # the few pixels the maps do not fit yet (a material front, an unconverged rim) cannot move
    # a light to explain them.
    w = (3.0 * math.sqrt(sigma2) / r.abs().clamp(min=1e-30)).clamp(max=1.0)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    jtj = torch.einsum("lni,lnj->lij", jac * w[..., None], jac) + (sigma2 / prior_sigma**2) * eye
    g = torch.einsum("lni,ln->li", jac, w * r) + (sigma2 / prior_sigma**2) * offset[idx]
    step = torch.linalg.solve(jtj, -g[..., None])[..., 0]
    if not at_camera:
        step[camera_lights(data.pos_stated[idx], cam, data.points.mean(0))] = 0.0
    out = offset.clone()
    out[idx] = (offset[idx] + torch.nan_to_num(step)).clamp(-5 * prior_sigma, 5 * prior_sigma)
    return out


def camera_lights(pos: Tensor, camera: Tensor, centre: Tensor, frac: float = 0.1) -> Tensor:
    """``(L,)`` bool: the lights beside the camera (a flash).

    Within ``frac`` × the camera's distance to the surface ``centre (3,)`` of ``camera (3,)``;
    ``pos (L, 3)``; the mask is on ``pos``'s device (any float dtype).

    Such a light lights every pixel from near the viewing direction, so a small move of it
    changes the images much as its intensity scale and a slow variation of the maps do: the
    least determined of the lights' positions (at a capture's true maps, about 10x the ring
    lights' posterior deviation along the axis), and the one
    that soaked up what the two-hypothesis maps had not yet fitted
    (``Settings.dual_calibration_at_camera``).
    """
    reach = frac * float((camera - centre).norm())
    return (pos - camera).norm(dim=-1) < reach


def rig_free_directions(pos: Tensor, centre: Tensor, held: Tensor | None = None) -> Tensor:
    """``(3L, 3L - 7 - 3H)`` orthonormal light-position changes that keep the rig's placement.

    Moving every light together (a translation, a turn or a dilation about the surface's
    ``centre``) changes the images almost as moving, tilting or scaling the surface would,
    which the per-pixel maps absorb (normals take a tilt; a near-uniform material is unchanged
    by a shift); with the maps eliminated these seven directions are barely constrained by the
    data, and a little model mismatch runs them to the clamp (every light centimetres inward on a
    capture without calibration error). Like the overall intensity scale, the rig's placement is
    the stated one. ``pos (L, 3)`` light positions, ``centre (3,)``; ``held (L,)`` bool: lights
    whose position is kept as stated (``H`` of them; no component on their coordinates; None:
    none); rows are light-major (light ``i``'s x, y, z at ``3i .. 3i+2``); ``pos``'s dtype and
    device.
    """
    n = pos.shape[0]
    rel = pos - centre
    eye = torch.eye(3, dtype=pos.dtype, device=pos.device)
    turns = [torch.linalg.cross(e.expand_as(rel), rel).reshape(-1, 1) for e in eye]
    modes = torch.cat((eye.repeat(n, 1), rel.reshape(-1, 1), *turns), 1)  # (3L, 7)
    if held is not None and bool(held.any()):  # ... and each held light's x, y and z alone
        coords = torch.eye(3 * n, dtype=pos.dtype, device=pos.device)
        modes = torch.cat((modes, coords[:, held.repeat_interleave(3)]), 1)
    q, _ = torch.linalg.qr(modes, mode="complete")
    return q[:, modes.shape[1]:]


def light_joint_step(data: LevelData, theta: Tensor, metal: Tensor, log_scale: Tensor, offset: Tensor,
                     ref_idx: list[int], model: str, position: bool = True,
                     map_prior: tuple[Tensor, Tensor] | None = None, scale_sigma: float = 0.1,
                     position_sigma: float = 0.01, max_pixels: int = 8192,
                     damping: float = 1e-3, at_camera: bool = True,
                     evidence: dict[str, float] | None = None) -> tuple[Tensor, Tensor]:
    """One Gauss–Newton step on the lights' log scales and offsets, the pixels' unknowns eliminated.

    ``theta (P, 7)``, ``metal (P, 1)`` the maps; ``log_scale (L,)`` and ``offset (L, 3)`` the
    current estimates; returns the updated pair (lights not in ``data.train_idx`` keep theirs).

    Stepping the lights with the maps held fixed (:func:`light_scale_step`,
    :func:`light_position_step`) sees only the part of a light's error the maps cannot absorb
    (a tilted normal, a wider lobe), so alternating with the map steps creeps toward the joint
    optimum. Here each pixel's 7 unknowns are eliminated (a Schur complement, as in bundle
    adjustment): with ``A = JpᵀWJp + H``, ``B = JpᵀWJg`` and ``gp = JpᵀWr + g`` per pixel,
    the reduced normal equations ``(Σ JgᵀWJg − Σ BᵀA⁻¹B) δg = −(Σ JgᵀWr − Σ BᵀA⁻¹ gp)`` give
    the step the maps would follow. ``map_prior = (g, H)``, both ``(P, 7)``, are the gradient
    and the Hessian's diagonal of the maps' prior energy at ``theta`` (:func:`map_prior_terms`;
    block-Jacobi: the prior's coupling between pixels is left out): after an LM step the data
    gradient balances the prior's rather than vanishing.

    One forward-mode pass with 5 + 4 tangents (5 + 1 for the scales alone; the base colour in
    one direction, each logit on its own channel)
    over at most ``max_pixels`` evenly strided pixels gives both Jacobians (a light's residuals
    depend only on its own 4 numbers); the reduction runs in float64 (``Σ BᵀA⁻¹B`` nearly cancels
    ``Σ JgᵀWJg`` in the weak directions). Huber weights ``W`` (3 noise deviations) as in
    :func:`light_position_step`; pixels with a non-finite residual or derivative are left out.
    Gaussian priors of
    ``scale_sigma`` (log) and ``position_sigma`` (world units). The step keeps the training
    lights' (``ref_idx``) mean log scale and, with ``position``, moves no light rig as a whole
    (:func:`rig_free_directions`): the maps absorb both, so the capture's stated values fix
    them; nor, with ``at_camera=False``, a light beside the camera (:func:`camera_lights`). With
    ``position=False``, or fewer than 3 lights, only the scales are stepped. The
    result has ``log_scale``'s and ``offset``'s dtype and device (CPU or CUDA alike).

    ``evidence``, a dict, receives what the step could still buy: ``"chi2"`` = ``δgᵀ H δg / σ²``
    and ``"dof"`` = K, the free directions (the basis). ``H`` is the reduced Hessian of
    ``½ Σ wr²`` plus the priors, so ``H / σ²`` is the lights' posterior precision with the maps
    eliminated: ``δgᵀ H δg / σ²`` is twice the cost decrease the step predicts, in noise
    variances, and the step's squared length in posterior deviations. Noise alone puts the
    data's optimum that far from the true lights with a ``χ²`` distribution of K degrees of
    freedom (mean K): steps whose sum stays well below that move the lights less than their
    own uncertainty (:meth:`~torchbrdf.recovery.engine.Recovery.step` skips the step for the
    rest of a stage once ``m²`` times it is below K, ``m`` the stage's iterations left). ``σ²`` is
    the noise variance: the median squared residual over 0.455, the median of ``χ²₁``. Left
    empty when no step is taken.
    """
    idx = data.train_idx
    n_l = len(idx)
    stride = max(1, math.ceil(theta.shape[0] / max_pixels))
    rows = torch.arange(0, theta.shape[0], stride, device=theta.device)
    t0, m = theta[rows], metal[rows]
    pts = data.points[rows]
    # (rows of the light set's cached targets, which the LM steps use: one contiguous gather)
    log_obs = data.log_targets(idx, rows)  # (n, L, 3)
    inten0 = data.inten_stated[idx]
    pos0 = data.pos_stated[idx] + offset[idx]
    s0 = log_scale[idx]

    position = position and n_l >= 3  # two lights have no position freedom beyond the rig's
    base_one = True  # (the base colour's 3 unknowns in one direction: 2 tangents fewer)
    r, cols = _pixel_and_light_jacobians(data, t0, m, pts, log_obs, inten0, pos0, s0, model, position,
                                         base_one)
    # One sum per pixel carries any NaN or inf among its residuals and derivatives (a sum that
    # overflows float32 marks derivatives beyond any meaningful scale: left out as well).
    ok = torch.isfinite(r.sum(1) + cols.sum((0, 2)))  # (n,)
    if not bool(ok.all()):
        if not bool(ok.any()):
            return log_scale, offset
        r, cols, rows = r[ok], cols[:, ok], rows[ok]
    keep = slice(0, 4) if position else slice(3, 4)  # the light unknowns: offset xyz, log scale
    prior_terms = None if map_prior is None else (map_prior[0][rows], map_prior[1][rows])
    schur, rhs, sigma2 = _reduced_light_system(r, cols, prior_terms, damping, base_one=base_one)
    f64 = torch.float64
    n_g = keep.stop - keep.start
    prior = torch.tensor([1 / position_sigma**2] * 3 + [1 / scale_sigma**2], dtype=f64,
                         device=r.device)[keep].repeat(n_l) * sigma2
    cur = torch.cat((offset[idx], s0[:, None]), -1)[:, keep].reshape(-1).to(f64)
    held = None if at_camera or not position else camera_lights(data.pos_stated[idx], data.camera,
                                                                 data.points.mean(0))
    basis, n_pos = _light_step_basis(data, ref_idx, position, held)  # (L G, K): the directions a step takes
    h = basis.T @ (schur + torch.diag(prior)) @ basis
    grad = basis.T @ (rhs + prior * cur)
    coef = torch.linalg.solve(h, -grad)
    step = (basis @ coef).reshape(n_l, n_g)
    if evidence is not None:  # δgᵀHδg = −δgᵀ(reduced gradient), over σ² = median r² / median χ²₁
        evidence.update(chi2=float(-(coef @ grad)) / (sigma2 / _CHI2_1_MEDIAN), dof=float(basis.shape[1]))
    if not bool(torch.isfinite(step).all()):
        return log_scale, offset
    step = step.to(theta.dtype)
    new_off, new_s = offset.clone(), log_scale.clone()
    if position:
        moved = (offset[idx] + step[:, :3]).clamp(-5 * position_sigma, 5 * position_sigma)
        free = basis[:, :n_pos].reshape(n_l, n_g, -1)[:, :3].reshape(3 * n_l, -1).to(theta.dtype)
        # the clamp may leave the subspace: project back
        new_off[idx] = (free @ (free.T @ moved.reshape(-1))).reshape(n_l, 3)
        if held is not None:  # exactly as before (the projection leaves rounding dust)
            fixed = torch.as_tensor(idx, device=offset.device)[held]
            new_off[fixed] = offset[fixed]
    new_s[idx] = log_scale[idx] + step[:, -1]
    new_s[ref_idx] = new_s[ref_idx] - new_s[ref_idx].mean()
    return new_s.clamp(-0.3, 0.3), new_off


def rest_iterations(chi2: float, dof: float) -> int:
    """How many iterations the joint light step may rest after a step of ``chi2`` (floats): the
    most ``s`` with ``s² χ² < K``, ``K = dof``.

    ``χ² = δgᵀHδg / σ²`` and K are :func:`light_joint_step`'s ``evidence``. While the maps move,
    consecutive steps point the same way, so ``s`` iterations without one leave about ``s δg``
    unapplied, a cost of ``s² χ²`` noise variances; below K, what noise alone puts between the
    data's optimum and the true lights, the lights lag by less than their own uncertainty. A
    step of ``χ² ≥ K`` rests none, nor does a negative or non-finite ``χ²``; ``χ² = 0`` (or so
    small that ``K/χ²`` passes 1e18) rests without end (``sys.maxsize``). ``dof`` must be finite
    and ≥ 0 (a NaN would read as a rest without end).
    """
    if not (dof >= 0 and math.isfinite(dof)):
        raise ValueError(f"rest_iterations: `dof` must be a finite number >= 0, got {dof!r}")
    if not (chi2 >= 0 and math.isfinite(chi2)):
        return 0
    if chi2 == 0 or not dof / chi2 < 1e18:
        return sys.maxsize
    s = math.isqrt(int(dof / chi2))  # a lower bound: ⌊√⌊K/χ²⌋⌋
    while (s + 1) ** 2 * chi2 < dof:  # (float rounding of the quotient, and the floor)
        s += 1
    while s > 0 and s * s * chi2 >= dof:
        s -= 1
    return s


def _reduced_light_system(r: Tensor, cols: Tensor, map_prior: tuple[Tensor, Tensor] | None, damping: float,
                          chunk: int = 1024, fused: bool = True, base_one: bool = False
                          ) -> tuple[Tensor, Tensor, float]:
    """The lights' reduced normal equations, each pixel's 7 unknowns eliminated (:func:`light_joint_step`).

    ``r (n, M)`` residuals and ``cols (7 + G, n, M)`` derivatives (``M = 3 L``, light-major;
    every one finite) along the pixel's unknowns, then the ``G`` light unknowns stepped (offset
    xyz and log scale, or the log scale alone), from :func:`_pixel_and_light_jacobians`
    (with ``base_one`` its ``(5 + G, n, M)`` layout, the base colour's unknowns in one row);
    ``map_prior`` the pixels' prior gradient and curvature, both ``(n, 7)``. Returns the Schur
    complement ``(L G, L G)``, the reduced gradient ``(L G,)`` (light-major, float64) and the
    residuals' robust variance σ².

    Per pixel, with ``A = JpᵀWJp + H = LLᵀ`` (Cholesky), ``Y = L⁻¹ [B | gp]`` makes
    ``Σ [B | gp]ᵀ A⁻¹ [B | gp] = Σ YᵀY`` one matrix product. The sums run ``chunk`` pixels at
    a time, so that a chunk's float64 ``Y`` stays in cache; on the CPU each chunk's per-pixel
    algebra is one C pass (:func:`torchbrdf.brdf.capture_residual.light_schur`, unless
    ``fused=False``: it is half the step's time in vector operations, each a pass through
    memory), elsewhere PyTorch operations (:func:`_reduced_light_terms`; on a GPU in one
    chunk). Float64 from the products on: the reduced system is a difference of two sums of
    positive terms, ``Σ JgᵀWJg − Σ BᵀA⁻¹B``, which nearly cancel along the directions the
    maps almost absorb.
    """
    n, m_cols = r.shape
    n_l, n_g = m_cols // 3, cols.shape[0] - (N_PARAMS - 2 if base_one else N_PARAMS)
    sigma2 = abs_median(r) ** 2 + 1e-12  # the median of r² is the median of |r|, squared
    f64 = torch.float64
    fast = None
    if fused:
        g, h = (r.new_zeros(n, N_PARAMS, dtype=f64),) * 2 if map_prior is None else \
            (torch.nan_to_num(map_prior[0].to(f64)), torch.nan_to_num(map_prior[1].to(f64)))
        fast = capture_residual.light_schur(r, cols, g, h, damping, 3.0 * math.sqrt(sigma2), chunk, base_one)
    if fast is not None:
        per_light, gram = fast
    else:
        if base_one:
            cols = _base_rows_apart(cols)
        if r.device.type != "cpu":
            chunk = n  # one launch per operation serves every pixel
        per_light = torch.zeros(n_l, n_g + 1, n_g + 1, dtype=f64, device=r.device)
        gram = torch.zeros(n_l * n_g + 1, n_l * n_g + 1, dtype=f64, device=r.device)
        for lo in range(0, n, chunk):
            part = slice(lo, lo + chunk)
            prior = None if map_prior is None else (map_prior[0][part], map_prior[1][part])
            _reduced_light_terms(r[part], cols[:, part], prior, damping, sigma2, per_light, gram)
    schur = torch.block_diag(*per_light[:, :n_g, :n_g]) - gram[:-1, :-1]
    return schur, per_light[:, :n_g, n_g].reshape(-1) - gram[:-1, -1], sigma2


def abs_median(r: Tensor) -> float:
    """The lower median of ``|r|`` over every element of ``r`` (any shape, every element finite):
    ``torch.median``'s order statistic, the ``⌊(N − 1)/2⌋``-th smallest of the ``N``.

    On the CPU in float32/float64 by NumPy's selection (``np.partition``, in place on the
    absolute values' copy): the same element, at half ``torch.median``'s time on a light
    step's 4·10⁵ residuals. Elsewhere ``torch.median``.
    """
    if r.numel() == 0:
        raise ValueError("abs_median: `r` must have at least one element, got an empty tensor")
    if r.device.type != "cpu" or r.dtype not in (torch.float32, torch.float64) or r.requires_grad:
        return float(r.abs().median())
    a = np.abs(r.numpy().reshape(-1))  # (a fresh array: partitioned in place)
    k = (a.size - 1) // 2
    a.partition(k)
    return float(a[k])


def _base_rows_apart(cols: Tensor) -> Tensor:
    """``(5 + G, n, M)`` derivatives with the base colour's unknowns in one row (``3 l + c`` of
    its channel ``c`` each) as the ``(7 + G, n, M)`` of one row per unknown, the other channels 0."""
    own = torch.arange(cols.shape[-1], device=cols.device) % 3 == torch.arange(3, device=cols.device)[:, None]
    return torch.cat((cols[:1] * own[:, None].to(cols.dtype), cols[1:]))


def _reduced_light_terms(r: Tensor, cols: Tensor, map_prior: tuple[Tensor, Tensor] | None,
                         damping: float, sigma2: float, per_light: Tensor, gram: Tensor) -> None:
    """Add a chunk of pixels' terms of :func:`_reduced_light_system`: ``[JgᵀWJg | JgᵀWr]`` per
    light to ``per_light (L, G + 1, G + 1)`` and ``Σ [B | gp]ᵀ A⁻¹ [B | gp]`` to ``gram
    (L G + 1, L G + 1)``.

    ``Y = L⁻¹ [B | gp]`` is formed as ``(L⁻¹ JpᵀW) Jg``, so the triangular solve runs on the 3L
    residual columns rather than the 4L + 1 light ones. Pixels are the innermost dimension:
    the 7×7 factorisations and solves are a few dozen vector operations, not one tiny one per
    pixel. A pixel whose ``A`` is not positive definite to rounding (never, as ``A`` carries
    the damping) is left out.
    """
    f64 = torch.float64
    n, m_cols = r.shape
    n_l, n_g = m_cols // 3, cols.shape[0] - N_PARAMS
    rt = r.T.to(f64, memory_format=torch.contiguous_format)  # (M, n)
    w = (3.0 * math.sqrt(sigma2) / rt.abs().clamp(min=1e-30)).clamp(max=1.0)  # Huber, (M, n)
    x = cols.permute(2, 0, 1).to(f64, memory_format=torch.contiguous_format)  # (M, 7 + G, n)
    jp = x[:, :N_PARAMS]
    jg = x.view(n_l, 3, -1, n)[:, :, N_PARAMS:]  # (L, 3, G, n)
    jpw = jp * w[:, None]
    a = x.new_empty(N_PARAMS, N_PARAMS, n)
    gp = x.new_empty(N_PARAMS, n)
    for i in range(N_PARAMS):
        gp[i] = torch.linalg.vecdot(jpw[:, i], rt, dim=0)
        for j in range(i + 1):
            a[j, i] = a[i, j] = torch.linalg.vecdot(jpw[:, i], jp[:, j], dim=0)
    diag = a.diagonal(0, 0, 1)  # (n, 7), a view
    extra = damping * diag + 1e-9
    if map_prior is not None:
        extra += torch.nan_to_num(map_prior[1].to(f64))
        gp += torch.nan_to_num(map_prior[0].T.to(f64))
    diag += extra
    low, good = cholesky_factor(a)
    if not bool(good.all()):
        w, jpw, gp = w * good, jpw * good, gp * good
    # per light, the G unknowns and the residual as G + 1 rows over (colour, pixel)
    aug = x.new_empty(n_l, n_g + 1, 3, n)
    aug[:, :n_g] = jg.transpose(1, 2)
    aug[:, n_g] = rt.view(n_l, 3, n)
    per_light.baddbmm_((aug * w.view(n_l, 1, 3, n)).view(n_l, n_g + 1, -1), aug.view(n_l, n_g + 1, -1).mT)
    # L⁻¹ JpᵀW (M, 7, n) and L⁻¹ gp (7, n) by forward substitution
    z = torch.empty_like(jpw)
    for k in range(N_PARAMS):
        acc, acc_g = jpw[:, k].clone(), gp[k]
        for j in range(k):
            acc.addcmul_(z[:, j], low[k, j], value=-1.0)
            acc_g.addcmul_(gp[j], low[k, j], value=-1.0)
        torch.div(acc, low[k, k], out=z[:, k])
        acc_g.div_(low[k, k])
    # Y (L G + 1, 7, n): per light and unknown Σ over colours of (L⁻¹ JpᵀW) Jg, then L⁻¹ gp
    y = x.new_empty(n_l * n_g + 1, N_PARAMS, n)
    y4, zl = y[:-1].view(n_l, n_g, N_PARAMS, n), z.view(n_l, 3, N_PARAMS, n)
    torch.mul(zl[:, None, 0], jg[:, 0, :, None], out=y4)
    for ch in (1, 2):
        y4.addcmul_(zl[:, None, ch], jg[:, ch, :, None])
    y[-1] = gp
    flat = y.view(y.shape[0], -1)
    gram.addmm_(flat, flat.T)


def _pixel_and_light_jacobians(data: LevelData, t0: Tensor, m: Tensor, pts: Tensor, log_obs: Tensor,
                               inten0: Tensor, pos0: Tensor, s0: Tensor, model: str, position: bool = True,
                               base_one: bool = False) -> tuple[Tensor, Tensor]:
    """Residuals ``(n, M)`` and their derivatives ``(7 + G, n, M)`` (``M = 3 L``, light-major)
    along each pixel's 7 unknowns and every light's offset xyz and log scale at once (``G = 4``;
    a light's residuals depend only on its own 4 numbers, so 4 shared directions cover all
    lights), or, without ``position``, its log scale alone (``G = 1``: 8 directions, one pass
    of the fused JVP kernel rather than two). With ``base_one`` the derivatives are
    ``(5 + G, n, M)``: the first along the three base-colour logits at once, which gives each
    its own channel's residuals ``3 l + c`` (under either model a channel's residual depends on
    its own base colour alone), the same numbers there as one direction per logit.

    The decode's tangents come in closed form (:func:`decode_directions`) and the residual's
    from one call of the fused operators (:func:`log_residual_points_jvp`, ``model`` its
    ``family``): what ``torch.func``'s ``vmap`` of ``jvp`` gives, at a fraction of the cost per
    call."""
    cam = data.camera
    n, n_l, n_g = t0.shape[0], s0.shape[0], 4 if position else 1
    tp = pos0.new_zeros(N_PARAMS + n_g, *pos0.shape)
    ts = s0.new_zeros(N_PARAMS + n_g, n_l)
    for k in range(n_g - 1):
        tp[N_PARAMS + k, :, k] = 1.0
    ts[-1] = 1.0
    scale = torch.exp(s0)
    pixel_dirs = [[0, 1, 2], *([j] for j in range(3, N_PARAMS))] if base_one else [[j] for j in range(N_PARAMS)]
    k = len(pixel_dirs)
    tp, ts = tp[N_PARAMS - k:], ts[N_PARAMS - k:]  # (the light directions' rows after the pixel's k)
    p, dp = decode_directions(t0, m, pixel_dirs + [[]] * n_g)
    # the intensity inten0 · exp(s): its tangent by the chain rule, as forward mode forms it
    dp["light_pos"], dp["light_int"] = tp, (ts * scale)[..., None] * inten0
    r, dr = log_residual_points_jvp(p["normal"], pts, cam, pos0, inten0 * scale[:, None], p, log_obs,
                                    data.eps, dp, any_size=True, family=model)
    return r.reshape(n, -1), dr.reshape(k + n_g, n, -1)


def _light_step_basis(data: LevelData, ref_idx: list[int], position: bool, held: Tensor | None = None
                      ) -> tuple[Tensor, int]:
    """Orthonormal directions ``(L G, K)`` a light step may take, and how many of them move positions.

    ``G`` = 4 with ``position`` (offset xyz, log scale per light, light-major), else 1: positions
    that move no rig as a whole and none of the ``held (L,)`` lights (:func:`rig_free_directions`,
    ``3L − 7 − 3H``; the first columns) and log scales that keep the mean over ``ref_idx``
    (``L − 1``, or ``L`` when none of ``data.train_idx`` is one).
    """
    idx = data.train_idx
    n_l, n_g = len(idx), 4 if position else 1
    dev, f64 = data.points.device, torch.float64
    ref = torch.tensor([float(i in ref_idx) for i in idx], dtype=f64, device=dev)
    if bool(ref.any()):
        scales = torch.linalg.qr(ref[:, None], mode="complete")[0][:, 1:]  # ⟂ the reference mean
    else:
        scales = torch.eye(n_l, dtype=f64, device=dev)
    parts = []
    n_pos = 0
    if position:
        free = rig_free_directions(data.pos_stated[idx].to(f64), data.points.mean(0).to(f64), held)
        n_pos = free.shape[1]
        pos_part = torch.zeros(n_l, n_g, n_pos, dtype=f64, device=dev)
        pos_part[:, :3] = free.view(n_l, 3, -1)
        parts.append(pos_part.reshape(n_l * n_g, -1))
    scale_part = torch.zeros(n_l, n_g, scales.shape[1], dtype=f64, device=dev)
    scale_part[:, -1] = scales
    parts.append(scale_part.reshape(n_l * n_g, -1))
    return torch.cat(parts, 1), n_pos


def light_scale_step(residual: Tensor, idx: list[int], log_scale: Tensor, ref_idx: list[int],
                     prior_sigma: float = 0.1) -> Tensor:
    """One Gauss–Newton update of the per-light log intensity scales ``(L,)``.

    ``residual (P, len(idx) * 3)`` are the log residuals on lights ``idx``. A light whose
    stated intensity is off by a factor ``c`` shifts every bright pixel's log residual by
    ``log c``; the update is minus the per-light *median* residual over pixels (robust to
    the few badly fitted ones; the log residual's derivative w.r.t. the log scale is
    ``pred / (pred + ε) ≈ 1``), shrunk by a Gaussian prior of width ``prior_sigma`` on the
    log scale. One number per light against every pixel (65k at 256²): 1 % noise moves it
    by ~5e-5, so it cannot fit noise. The absolute scale is fixed by the capture's stated
    intensities: the mean log scale over ``ref_idx`` (the training lights) is kept at 0.
    """
    p = residual.shape[0]
    r = residual.reshape(p, len(idx), -1).mean(-1)  # (P, n) per pixel and light
    r = torch.where(torch.isfinite(r), r, torch.zeros_like(r))
    med = r.median(0).values  # (n,)
    noise = float((r - med).abs().median()) * 1.4826 + 1e-12  # robust std of one pixel's residual
    shrink = p / (p + (noise / prior_sigma) ** 2)
    out = log_scale.clone()
    out[idx] = shrink * (out[idx] - med)  # posterior mean: data optimum shrunk toward 0
    out[ref_idx] = out[ref_idx] - out[ref_idx].mean()
    return out.clamp(-0.3, 0.3)
