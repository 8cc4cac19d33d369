"""The coupled prior, propagation, normal search and the metal/dielectric class choice."""

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

from tests.recovery.recovery_fixtures import flat_level
from torchbrdf.recovery.svbrdf import CHECKPOINT, RecoveryConfig, main, recover

CONTRACT_FILES = ["base_color.exr", "roughness.exr", "metallic.exr", "specular.exr", "normal.exr", "report.json"]


# --------------------------------------------------------------------------------------
# The coupled prior, propagation, normal search and the class choice
# --------------------------------------------------------------------------------------


def _random_edges(size, c=7, seed=0):
    gen = torch.Generator().manual_seed(seed)
    wx = torch.rand(size, size - 1, c, generator=gen, dtype=torch.float64)
    wy = torch.rand(size - 1, size, c, generator=gen, dtype=torch.float64)
    return wx, wy


def test_laplacian_is_the_gradient_of_the_prior_energy():
    size = 5
    wx, wy = _random_edges(size)
    x = torch.randn(size * size, 7, dtype=torch.float64, requires_grad=True)
    energy = 0.5 * smoothness_prior.prior_energy(x, wx, wy, size).sum()  # per-pixel shares sum to 2 E
    (grad,) = torch.autograd.grad(energy, x)
    assert torch.allclose(grad, smoothness_prior.laplacian(x.detach(), wx, wy, size), atol=1e-12)
    # Diagonal: L applied to a unit vector at pixel p, channel c.
    e = torch.zeros(size * size, 7, dtype=torch.float64)
    e[7, 3] = 1.0
    assert math.isclose(float(smoothness_prior.laplacian(e, wx, wy, size)[7, 3]), float(smoothness_prior.laplacian_diag(wx, wy, size)[7, 3]))


def test_metal_base_tie_is_guided_by_base_colour():
    """Two metal pixels' base colours are tied only where they are alike (metal_base_guided).

    A dark red rust island called metal inside a bright metal is cut loose from it, so its F0
    does not pull the bright metal's down through the chain of ties. Unguided (as before
    2026-12-02), the tie is class-only; a dielectric pair has no base-colour tie at all.
    """
    from torchbrdf.recovery.smoothness_prior import edge_weights
    from torchbrdf.recovery.params import encode

    size = 4
    base = torch.tensor([0.95, 0.93, 0.88]).repeat(size, size, 1)
    base[:, 2:] = torch.tensor([0.45, 0.2, 0.1])  # columns 2-3: the island
    n = size * size
    theta = encode({"base_color": base.reshape(n, 3), "specular": torch.full((n, 1), 0.5),
                    "roughness": torch.full((n, 1), 0.3),
                    "normal": torch.tensor([0.0, 0.0, 1.0]).repeat(n, 1)})
    metal = torch.ones(n, 1)
    for guided in (True, False):
        cfg = Settings(metal_base_guided=guided)
        wx, wy = edge_weights(theta, metal, size, cfg)
        w = cfg.prior_metal_base
        assert torch.allclose(wx[:, 0, 0:3], torch.full((size, 3), w))  # alike: tied
        assert torch.allclose(wy[..., 0:3], torch.full((size - 1, size, 3), w))
        across = wx[:, 1, 0:3]  # between columns 1 and 2
        assert torch.allclose(across, torch.full_like(across, w)) != guided
        if guided:
            assert float(across.max()) < 1e-6 * w
    wx, _ = edge_weights(theta, torch.zeros(n, 1), size, Settings())
    assert float(wx[..., 0:3].abs().max()) == 0.0


