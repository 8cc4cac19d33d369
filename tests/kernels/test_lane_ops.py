"""The LM step's lane-wise linear algebra in C (kernels/lane_ops.py) against the PyTorch forms and
dense float64 references.

The C operators repeat the PyTorch forms' floating-point operations in the same order per element
(ATen's ``addcmul`` as one fused multiply-add where its kernels use them), so they are compared
bit for bit with the forms of :mod:`torchbrdf.recovery.pixel_systems` (run with the fused path
off), and each against a dense float64 reference that a wrong order, a wrong border or swapped
weights would not match. The CG loop in one call (``lane_cg``) sums its dot products in float64
in its own order: :func:`torchbrdf.recovery.smoothness_prior.pcg` on it is compared with the
PyTorch loop to rounding, after each of the first iterations (where a wrong step length or
direction would show).
"""

import contextlib

import pytest
import torch

from torchbrdf.brdf import principled
from torchbrdf.kernels import build, lane_ops
from torchbrdf.recovery import pixel_systems, smoothness_prior

pytestmark = pytest.mark.skipif(not build.available(), reason="needs the C kernels")

F64 = torch.float64


@contextlib.contextmanager
def pytorch_forms():
    """The PyTorch forms inside the block (the fused path off), the default after it."""
    principled.set_fast_path(False)
    try:
        yield
    finally:
        principled.set_fast_path(None)


def _spd_lanes(n, p, seed=0, dtype=F64):
    """``p`` SPD matrices as lanes ``(n, n, p)``, condition numbers up to 1e4; the last is
    numerically singular (a direction with nothing on it: its last pivot meets the floor)."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(p, n, n + 2, generator=gen, dtype=F64)
    m = a @ a.mT + 1e-4 * torch.eye(n, dtype=F64)
    m[-1] = torch.ones(n, n, dtype=F64) + torch.diag(torch.linspace(1.0, 2.0, n, dtype=F64))
    m[-1, :, -1] = m[-1, -1, :] = m[-1, :, 0]  # last row = first row: singular
    m[-1, -1, -1] = m[-1, 0, 0]
    return pixel_systems.to_lanes(m).to(dtype)


def _lower(low):
    n = low.shape[0]
    return low[torch.tril(torch.ones(n, n, dtype=torch.bool), -1)]


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("n", [1, 3, 7])
def test_lane_ldl_is_the_pytorch_form_bit_for_bit(n, dtype):
    m = _spd_lanes(n, 300, seed=n, dtype=dtype)  # 300 lanes: whole blocks of 256 and a partial one
    with pytorch_forms():
        low0, d0 = pixel_systems.ldl_factor(m)
    low1, d1 = lane_ops.lane_ldl(m)
    assert torch.equal(d0, d1) and torch.equal(_lower(low0), _lower(low1))
    if n > 1:  # the singular block's last pivot is the floor, not a rounding residue or a NaN
        floor = m[-1, -1, -1].abs() * lane_ops.PIVOT_FLOOR + torch.finfo(dtype).tiny
        assert float(d1[-1, -1]) == float(floor) or float(d1[-1, -1]) > 0


def test_lane_ldl_factors_each_pixels_own_matrix():
    """``L D Lᵀ`` rebuilds every pixel's matrix (lanes, rows and columns kept apart) to 1e-14."""
    m = _spd_lanes(5, 40, seed=2)[..., :-1]
    low, d = lane_ops.lane_ldl(m)
    ll = torch.tril(low.permute(2, 0, 1), -1) + torch.eye(5, dtype=F64)
    rebuilt = ll @ torch.diag_embed(d.T) @ ll.mT
    scale = m.permute(2, 0, 1).abs().amax((1, 2), keepdim=True)
    assert float(((rebuilt - m.permute(2, 0, 1)) / scale).abs().max()) < 1e-14


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_lane_solves_are_the_pytorch_forms_and_the_triangular_solves(dtype):
    m = _spd_lanes(6, 70, seed=4)[..., :-1]
    low, _ = lane_ops.lane_ldl(m)
    low = low.to(dtype)
    v = torch.randn(6, 3, 69, generator=torch.Generator().manual_seed(5), dtype=dtype)
    with pytorch_forms():
        lo0, up0 = pixel_systems.lower_solve(low, v.clone()), pixel_systems.upper_solve(low, v.clone())
    lo1, up1 = lane_ops.lane_lower_solve(low, v.clone()), lane_ops.lane_upper_solve(low, v.clone())
    assert torch.equal(lo0, lo1) and torch.equal(up0, up1)
    ll = (torch.tril(low.permute(2, 0, 1), -1) + torch.eye(6, dtype=dtype)).double()
    ref = torch.linalg.solve_triangular(ll, v.permute(2, 0, 1).double(), upper=False, unitriangular=True)
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == F64 else {"rtol": 1e-5, "atol": 1e-6}
    torch.testing.assert_close(lo1.permute(2, 0, 1).double(), ref, **tol)
    ref_up = torch.linalg.solve_triangular(ll.mT, v.permute(2, 0, 1).double(), upper=True, unitriangular=True)
    torch.testing.assert_close(up1.permute(2, 0, 1).double(), ref_up, **tol)


