"""The joint light step's per-pixel elimination in C (kernels/schur_ops.py) against a dense float64 reference.

The reference forms, per pixel, ``A = JpᵀWJp + H``, ``B = JpᵀWJg`` (light by light) and
``gp = JpᵀWr + g``, inverts ``A`` densely and sums ``[B | gp]ᵀ A⁻¹ [B | gp]``; the per-light
terms are ``Σ [Jg | r]ᵀ W [Jg | r]`` over the light's colours and every pixel.
"""

import pytest
import torch

from torchbrdf.kernels import build, schur_ops

pytestmark = pytest.mark.skipif(not build.available(), reason="needs the C kernels")


def _case(n, n_l, G, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    r = 0.05 * torch.randn(n, 3 * n_l, generator=g, dtype=f64)
    r[0, 1] = 2.0  # a residual far beyond 3 noise deviations: a Huber weight below 1
    cols = torch.randn(7 + G, n, 3 * n_l, generator=g, dtype=f64)
    prior_g = 1e-2 * torch.randn(n, 7, generator=g, dtype=f64)
    prior_h = torch.rand(n, 7, generator=g, dtype=f64)
    return r.to(dtype), cols.to(dtype), prior_g, prior_h


def _reference(r, cols, prior_g, prior_h, damping, huber):
    f64 = torch.float64
    r, cols = r.to(f64), cols.to(f64)
    n, M = r.shape
    n_l, G = M // 3, cols.shape[0] - 7
    w = (huber / r.abs().clamp(min=1e-30)).clamp(max=1.0)
    jp = cols[:7].permute(1, 0, 2)  # (n, 7, M)
    jg = cols[7:].permute(1, 2, 0).reshape(n, n_l, 3, G)
    jpw = jp * w[:, None]
    a = jpw @ jp.mT
    a = a + torch.diag_embed(damping * a.diagonal(dim1=-2, dim2=-1) + 1e-9 + prior_h)
    good = torch.linalg.cholesky_ex(a).info == 0
    b = torch.einsum("nklc,nlcg->nklg", jpw.reshape(n, 7, n_l, 3), jg).reshape(n, 7, -1)
    bg = torch.cat((b, ((jpw @ r[..., None])[..., 0] + prior_g)[..., None]), -1)[good]
    gram = torch.einsum("nki,nkj->ij", bg, torch.linalg.inv(a[good]) @ bg)
    aug = torch.cat((jg, r.reshape(n, n_l, 3, 1)), -1)[good]  # (n, L, 3, G + 1)
    per = torch.einsum("nlcg,nlc,nlch->lgh", aug, w.reshape(n, n_l, 3)[good], aug)
    return per, gram


@pytest.mark.parametrize("G", [4, 1])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_light_schur_is_the_dense_elimination(G, dtype):
    """21 pixels in chunks of 16 (a full and a partial block of 8 pixels, and a partial chunk),
    5 lights; one pixel's ``A`` is not positive definite and is left out."""
    r, cols, prior_g, prior_h = _case(21, 5, G, dtype)
    prior_h[6, 3] = -1e6
    per, gram = schur_ops.light_schur(r, cols, prior_g, prior_h, 1e-3, 0.15, chunk=16)
    ref_per, ref_gram = _reference(r, cols, prior_g, prior_h, 1e-3, 0.15)
    assert per.dtype == gram.dtype == torch.float64
    assert per.shape == (5, G + 1, G + 1) and gram.shape == (5 * G + 1,) * 2
    torch.testing.assert_close(per, ref_per, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(gram, ref_gram, rtol=1e-11, atol=1e-11 * float(ref_gram.abs().max()))
    # the left-out pixel would have changed both
    prior_h[6, 3] = 1.0
    assert float((_reference(r, cols, prior_g, prior_h, 1e-3, 0.15)[1] - ref_gram).abs().max()) > 1e-6


@pytest.mark.parametrize("G", [4, 1])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_light_schur_takes_the_base_colour_in_one_row_with_the_bits_of_three(G, dtype):
    """``base_one``: the base colour's unknowns in one row of ``cols``, each read on its own
    channel's residuals only (the row's other entries are not theirs: random here), give the
    bits of the full layout with those entries zero (21 pixels, chunks of 16, 5 lights)."""
    r, cols, prior_g, prior_h = _case(21, 5, G, dtype, seed=2)
    own = torch.arange(15) % 3 == torch.arange(3)[:, None]  # (3, M): unknown c on channel c
    full = torch.cat((cols[:1] * own[:, None].to(dtype), cols[3:]))  # (7 + G, n, M)
    compact = torch.cat((cols[:1], cols[3:]))  # (5 + G, n, M)
    per, gram = schur_ops.light_schur(r, compact, prior_g, prior_h, 1e-3, 0.15, chunk=16, base_one=True)
    want_per, want_gram = schur_ops.light_schur(r, full, prior_g, prior_h, 1e-3, 0.15, chunk=16)
    assert per.shape == (5, G + 1, G + 1) and gram.shape == (5 * G + 1,) * 2
    assert torch.equal(per, want_per) and torch.equal(gram, want_gram)
    with pytest.raises(ValueError, match="cols"):
        schur_ops.light_schur(r, compact[:4], prior_g, prior_h, 1e-3, 0.1, base_one=True)


def test_light_schur_passes_opcheck():
    r, cols, prior_g, prior_h = _case(10, 3, 4, torch.float64, seed=1)
    torch.library.opcheck(torch.ops.torchbrdf.light_schur, (r, cols, prior_g, prior_h, 1e-3, 0.1, 8))


def test_light_schur_names_a_bad_argument():
    r, cols, prior_g, prior_h = _case(6, 2, 4, torch.float64)
    with pytest.raises(ValueError, match="cols"):
        schur_ops.light_schur(r, cols[:, :5], prior_g, prior_h, 1e-3, 0.1)
    with pytest.raises(ValueError, match="priors"):
        schur_ops.light_schur(r, cols, prior_g[:5], prior_h, 1e-3, 0.1)


def test_light_schur_refuses_what_the_kernel_cannot_read():
    """The C loop reads raw CPU memory as float32 or float64 and keeps a pixel's residuals on its
    stack: another dtype, a tensor off the CPU, more than MAX_RESIDUALS residuals or no pixels
    per chunk are refused by name before any memory is read (not read as garbage)."""
    r, cols, prior_g, prior_h = _case(6, 2, 4, torch.float64)
    with pytest.raises(ValueError, match="dtype"):
        schur_ops.light_schur(r.half(), cols.half(), prior_g, prior_h, 1e-3, 0.1)
    with pytest.raises(ValueError, match="dtype"):
        torch.ops.torchbrdf.light_schur(r.half(), cols.half(), prior_g, prior_h, 1e-3, 0.1, 8)
    with pytest.raises(ValueError, match="CPU"):
        schur_ops.light_schur(r, cols, prior_g.to("meta"), prior_h, 1e-3, 0.1)
    m_big = 3 * (schur_ops.MAX_RESIDUALS // 3 + 1)
    with pytest.raises(ValueError, match="MAX_RESIDUALS"):
        schur_ops.light_schur(torch.zeros(0, m_big), torch.zeros(8, 0, m_big), torch.zeros(0, 7),
                              torch.zeros(0, 7), 1e-3, 0.1)
    with pytest.raises(ValueError, match="MAX_RESIDUALS"):
        schur_ops.light_schur(r[:, :0], cols[:, :, :0], prior_g, prior_h, 1e-3, 0.1)
    with pytest.raises(ValueError, match="chunk"):
        schur_ops.light_schur(r, cols, prior_g, prior_h, 1e-3, 0.1, chunk=0)
    with pytest.raises(ValueError, match=r"r must be \(n, M\)"):
        schur_ops.light_schur(r[None], cols, prior_g, prior_h, 1e-3, 0.1)
