"""Light calibration (scale, position, joint steps), the F0 ties and pixel subsets."""

import json
import math
import time

import pytest
import torch

from torchbrdf.brdf import capture_residual
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.kernels import build
from torchbrdf.recovery import (calibration, classes, engine, levels, lm, map_ops, params, priors, search,
                                smoothness_prior, soft_metal)
from torchbrdf.recovery.config import Settings

from tests.recovery.recovery_fixtures import flat_level, recovery_at_polish
from torchbrdf.recovery.svbrdf import CHECKPOINT, RecoveryConfig, main, recover

CONTRACT_FILES = ["base_color.exr", "roughness.exr", "metallic.exr", "specular.exr", "normal.exr", "report.json"]


def test_light_scale_step_recovers_per_light_calibration_error():
    """Issue 13: images taken with intensities off by a few percent per light; the per-light
    scale step finds the factors (up to the fixed overall scale) from the residuals at the
    true maps, and a capture without error gives scales of exactly-ish 1."""
    data, theta, metal = flat_level()
    n_l = data.pos.shape[0]
    true = 0.03 * torch.randn(n_l, generator=torch.Generator().manual_seed(3))
    true = true - true.mean()
    data.log_obs = data.log_obs + true[:, None, None] * data.obs / (data.obs + data.eps)  # images × e^true (bright pixels)
    idx = list(range(n_l))
    est = torch.zeros(n_l)
    for _ in range(3):
        data.set_light_scale(est)
        est = calibration.light_scale_step(data.residual(theta, metal, idx), idx, est, idx)
    assert torch.allclose(est, true, atol=2e-3)
    clean, _, _ = flat_level()
    r = clean.residual(theta, metal, idx)
    assert float(calibration.light_scale_step(r, idx, torch.zeros(n_l), idx).abs().max()) < 1e-4


def test_light_position_step_finds_a_moved_light():
    """Issue 13: a light 1.5 cm from where capture.json says; the position step finds the offset."""
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = flat_level(size=24)
    n_l = data.pos.shape[0]
    true = torch.zeros(n_l, 3)
    true[2] = torch.tensor([0.015, -0.01, 0.005])
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true, data.inten_stated), backend="compact")
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    off = torch.zeros(n_l, 3)
    for _ in range(4):
        data.set_light_offset(off)
        off = calibration.light_position_step(data, theta, metal, off, "principled", stride=1)
    assert torch.allclose(off, true, atol=2e-3)


def test_light_beside_the_camera_keeps_its_stated_position():
    """With ``at_camera=False`` the flash's position is held as capture.json states it.

    It is the lights' least determined position and took up what the two-hypothesis maps had
    not yet fitted (docs/recovery.md: the recovery holds it in that stage); by
    default both steps move it toward where it is.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = flat_level(size=24)
    n_l = data.pos.shape[0]
    true = torch.zeros(n_l, 3)
    true[-1] = torch.tensor([0.01, -0.01, -0.02])  # the flash (last light of light_layout)
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true, data.inten_stated), backend="compact")
    data.log_obs = torch.log(torch.clamp(img.permute(0, 2, 3, 1).reshape(n_l, -1, 3) + data.eps,
                                         min=0.5 * data.eps))
    zero, idx = torch.zeros(n_l, 3), list(range(n_l))
    held = calibration.light_position_step(data, theta, metal, zero, "principled", stride=1, at_camera=False)
    moved = calibration.light_position_step(data, theta, metal, zero, "principled", stride=1)
    assert torch.equal(held[-1], torch.zeros(3))
    assert float(torch.nn.functional.cosine_similarity(moved[-1], true[-1], dim=0)) > 0.5
    _, held = calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), zero, idx, "principled",
                                 at_camera=False)
    _, moved = calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), zero, idx, "principled")
    assert torch.equal(held[-1], torch.zeros(3)) and float(moved[-1].norm()) > 2e-3


def test_light_position_step_is_not_moved_by_pixels_the_maps_do_not_fit():
    """Lights where capture.json says, 1 % noise, and 4 % of the pixels rendered from another
    material (a front the maps have not fitted yet): the offsets stay within 5 mm (the noise
    alone moves them ~2 mm on these 576 pixels).

    Least squares let those pixels' residuals pull the lights to the 5 cm clamp.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = flat_level(size=24)
    n_l = data.pos.shape[0]
    g = torch.Generator().manual_seed(3)
    other = theta.clone()
    wrong = torch.rand(theta.shape[0], generator=g) < 0.04
    other[wrong, 0:3] += 2.0  # a much brighter base colour there
    other[wrong, 4] -= 2.0  # and glossier
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(other, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated, data.inten_stated), backend="compact")
    img = img * (1 + 0.01 * torch.randn(img.shape, generator=g, dtype=img.dtype))
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    off = torch.zeros(n_l, 3)
    for _ in range(4):
        data.set_light_offset(off)
        off = calibration.light_position_step(data, theta, metal, off, "principled", stride=1)
    assert float(off.abs().max()) < 5e-3, off


