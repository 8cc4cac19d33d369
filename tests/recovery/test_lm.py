"""Levenberg-Marquardt pieces: the soft LM, the priors' residuals, conditional shifts, held refits, Newton steps, Jacobians."""

import json
import math
import time

import pytest
import torch

from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.recovery import (calibration, classes, engine, levels, lm, map_ops, params, priors, search,
                                smoothness_prior, soft_metal)
from torchbrdf.recovery.config import Settings

from tests.recovery.recovery_fixtures import recovery_at_polish
from torchbrdf.recovery.svbrdf import CHECKPOINT, RecoveryConfig, main, recover

CONTRACT_FILES = ["base_color.exr", "roughness.exr", "metallic.exr", "specular.exr", "normal.exr", "report.json"]


def test_soft_lm_judges_each_candidate_by_its_linearisation():
    """One residual evaluation per LM iteration: a candidate's cost comes with its Jacobian.

    The start and each iteration's candidates but the last are linearised (the accepted ones'
    normal equations are the next iteration's; a rejected pixel keeps its own), the last
    iteration's candidates are only costed; the returned cost is ``cost`` at the returned
    unknowns, the priors' residuals included, and a candidate with non-finite residuals costs
    +inf. Fails if a candidate were costed and then linearised anew, if the cost left out the
    prior, or if it were taken from the cleaned residuals.
    """

    gen = torch.Generator().manual_seed(4)
    n, m = 6, 15
    a = torch.randn(n, m, 8, generator=gen, dtype=torch.float64)
    a[..., :3] *= (torch.arange(m)[:, None] % 3 == torch.arange(3)).to(a.dtype)
    b = torch.randn(n, m, generator=gen, dtype=torch.float64)
    at = lambda v, r: v if r is None else v[r]  # noqa: E731
    fn = lambda x, r=None: torch.einsum("nmk,nk->nm", at(a, r), x) - at(b, r)  # noqa: E731

    def prior(x, r=None):  # 2 (m - 0.3): metallic pulled toward 0.3
        row = torch.zeros(x.shape[0], 1, 8, dtype=x.dtype)
        row[:, 0, 7] = 2.0
        return 2.0 * (x[:, 7:8] - 0.3), row

    counts = {"jvp": 0, "cost": 0}

    def cost(x, r=None):
        counts["cost"] += 1
        return (torch.cat((fn(x, r), prior(x, r)[0]), -1) ** 2).sum(-1, keepdim=True)

    def jvp(v, tg, r):
        counts["jvp"] += 1
        return levels.vmapped_jvp(lambda u: fn(u, r))(v, tg)

    x0 = torch.zeros(n, 8, dtype=torch.float64)
    x, c = lm.soft_lm(jvp, cost, x0, 4, prior=prior, tol=0.0)
    assert counts == {"jvp": 4, "cost": 1}
    counts["cost"] = 0
    assert torch.allclose(c, cost(x), rtol=1e-12)
    assert float(c.sum()) < float(cost(x0).sum())
    # a candidate whose residuals are not finite costs +inf and is refused: pixel 0's optimum
    # lies at x[3] = 2, behind a wall at 0.5
    b[0] = a[0] @ torch.tensor([0.0, 0, 0, 2, 0, 0, 0, 0], dtype=torch.float64)

    def walled(x, r=None):
        out = fn(x, r)
        first = (torch.arange(n) if r is None else r) == 0
        return torch.where((first & (x[:, 3] > 0.5))[:, None], float("nan"), out)

    x, c = lm.soft_lm(lambda v, tg, r: levels.vmapped_jvp(lambda u: walled(u, r))(v, tg),
                      lambda v, r=None: lm.pixel_cost(walled(v, r)), x0, 6, tol=0.0)
    assert bool(torch.isfinite(c).all()) and float(x[0, 3]) <= 0.5
    assert torch.equal(c, lm.pixel_cost(walled(x)))


