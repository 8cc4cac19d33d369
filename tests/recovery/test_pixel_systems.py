"""Per-pixel symmetric positive definite systems stored lane-wise (``pixel_systems``), and the
coupled solve (``smoothness_prior.pcg``) and marginal information built on them."""

import pytest
import torch

from torchbrdf.recovery import lm, smoothness_prior
from torchbrdf.recovery.pixel_systems import cholesky_factor, inverse_diagonal, ldl_factor, ldl_solve, to_lanes


def _spd(p, n, seed=0, cond=1e3):
    """``p`` different SPD matrices ``(p, n, n)`` float64, condition numbers up to ``cond``."""
    gen = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(p, n, n, generator=gen, dtype=torch.float64))
    ev = torch.logspace(0, float(torch.log10(torch.tensor(cond))), n, dtype=torch.float64)
    ev = ev[torch.randperm(n, generator=gen)] * (1 + torch.rand(p, 1, generator=gen, dtype=torch.float64))
    return q @ torch.diag_embed(ev) @ q.transpose(-1, -2)


def test_cholesky_factor_matches_a_batched_cholesky_and_marks_the_indefinite():
    """Each pixel's factor is its own matrix's (lanes, rows and columns kept apart); a pixel that
    is not positive definite is marked and keeps a finite factor."""
    m = _spd(6, 7, seed=3)
    m[2] = -m[2]
    low, good = cholesky_factor(to_lanes(m))
    assert good.tolist() == [True, True, False, True, True, True]
    ref = torch.linalg.cholesky(m[good])  # (5, 7, 7)
    torch.testing.assert_close(low.permute(2, 0, 1)[good], ref, rtol=1e-12, atol=1e-12)
    assert torch.isfinite(low).all()