def test_light_joint_step_finds_light_errors_the_maps_absorb():
    """A moved and a brightened light are found although the maps are fitted alongside.

    One light 1.9 cm from where capture.json says and another 6 % brighter: six rounds of (map
    LM step, joint light step) find both within 4 mm (up to a move of the whole rig) and
    0.2 %. The joint step eliminates each pixel's unknowns (the maps would follow a light's
    move); stepping the lights with the maps held fixed sees only what the maps have not
    already absorbed, and after the same six rounds is still ~1.2 cm and 0.7 % off here.
    """
    from torchbrdf.capture.synthetic import render_capture

    data, theta, metal = flat_level(size=24)
    n_l = data.pos.shape[0]
    true_off = torch.zeros(n_l, 3)
    true_off[2] = torch.tensor([0.015, -0.01, 0.005])
    true_s = torch.zeros(n_l)
    true_s[4] = 0.06
    true_s = true_s - true_s.mean()  # the overall scale is the stated one
    maps = {k: v.T.reshape(-1, 24, 24) for k, v in params.decode(theta, metal).items()}
    with torch.no_grad():
        img = render_capture(maps, (data.pos_stated + true_off, data.inten_stated * true_s.exp()[:, None]),
                             backend="compact")
    obs = img.permute(0, 2, 3, 1).reshape(n_l, -1, 3)
    data.log_obs = torch.log(torch.clamp(obs + data.eps, min=0.5 * data.eps))
    idx = list(range(n_l))
    lam = torch.full((theta.shape[0], 1), 1e-3)
    th, s, off = theta.clone(), torch.zeros(n_l), torch.zeros(n_l, 3)
    for _ in range(6):
        th, lam, _, _ = lm.lm_step(data, th, metal, lam, Settings(), 1.0)
        s, off = calibration.light_joint_step(data, th, metal, s, off, idx, "principled")
        data.set_light_scale(s)
        data.set_light_offset(off)
    # What the images tell apart from a move of the whole rig (which the maps absorb: the
    # rig's placement is the stated one) is found; the rig's own moves are not made.
    free = calibration.rig_free_directions(data.pos_stated, data.points.mean(0))
    seen = (free @ (free.T @ true_off.reshape(-1))).reshape(n_l, 3)
    assert float((off - seen).norm(dim=1).max()) < 4e-3, off
    assert float((free @ (free.T @ off.reshape(-1)) - off.reshape(-1)).abs().max()) < 1e-6
    assert float((s - true_s).abs().max()) < 2e-3, s
    # Scales only: the offsets are left as they are.
    s2, off2 = calibration.light_joint_step(data, th, metal, s, off, idx, "principled", position=False)
    assert torch.equal(off2, off)


def test_light_joint_step_is_the_dense_joint_gauss_newton_step():
    """The Schur-complement step is the light part of one dense joint Gauss–Newton step.

    The dense step takes all the unknowns at once (every pixel's 7 and the lights'), from the
    full Jacobian (``jacfwd``), with the same weights, priors, damping and constraints; a map
    prior's gradient and curvature enter as the pixels' own do. In float64, so the two agree
    closely.
    """
    from torchbrdf.capture.synthetic import log_residual_points

    f64 = torch.float64
    data, theta, metal = flat_level(size=8, lights=8, normal_tilt_deg=10.0)
    g = torch.Generator().manual_seed(1)
    data.points, data.camera, data.pos_stated, data.inten_stated = (
        data.points.to(f64), data.camera.to(f64), data.pos_stated.to(f64), data.inten_stated.to(f64))
    data.log_obs = data.log_obs.to(f64) + 0.01 * torch.randn(data.log_obs.shape, generator=g, dtype=f64)
    theta, metal = theta.to(f64), metal.to(f64)
    n_px, n_l = theta.shape[0], data.pos_stated.shape[0]
    idx = list(range(n_l))
    ref = idx[:-1]  # the last light is not a reference (as a held-out light that joined)
    s0 = 0.02 * torch.randn(n_l, generator=g, dtype=f64)
    s0[ref] -= s0[ref].mean()
    off0 = torch.zeros(n_l, 3, dtype=f64)
    grad = 1e-3 * torch.randn(theta.shape, generator=g, dtype=f64)
    curv = 0.5 * torch.rand(theta.shape, generator=g, dtype=f64)
    s1, off1 = calibration.light_joint_step(data, theta, metal, s0, off0, ref, "principled", map_prior=(grad, curv),
                                  scale_sigma=0.05, position_sigma=0.02, damping=1e-3, at_camera=False)

    def residual(x):  # all unknowns -> (P * L * 3,)
        t = x[: n_px * 7].reshape(n_px, 7)
        pos = data.pos_stated + x[n_px * 7: n_px * 7 + 3 * n_l].reshape(n_l, 3)
        inten = data.inten_stated * x[n_px * 7 + 3 * n_l:].exp()[:, None]
        p = params.decode(t, metal)
        return log_residual_points(p["normal"], data.points, data.camera, pos, inten, p,
                                   data.log_obs.permute(1, 0, 2), data.eps).reshape(-1)

    n_p = n_px * 7
    x0 = torch.cat((theta.reshape(-1), off0.reshape(-1), s0))
    r = residual(x0)
    j = torch.func.jacfwd(residual)(x0)
    sigma2 = float(r.pow(2).median())
    w = (3 * sigma2**0.5 / r.abs()).clamp(max=1.0)  # Huber weights
    hess = j.T @ (w[:, None] * j)
    grad_all = j.T @ (w * r)
    grad_all[:n_p] += grad.reshape(-1)
    pix = torch.arange(n_p)
    hess[pix, pix] += 1e-3 * hess[pix, pix] + 1e-9 + curv.reshape(-1)  # damping, the prior's curvature
    prior = torch.cat((torch.full((3 * n_l,), 1 / 0.02**2), torch.full((n_l,), 1 / 0.05**2))).to(f64) * sigma2
    hess[n_p:, n_p:] += torch.diag(prior)
    grad_all[n_p:] += prior * x0[n_p:]
    # Constraints: no move of the whole rig nor (at_camera=False) of the light beside the
    # camera, the reference lights' mean log scale kept.
    flash = calibration.camera_lights(data.pos_stated, data.camera, data.points.mean(0))
    assert flash.tolist() == [False] * (n_l - 1) + [True]
    free = calibration.rig_free_directions(data.pos_stated, data.points.mean(0), flash)
    is_ref = torch.tensor([float(i in ref) for i in idx], dtype=f64)
    keep_mean = torch.linalg.qr(is_ref[:, None], mode="complete")[0][:, 1:]
    t = torch.block_diag(torch.eye(n_p, dtype=f64), free, keep_mean)
    step = t @ torch.linalg.solve(t.T @ hess @ t, -(t.T @ grad_all))
    ref_off = step[n_p: n_p + 3 * n_l].reshape(n_l, 3)
    ref_s = s0 + step[n_p + 3 * n_l:]
    assert 2e-3 < float(ref_off.abs().max()) < 0.05 and float((ref_s - s0).abs().max()) > 1e-3  # it moves
    assert torch.allclose(off1, ref_off, atol=1e-7, rtol=1e-5), (off1, ref_off)
    assert torch.allclose(s1, ref_s, atol=1e-7, rtol=1e-5), (s1, ref_s)