@pytest.mark.parametrize("joined", [range(7), range(3, 5), range(0, 5), range(0)])
def test_pcg_solves_the_coupled_system(joined):
    """Every pattern of prior-joined channels (all; a dielectric's specular and roughness; with
    a metal's base colour; none), so the per-pixel elimination of the others is exact."""
    size, c = 4, 7
    p = size * size
    wx, wy = _random_edges(size, c, seed=1)
    free = [k for k in range(c) if k not in joined]
    wx[..., free], wy[..., free] = 0.0, 0.0
    a = torch.randn(p, c, c, dtype=torch.float64)
    hess = a @ a.transpose(-1, -2) + 1e-2 * torch.eye(c, dtype=torch.float64)  # SPD blocks
    rhs = torch.randn(p, c, dtype=torch.float64)
    x = smoothness_prior.pcg(hess, wx, wy, rhs, size, iters=300)
    # Dense reference: assemble the (P·C)² matrix column by column.
    cols = []
    for k in range(p * c):
        e = torch.zeros(p * c, dtype=torch.float64)
        e[k] = 1.0
        e = e.reshape(p, c)
        cols.append((torch.einsum("pij,pj->pi", hess, e) + smoothness_prior.laplacian(e, wx, wy, size)).flatten())
    dense = torch.stack(cols, 1)
    ref = torch.linalg.solve(dense, rhs.flatten()).reshape(p, c)
    assert torch.allclose(x, ref, atol=1e-8, rtol=1e-6)


def test_normal_equations_match_reverse_mode_and_the_fused_kernels():
    # The fit's JᵀJ and Jᵀr come from forward mode vmapped over the 7 unknowns through
    # torchbrdf.principled, block by block. Against them: the full Jacobian by reverse mode
    # (eager), and the same computation through the fused kernels (used at fit sizes).
    import torchbrdf
    from torchbrdf.kernels import fused

    data, theta, metal = flat_level(size=12, lights=6, normal_tilt_deg=10.0)
    theta = theta + 0.3 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(0))
    metal = metal.clone()
    metal[::3] = 1.0
    idx = data.train_idx
    P = theta.shape[0]
    torchbrdf.set_fast_path(False)
    try:
        r_ref = data.residual(theta, metal, idx)
        # d r[p] / d theta[p]: the residual of pixel p depends only on its own unknowns.
        full = torch.func.jacrev(lambda t: data.residual(t, metal, idx))(theta)  # (P, M, P, 7)
        jac = full[torch.arange(P), :, torch.arange(P)]  # (P, M, 7)
        got = {False: lm.gauss_newton(data, theta, metal, idx, "principled", chunk=50)}
    finally:
        torchbrdf.set_fast_path(None)
    jtj_ref = torch.einsum("pmi,pmj->pij", jac, jac)
    jtr_ref = torch.einsum("pmi,pm->pi", jac, r_ref)
    if fused.available():
        torchbrdf.set_fast_path(True)
        try:
            got[True] = lm.gauss_newton(data, theta, metal, idx, "principled", chunk=50)
        finally:
            torchbrdf.set_fast_path(None)
    for r, jtj, jtr in got.values():
        assert jtj.shape == (P, 7, 7) and jtr.shape == (P, 7) and r.shape == r_ref.shape
        assert torch.allclose(r, r_ref, rtol=1e-5, atol=1e-6)
        scale = float(jtj_ref.abs().max())
        assert torch.allclose(jtj, jtj_ref, rtol=1e-4, atol=1e-5 * scale)
        assert torch.allclose(jtr, jtr_ref, rtol=1e-4, atol=1e-5 * float(jtr_ref.abs().max()))


def test_a_propagation_pass_restricted_to_the_last_changes_equals_a_full_pass():
    # Pass 2 can differ from pass 1 only where a 3x3 neighbourhood changed in pass 1, so the
    # recovery evaluates only those pixels; the result must be exactly the full pass's. A
    # wrong 6x6 block is repaired one ring per pass, so pass 2 has work to do.
    data, theta, metal = flat_level(size=12, lights=6)
    bad = theta.clone().reshape(12, 12, -1)
    bad[3:9, 3:9, 0:5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])
    bad = bad.reshape(theta.shape)
    t1, m1, changed = search.propagate(data, bad, metal, Settings())
    full = search.propagate(data, t1, m1, Settings())
    part = search.propagate(data, t1, m1, Settings(), active=map_ops.dilate(changed, 12))
    assert bool(changed.any()) and bool(full[2].any())
    assert torch.equal(full[0], part[0]) and torch.equal(full[1], part[1]) and torch.equal(full[2], part[2])
    # Only the changed pixels themselves would miss the next ring.
    only = search.propagate(data, t1, m1, Settings(), active=changed)
    assert not torch.equal(full[0], only[0])