def test_soft_lm_solves_a_linear_least_squares_problem_with_metallic_free_or_held():
    """The soft-metal stage's per-pixel LM reaches each pixel's least-squares solution.

    Residuals linear in the 8 unknowns (each base-colour unknown acting on its own channel's
    residuals, every third: :func:`fit_jacobian`'s premise); with ``fix_metal`` the last
    unknown keeps its value (no tangent) and the other 7 solve the reduced problem. With
    ``tol`` a pixel whose accepted step gained less than that fraction of its cost stops (the
    others go on, evaluated on their rows alone); on these linear problems its cost is then
    within about that fraction of the optimum's.
    A pixel whose cost starts infinite does not stop on its first finite one. Per-pixel
    ``held`` unknowns keep their start and the others solve the reduced problem.
    """

    gen = torch.Generator().manual_seed(3)
    n, m = 5, 21
    a = torch.randn(n, m, 8, generator=gen, dtype=torch.float64)
    a[..., :3] *= (torch.arange(m)[:, None] % 3 == torch.arange(3)).to(a.dtype)  # channel c: base c only
    b = torch.randn(n, m, generator=gen, dtype=torch.float64)
    at = lambda v, r: v if r is None else v[r]  # noqa: E731
    fn = lambda x, r=None: torch.einsum("nmk,nk->nm", at(a, r), x) - at(b, r)  # noqa: E731

    def cost(x, r=None):
        return (fn(x, r) ** 2).sum(-1, keepdim=True)

    def jvp(f):  # the residuals and their derivatives along K directions, as LevelData.residual_jvp
        return lambda v, tg, r: levels.vmapped_jvp(lambda u: f(u, r))(v, tg)

    x0 = torch.zeros(n, 8, dtype=torch.float64)
    x0[:, 7] = 0.5
    x, c = lm.soft_lm(jvp(fn), cost, x0, 30, fix_metal=True, tol=0.0)
    want = torch.linalg.lstsq(a[..., :7], (b - a[..., 7] * 0.5)[..., None]).solution[..., 0]
    assert torch.equal(x[:, 7], x0[:, 7])
    assert torch.allclose(x[:, :7], want, atol=1e-6)
    assert torch.allclose(c, cost(x))
    # metallic free: the full solution, its last unknown clamped to [0, 1] by the projected steps
    x, _ = lm.soft_lm(jvp(fn), cost, x0, 60, tol=0.0)
    full = torch.linalg.lstsq(a, b[..., None]).solution[..., 0]
    inside = (full[:, 7] > 0) & (full[:, 7] < 1)
    assert torch.allclose(x[inside], full[inside], atol=1e-5)
    assert bool(((x[:, 7] >= 0) & (x[:, 7] <= 1)).all())
    # converged pixels leave: each pixel's cost within 1 % of its optimum, and the calls on a
    # subset of the rows (some pixels stop before others) give each pixel its own data
    # (two pixels start near their optimum, three far: the clamped steps take those longer)
    calls: list = []
    near = torch.tensor([0.01, 0.01, 20.0, 20.0, 20.0], dtype=torch.float64)[:, None]
    start = torch.cat((want + near, x0[:, 7:]), -1)
    logged = lambda v, r=None: calls.append(r) or fn(v, r)  # noqa: E731
    x, c = lm.soft_lm(jvp(logged), cost, start, 60, fix_metal=True, tol=1e-2)
    best = cost(torch.cat((want, x0[:, 7:]), -1))
    assert bool((c <= best * 1.02 + 1e-9).all()) and torch.allclose(c, cost(x))
    assert any(r is not None and 0 < len(r) < n for r in calls)
    # priors given with their Jacobian (not part of fn): the augmented problem's solution, more
    # rows per pixel — one on metallic alone, sqrt(s) (m - t), and one coupling an unknown to
    # metallic, sqrt(s) (x0 - 0.3 - 0.5 m) (as the blend line couples base colour and metallic)
    s, t = 4.0, torch.full((n, 1), 0.4, dtype=torch.float64)
    row = torch.zeros(n, 2, 8, dtype=torch.float64)
    row[:, 0, 7] = math.sqrt(s)
    row[:, 1, 0], row[:, 1, 7] = math.sqrt(s), -0.5 * math.sqrt(s)
    rhs = torch.cat((b, math.sqrt(s) * t, torch.full_like(t, 0.3 * math.sqrt(s))), 1)

    def prior(v, r=None):
        return torch.einsum("nkj,nj->nk", at(row, r), v) - at(rhs[:, m:], r), at(row, r)

    def cost_p(v, r=None):
        return cost(v, r) + (prior(v, r)[0] ** 2).sum(-1, keepdim=True)

    x, _ = lm.soft_lm(jvp(fn), cost_p, x0, 60, prior=prior, tol=0.0)
    aug = torch.linalg.lstsq(torch.cat((a, row), 1), rhs[..., None]).solution[..., 0]
    inside = (aug[:, 7] > 0) & (aug[:, 7] < 1)
    assert bool(inside.any()) and not torch.allclose(aug[inside], full[inside], atol=1e-3)
    assert torch.allclose(x[inside], aug[inside], atol=1e-5)
    # ... also when the converged pixels leave (the prior evaluated on row subsets)
    calls.clear()
    logged_p = lambda v, r=None: calls.append(r) or prior(v, r)  # noqa: E731
    x, c = lm.soft_lm(jvp(fn), cost_p, torch.cat((aug[:, :7] + near, x0[:, 7:]), -1), 60, prior=logged_p,
                      tol=1e-2)
    assert any(r is not None and 0 < len(r) < n for r in calls)
    # (where the optimum's metallic is in [0, 1]: elsewhere the clamped fit cannot reach it)
    assert bool((c[inside] <= cost_p(aug)[inside] * 1.02 + 1e-9).all()) and torch.allclose(c, cost_p(x))
    # a cost that starts infinite (a residual undefined at the start, NaN): its first finite
    # step is not convergence
    def fn_inf(v, r=None):  # its first residual undefined while the first unknown is below -5
        f = fn(v, r)
        return torch.cat((torch.where(v[:, :1] < -5.0, float("nan"), f[:, :1]), f[:, 1:]), -1)

    cost_inf = lambda v, r=None: lm.pixel_cost(fn_inf(v, r))  # noqa: E731
    start_inf = torch.cat((want, x0[:, 7:]), -1)
    start_inf[:, 0] = -6.0
    x, c = lm.soft_lm(jvp(fn_inf), cost_inf, start_inf, 60, fix_metal=True, tol=1e-2)
    assert bool((c <= best * 1.02 + 1e-9).all()), (c, best)
    # ... and with metallic held, the prior's other columns still act (the coupled row)
    x, _ = lm.soft_lm(jvp(fn), cost_p, x0, 30, fix_metal=True, prior=prior, tol=0.0)
    rhs_h = rhs - torch.cat((a, row), 1)[..., 7] * 0.5
    held = torch.linalg.lstsq(torch.cat((a, row), 1)[..., :7], rhs_h[..., None]).solution[..., 0]
    assert torch.allclose(x[:, :7], held, atol=1e-6)
    # per-pixel held unknowns (``held``, as the glossy/rough tie holds roughness): a held entry
    # keeps its start exactly and the others solve the reduced problem, also when converged
    # pixels leave and the mask is taken on their rows
    hold = torch.zeros(n, 8, dtype=torch.bool)
    for i in range(n - 1):  # the last pixel holds nothing
        hold[i, 3 + i % 4] = True
    calls.clear()
    x, _ = lm.soft_lm(jvp(logged), cost, start, 60, fix_metal=True, tol=1e-2, held=hold)
    assert any(r is not None and 0 < len(r) < n for r in calls)
    assert torch.equal(x[hold], start[hold])
    x, _ = lm.soft_lm(jvp(fn), cost, start, 60, fix_metal=True, tol=0.0, held=hold)
    assert torch.equal(x[hold], start[hold])
    for i in range(n):
        f = (~hold[i, :7]).nonzero()[:, 0]
        rhs_i = b[i] - a[i, :, 7] * 0.5 - a[i][:, hold[i]] @ start[i][hold[i]]
        want_i = torch.linalg.lstsq(a[i][:, f], rhs_i[:, None]).solution[:, 0]
        assert torch.allclose(x[i, f], want_i, atol=1e-6), i