def _reference_reduced_light_system(r, cols, keep, map_prior, damping, leave_out=None):
    """The lights' reduced system as first written: a dense inverse per pixel, float64 throughout
    (``leave_out``: pixels dropped)."""
    f64 = torch.float64
    r, cols = r.to(f64), cols.to(f64)
    sigma2 = float(r.pow(2).median()) + 1e-12
    g, h = map_prior[0].to(f64), map_prior[1].to(f64)
    if leave_out is not None:
        r, cols, g, h = r[~leave_out], cols[:, ~leave_out], g[~leave_out], h[~leave_out]
    n, n_l = r.shape[0], r.shape[1] // 3
    w = (3.0 * math.sqrt(sigma2) / r.abs().clamp(min=1e-30)).clamp(max=1.0)
    jp = cols[:7].permute(1, 0, 2)  # (n, 7, M)
    jg = cols[7:].permute(1, 2, 0).reshape(n, n_l, 3, 4)[..., keep]  # (n, L, 3, G)
    jpw = jp * w[:, None]
    a = jpw @ jp.mT
    a = a + torch.diag_embed(damping * a.diagonal(dim1=-2, dim2=-1) + 1e-9 + h)
    b = torch.einsum("nklc,nlcg->nklg", jpw.reshape(n, 7, n_l, 3), jg).reshape(n, 7, -1)
    bg = torch.cat((b, ((jpw @ r[..., None])[..., 0] + g)[..., None]), -1)
    gram = torch.einsum("nki,nkj->ij", bg, torch.linalg.inv(a) @ bg)
    c = torch.einsum("nlcg,nlc,nlch->lgh", jg, w.reshape(n, n_l, 3), jg)
    gg = torch.einsum("nlcg,nlc->lg", jg, (w * r).reshape(n, n_l, 3)).reshape(-1)
    return torch.block_diag(*c) - gram[:-1, :-1], gg - gram[:-1, -1], sigma2


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("position", [True, False])
def test_the_reduced_light_system_is_the_schur_complement_of_each_pixels_unknowns(position, fused):
    """The joint step's reduced normal equations equal the dense per-pixel formula.

    ``Σ JgᵀWJg − Σ BᵀA⁻¹B`` and ``Σ JgᵀWr − Σ BᵀA⁻¹gp`` with ``A⁻¹`` a dense inverse per pixel,
    float64 throughout, against the Cholesky factors with the pixels innermost, summed a
    chunk at a time (64 pixels: chunks of 24, 24 and 16), in the C pass (``fused``) and in
    PyTorch operations; positions and scales, and scales alone (the Jacobians' 7 + 1
    directions equal the full pass's scale column). A pixel whose ``A`` is not positive
    definite (here a negative prior curvature) is left out.
    """
    data, theta, metal = flat_level(size=8, lights=6, normal_tilt_deg=10.0)
    gen = torch.Generator().manual_seed(3)
    data.log_obs = data.log_obs + 0.02 * torch.randn(data.log_obs.shape, generator=gen)
    theta = theta + 0.05 * torch.randn(theta.shape, generator=gen)
    n_l = data.pos_stated.shape[0]
    keep = slice(0, 4) if position else slice(3, 4)
    args = (data, theta, metal, data.points, data.log_obs.permute(1, 0, 2), data.inten_stated,
            data.pos_stated, torch.zeros(n_l), "principled")
    r, cols = calibration._pixel_and_light_jacobians(*args)  # (11, n, M): offset xyz, log scale
    r1, cols1 = calibration._pixel_and_light_jacobians(*args, position=position)
    assert torch.equal(r1, r) and torch.equal(cols1, cols[list(range(7)) + list(range(7 + keep.start, 11))])
    prior = (1e-3 * torch.randn(theta.shape, generator=gen), torch.rand(theta.shape, generator=gen))
    if fused and build.available():  # the C pass runs here
        g, h = prior[0].double(), prior[1].double()
        assert capture_residual.light_schur(r, cols1, g, h, 1e-3, 1.0) is not None
    for leave_out in (None, torch.arange(theta.shape[0]) == 5):
        if leave_out is not None:
            prior[1][5, 2] = -1e6
        schur, rhs, sigma2 = calibration._reduced_light_system(r, cols1, prior, 1e-3, chunk=24, fused=fused)
        ref_schur, ref_rhs, ref_sigma2 = _reference_reduced_light_system(r, cols, keep, prior, 1e-3, leave_out)
        assert schur.dtype == rhs.dtype == torch.float64 and sigma2 == ref_sigma2
        assert schur.shape == (n_l * (keep.stop - keep.start),) * 2
        scale = float(ref_schur.abs().max())
        assert float((schur - ref_schur).abs().max()) < 1e-10 * scale, (schur - ref_schur).abs().max()
        assert float((rhs - ref_rhs).abs().max()) < 1e-10 * float(ref_rhs.abs().max())
    # the left-out pixel mattered: with it, the system differs
    assert float((ref_schur - _reference_reduced_light_system(r, cols, keep, (prior[0], prior[1].abs()), 1e-3)[0])
                 .abs().max()) > 1e-6 * scale