def _grid_case(n, size, seed=0, dtype=F64):
    gen = torch.Generator().manual_seed(seed)
    low, d = lane_ops.lane_ldl(_spd_lanes(n, size * size + 1, seed=seed)[..., :-1])
    wx = torch.rand(n, size, size - 1, generator=gen, dtype=F64)
    wy = 2.0 + torch.rand(n, size - 1, size, generator=gen, dtype=F64)  # unlike wx: a swap shows
    v = torch.randn(n, size * size, generator=gen, dtype=F64)
    return [t.to(dtype) for t in (low, torch.rsqrt(d), wx, wy, v)]


def _dense_coupling(low, d_isqrt, wx, wy, v, wrap=False):
    """``D^-½ L⁻¹ N L⁻ᵀ D^-½ v`` with ``N`` a dense ``(n P, n P)`` matrix built edge by edge
    (``wrap``: a wrong border, also joining each row's last pixel to its first with ``wx[..., 0]``)."""
    n, p = v.shape
    size = wx.shape[1]
    big = torch.zeros(n, p, n, p, dtype=F64)
    for c in range(n):
        for i in range(size):
            for j in range(size):
                here = i * size + j
                if j + 1 < size:
                    big[c, here, c, here + 1] = big[c, here + 1, c, here] = wx[c, i, j]
                elif wrap:
                    big[c, here, c, i * size] = big[c, i * size, c, here] = wx[c, i, 0]
                if i + 1 < size:
                    big[c, here, c, here + size] = big[c, here + size, c, here] = wy[c, i, j]
    ll = torch.tril(low.double().permute(2, 0, 1), -1) + torch.eye(n, dtype=F64)  # (p, n, n)
    t = torch.linalg.solve_triangular(ll.mT, (v.double() * d_isqrt.double()).T[..., None], upper=True,
                                      unitriangular=True)[..., 0].T  # (n, p)
    nb = (big.reshape(n * p, n * p) @ t.reshape(-1)).reshape(n, p)
    return torch.linalg.solve_triangular(ll, nb.T[..., None], upper=False, unitriangular=True)[..., 0].T \
        * d_isqrt.double()