def test_soft_prior_residuals_and_jacobian():
    """The soft-metal priors' residuals, and their Jacobian against ``torch.func.jacrev``.

    The double well is 0 at metallic 0 and 1; the pull is 0 at its target; the blend line is 0
    where the base colour is the blend of its two ends at the pixel's own metallic, and moves by
    −√w (metal − dielectric) per unit of metallic. Per-pixel weights too.
    """

    gen = torch.Generator().manual_seed(4)
    n = 6
    x = torch.randn(n, 8, generator=gen, dtype=torch.float64)
    x[:, 7] = torch.rand(n, generator=gen, dtype=torch.float64)
    d = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.5
    e = 0.5 + torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.5
    target = torch.rand(n, 1, generator=gen, dtype=torch.float64)
    smooth = torch.rand(n, 1, generator=gen, dtype=torch.float64) + 0.5
    lw = torch.rand(n, 1, generator=gen, dtype=torch.float64) + 1.0
    res, jac = soft_metal.soft_prior(x, 3.0, target, smooth, (d, e), lw)
    assert res.shape == (n, 5) and jac.shape == (n, 5, 8)
    want = torch.func.vmap(torch.func.jacrev(
        lambda xi, ti, si, di, ei, wi: soft_metal.soft_prior(xi[None], 3.0, ti[None], si[None], (di[None], ei[None]),
                                                     wi[None])[0][0]))(x, target, smooth, d, e, lw)
    assert torch.allclose(jac, want, atol=1e-12)
    m = x[:, 7:8]
    assert torch.allclose(res[:, 0:1], math.sqrt(3.0) * m * (1 - m))
    assert torch.allclose(res[:, 1:2], smooth.sqrt() * (m - target))
    on_line = x.clone()
    on_line[:, 0:3] = torch.logit(d + m * (e - d))
    r_on = soft_metal.soft_prior(on_line, 3.0, None, 0.0, (d, e), lw)[0]
    assert r_on.shape == (n, 4) and float(r_on[:, 1:].abs().max()) < 1e-12
    moved = on_line.clone()
    moved[:, 7] += 0.01
    r_mv = soft_metal.soft_prior(moved, 3.0, None, 0.0, (d, e), lw)[0]
    assert torch.allclose(r_mv[:, 1:], -lw.sqrt() * (e - d) * 0.01, atol=1e-12)
    # a float weight is the same as a constant per-pixel one; no line, no line rows
    r_f = soft_metal.soft_prior(x, 3.0, target, 2.0, (d, e), 1.5)[0]
    r_t = soft_metal.soft_prior(x, 3.0, target, torch.full_like(m, 2.0), (d, e), torch.full_like(m, 1.5))[0]
    assert torch.allclose(r_f, r_t) and soft_metal.soft_prior(x, 3.0)[0].shape == (n, 1)