def test_rig_free_directions_exclude_every_move_of_the_whole_rig():
    """``3L − 7`` orthonormal directions that exclude every move of all the lights together.

    Orthogonal to every translation, turn (about any axis through the centre) and dilation;
    one light alone moves freely.
    """
    from torchbrdf.capture.synthetic import light_layout

    f64 = torch.float64
    pos, _ = light_layout(8)
    centre = torch.tensor([0.1, -0.2, 0.0], dtype=f64)
    free = calibration.rig_free_directions(pos.to(f64), centre)
    n = pos.shape[0]
    assert free.shape == (3 * n, 3 * n - 7)
    assert torch.allclose(free.T @ free, torch.eye(3 * n - 7, dtype=f64), atol=1e-12)
    rel = pos.to(f64) - centre
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=f64)
    moves = [torch.tensor([0.3, -0.1, 0.2], dtype=f64).expand_as(rel),  # a translation
             0.05 * rel,  # a dilation about the centre
             torch.linalg.cross(axis.expand_as(rel), rel)]  # a turn about an axis through it
    for d in moves:
        assert float((free.T @ d.reshape(-1)).abs().max()) < 1e-12
    one = torch.zeros_like(rel)
    one[3, 0] = 1.0
    assert float((free.T @ one.reshape(-1)).norm()) > 0.8
    # Held lights: no component on their coordinates, three directions fewer each, still
    # orthonormal and free of every rig move; the others still move.
    held = torch.zeros(n, dtype=torch.bool)
    held[[1, 5]] = True
    part = calibration.rig_free_directions(pos.to(f64), centre, held)
    assert part.shape == (3 * n, 3 * n - 13)
    assert torch.allclose(part.T @ part, torch.eye(3 * n - 13, dtype=f64), atol=1e-12)
    assert float(part.reshape(n, 3, -1)[held].abs().max()) < 1e-12
    for d in moves:
        assert float((part.T @ d.reshape(-1)).abs().max()) < 1e-12
    assert float((part.T @ one.reshape(-1)).norm()) > 0.8


@pytest.mark.parametrize("at_camera", [True, False])
def test_flash_position_in_the_dual_stage_is_a_choice(tiny, at_camera):
    """``dual_calibration_at_camera=False`` holds the flash through the two-hypothesis stage.

    The light beside the camera keeps its stated position through the full-resolution
    two-hypothesis stage (the ring lights move already) and is estimated from the single-class
    stages on; by default it moves there too.
    """
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery
    from torchbrdf.recovery.calibration import camera_lights

    cap = load_capture(tiny)
    rec = Recovery(cap, Settings(seed=0, soft_metal=False, dual_calibration_at_camera=at_camera),
                   log=lambda m: None)
    full = rec.plan[-1][0]
    dual_end = max(i for i, (s, k, _) in enumerate(rec.plan) if s == full and k == "dual") + 1
    flash = camera_lights(cap.light_positions, cap.camera_position, rec.data(full).points.mean(0))
    assert int(flash.sum()) == 1
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < dual_end:
            rec.tick()
        assert float(rec.light_offset()[~flash].abs().max()) > 0
        assert bool((rec.light_offset()[flash] != 0).any()) == at_camera
        while rec.state["stage"] < len(rec.plan):
            rec.tick()
    assert bool((rec.light_offset()[flash] != 0).any())