def test_propagation_repairs_a_pixel_from_its_neighbours():
    data, theta, metal = flat_level()
    bad = theta.clone()
    bad[40, 0:5] = torch.tensor([-3.0, 2.0, 1.0, -4.0, 2.0])  # a wrong local optimum
    fixed, new_metal, changed = search.propagate(data, bad, metal, Settings())
    assert int(changed.sum()) >= 1 and torch.allclose(fixed[40], theta[40], atol=1e-5)
    assert torch.equal(new_metal, metal)
    # Across classes: a pixel wrongly called metal returns to dielectric by the evidence rule.
    m2 = metal.clone()
    m2[40] = 1.0
    fixed, new_metal, _ = search.propagate(data, bad, m2, Settings(), class_sigma2=1e-4)
    assert float(new_metal[40]) == 0.0 and torch.allclose(fixed[40], theta[40], atol=1e-5)


def test_unexplained_flags_the_noise_tail_at_its_rate():
    """Noise alone (σ² × χ² of ``n − 7`` degrees of freedom) is called unexplained at the rate asked
    for; a misfit far above the noise, and a non-finite cost, always."""
    sigma2, n, rate = 1e-4, 36, 0.05
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn(200_000, n - params.N_PARAMS, generator=gen, dtype=torch.float64)
    cost = sigma2 * (noise * noise).sum(-1, keepdim=True)
    flagged = search.unexplained(cost, sigma2, n, rate)
    assert flagged.shape == (cost.shape[0],) and flagged.dtype == torch.bool
    assert abs(float(flagged.double().mean()) - rate) < 0.003
    odd = torch.tensor([[10 * n * sigma2], [float("nan")], [float("inf")], [0.0]], dtype=torch.float64)
    assert search.unexplained(odd, sigma2, n, rate).tolist() == [True, True, True, False]


def test_a_stages_later_passes_try_only_the_unexplained_pixels(tiny, monkeypatch):
    """Within a single-class stage, a propagation pass runs only on the pixels whose data cost at
    the last LM step the noise does not explain (``search.unexplained``); the others keep their
    parameters. A stage's first pass tries every pixel."""
    calls = []
    plain = engine.propagate_passes

    def recording(data, theta, metal, cfg, passes, class_sigma2=None, unary=None, active=None):
        out = plain(data, theta, metal, cfg, passes, class_sigma2=class_sigma2, unary=unary,
                    **({} if active is None else {"active": active}))
        calls.append((class_sigma2 is not None, passes, active, (out[0] != theta).any(-1)))
        return out

    monkeypatch.setattr(engine, "propagate_passes", recording)
    recover(tiny, RecoveryConfig(seed=0, threads=2, converge_tol=0.0), None, progress=False)
    later = [c for c in calls if c[0] and c[1] == 1 and c[2] is not None]
    assert later, "no restricted pass within a single-class stage"
    for _, _, active, moved in later:
        assert active.dtype == torch.bool and bool(active.any()) and not bool(active.all())
        assert not bool((moved & ~active).any())
    assert all(c[2] is None for c in calls if not c[0])  # (the two-hypothesis stages: every pixel)