def _silver_capture(size=8, lights=8):
    """A noise-free flat silver metal (F0 0.9 / 0.85 / 0.8, roughness 0.25), float64."""
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import light_layout, render_capture

    maps = _silver_maps(size)
    pos, inten = light_layout(lights)
    imgs = render_capture(maps, (pos, inten), backend="compact").double()
    camera = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    return Capture(images=imgs, light_positions=pos.double(), light_intensities=inten.double(),
                   camera_position=camera, width=size, height=size,
                   files=tuple(f"{k}.exr" for k in range(len(pos))))


def _silver_maps(size):
    return {"base_color": torch.tensor([0.9, 0.85, 0.8])[:, None, None].expand(3, size, size),
            "roughness": torch.full((1, size, size), 0.25), "metallic": torch.ones(1, size, size),
            "specular": torch.full((1, size, size), 0.5),
            "normal": torch.tensor([0.0, 0.0, 1.0])[:, None, None].expand(3, size, size)}


def _silver_level(size=8, lights=8):
    """:func:`_silver_capture` at one level: ``(LevelData, theta (P, 7) at the truth, metal (P, 1))``."""

    cap = _silver_capture(size, lights)
    data = levels.LevelData(cap, size, list(range(len(cap))), float(0.01 * cap.images.mean()))
    p = {k: v.reshape(v.shape[0], -1).T.contiguous().double() for k, v in _silver_maps(size).items()}
    metal = p.pop("metallic")
    return data, params.encode(p), metal