@pytest.mark.parametrize("tie", [True, False])
def test_the_nonlocal_f0_tie_is_a_prior_of_the_fit(tiny, tie):
    """From the polish stage on, the metals' non-local F0 average is a unary prior of the fit.

    Set at the stage's start: precision ``prior_nonlocal_base`` on exactly the metal pixels'
    base colour, zero elsewhere, the target :func:`nonlocal_prior`'s average at that state; the
    stage's LM steps are given it. Without ``fit_nonlocal_tie`` there is none.
    """

    cfg = Settings(seed=0, soft_metal=False, fit_nonlocal_tie=tie)
    rec, polish = recovery_at_polish(tiny, cfg)
    if not tie:
        assert "tie" not in rec.state
        return
    target, prec = rec.state["tie"]
    ism = rec.state["metal"][:, 0] > 0.5
    assert bool(ism.any()) and bool((~ism).any())
    assert torch.all(prec[ism, :3] == cfg.prior_nonlocal_base) and torch.all(prec[~ism] == 0)
    assert torch.all(prec[:, 3:] == 0)
    d = rec.data(rec.plan[polish][0])
    th, mt = rec.state["theta"][0], rec.state["metal"]
    r0, jtj, jtr = lm.gauss_newton(d, th, mt, d.train_idx, cfg.model)
    avg = priors.nonlocal_prior(d, th, mt, cfg, jtj, lm.pixel_cost(r0), jtr)[1]
    assert torch.allclose(target[ism, :3], avg[ism, :3], atol=1e-5)
    assert float((target[ism, :3] - th[ism, :3]).abs().max()) > 1e-3  # not the pixel's own value
    seen = []
    step = engine.lm_step

    def spy(*args, **kwargs):
        seen.append(kwargs.get("unary", args[7] if len(args) > 7 else None))
        return step(*args, **kwargs)

    engine.lm_step = spy
    try:
        with torch.no_grad():
            rec.tick()
    finally:
        engine.lm_step = step
    assert seen and seen[0] is not None and torch.equal(seen[0][1], prec)


def test_a_tie_pass_on_the_metal_pixels_alone_gives_the_full_passs_average(tiny):
    """The stage-start tie's pass on the metal pixels alone (``nonlocal_prior(rows=...)``).

    Without the roughness average only the metal pixels' normal equations enter the F0
    average, so the pass nobody takes up (the last stage's) is made on them alone: the same
    precisions and targets on every pixel as the full pass, the metal pixels' information, 0
    elsewhere. Fails if the rows are mixed up (a pixel given another's normal equations); rows
    without every metal pixel, or with the roughness average (which needs every pixel), are
    refused.
    """

    cfg = Settings(seed=0, soft_metal=False)
    rec, polish = recovery_at_polish(tiny, cfg)
    d = rec.data(rec.plan[polish][0])
    th, mt = rec.state["theta"][0], rec.state["metal"]
    ism = mt[:, 0] > 0.5
    assert bool(ism.any()) and bool((~ism).any())
    r0, jtj, jtr = lm.gauss_newton(d, th, mt, d.train_idx, cfg.model)
    w, m, info = priors.nonlocal_prior(d, th, mt, cfg, jtj, lm.pixel_cost(r0), jtr)
    rows = torch.nonzero(ism)[:, 0]
    r_m, jtj_m, jtr_m = lm.gauss_newton(d.subset(rows), th[rows], mt[rows], d.train_idx, cfg.model)
    w_m, m_m, info_m = priors.nonlocal_prior(d, th, mt, cfg, jtj_m, lm.pixel_cost(r_m), jtr_m, rows=rows)
    assert torch.equal(w_m, w)
    assert torch.allclose(m_m, m, atol=1e-5, rtol=0)
    assert torch.allclose(info_m[ism], info[ism], rtol=1e-4) and torch.all(info_m[~ism] == 0)
    with pytest.raises(ValueError, match="prior_nonlocal"):
        priors.nonlocal_prior(d, th, mt, Settings(prior_nonlocal=1.0), jtj_m, lm.pixel_cost(r_m), jtr_m,
                         rows=rows)
    with pytest.raises(ValueError, match="every metal pixel"):  # a metal pixel left out
        priors.nonlocal_prior(d, th, mt, cfg, jtj_m[1:], lm.pixel_cost(r_m[1:]), jtr_m[1:], rows=rows[1:])


