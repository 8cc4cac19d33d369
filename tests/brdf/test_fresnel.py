"""Fresnel terms against their closed forms and physical identities."""

import math

import pytest
import torch

from torchbrdf.brdf import fresnel as fr


def test_schlick_formula_and_endpoints():
    c = torch.linspace(0, 1, 11, dtype=torch.float64)[:, None]
    f0 = torch.tensor([0.04, 0.5, 0.9], dtype=torch.float64)
    out = fr.fresnel_schlick(c, f0)
    torch.testing.assert_close(out, f0 + (1 - f0) * (1 - c) ** 5)
    torch.testing.assert_close(fr.fresnel_schlick(c, f0, 0.5)[0], torch.full((3,), 0.5, dtype=torch.float64))


@pytest.mark.parametrize("ior", [1.33, 1.5, 2.4])
def test_dielectric_normal_incidence_and_snell(ior):
    f = fr.fresnel_dielectric(torch.tensor([[1.0]], dtype=torch.float64), ior)
    assert float(f) == pytest.approx(fr.f0_from_ior(ior), rel=1e-12)
    # Independent textbook form through the refraction angle.
    ti = torch.linspace(0.01, 1.5, 50, dtype=torch.float64)[:, None]
    tt = torch.asin(torch.sin(ti) / ior)
    rs = (torch.sin(ti - tt) / torch.sin(ti + tt)) ** 2
    rp = (torch.tan(ti - tt) / torch.tan(ti + tt)) ** 2
    torch.testing.assert_close(fr.fresnel_dielectric(torch.cos(ti), ior), 0.5 * (rs + rp), rtol=1e-10, atol=1e-12)


def test_total_internal_reflection_from_inside():
    critical = math.asin(1 / 1.5)
    c = torch.tensor([[-math.cos(critical + 0.05)], [-math.cos(critical - 0.05)]], dtype=torch.float64)
    f = fr.fresnel_dielectric(c, 1.5)
    assert float(f[0]) == 1.0 and float(f[1]) < 1.0