def test_conditional_shift_keeps_a_metal_on_its_f0_roughness_valley():
    """After the non-local fusion moves a metal's F0, its other unknowns follow it.

    Without ``conditional_shift`` the pixel leaves the F0–roughness valley of the GGX tail and
    no longer fits its images (dusty_metal 3: 8645 such pixels at 10–100× the noise). The shift
    is the linear least-squares response of the free unknowns, checked against a dense solve,
    and it takes back most of the cost the F0 move alone adds.
    """

    size = 8
    data, theta, metal = _silver_level(size)
    idx = data.train_idx
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    delta = torch.zeros_like(theta)
    delta[:, 0:3] = 0.4  # F0 0.9 -> 0.93: what the fusion does to a dark tail pixel
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    moved[5] = False  # a pixel the fusion leaves alone: no shift at all
    moved[9, 0:3] = False  # one whose roughness was moved instead
    moved[9, 4] = True
    delta[9] = 0.0
    delta[9, 4] = 0.05  # small: the F0 response is ~16x (the valley), inside the ±3 clamp
    shift = lm.conditional_shift(jtj, delta, moved)
    assert torch.equal(lm.conditional_shift(jtj, delta, moved, chunk=7), shift)  # blocks change nothing
    assert torch.equal(shift[moved], torch.zeros_like(shift[moved]))
    assert torch.equal(shift[5], torch.zeros_like(shift[5]))
    # Against a dense least-squares solve of the linearised residuals, pixel by pixel.
    for k in (0, 9, 27, 63):
        fn = lambda t: data.residual(t, metal[k:k + 1], idx, "principled", rows=slice(k, k + 1))[0]  # noqa: E731
        j = torch.func.jacfwd(fn)(theta[k:k + 1])[:, 0]  # (M, 7)
        free = ~moved[k]
        jo = j[:, free]
        rhs = -(j[:, ~free] @ delta[k, ~free])
        keep = jo.abs().sum(0) > 0  # a metal's specular does not reach the image
        sol = torch.linalg.lstsq(jo[:, keep], rhs[:, None]).solution[:, 0]
        assert torch.allclose(shift[k, free][keep], sol, rtol=1e-4, atol=1e-6), (k, shift[k], sol)

    def cost(t):
        r = data.residual(t, metal, idx, "principled")
        return float((r * r).sum())

    alone = cost(theta + delta)
    followed = cost(theta + delta + shift)
    assert float(shift[9, 0:3].abs().max()) > 0  # F0 follows a moved roughness
    assert cost(theta) < 1e-8 and followed < 0.2 * alone, (alone, followed)


def test_a_held_refit_takes_the_free_unknowns_to_their_conditional_optimum():
    """``refit_pixels(held=...)`` takes the free unknowns to the data optimum given the held.

    The held unknowns keep their start exactly; the others go further than the linear
    response where the valley bends.

    This is how a fused metal's roughness and normal follow its fused F0 when
    ``conditional_shift`` falls short (rusted_metal 68's corners: 10³–10⁴ noise variances).
    """

    data, theta, metal = _silver_level()
    idx, n = data.train_idx, theta.shape[0]
    rows = torch.arange(n)
    held = torch.zeros(n, 7, dtype=torch.bool)
    held[:, 0:3] = True
    # F0 0.9 -> 0.96 (held), roughness left at the truth: off the valley of the moved F0
    start = theta.clone()
    start[:, 0:3] += 1.0

    def cost(t):
        return lm.pixel_cost(data.residual(t, metal, idx, "principled"))[:, 0]

    out, c = lm.refit_pixels(data, theta, metal, rows, [start], idx, "principled", iters=10, held=held)
    assert torch.equal(out[:, 0:3], start[:, 0:3])  # held exactly
    assert torch.allclose(c[:, 0], cost(out))
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    linear = start + lm.conditional_shift(jtj, start - theta, held)
    # the F0 rise is paid back by a smoother lobe; the refit fits better than the linear
    # response from the truth, and far better than the move alone
    assert float((out[:, 4] - theta[:, 4]).mean()) < -0.02
    assert float(cost(out).sum()) < 0.5 * float(cost(linear).sum()) < 0.5 * float(cost(start).sum())
    free = lm.refit_pixels(data, theta, metal, rows, [start], idx, "principled", iters=10)[0]
    assert float((free[:, 0:3] - start[:, 0:3]).abs().max()) > 0.1  # without held, F0 moves