def test_a_pixel_subset_gathers_its_levels_targets(tiny):
    """``LevelData.subset``: a pixel list whose observations, log targets and residuals are the level's.

    Rows may repeat, come as a mask, or index a subset again; the targets are gathered from
    the level's when first used, and new targets set on the level reach the subsets made after;
    a subset given targets of its own is its subsets' level. A mask must cover every pixel.
    """
    import dataclasses

    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.levels import LevelData
    from torchbrdf.recovery.params import encode

    cap = load_capture(tiny)
    data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    g = torch.Generator().manual_seed(0)
    p = data.points.shape[0]
    theta = encode({"base_color": torch.rand(p, 3, generator=g), "specular": torch.full((p, 1), 0.5),
                    "roughness": torch.rand(p, 1, generator=g) * 0.8 + 0.1,
                    "normal": torch.nn.functional.normalize(torch.randn(p, 3, generator=g) * 0.1
                                                            + torch.tensor([0.0, 0.0, 1.0]), dim=-1)})
    metal = (torch.rand(p, 1, generator=g) > 0.5).to(theta.dtype)
    idx = data.train_idx[:5]
    full = data.residual(theta, metal, idx)
    rows = torch.tensor([7, 3, 3, 900, 0])
    mask = torch.zeros(p, dtype=torch.bool)
    mask[[5, 40, 41]] = True
    for sub, at in ((data.subset(rows), rows), (data.subset(mask), mask.nonzero()[:, 0]),
                    (data.subset(rows).subset(torch.tensor([4, 1])), rows[[4, 1]])):
        assert torch.equal(sub.residual(theta[at], metal[at], idx), full[at])
        assert torch.equal(sub.obs, data.obs[:, at]) and torch.equal(sub.log_obs, data.log_obs[:, at])
        assert torch.equal(sub.points, data.points[at]) and sub.size == 0 and sub.images is None
    # a subset made before its level's first residual on a light set gathers them as well
    fresh = LevelData(dataclasses.replace(cap), 32, data.train_idx, data.eps).subset(rows)
    assert torch.equal(fresh.residual(theta[rows], metal[rows], idx), full[rows])
    # a subset with targets of its own is the level of its subsets
    own = data.subset(rows)
    own.log_obs = own.log_obs - 2.0
    at = rows[[4, 1]]
    nested = own.subset(torch.tensor([4, 1]))
    assert torch.allclose(nested.residual(theta[at], metal[at], idx), full[at] + 2.0)
    with pytest.raises(IndexError, match="mask"):
        data.subset(mask[:-1])
    # new targets on the level: the cached ones go
    data.log_obs = data.log_obs + 1.0
    assert torch.allclose(data.subset(rows).residual(theta[rows], metal[rows], idx), full[rows] - 1.0)


def test_log_targets_are_the_observed_logs_of_the_lights_at_the_rows(tiny):
    """``LevelData.log_targets``: ``log_obs`` on a light set, pixel-major ``(N, L, 3)``, at the
    listed rows (every pixel without rows), on a level and on a pixel subset, and anew once the
    level is given new targets."""
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.levels import LevelData

    cap = load_capture(tiny)
    data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
    idx, rows = [3, 1, 4], torch.tensor([9, 2, 2, 1023, 0])
    want = data.log_obs[idx].permute(1, 0, 2)
    assert torch.equal(data.log_targets(idx), want) and data.log_targets(idx).is_contiguous()
    assert torch.equal(data.log_targets(idx, rows), want[rows])
    sub = data.subset(rows)
    assert torch.equal(sub.log_targets(idx), want[rows])
    assert torch.equal(sub.log_targets(idx, torch.tensor([4, 0])), want[rows[[4, 0]]])
    data.log_obs = data.log_obs + 1.0
    assert torch.equal(data.log_targets(idx, rows), want[rows] + 1.0)


def test_two_unary_priors_sum_to_one():
    """``sum_unary``: the target and precision whose quadratic is the two priors' sum (up to a constant)."""
    from torchbrdf.recovery.lm import sum_unary, unary_cost

    g = torch.Generator().manual_seed(0)
    a = (torch.randn(5, 7, generator=g), torch.rand(5, 7, generator=g))
    b = (torch.randn(5, 7, generator=g), torch.rand(5, 7, generator=g))
    b[1][0] = 0.0  # absent on one pixel
    s = sum_unary(a, b)
    x, y = torch.randn(5, 7, generator=g), torch.randn(5, 7, generator=g)
    both = lambda t: unary_cost(t, a) + unary_cost(t, b)  # noqa: E731
    assert torch.allclose(both(x) - both(y), unary_cost(x, s) - unary_cost(y, s), atol=1e-5)
    assert sum_unary(a, None) is a and sum_unary(None, b) is b


def _iterations_to_the_last_stage(rec):
    """Run ``rec`` (no gradient) until its last stage; returns stage -> iterations run."""
    with torch.no_grad():
        rec.init_state()
        iterations = {}
        while rec.state["stage"] < len(rec.plan) - 1:
            stage = rec.state["stage"]
            iterations[stage] = iterations.get(stage, 0) + 1
            rec.tick()
    return iterations


def _recovery_with_a_brighter_light(tiny, **settings):
    """A :class:`Recovery` of ``tiny`` whose training light 3 is 6 % brighter than capture.json states."""
    import dataclasses as dc

    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery

    cap = load_capture(tiny)
    images = cap.images.clone()
    images[3] *= 1.06
    return Recovery(dc.replace(cap, images=images), Settings(seed=0, soft_metal=False, **settings),
                    log=lambda m: None)