def test_conductor_reduces_to_dielectric_and_normal_incidence():
    c = torch.linspace(0.02, 1.0, 30, dtype=torch.float64)[:, None]
    torch.testing.assert_close(fr.fresnel_conductor(c, 1.5, 0.0), fr.fresnel_dielectric(c, 1.5), rtol=1e-9, atol=1e-12)
    eta, k = 0.2, 3.9  # roughly gold at 550 nm
    one = fr.fresnel_conductor(torch.tensor([[1.0]], dtype=torch.float64), eta, k)
    assert float(one) == pytest.approx(((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2), rel=1e-10)
    # Against complex arithmetic.
    ti = torch.acos(c)
    n_c = complex(eta, k)
    ci = torch.cos(ti).to(torch.complex128)
    ct = torch.sqrt(1 - torch.sin(ti).to(torch.complex128) ** 2 / n_c ** 2)
    rs = (ci - n_c * ct) / (ci + n_c * ct)
    rp = (n_c * ci - ct) / (n_c * ci + ct)
    ref = 0.5 * (rs.abs() ** 2 + rp.abs() ** 2)
    torch.testing.assert_close(fr.fresnel_conductor(c, eta, k), ref, rtol=1e-9, atol=1e-12)


def test_conversions_round_trip():
    assert fr.f0_from_specular(0.5) == pytest.approx(0.04)
    assert fr.specular_from_f0(0.04) == pytest.approx(0.5)
    assert float(fr.ior_from_f0(fr.f0_from_ior(1.5))) == pytest.approx(1.5)


def test_gradcheck_and_finite_at_edges():
    c = torch.tensor([[0.1], [0.5], [0.9]], dtype=torch.float64, requires_grad=True)
    eta = torch.tensor([[1.3], [1.6], [2.0]], dtype=torch.float64, requires_grad=True)
    k = torch.tensor([[0.5], [2.0], [3.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fr.fresnel_dielectric, (c, eta))
    assert torch.autograd.gradcheck(fr.fresnel_conductor, (c, eta, k))
    assert torch.autograd.gradcheck(lambda c, e: fr.fresnel_schlick(c, e * 0.1), (c, eta))
    edge = torch.tensor([[0.0], [1.0], [-0.2]], dtype=torch.float64, requires_grad=True)
    out = fr.fresnel_dielectric(edge, 1.5) + fr.fresnel_conductor(edge, 0.2, 3.0)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(edge.grad).all()


# --------------------------------------------------------------------------------------
# Conductor Fresnel against pbrt-v4's FrComplex, everywhere
# --------------------------------------------------------------------------------------


def fr_complex(cos_i, eta, k):
    """pbrt-v4 ``FrComplex`` in numpy complex128: the deliberate independent copy.

    ``sin2_t = sin2_i / eta^2``, ``cos_t = sqrt(1 - sin2_t)`` (principal branch),
    ``r_parl = (eta cos_i - cos_t) / (eta cos_i + cos_t)``,
    ``r_perp = (cos_i - eta cos_t) / (cos_i + eta cos_t)``, ``R = (|r_parl|^2 + |r_perp|^2) / 2``.
    """
    import numpy as np

    n = np.asarray(eta, dtype=np.float64) + 1j * np.asarray(k, dtype=np.float64)
    cos_i = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0).astype(np.complex128)
    sin2_i = 1.0 - cos_i * cos_i
    sin2_t = sin2_i / (n * n)
    cos_t = np.sqrt(1.0 - sin2_t)
    r_parl = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    r_perp = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    return 0.5 * (np.abs(r_parl) ** 2 + np.abs(r_perp) ** 2)


def _conductor_grid():
    import numpy as np

    eta = np.concatenate([np.geomspace(0.05, 5.0, 41), [0.5, 0.999, 1.0, 1.001]])
    k = np.concatenate([[0.0], np.geomspace(1e-12, 10.0, 41), [1e-6, 2e-5]])
    theta = np.linspace(0.0, math.pi / 2, 181)
    # Beside each critical angle asin(eta) of eta < 1 too (exactly at it: see the mpmath test).
    crit = np.arcsin(eta[eta < 1])
    theta = np.concatenate([theta, *(crit + d for d in (-1e-4, -1e-9, 1e-9, 1e-6, 1e-4))])
    return np.meshgrid(np.cos(theta), eta, k, indexing="ij")


def test_conductor_matches_pbrt_frcomplex_everywhere():
    """<= 1e-8 relative over eta in [0.05, 5], k in [0, 10], every angle (float64).

    The 1e-15 absolute term only matters where R itself is ~0 (eta = 1, k = 0: no interface).
    """
    import numpy as np

    cos_i, eta, k = _conductor_grid()
    ref = fr_complex(cos_i, eta, k)
    got = fr.fresnel_conductor(*(torch.tensor(a) for a in (cos_i, eta, k))).numpy()
    err = np.abs(got - ref)
    # Points on a critical angle (the uniform grid hits 30 degrees for eta = 0.5) are
    # ill-conditioned for any float algorithm: test_conductor_at_the_exact_critical_angle.
    on_critical = (np.abs(np.arccos(cos_i) - np.arcsin(np.minimum(eta, 1.0))) < 1e-12) & (k < 1e-3)
    err[on_critical] = 0.0
    assert on_critical.sum() < 0.002 * on_critical.size
    worst = np.unravel_index(np.argmax(err / (1e-8 * ref + 1e-15)), err.shape)
    assert (err <= 1e-8 * ref + 1e-15).all(), (
        f"cos {cos_i[worst]}, eta {eta[worst]}, k {k[worst]}: {got[worst]} vs {ref[worst]}"
    )


def test_conductor_at_the_exact_critical_angle():
    """At the critical angle R has a square-root singularity: rounding sin^2 by 1 ulp moves R by
    ~1e-8..1e-6, so neither this form nor FrComplex can give 1e-8 there. Both are compared with
    a 60-digit evaluation; this form is within 1e-6 (FrComplex within 5e-6)."""
    mpmath = pytest.importorskip("mpmath")
    import numpy as np

    mpmath.mp.dps = 60

    def exact(cos_i, eta, k):
        c, n = mpmath.mpf(float(cos_i)), mpmath.mpc(float(eta), float(k))
        ct = mpmath.sqrt(1 - (1 - c * c) / (n * n))
        return float((abs((n * c - ct) / (n * c + ct)) ** 2 + abs((c - n * ct) / (c + n * ct)) ** 2) / 2)

    for eta in np.concatenate([np.geomspace(0.05, 0.999, 25), [0.5, 0.9976311574844398]]):
        cos_i = math.cos(math.asin(eta))
        for k in (0.0, 1e-12, 1e-8, 2e-5):
            got = float(fr.fresnel_conductor(torch.tensor([[cos_i]], dtype=torch.float64), float(eta), k))
            assert got == pytest.approx(exact(cos_i, eta, k), rel=1e-6), (eta, k)


@pytest.mark.parametrize("k", [0.0, 1e-8, 1e-6, 2e-5])
def test_conductor_nearly_lossless_beyond_critical_angle(k):
    """The old safe_sqrt floor forced a >= 1e-6 and was wrong by up to 4e-4 relative here."""
    import numpy as np

    eta = 0.5  # seen from the denser side: critical angle 30 degrees
    cos_i = np.cos(np.linspace(math.radians(30.5), math.radians(89.5), 60))[:, None]
    ref = fr_complex(cos_i, eta, k)
    got = fr.fresnel_conductor(torch.tensor(cos_i), eta, k).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=0)


@pytest.mark.parametrize(
    "cos_i, eta, k",
    [
        (0.3, 0.5, 0.0),  # lossless, total internal reflection
        (0.3, 0.5, 1e-3),  # nearly lossless beyond the critical angle
        (0.9, 0.5, 0.0),  # lossless, before the critical angle
        (0.5, 1.5, 0.0),  # dielectric from outside
        (0.2, 0.2, 3.0),  # gold-like
        (0.05, 4.0, 10.0),
    ],
)
def test_conductor_gradcheck(cos_i, eta, k):
    args = [torch.tensor([[v]], dtype=torch.float64, requires_grad=True) for v in (cos_i, eta, k)]
    assert torch.autograd.gradcheck(fr.fresnel_conductor, args)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_conductor_finite_values_and_gradients_everywhere(dtype):
    """Including k = 0 at and beyond the critical angle, eta = 1 (no interface), and grazing."""
    cos_i, eta, k = (torch.tensor(a).to(dtype).requires_grad_(True) for a in _conductor_grid())
    out = fr.fresnel_conductor(cos_i, eta, k)
    out.sum().backward()
    assert torch.isfinite(out).all() and (out >= 0).all() and (out <= 1).all()
    for t in (cos_i, eta, k):
        assert torch.isfinite(t.grad).all()