def test_fusion_averages_each_metals_own_data_optimum_not_where_its_fit_stopped():
    """With the data gradients, the non-local F0 average takes each pixel at its own optimum.

    ``nonlocal_prior(jtr=...)``: where one Gauss–Newton step predicts it.

    A metal fit left part-way along the F0–roughness valley (its F0 dark, its roughness
    compensating, as from the dark metal start) otherwise drags the average toward where it
    stopped: rusted_metal's bright silver came out 1–2 % dark.
    """
    import types


    size = 8
    data, theta, metal = _silver_level(size)
    idx = data.train_idx
    _, jtj, _ = lm.gauss_newton(data, theta, metal, idx, "principled")
    # Half the pixels stopped along the valley: F0 darker by 0.3 logit, the others following.
    stopped = (torch.arange(theta.shape[0]) % 2 == 0)[:, None]
    delta = torch.zeros_like(theta)
    delta[:, 0:3] = -0.3
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    off = theta + delta + lm.conditional_shift(jtj, delta, moved)
    off = torch.where(stopped, off, theta)
    _, jtj_off, jtr_off = lm.gauss_newton(data, off, metal, idx, "principled")
    cfg = Settings(nonlocal_sigma=1000.0)  # one flat window
    lvl = types.SimpleNamespace(size=size, train_idx=idx)
    # (no fit weights: noise-free, the stopped pixels would weigh ~0 against the exact ones)
    _, m_stop, _ = priors.nonlocal_prior(lvl, off, metal, cfg, jtj_off)
    _, m_opt, _ = priors.nonlocal_prior(lvl, off, metal, cfg, jtj_off, jtr=jtr_off)
    err_stop = float((m_stop[:, 0:3] - theta[:, 0:3]).abs().mean())
    err_opt = float((m_opt[:, 0:3] - theta[:, 0:3]).abs().mean())
    assert err_stop > 0.05  # the stopped pixels' share of the weights × 0.3
    assert err_opt < 0.2 * err_stop, (err_stop, err_opt)
    # the Newton step itself: zero at the truth, and it leaves held unknowns alone
    assert float(lm.newton_step(jtj, torch.zeros_like(theta)).abs().max()) == 0.0
    g = torch.randn(theta.shape, generator=torch.Generator().manual_seed(0), dtype=theta.dtype)
    held = torch.zeros_like(moved)
    held[:, 4] = True
    assert float(lm.newton_step(jtj, g, held)[:, 4].abs().max()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_newton_step_solves_the_damped_normal_equations_on_the_free_unknowns(dtype):
    """``newton_step`` is ``−(H_ff + diag(1e-6 diag(H_ff) + 1e-9))⁻¹ g_f``, 0 on the held unknowns.

    An independent float64 solve per pixel, with and without held unknowns (a singular ``H``
    whose held direction is the null one included); neither input is written to (the float64
    algebra works in place on copies, and a float64 input is no copy by ``.double()``).
    """

    gen = torch.Generator().manual_seed(3)
    P = 40
    j = torch.randn(P, 7, 12, generator=gen, dtype=torch.float64)
    jtj = (j @ j.transpose(1, 2)).to(dtype)
    jtj[:5, 4, :] = 0.0  # singular along roughness: held below, so the free block is regular
    jtj[:5, :, 4] = 0.0
    g = (0.1 * torch.randn(P, 7, generator=gen, dtype=torch.float64)).to(dtype)
    held = torch.zeros(P, 7, dtype=torch.bool)
    held[:5, 4] = True
    held[10:20, 0:3] = True
    jtj0, g0 = jtj.clone(), g.clone()

    def reference(h_all, g_all, hd):
        out = torch.zeros(P, 7, dtype=torch.float64)
        for p in range(P):
            f = ~hd[p]
            h = h_all[p].double()[f][:, f]
            h = h + torch.diag(1e-6 * torch.diagonal(h) + 1e-9)
            out[p, f] = torch.linalg.solve(h, -g_all[p].double()[f]).clamp(-3, 3)
        return out

    tol = 1e-9 if dtype == torch.float64 else 1e-5
    no_held = torch.zeros_like(held)
    for hd, arg in ((no_held, None), (held, held)):
        step = lm.newton_step(jtj[5:] if arg is None else jtj, g[5:] if arg is None else g,
                             None if arg is None else arg)
        want = reference(jtj, g, hd)[5:] if arg is None else reference(jtj, g, hd)
        assert step.dtype == dtype
        torch.testing.assert_close(step.double(), want, rtol=tol, atol=tol)
    assert torch.equal(jtj, jtj0) and torch.equal(g, g0)  # the inputs are the caller's, unchanged


def test_fusion_rounds_refine_the_average_without_compounding_the_pull():
    """``fuse_rounds``: every round combines the same own value with its round's average.

    A pixel's pull toward the average stays ``κ / (info + κ)`` however many rounds. A first
    version fused each round from the last one's fused value: three rounds pulled a pixel
    ``1 − (1 − s)³`` of the way, a hidden multiplier on ``prior_nonlocal_base``.
    """

    cap = _silver_capture()
    data, theta, metal = _silver_level()
    _, jtj, _ = lm.gauss_newton(data, theta, metal, data.train_idx, "principled")
    delta = torch.zeros_like(theta)
    gen = torch.Generator().manual_seed(1)
    delta[:, 0:3] = 0.3 * torch.randn(theta.shape[0], 1, generator=gen, dtype=theta.dtype)  # F0 spread
    moved = torch.zeros_like(theta, dtype=torch.bool)
    moved[:, 0:3] = True
    start = theta + delta + lm.conditional_shift(jtj, delta, moved)  # each on its own valley
    info = lm.marginal_information(data, start, metal, "principled")[:, 0]
    well = info > info.median()  # pulled only part of the way (info ≫ κ)
    pull = {}
    for rounds in (1, 3):
        cfg = Settings(soft_metal=False, fuse_rounds=rounds, nonlocal_sigma=1000.0)
        rec = engine.Recovery(cap, cfg, log=lambda *a: None)
        rec.init_state()
        st = rec.state
        st["stage"], st["theta"], st["metal"] = len(rec.plan) - 1, [start.clone()], metal
        st["lam"] = [torch.full_like(metal, 1e-2)]
        rec.end_stage()
        pull[rounds] = float((st["theta"][0][well, 0:3] - start[well, 0:3]).abs().mean())
    assert pull[1] > 1e-3  # the fusion does move them
    assert pull[3] < 1.3 * pull[1], pull  # compounding: about 2.5x here


@pytest.mark.parametrize("model", ["principled", "svbrdf_ggx"])
@pytest.mark.parametrize("n_t", [7, 8])
def test_fit_jacobian_is_the_per_unknown_forward_mode_jacobian(tiny, n_t, model):
    """``fit_jacobian`` equals one forward-mode pass per unknown, column by column.

    The base colour's three columns come from one pass; checked for the seven map unknowns and
    with metallic as an eighth (the soft-metal fit's). Fails if a base-colour column took
    another channel's residuals, or if a channel leaked into another (a tint would couple them);
    for both of the fit's models.
    """
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.levels import LevelData, vmapped_jvp
    from torchbrdf.recovery.lm import fit_jacobian

    cap = load_capture(tiny)
    data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(3)
    x = torch.randn(32 * 32, 8, generator=g) * 0.4
    x[:, 7] = torch.rand(32 * 32, generator=g)  # a fractional metallic

    def fn(v):
        return data.residual(v[:, :7], v[:, 7:8] if n_t == 8 else x[:, 7:8], data.train_idx, model)

    xs = x if n_t == 8 else x[:, :7]
    for jvp in (lambda v, tg: data.residual_jvp(v, x[:, 7:8], data.train_idx, model, tg), vmapped_jvp(fn)):
        r, jac = fit_jacobian(jvp, xs, n_t)
        assert jac.shape == (32 * 32, n_t, 3 * len(data.train_idx))
        assert torch.allclose(r, fn(xs), rtol=1e-6, atol=1e-6)
        for k in range(n_t):
            col = torch.func.jvp(fn, (xs,), (torch.eye(xs.shape[1])[k].expand_as(xs),))[1]
            assert torch.allclose(jac[:, k], col, rtol=1e-5, atol=1e-6), k


def test_fit_jacobian_benchmark_times_both_ways(tiny):
    """``python -m torchbrdf.bench.jvp --fit``: the direct and the vmapped Jacobian, side by side."""
    from torchbrdf.bench.jvp import fit_jacobian_times

    threads = torch.get_num_threads()
    res = fit_jacobian_times(sizes=(16, 64), threads=1, reps=1, capture=str(tiny))
    assert set(res) == {(16, "direct"), (16, "vmap"), (64, "direct"), (64, "vmap")}
    assert all(t > 0 for t in res.values())
    assert torch.get_num_threads() == threads  # restored


def test_light_step_bench_alternates_the_passes_and_restores_them(tiny):
    """``python -m torchbrdf.bench.jvp --light-step``: passes of 8 and 12 tangents, each timed
    ``reps`` times, CPU and wall; the thread count and the pass size are restored."""
    from torchbrdf.bench.jvp import light_step_times
    from torchbrdf.kernels import c_runner

    threads, per_pass = torch.get_num_threads(), c_runner.TANGENTS_PER_PASS
    res = light_step_times(threads=1, reps=2, capture=str(tiny))
    assert set(res) == {8, 12}
    assert all(len(row[k]) == 2 and min(row[k]) > 0 for row in res.values() for k in ("cpu", "wall"))
    assert torch.get_num_threads() == threads and c_runner.TANGENTS_PER_PASS == per_pass


def test_light_step_bench_reverses_the_order_and_prints_the_pixels_used(tiny, monkeypatch, capsys):
    """Neither pass size always runs first (a fixed order biases a loaded machine's timings), and
    the printed count is the light step's strided pixels of this capture (32², all used)."""
    from torchbrdf.bench.jvp import light_step_times
    from torchbrdf.kernels import c_runner
    from torchbrdf.recovery import calibration

    import functools

    order = []

    @functools.wraps(calibration.light_joint_step)  # (its signature: the bench reads max_pixels)
    def step(*args, **kwargs):
        order.append(c_runner.TANGENTS_PER_PASS)

    monkeypatch.setattr(calibration, "light_joint_step", step)
    light_step_times(threads=1, reps=4, capture=str(tiny))
    assert order[2:] == [8, 12, 12, 8, 8, 12, 12, 8]  # after the warm-up of each
    assert "1024 pixels (1024 used)" in capsys.readouterr().out


def test_blur_is_the_truncated_normalised_gaussian():
    """``blur`` is the truncated, normalised Gaussian, against a direct double sum.

    Σ over the pixels within 3σ (and the map) of g(dx) g(dy) x, g the Gaussian normalised over
    its 2r + 1 taps, zero outside the map.
    """
    from torchbrdf.recovery.map_ops import blur

    size = 9
    g = torch.Generator().manual_seed(0)
    x = torch.rand(size * size, 2, generator=g, dtype=torch.float64)
    img = x.T.reshape(2, size, size)
    for sigma in (0.8, 2.0, 5.0):  # r = 2, 6 and (capped at the map) 8
        r = int(min(3 * sigma, size - 1))
        taps = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma) ** 2)
        k = lambda d: math.exp(-0.5 * (d / sigma) ** 2) / float(taps.sum()) if abs(d) <= r else 0.0  # noqa: E731
        want = torch.zeros(2, size, size, dtype=torch.float64)
        for i in range(size):
            for j in range(size):
                for a in range(size):
                    for b in range(size):
                        want[:, i, j] += k(a - i) * k(b - j) * img[:, a, b]
        got = blur(x, size, sigma).T.reshape(2, size, size)
        assert torch.allclose(got, want, atol=1e-12), sigma