@pytest.mark.parametrize("dual_calibration", [True, False])
def test_lights_are_estimated_from_the_dual_stages_on(tiny, dual_calibration):
    """A training light 6 % brighter than stated is found by the end of the full-resolution dual stage.

    Each pixel's better hypothesis gives the residuals, before the single-class stages; without
    ``dual_calibration`` the scale is still as stated there (the maps absorb it first). By
    default the intensity scales start at the coarsest level (the positions at full
    resolution); ``dual_calibration_coarse=False`` waits for the full-resolution level for
    both. By the end of the fit every light's scale is found to 1 % (0.3 % here; the
    alternating steps of ``light_joint=False`` end 1.2 % off on this capture, and move its
    correctly stated lights by 0.9–1.8 cm, against 0.2–0.7 cm).
    """
    rec = _recovery_with_a_brighter_light(tiny, dual_calibration=dual_calibration)
    full = rec.plan[-1][0]
    dual_end = max(i for i, (s, k, _) in enumerate(rec.plan) if s == full and k == "dual") + 1
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < dual_end:
            rec.tick()
    scale = rec.light_log_scale()
    rel = scale[3] - scale[rec.train_idx].mean()  # the overall scale is fixed by the stated ones
    if dual_calibration:  # most of it already (the single-class stages continue the estimate)
        assert 0.6 * math.log(1.06) < float(rel) < 1.2 * math.log(1.06), scale
        others = [k for k in rec.train_idx if k != 3]
        assert float((scale[others] - scale[rec.train_idx].mean()).abs().max()) < 0.03, scale
        # ... and by the end of the fit every training light's scale is within 1 % of the truth
        # (relative to the training lights' mean, which the stated intensities fix).
        with torch.no_grad():
            while rec.state["stage"] < len(rec.plan):
                rec.tick()
        scale = rec.light_log_scale()[rec.train_idx]
        true = torch.tensor([math.log(1.06) * (k == 3) for k in rec.train_idx])
        assert float(((scale - scale.mean()) - (true - true.mean())).abs().max()) < 0.01, scale
    else:
        assert float(scale.abs().max()) == 0.0


@pytest.mark.parametrize("light_joint", [True, False])
def test_coarse_dual_levels_estimate_the_intensity_scales_not_the_positions(tiny, light_joint):
    """The coarsest two-hypothesis level moves a light 6 % brighter than stated, and no light's position.

    Both light steps (the joint one and the alternating ``light_joint=False``): a coarse level's
    blended pixels would move the positions, which start at full resolution.
    """
    rec = _recovery_with_a_brighter_light(tiny, light_joint=light_joint)
    assert rec.plan[0][0] < rec.plan[-1][0] and rec.plan[0][1] == "dual"  # a coarse dual level
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < 1:
            rec.tick()
    coarse = float(rec.light_log_scale()[3] - rec.light_log_scale()[rec.train_idx].mean())
    assert coarse > 0.3 * math.log(1.06), rec.light_log_scale()
    assert float(rec.light_offset().abs().max()) == 0.0


def test_coarse_dual_calibration_can_be_left_to_full_resolution(tiny):
    """``dual_calibration_coarse=False``: the coarse two-hypothesis levels keep the stated lights.

    The full-resolution one estimates the intensity scales and positions from its first iteration.
    """
    rec = _recovery_with_a_brighter_light(tiny, dual_calibration_coarse=False)
    full = rec.plan[-1][0]
    first_full = min(i for i, (s, _, _) in enumerate(rec.plan) if s == full)
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < first_full:
            rec.tick()
        assert float(rec.light_log_scale().abs().max()) == 0.0
        assert float(rec.light_offset().abs().max()) == 0.0
        rec.tick()  # the full-resolution dual stage's first iteration estimates them
    assert float(rec.light_log_scale()[3] - rec.light_log_scale()[rec.train_idx].mean()) > 0.01
    assert float(rec.light_offset().abs().max()) > 0.0


def test_the_light_steps_evidence_is_chi2_with_its_degrees_of_freedom():
    """At the true lights, with the maps fitted, the step's ``δgᵀHδg / σ²`` is a χ² with K dof.

    Noise alone puts the joint optimum about one posterior deviation per free direction from
    the truth: over four noise draws the mean is within 0.6–1.5 K (26.7 of 28 here; with σ²
    the median squared residual, not its Gaussian variance, it would be 2.2× lower). A light
    estimate 2 cm from where the images were made gives a step far beyond that.
    """
    chi2 = []
    for seed in range(4):
        data, theta, metal = flat_level(size=16, lights=8, normal_tilt_deg=10.0)
        gen = torch.Generator().manual_seed(seed)
        data.log_obs = data.log_obs + 0.01 * torch.randn(data.log_obs.shape, generator=gen)
        n_l = data.pos_stated.shape[0]
        lam = torch.full((theta.shape[0], 1), 1e-3)
        for _ in range(4):
            theta, lam, _, _ = lm.lm_step(data, theta, metal, lam, Settings(), 1.0)
        evidence = {}
        calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), torch.zeros(n_l, 3), list(range(n_l)),
                                     "principled", evidence=evidence)
        dof = evidence["dof"]
        assert dof == 3 * n_l - 7 + n_l - 1  # the rig-free positions and the scales keeping their mean
        chi2.append(evidence["chi2"])
    assert 0.6 * dof < sum(chi2) / len(chi2) < 1.5 * dof, chi2
    wrong = torch.zeros(n_l, 3)
    wrong[2, 0] = 0.02  # the current estimate; the images were made at the stated place
    evidence = {}
    calibration.light_joint_step(data, theta, metal, torch.zeros(n_l), wrong, list(range(n_l)), "principled",
                                 evidence=evidence)
    assert evidence["chi2"] > 5 * dof, evidence  # 242 of 28 here


@pytest.mark.parametrize("ratio, rest", [(1.0, 0), (3.0, 0), (0.3, 1), (0.25, 1), (0.2499, 2), (0.11, 3),
                                         (0.1112, 2), (1e-3, 31)])