def test_normal_search_finds_a_steep_normal():
    data, theta, metal = flat_level(normal_tilt_deg=24.0)
    rows = torch.arange(100, 110)
    flat = theta.clone()
    flat[rows, 5:7] = 0.0  # these normals started flat, 24° off: a glossy local optimum
    flat[rows - 16, 5:7] = 0.0  # ... and so did the rows above and below: only the grid
    flat[rows + 16, 5:7] = 0.0  # of normals can help the middle ones
    cost = lambda t: (data.residual(t, metal, data.train_idx) ** 2).sum(-1)  # noqa: E731
    found, changed = search.normal_search(data, flat, metal, "principled")
    assert changed >= len(rows)
    assert bool((cost(found)[rows] < 0.1 * cost(flat)[rows]).all())
    nz = 1 / torch.sqrt(1 + (found[rows, 5:7] ** 2).sum(-1))
    # The best candidate is the true normal of a neighbour or a grid normal within 4° of it.
    assert torch.allclose(torch.rad2deg(torch.acos(nz)), torch.full_like(nz, 24.0), atol=4.0)


def test_ambiguous_pixels_take_their_neighbours_class():

    size = 6
    diel = torch.ones(size * size, 1)
    met = torch.full((size * size, 1), 10.0)  # decisively dielectric everywhere ...
    met.view(size, size)[:, :3] = 0.01  # ... except the left half, decisively metal
    met.view(size, size)[2, 2] = 1.0  # ambiguous, among metals
    met.view(size, size)[3, 4] = 1.0  # ambiguous, among dielectrics
    label = classes.choose_class(diel, met, size, 1 / 36, 36, 1e-4).view(size, size)
    assert float(label[2, 2]) == 1.0 and float(label[3, 4]) == 0.0
    assert torch.equal(label[:, :2], torch.ones(size, 2)) and torch.equal(label[:, 4:], torch.zeros(size, 2))


def test_a_metal_win_over_an_unconverged_dielectric_is_refitted_first():
    """A metal win over a dielectric stuck well above the noise is no evidence: refit first.

    Here 7× the median, as the README example's bottom-edge grout; not when the metal fits at
    the noise level (below the χ²(29) quantile at 1 − 1e-4: 1.78× the median of 36 residuals).
    """

    diel = torch.ones(100, 1)
    metal = torch.full((100, 1), 5.0)  # dielectric clearly better everywhere ...
    diel[0], metal[0] = 7.0, 2.5  # stuck dielectric, metal fits only at 2.5x the noise: refit
    diel[1], metal[1] = 7.0, 1.5  # ... a metal at the noise level: a metal
    diel[2], metal[2] = 3.0, 1.0  # ... and here: no refit needed
    diel[3], metal[3] = 20.0, 4.0  # stuck far above the noise: refit
    rows = classes.unconverged_dielectric_rows(diel, metal, 1 / 36, 36, 1e-4)
    assert rows.tolist() == [0, 3]


def test_edge_pixels_vote_with_the_neighbours_they_have():
    """Issue 13: an edge pixel has 5 neighbours (a corner 3), not copies of itself (replicate
    padding let an edge row outvote the rows inside and kept a frame of the wrong class)."""

    size = 6
    diel = torch.ones(size * size, 1)
    met = torch.full((size * size, 1), 0.01)  # decisively metal everywhere ...
    met.view(size, size)[0, :] = 1.0  # ... except the top edge row: ambiguous
    label = classes.choose_class(diel, met, size, 1 / 36, 36, 1e-4).view(size, size)
    assert torch.equal(label, torch.ones(size, size))  # the edge row joins the metal inside it
    # A corner pixel with 2 of its 3 neighbours decisively metal takes their class.
    met = torch.full((size * size, 1), 10.0)
    met.view(size, size)[0, 0] = 1.0
    met.view(size, size)[0, 1] = met.view(size, size)[1, 0] = 0.01
    assert float(classes.choose_class(diel, met, size, 1 / 36, 36, 1e-4).view(size, size)[0, 0]) == 1.0
    # The NaN fill averages the neighbours that exist.
    x = torch.arange(size * size, dtype=torch.float32).reshape(-1, 1)
    assert float(map_ops.neighbour_mean(x, size)[0]) == (1.0 + size) / 2