def test_the_polish_stage_first_step_reuses_the_ties_linearisation(tiny):
    """The polish stage's first LM step is handed the Gauss–Newton pass of its F0 tie.

    Made at the stage's start and re-linearised where propagation and the normal search moved
    pixels since: equal to the step's own pass (so the step is the same), handed on once only.
    """

    rec, _ = recovery_at_polish(tiny, RecoveryConfig(seed=0, soft_metal=False))
    assert rec._stage_gn is not None
    th0 = rec._stage_gn[0]
    seen = []
    step = engine.lm_step

    def spy(data, theta, metal, lam, cfg_, lr, extra=None, unary=None, gn=None, residual=True):
        own = lm.gauss_newton(data, theta, metal, data.train_idx, cfg_.model)
        seen.append((gn, own, bool((theta != th0).any())))
        return step(data, theta, metal, lam, cfg_, lr, extra, unary, gn, residual)

    engine.lm_step = spy
    try:
        with torch.no_grad():
            rec.tick()
            rec.tick()
    finally:
        engine.lm_step = step
    (gn, own, moved), (gn2, _, _) = seen
    assert moved  # propagation / normal search moved some pixels: they were re-linearised
    assert gn is not None and gn2 is None and rec._stage_gn is None
    for a, b in zip(gn, own):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