def test_the_light_step_rests_the_most_iterations_whose_drift_stays_below_its_dof(ratio, rest):
    """``s`` iterations without a step leave about ``s δg`` unapplied, ``s² χ²``: the rest is the
    most ``s`` with ``s² χ² < K`` (``χ² = ratio · K``; at ``s² χ² = K`` exactly one fewer)."""
    for dof in (15.0, 56.0):
        assert calibration.rest_iterations(ratio * dof, dof) == rest


def test_the_light_steps_rest_has_its_ends():
    """No rest after a step beyond noise or one whose χ² is not a number; without end at χ² = 0."""
    import sys

    assert calibration.rest_iterations(0.0, 56.0) == sys.maxsize
    assert calibration.rest_iterations(1e-300, 56.0) == sys.maxsize
    for chi2 in (float("nan"), float("inf"), -1.0):
        assert calibration.rest_iterations(chi2, 56.0) == 0


@pytest.mark.parametrize("dof", [float("nan"), float("inf"), -1.0])
def test_the_light_steps_rest_refuses_degrees_of_freedom_that_are_not_a_count(dof):
    # A NaN K read as a rest without end (every comparison with it false), a negative one
    # failed inside math.isqrt without naming it.
    with pytest.raises(ValueError, match=r"rest_iterations: `dof` must be a finite number >= 0"):
        calibration.rest_iterations(1.0, dof)


def test_the_light_step_rests_within_a_stage_and_steps_again(tiny, monkeypatch):
    """A step whose χ² is 0.3 K rests one iteration (``4 · 0.3 K ≥ K``) and then steps again,
    within the stage: every other iteration of a long stage steps the lights (resting only
    once the stage's remaining iterations ``m`` had ``m² χ² < K`` would step at every one)."""
    steps = []
    dof = 5.0

    def step(*args, evidence=None, **kwargs):
        evidence.update(chi2=0.3 * dof, dof=dof)
        steps.append((rec.state["stage"], rec.state["it"]))
        return args[3], args[4]

    monkeypatch.setattr(engine, "light_joint_step", step)
    rec = _recovery_with_a_brighter_light(tiny, converge_tol=0.0)
    iterations = _iterations_to_the_last_stage(rec)
    stages = sorted({s for s, _ in steps})
    assert any(iterations[s] >= 4 for s in stages)
    for s in stages:
        assert [it for t, it in steps if t == s] == list(range(0, iterations[s], 2))


@pytest.mark.parametrize("light_rest", [True, False])
def test_the_light_step_rests_once_the_iterations_left_could_not_move_it_beyond_noise(tiny, monkeypatch,
                                                                                       light_rest):
    """With ``m`` planned iterations left in the stage, the joint light step rests to the stage's
    end exactly when ``m²`` times its χ² is below its degrees of freedom: a stage's first step
    2 % above that (it rests until the stage's last iteration), its second 2 % below (a count
    of ``m`` left off by one, ``m`` instead of ``m²``, or a fixed fraction of K would rest
    elsewhere). The next stage steps the lights again; with ``light_rest=False`` every
    iteration steps them."""
    calls = []
    dof = 5.0

    def at_the_bound(*args, evidence=None, **kwargs):
        st = rec.state
        left = rec.plan[st["stage"]][2] - st["it"] - 1
        factor = 0.98 if calls and calls[-1] == st["stage"] else 1.02
        evidence.update(chi2=factor * dof / max(left, 1) ** 2, dof=dof)
        calls.append(st["stage"])
        return args[3], args[4]

    monkeypatch.setattr(engine, "light_joint_step", at_the_bound)
    rec = _recovery_with_a_brighter_light(tiny, light_rest=light_rest, converge_tol=0.0)
    iterations = _iterations_to_the_last_stage(rec)
    calibrated = [s for s, (size, kind, _) in enumerate(rec.plan[:-1])
                  if kind != "dual" or size == rec.plan[-1][0] or rec.cfg.dual_calibration_coarse]
    if light_rest:  # 2 % above, then 2 % below the bound: two steps per stage
        assert calls == [s for s in calibrated for _ in range(min(2, iterations[s]))]
        assert len(calls) < sum(iterations[s] for s in calibrated)
    else:
        assert calls == [s for s in calibrated for _ in range(iterations[s])]
        assert len(calls) > len(calibrated)


@pytest.mark.parametrize("shape", [(1, 1), (7, 3), (8, 6), (4096, 48)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_light_steps_noise_median_is_torchs_lower_median_of_the_absolute_residuals(shape, dtype):
    """The light step's noise level takes ``torch.median``'s element of ``|r|``, the lower of the
    two middle ones for an even count (not their mean, not the upper one), ties and signs
    included."""
    g = torch.Generator().manual_seed(sum(shape))
    r = (torch.randn(shape, generator=g, dtype=dtype) * 0.01).round(decimals=3)  # ties among |r|
    want = float(r.abs().median())
    assert calibration.abs_median(r) == want
    assert calibration.abs_median(-r) == want
    assert calibration.abs_median(r.T) == want  # a non-contiguous view
    if r.numel() % 2 == 0 and r.numel() > 1:  # the two middle values differ: the lower one is taken
        s = torch.arange(1, r.numel() + 1, dtype=dtype).reshape(shape)
        assert calibration.abs_median(s) == float(r.numel() // 2)
    with pytest.raises(ValueError, match="`r`"):
        calibration.abs_median(r[:0])