@pytest.mark.parametrize("n", [1, 2, 5])
def test_lane_coupling_is_the_stencil(n):
    """A 5×5 grid (border pixels with 2 and 3 neighbours, in blocks the C loop splits): the
    operator is the dense definition to 1e-13; swapped ``wx``/``wy`` or a grid that wraps
    around at its border would be far from it."""
    low, d_isqrt, wx, wy, v = _grid_case(n, 5, seed=n)
    k = lane_ops.lane_coupling(low, d_isqrt, wx, wy, v, False)
    ref = _dense_coupling(low, d_isqrt, wx, wy, v)
    torch.testing.assert_close(k, ref, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(lane_ops.lane_coupling(low, d_isqrt, wx, wy, v, True), v - ref, rtol=1e-13,
                               atol=1e-13)
    swapped = _dense_coupling(low, d_isqrt, wy.transpose(1, 2), wx.transpose(1, 2), v)
    assert float((swapped - k).abs().max()) > 1e-2
    assert float((_dense_coupling(low, d_isqrt, wx, wy, v, wrap=True) - k).abs().max()) > 1e-2


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("n", [1, 2, 5])
def test_lane_coupling_is_the_pytorch_form_bit_for_bit(n, dtype):
    """The operator ``K v`` and ``(I − K) v`` of one CG iteration: exactly the PyTorch form's bits
    (on a 17×17 grid: rows longer than the vector width, blocks the C loop splits)."""
    low, d_isqrt, wx, wy, v = _grid_case(n, 17, seed=n, dtype=dtype)
    with pytorch_forms():
        k_ref, apply_ref = smoothness_prior._torch_coupling(low, d_isqrt, wx, wy, 17)
        ref, ref_sub = k_ref(v), apply_ref(v)
    assert torch.equal(lane_ops.lane_coupling(low, d_isqrt, wx, wy, v, False), ref)
    assert torch.equal(lane_ops.lane_coupling(low, d_isqrt, wx, wy, v, True), ref_sub)


def _pcg_case(size, joined, dtype, seed=0):
    """A coupled system like the LM step's: SPD blocks ``(P, 7, 7)`` float32/64, edge weights
    non-zero only on the ``joined`` channels (the others are eliminated per pixel first)."""
    gen = torch.Generator().manual_seed(seed)
    p, c = size * size, 7
    a = torch.randn(p, c, c + 3, generator=gen, dtype=F64)
    hess = a @ a.mT
    hess[3, :, 5] = hess[3, 5, :] = 0.0  # a pixel with no data on channel 5: held by its damping alone
    hess[3, 5, 5] = 0.0
    wx = torch.rand(size, size - 1, c, generator=gen, dtype=F64)
    wy = torch.rand(size - 1, size, c, generator=gen, dtype=F64)
    free = [k for k in range(c) if k not in joined]
    wx[..., free], wy[..., free] = 0.0, 0.0
    rhs = torch.randn(p, c, generator=gen, dtype=F64)
    diag = 1e-3 * torch.rand(p, c, generator=gen, dtype=F64)
    return [t.to(dtype) for t in (hess, wx, wy, rhs, diag)]


@pytest.mark.parametrize("joined", [[3, 4], [0, 1, 2, 3, 4], list(range(7)), []])
def test_pcg_on_the_c_operators_is_the_pytorch_form(joined):
    """The whole coupled solve (elimination, factorisation, CG iterations, back substitution) on a
    17×17 grid, float64: the C path (``lane_schur``, ``lane_cg``) gives the PyTorch form's
    iterates to rounding after 1, 2, 3, 5 and 25 iterations (the early ones far from the
    solution, so a wrong step length or search direction would be off by far more), with the
    damping diagonal and without, and when no channel is coupled."""
    hess, wx, wy, rhs, diag = _pcg_case(17, joined, F64, seed=len(joined))
    for d in (diag, None):
        for iters in (1, 2, 3, 5, 25):
            with pytorch_forms():
                ref = smoothness_prior.pcg(hess, wx, wy, rhs, 17, iters, diag=d)
            x = smoothness_prior.pcg(hess, wx, wy, rhs, 17, iters, diag=d)
            if d is None:  # (without damping pixel 3 has nothing on channel 5: a huge value)
                torch.testing.assert_close(x, ref, rtol=1e-10, atol=0, equal_nan=True)
                continue
            assert torch.isfinite(x).all()
            torch.testing.assert_close(x, ref, rtol=1e-10, atol=1e-10 * float(ref.abs().max()))
            if joined and iters < 5:  # an early iterate is not the solution: the comparison bites
                later = smoothness_prior.pcg(hess, wx, wy, rhs, 17, 200, diag=d)
                assert float((later - ref).abs().max()) > 1e-6 * float(ref.abs().max())


def _cg_case(n=2, size=6, seed=0):
    """A split-preconditioned CG system of :func:`lane_ops.lane_cg` (``I − K`` positive definite:
    ``K``'s weights small against the blocks) and its start ``y₀ = G⁻¹ b``, ``r₀ = K y₀``."""
    low, d_isqrt, wx, wy, b = _grid_case(n, size, seed=seed)
    wx, wy = 0.01 * wx, 0.01 * wy  # (I − K positive definite: K's spectrum within ±0.3)
    y0 = pixel_systems.lower_solve(low, b.clone()).mul_(d_isqrt)
    return low, d_isqrt, wx, wy, y0, lane_ops.lane_coupling(low, d_isqrt, wx, wy, y0, False)


def test_lane_cg_solves_the_split_system_and_its_sums_do_not_depend_on_the_threads():
    """Enough iterations solve ``(I − K) y = G⁻¹ b`` (checked with the dense operator); the
    result has the same bits at 1 and 2 threads (the dot products are summed by grid rows,
    then over the rows in order); ``y`` and ``r`` are left as they were."""
    low, d_isqrt, wx, wy, y0, r0 = _cg_case()
    y0_copy, r0_copy = y0.clone(), r0.clone()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = lane_ops.lane_cg(low, d_isqrt, wx, wy, y0, r0, 60)
        torch.set_num_threads(2)
        two = lane_ops.lane_cg(low, d_isqrt, wx, wy, y0, r0, 60)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)
    assert torch.equal(y0, y0_copy) and torch.equal(r0, r0_copy)
    g_inv_b = y0  # (y₀ = G⁻¹ b)
    residual = one - _dense_coupling(low, d_isqrt, wx, wy, one) - g_inv_b
    assert float(residual.abs().max()) < 1e-10 * float(g_inv_b.abs().max())
    start = y0 - _dense_coupling(low, d_isqrt, wx, wy, y0) - g_inv_b
    assert float(start.abs().max()) > 1e-3  # (y₀ is not the solution)