def test_lm_step_hands_on_the_summed_squares_of_the_residuals_it_returns():
    """``extra["data_cost"]`` is each pixel's summed squared ``extra["residual"]`` at the returned
    unknowns, bit for bit (the fit loss takes it instead of summing the residuals again), for
    pixels whose step was taken and pixels whose step was rejected; ``residual=False`` leaves
    the residuals out and changes nothing else."""
    from tests.recovery.recovery_fixtures import flat_level

    data, theta, metal = flat_level(size=12)
    gen = torch.Generator().manual_seed(5)
    theta = theta + 0.3 * torch.randn(theta.shape, generator=gen)
    theta[::7, 4] += 6.0  # far off in roughness: some steps are rejected
    lam = torch.full((theta.shape[0], 1), 1e-2)
    extra, lean = {}, {}
    out = lm.lm_step(data, theta, metal, lam, Settings(), 1.0, extra)
    lean_out = lm.lm_step(data, theta, metal, lam, Settings(), 1.0, lean, residual=False)
    moved = (out[0] != theta).any(-1)
    assert bool(moved.any()) and not bool(moved.all())
    r = extra["residual"]
    assert torch.equal(extra["data_cost"], (r * r).sum(-1, keepdim=True))
    assert "residual" not in lean and torch.equal(lean["data_cost"], extra["data_cost"])
    assert all(torch.equal(a, b) for a, b in zip(out[:3], lean_out[:3])) and out[3] == lean_out[3]