@pytest.mark.parametrize("n", [1, 2, 5, 7])
def test_ldl_solve_matches_a_batched_dense_solve(n):
    """Every pixel its own matrix and several right-hand sides: a factor or a solve that mixed
    up pixels (lanes), rows and columns, or the right-hand sides would not match."""
    p, k = 9, 3
    m = _spd(p, n, seed=n)
    rhs = torch.randn(p, n, k, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref = torch.linalg.solve(m, rhs)  # (p, n, k)
    lanes = to_lanes(m)
    assert lanes.shape == (n, n, p) and torch.equal(lanes[:, :, 4], m[4])
    lanes[0, 1:] = float("nan")  # the upper triangle is never read
    low, d = ldl_factor(lanes)
    x = ldl_solve(low, 1.0 / d, rhs.permute(1, 2, 0).clone())  # (n, k, p)
    torch.testing.assert_close(x.permute(2, 0, 1), ref, rtol=1e-9, atol=1e-12)


def test_inverse_diagonal_matches_the_inverse():
    m = _spd(11, 7, seed=3, cond=1e6)
    ref = torch.diagonal(torch.linalg.inv(m), dim1=-2, dim2=-1)
    torch.testing.assert_close(inverse_diagonal(to_lanes(m)).T, ref, rtol=1e-8, atol=0.0)


def test_to_lanes_copies_even_when_the_layout_needs_no_transpose():
    m = torch.eye(3, dtype=torch.float64)[None]  # one pixel: the transposed view is contiguous
    lanes = to_lanes(m)
    lanes += 1.0
    assert torch.equal(m[0], torch.eye(3, dtype=torch.float64))


def test_a_singular_block_gives_a_finite_solution():
    """A direction with no data and no damping: the pivot floor keeps the solve finite (a NaN
    would spread to every pixel through the coupled solve)."""
    m = torch.zeros(2, 3, 3, dtype=torch.float64)
    m[:, 0, 0] = 1.0  # rank 1
    m[1] = _spd(1, 3)[0]
    low, d = ldl_factor(to_lanes(m))
    assert bool((d > 0).all()) and bool(torch.isfinite(d).all())
    x = ldl_solve(low, 1.0 / d, torch.ones(3, 2, dtype=torch.float64))
    assert bool(torch.isfinite(x).all())
    assert float(x[0, 0]) == 1.0


def test_marginal_information_is_one_over_the_inverse_diagonal():
    p = 6
    jtj = _spd(p, 7, seed=5, cond=1e5).float()
    info = lm.marginal_information(None, torch.zeros(p, 7), torch.zeros(p, 1), "principled", jtj)
    ref = 1.0 / torch.diagonal(torch.linalg.inv(jtj.double() + 1e-6 * torch.eye(7, dtype=torch.float64)),
                               dim1=-2, dim2=-1)
    assert info.dtype == torch.float32
    torch.testing.assert_close(info, ref.float(), rtol=1e-5, atol=0.0)


def _coupled_case(size=4, c=7, joined=range(0, 5), seed=0):
    gen = torch.Generator().manual_seed(seed)
    wx = torch.rand(size, size - 1, c, generator=gen, dtype=torch.float64)
    wy = torch.rand(size - 1, size, c, generator=gen, dtype=torch.float64)
    free = [k for k in range(c) if k not in joined]
    wx[..., free], wy[..., free] = 0.0, 0.0
    hess = _spd(size * size, c, seed=seed + 1, cond=1e2)
    rhs = torch.randn(size * size, c, generator=gen, dtype=torch.float64)
    return hess, wx, wy, rhs


def test_pcg_adds_the_diagonal_it_is_given():
    hess, wx, wy, rhs = _coupled_case()
    damp = torch.rand(rhs.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    x = smoothness_prior.pcg(hess, wx, wy, rhs, 4, 200, diag=damp)
    ref = smoothness_prior.pcg(hess + torch.diag_embed(damp), wx, wy, rhs, 4, 200)
    torch.testing.assert_close(x, ref, rtol=1e-9, atol=1e-11)
    assert not torch.allclose(x, smoothness_prior.pcg(hess, wx, wy, rhs, 4, 200))


def test_pcg_stops_at_its_start_on_non_finite_data():
    """A NaN right-hand side at one pixel: every other pixel keeps its own block solve (CG's
    start), as a stop at the first non-finite ``dᵀAd`` gives; iterating on would spread the NaN
    to the neighbours, and on to every pixel."""
    hess, wx, wy, rhs = _coupled_case(size=5)
    rhs[12, 3] = float("nan")
    start = smoothness_prior.pcg(hess, wx, wy, rhs, 5, 0)
    x = smoothness_prior.pcg(hess, wx, wy, rhs, 5, 30)
    assert int((~torch.isfinite(x)).any(-1).sum()) == 1
    torch.testing.assert_close(x, start, equal_nan=True, rtol=0.0, atol=0.0)


def test_pcg_iterates_in_the_right_hand_sides_dtype():
    hess, wx, wy, rhs = _coupled_case()
    x32 = smoothness_prior.pcg(hess.float(), wx.float(), wy.float(), rhs.float(), 4, 100)
    x64 = smoothness_prior.pcg(hess, wx, wy, rhs, 4, 100)
    assert x32.dtype == torch.float32
    torch.testing.assert_close(x32.double(), x64, rtol=1e-4, atol=1e-5)


def _reference_pcg(hess, wx, wy, rhs, size, iters, lo, hi):
    """The coupled solve's definition, dense, float64: the per-pixel elimination of the channels
    outside ``[lo, hi)``, then ``iters`` CG iterations on the Schur complement plus the Laplacian,
    preconditioned by the inverse of its per-pixel blocks, from ``x₀ = M⁻¹ b``."""
    p, c = rhs.shape
    a = list(range(lo, hi))
    u = [k for k in range(c) if k not in a]
    A, B, D = hess[:, a][:, :, a], hess[:, a][:, :, u], hess[:, u][:, :, u]
    bd = B @ torch.linalg.inv(D)
    s = A - bd @ B.transpose(1, 2)
    b = rhs[:, a] - (bd @ rhs[:, u, None])[..., 0]
    lap = []
    for k in range(p * len(a)):  # the joined channels' Laplacian, column by column
        e = torch.zeros(p * len(a), dtype=torch.float64)
        e[k] = 1.0
        full = torch.zeros(p, c, dtype=torch.float64)
        full[:, a] = e.reshape(p, len(a))
        lap.append(smoothness_prior.laplacian(full, wx, wy, size)[:, a].flatten())
    lap = torch.stack(lap, 1)
    blocks = s + torch.diag_embed(torch.diagonal(lap).reshape(p, len(a)))
    op = torch.block_diag(*s) + lap
    pre = torch.block_diag(*torch.linalg.inv(blocks))
    bf = b.flatten()
    x = pre @ bf
    r = bf - op @ x
    z = pre @ r
    d = z.clone()
    for _ in range(iters):
        alpha = (r @ z) / (d @ op @ d)
        x, r_new = x + alpha * d, r - alpha * (op @ d)
        z_new = pre @ r_new
        d = z_new + (r_new @ z_new) / (r @ z) * d
        r, z = r_new, z_new
    xa = x.reshape(p, len(a))
    xu = torch.linalg.solve(D, (rhs[:, u] - (B.transpose(1, 2) @ xa[..., None])[..., 0])[..., None])[..., 0]
    out = torch.empty_like(rhs)
    out[:, a], out[:, u] = xa, xu
    return out


@pytest.mark.parametrize("lo,hi", [(0, 5), (3, 5)])
def test_pcg_takes_the_preconditioned_iterates_of_its_definition(lo, hi):
    """After a few iterations, far from converged: the split-preconditioned iteration has the
    iterates of CG preconditioned by the complement's blocks. A wrong preconditioner (a missing
    Laplacian diagonal, the uncomplemented blocks) converges to the same solution, but not
    through the same iterates."""
    hess, wx, wy, rhs = _coupled_case(size=5, joined=range(lo, hi), seed=3)
    wx, wy = wx * 20.0, wy * 20.0  # strong coupling: CG needs many iterations
    for iters in (1, 3):
        x = smoothness_prior.pcg(hess, wx, wy, rhs, 5, iters)
        ref = _reference_pcg(hess, wx, wy, rhs, 5, iters, lo, hi)
        torch.testing.assert_close(x, ref, rtol=1e-8, atol=1e-10)
    far = smoothness_prior.pcg(hess, wx, wy, rhs, 5, 300)
    assert float((far - x).abs().max()) > 1e-3 * float(far.abs().max())  # 3 iterations: not converged yet


@pytest.mark.parametrize("nan", [False, True])
def test_pcg_takes_the_same_steps_with_host_reads_and_with_device_masks(nan, monkeypatch):
    """The CPU path (step lengths read on the host, a break at a breakdown) and the device path
    (masks, no synchronisation) give the same bits, with finite and non-finite data."""
    hess, wx, wy, rhs = _coupled_case(size=5, seed=4)
    hess, wx, wy, rhs = hess.float(), wx.float(), wy.float(), rhs.float()
    if nan:
        rhs[7, 4] = float("nan")
    host = smoothness_prior.pcg(hess, wx, wy, rhs, 5, 12)
    monkeypatch.setattr(smoothness_prior, "reads_host", lambda device: False)
    masked = smoothness_prior.pcg(hess, wx, wy, rhs, 5, 12)
    torch.testing.assert_close(masked, host, equal_nan=True, rtol=0.0, atol=0.0)
    assert bool(torch.isfinite(host).all()) != nan
