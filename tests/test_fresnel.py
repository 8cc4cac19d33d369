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