def test_lane_cg_stops_at_a_breakdown():
    """No coupling (zero weights): the start is the solution, ``r₀ = 0`` and ``dᵀ(I − K)d = 0`` at
    the first iteration: CG stops there and returns the start, not a NaN step (0 / 0); no iteration
    returns the start too."""
    low, d_isqrt, wx, wy, y0, _ = _cg_case(seed=2)
    zero_x, zero_y = torch.zeros_like(wx), torch.zeros_like(wy)
    r0 = lane_ops.lane_coupling(low, d_isqrt, zero_x, zero_y, y0, False)
    assert not r0.any()
    assert torch.equal(lane_ops.lane_cg(low, d_isqrt, zero_x, zero_y, y0, r0, 10), y0)
    assert torch.equal(lane_ops.lane_cg(low, d_isqrt, wx, wy, y0, r0, 0), y0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_pcg_without_coupling_solves_on_the_c_operators(monkeypatch, dtype):
    """With no channel coupled each pixel's block is solved alone: its right-hand sides are laid
    out contiguously, so the substitutions run in C too (a strided view kept the PyTorch loops)."""
    hess, wx, wy, rhs, diag = _pcg_case(5, [], dtype)
    calls = []
    for name in ("lane_lower_solve", "lane_upper_solve"):
        real = getattr(lane_ops, name)
        monkeypatch.setattr(lane_ops, name, lambda low, v, real=real: calls.append(1) or real(low, v))
    smoothness_prior.pcg(hess, wx, wy, rhs, 5, 10, diag=diag)
    assert len(calls) == 2


def test_lane_schur_is_the_dense_elimination():
    """The complement ``S = A − B D⁻¹ Bᵀ + diag(lapd)`` rebuilt from the factors, and
    ``b = rhs_a − B D⁻¹ rhs_u``, against dense float64 algebra per pixel (the channels reordered)."""
    hess, _, _, rhs, diag = _pcg_case(4, [0, 1, 2], F64, seed=3)
    order, nu = [3, 4, 5, 6, 0, 1, 2], 4
    lapd = torch.rand(16, 3, generator=torch.Generator().manual_seed(8), dtype=F64)
    low_u, d_u, bt, rhs_u, low, d_isqrt, b = lane_ops.lane_schur(hess, diag, rhs, order, nu, lapd)
    h = (hess + torch.diag_embed(diag))[:, order][:, :, order]
    r = rhs[:, order]
    dm, bm, am = h[:, :nu, :nu], h[:, :nu, nu:], h[:, nu:, nu:]
    s_ref = am - bm.mT @ torch.linalg.solve(dm, bm) + torch.diag_embed(lapd)
    b_ref = r[:, nu:] - (bm.mT @ torch.linalg.solve(dm, r[:, :nu, None]))[..., 0]
    ll = torch.tril(low.permute(2, 0, 1), -1) + torch.eye(3, dtype=F64)
    s = ll @ torch.diag_embed(d_isqrt.T ** -2) @ ll.mT
    torch.testing.assert_close(s, s_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(b.T, b_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(bt.permute(2, 0, 1), bm, rtol=0, atol=0)
    torch.testing.assert_close(rhs_u.T, r[:, :nu], rtol=0, atol=0)
    lu = torch.tril(low_u.permute(2, 0, 1), -1) + torch.eye(nu, dtype=F64)
    torch.testing.assert_close(lu @ torch.diag_embed(d_u.T) @ lu.mT, dm, rtol=1e-12, atol=1e-12)


def _args():
    low, d_isqrt, wx, wy, v = _grid_case(3, 4, seed=1)
    hess, _, _, rhs, diag = _pcg_case(4, [3, 4], F64)
    return low, d_isqrt, wx, wy, v, hess, rhs, diag


def test_lane_ops_pass_opcheck():
    low, d_isqrt, wx, wy, v, hess, rhs, diag = _args()
    m = _spd_lanes(3, 16)
    torch.library.opcheck(torch.ops.torchbrdf.lane_ldl, (m,))
    torch.library.opcheck(torch.ops.torchbrdf.lane_lower_solve_, (low, v.clone()))
    torch.library.opcheck(torch.ops.torchbrdf.lane_upper_solve_, (low, v.clone()))
    torch.library.opcheck(torch.ops.torchbrdf.lane_coupling, (low, d_isqrt, wx, wy, v, True))
    torch.library.opcheck(torch.ops.torchbrdf.lane_cg, (*_cg_case(3, 4, seed=1), 5))
    lapd = torch.rand(16, 2, dtype=F64)
    torch.library.opcheck(torch.ops.torchbrdf.lane_schur, (hess, diag, rhs, [0, 1, 2, 5, 6, 3, 4], 5, lapd))
    torch.library.opcheck(torch.ops.torchbrdf.lane_schur, (hess, None, rhs, [0, 1, 2, 5, 6, 3, 4], 5, lapd))


def test_lane_ops_fake_outputs_are_laid_out_as_the_real_ones_for_strided_inputs():
    """The C loops read a contiguous copy and write fresh contiguous outputs; the fake
    implementations torch.compile plans with must give those strides too, not the input's."""
    low, d_isqrt, wx, wy, v, *_ = _args()
    m = _spd_lanes(3, 16).permute(2, 0, 1).contiguous().permute(1, 2, 0)  # (n, n, P), pixels outermost
    torch.library.opcheck(torch.ops.torchbrdf.lane_ldl, (m,))
    v_t = v.T.contiguous().T  # (n, P) with the channels innermost
    torch.library.opcheck(torch.ops.torchbrdf.lane_coupling, (low, d_isqrt, wx, wy, v_t, False))


def test_lane_ops_do_not_drop_a_gradient_or_an_in_place_change_silently():
    """The operators have no autograd: an input that needs a gradient gets the operator's
    "no autograd" error at backward (not a result silently cut off the graph), and a solve in
    place marks its ``v`` changed, so a backward that saved ``v`` refuses to run."""
    low, d_isqrt, wx, wy, v, *_ = _args()
    m = _spd_lanes(3, 16).requires_grad_()
    low_m, d_m = lane_ops.lane_ldl(m)
    assert low_m.requires_grad
    with pytest.raises(RuntimeError):
        low_m.sum().backward()
    out = lane_ops.lane_coupling(low, d_isqrt, wx, wy, v.clone().requires_grad_(), True)
    assert out.requires_grad
    x = torch.ones_like(v, requires_grad=True)
    rhs = v.clone()
    y = (x * rhs).sum()  # saves rhs for its backward
    lane_ops.lane_lower_solve(low, rhs)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        y.backward()
    with torch.inference_mode():  # (no version counter there: the solve still runs)
        lane_ops.lane_upper_solve(low, v.clone())


def test_lane_ops_refuse_what_the_kernels_cannot_read():
    """Raw CPU memory of one float type, read at the shapes given: another dtype, a tensor off
    the CPU, a wrong shape or a bad channel order is refused by name before anything is read."""
    low, d_isqrt, wx, wy, v, hess, rhs, diag = _args()
    with pytest.raises(ValueError, match="low must be float32 or float64"):
        lane_ops.lane_coupling(low.half(), d_isqrt, wx, wy, v, True)
    with pytest.raises(ValueError, match="d_isqrt must be float32 or float64"):
        lane_ops.lane_coupling(low, d_isqrt.float(), wx, wy, v, True)
    with pytest.raises(ValueError, match="wx must be on the CPU"):
        lane_ops.lane_coupling(low, d_isqrt, wx.to("meta"), wy, v, True)
    with pytest.raises(ValueError, match=r"wy must have shape \(3, 3, 4\)"):
        lane_ops.lane_coupling(low, d_isqrt, wx, wy.transpose(1, 2), v, True)
    with pytest.raises(ValueError, match="wx must have shape"):  # wx and wy swapped
        lane_ops.lane_coupling(low, d_isqrt, wy, wx, v, True)
    with pytest.raises(ValueError, match="v must have shape"):
        lane_ops.lane_coupling(low, d_isqrt, wx, wy, v[:, :-1], True)
    with pytest.raises(ValueError, match="not a square grid"):
        lane_ops.lane_coupling(low[..., :-1], d_isqrt, wx, wy, v, True)
    with pytest.raises(ValueError, match="MAX_SIZE"):
        lane_ops.lane_ldl(torch.zeros(17, 17, 4, dtype=F64))
    with pytest.raises(ValueError, match="v must be contiguous"):
        lane_ops.lane_lower_solve(low, torch.empty(16, 3, dtype=F64).T.copy_(v))
    with pytest.raises(ValueError, match="v must be"):
        lane_ops.lane_upper_solve(low, v.float())
    y0, r0 = v, v.clone()
    with pytest.raises(ValueError, match="iters must be >= 0"):
        lane_ops.lane_cg(low, d_isqrt, wx, wy, y0, r0, -1)
    with pytest.raises(ValueError, match="r must have shape"):
        lane_ops.lane_cg(low, d_isqrt, wx, wy, y0, r0[:, :-1], 3)
    with pytest.raises(ValueError, match="y must be float32 or float64"):
        lane_ops.lane_cg(low, d_isqrt, wx, wy, y0.float(), r0, 3)
    with pytest.raises(ValueError, match="order must be a permutation"):
        lane_ops.lane_schur(hess, diag, rhs, [0, 1, 2, 3, 4, 5, 5], 5, torch.zeros(16, 2, dtype=F64))
    with pytest.raises(ValueError, match="lapd must have shape"):
        lane_ops.lane_schur(hess, diag, rhs, [0, 1, 2, 5, 6, 3, 4], 5, torch.zeros(16, 3, dtype=F64))
    with pytest.raises(ValueError, match="MAX_SCHUR"):
        lane_ops.lane_schur(torch.zeros(4, 9, 9, dtype=F64), None, torch.zeros(4, 9, dtype=F64),
                            list(range(9)), 0, torch.zeros(4, 9, dtype=F64))
    with pytest.raises(ValueError, match="rhs must be float32 or float64"):
        lane_ops.lane_schur(hess, diag, rhs.float(), [0, 1, 2, 5, 6, 3, 4], 5, torch.zeros(16, 2, dtype=F64))
