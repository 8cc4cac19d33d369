"""Every NDF integrates to one (∫ D (n·m) dω = 1), and the removable singularities are exact."""

import math

import pytest
import torch

from torchbrdf.brdf import distributions as nd

# Quadrature over θ with t = tan θ = e^u: 2π ∫ D t² / (1 + t²)² du, trapezoid on a wide u grid
# (covers θ from 1e-9 rad to within 1e-9 of the horizon), error << 1e-6 for these widths.
U = torch.linspace(-21.0, 21.0, 200001, dtype=torch.float64)
T = torch.exp(U)
COS = 1.0 / torch.sqrt(1.0 + T * T)
SIN2 = (T * T) / (1.0 + T * T)
JAC = T * T / (1.0 + T * T) ** 2


def integrate(d):
    return float(2 * math.pi * torch.trapezoid(d.reshape(-1) * JAC, U))


@pytest.mark.parametrize("alpha", [0.001, 0.01, 0.1, 0.5, 1.0, 1.7])
def test_ggx_normalised(alpha):
    assert abs(integrate(nd.ndf_ggx(COS, alpha, SIN2)) - 1.0) <= 1e-3


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.5, 1.0, 1.5])
@pytest.mark.parametrize("gamma", [0.6, 1.0, 1.5, 2.0, 3.0, 10.0])
def test_gtr_normalised(alpha, gamma):
    # γ <= 0.5 has a tail too heavy for this quadrature at α >= 1; γ >= 0.6 covers the fits.
    assert abs(integrate(nd.ndf_gtr(COS, alpha, gamma, SIN2)) - 1.0) <= 1e-3


@pytest.mark.parametrize("alpha", [0.001, 0.05, 0.3, 1.0])
def test_gtr1_normalised(alpha):
    assert abs(integrate(nd.ndf_gtr1(COS, alpha, SIN2)) - 1.0) <= 1e-3


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.5, 1.0])
def test_beckmann_normalised(alpha):
    assert abs(integrate(nd.ndf_beckmann(COS, alpha, SIN2)) - 1.0) <= 1e-3


@pytest.mark.parametrize("p", [0.0, 1.0, 10.0, 100.0, 5000.0])
def test_blinn_phong_normalised(p):
    assert abs(integrate(nd.ndf_blinn_phong(COS, p)) - 1.0) <= 1e-3


@pytest.mark.parametrize("a", [1.0, 10.0, 300.0])
@pytest.mark.parametrize("gamma", [0.5, 1.0, 1.75, 2.0, 3.0])
def test_abc_normalised(a, gamma):
    assert abs(integrate(nd.ndf_abc(COS, a, gamma)) - 1.0) <= 1e-3


@pytest.mark.parametrize("ax,ay", [(0.1, 0.4), (0.5, 0.05), (0.3, 0.3)])
@pytest.mark.parametrize("kind", ["ggx", "beckmann"])
def test_anisotropic_normalised(ax, ay, kind):
    th = torch.linspace(0, math.pi / 2, 2001, dtype=torch.float64)[:, None]
    ph = torch.linspace(0, 2 * math.pi, 1201, dtype=torch.float64)[None, :]
    hx, hy, hn = torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph), torch.cos(th).expand_as(ph * th)
    fn = nd.ndf_ggx_aniso if kind == "ggx" else nd.ndf_beckmann_aniso
    d = fn(hx, hy, hn, ax, ay) * hn * torch.sin(th)
    val = torch.trapezoid(torch.trapezoid(d, ph[0], dim=1), th[:, 0])
    assert abs(float(val) - 1.0) <= 1e-3


def test_gtr_singularities_are_exact():
    a = torch.tensor([0.05, 0.3, 0.9], dtype=torch.float64)
    # γ = 1 equals eq. 4; α = 1 gives 1/π; the neighbourhoods are continuous.
    eq4 = (a * a - 1) / (math.pi * torch.log(a * a))
    torch.testing.assert_close(nd.gtr_normalization(a, 1.0), eq4, rtol=1e-12, atol=0)
    for g in (0.5, 1.0, 2.0, 3.5):
        assert float(nd.gtr_normalization(torch.tensor(1.0, dtype=torch.float64), g)) == pytest.approx(1 / math.pi, rel=1e-15)
    for eps in (1e-9, 1e-6, 1e-3):
        near = nd.gtr_normalization(a, 1.0 + eps)
        # eq. 1 with its 1 - (α²)^(-ε) formed by expm1 so the reference itself keeps its digits
        general = eps * (a * a - 1) / (math.pi * -torch.expm1(-eps * torch.log(a * a)))
        torch.testing.assert_close(near, general, rtol=1e-9, atol=0)
        one = nd.gtr_normalization(torch.tensor(1.0 + eps, dtype=torch.float64), 2.0)
        assert float(one) == pytest.approx((1 + eps) ** 2 / math.pi, rel=1e-9)
    # γ = 2 is GGX's α²/π.
    torch.testing.assert_close(nd.gtr_normalization(a, 2.0), a * a / math.pi, rtol=1e-12, atol=0)


def test_abc_singular_cases_match_closed_forms():
    a = torch.tensor([0.5, 4.0, 100.0], dtype=torch.float64)
    eq21 = a * a / (2 * math.pi * ((1 + a) * torch.log1p(a) - a))
    eq22 = a * a / (2 * math.pi * (a - torch.log1p(a)))
    torch.testing.assert_close(nd.abc_normalization(a, 1.0), eq21, rtol=1e-10, atol=0)
    torch.testing.assert_close(nd.abc_normalization(a, 2.0), eq22, rtol=1e-10, atol=0)
    g = 1.3
    eq20 = a * a * (1 + a) ** g * (g - 2) * (g - 1) / (2 * math.pi * ((1 + a) ** 2 + (1 + a) ** g * (a * (g - 2) - 1)))
    torch.testing.assert_close(nd.abc_normalization(a, g), eq20, rtol=1e-10, atol=0)


def test_narrow_peak_float32_has_no_cancellation():
    # At α = 0.001 the naive 1 + (α² - 1) cos² loses everything in float32; the sin² form does not.
    th = torch.tensor([0.0, 2e-4, 1e-3, 5e-3], dtype=torch.float64)[:, None]
    ref = nd.ndf_ggx(torch.cos(th), 0.001, torch.sin(th) ** 2)
    out = nd.ndf_ggx(torch.cos(th).float(), 0.001, (torch.sin(th) ** 2).float()).double()
    assert ((out - ref).abs() / ref).max() <= 1e-5
    out1 = nd.ndf_gtr1(torch.cos(th).float(), 0.001, (torch.sin(th) ** 2).float()).double()
    ref1 = nd.ndf_gtr1(torch.cos(th), 0.001, torch.sin(th) ** 2)
    assert ((out1 - ref1).abs() / ref1).max() <= 1e-5


def test_roughness_to_alpha_floor():
    assert nd.roughness_to_alpha(0.0) == nd.ALPHA_MIN
    assert nd.roughness_to_alpha(0.5) == 0.25
    r = torch.tensor([0.0, 0.5])
    torch.testing.assert_close(nd.roughness_to_alpha(r), torch.tensor([1e-3, 0.25]))


def test_gradcheck_ndfs():
    c = torch.tensor([[0.3], [0.8], [0.99]], dtype=torch.float64, requires_grad=True)
    a = torch.tensor([[0.2], [0.5], [0.9]], dtype=torch.float64, requires_grad=True)
    g = torch.tensor([[0.7], [1.0], [2.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(nd.ndf_ggx, (c, a))
    assert torch.autograd.gradcheck(nd.ndf_gtr, (c, a, g))
    assert torch.autograd.gradcheck(nd.ndf_gtr1, (c, a))
    assert torch.autograd.gradcheck(nd.ndf_beckmann, (c, a))
    assert torch.autograd.gradcheck(lambda c, g: nd.ndf_blinn_phong(c, g * 10), (c, g))
    assert torch.autograd.gradcheck(lambda c, a, g: nd.ndf_abc(c, a * 10, g), (c, a, g))
    hx = torch.tensor([[0.1], [0.2], [-0.3]], dtype=torch.float64, requires_grad=True)
    hy = torch.tensor([[0.05], [-0.1], [0.2]], dtype=torch.float64, requires_grad=True)
    ay = (a * 0.5).detach().requires_grad_()
    assert torch.autograd.gradcheck(nd.ndf_ggx_aniso, (hx, hy, c, a, ay))
    assert torch.autograd.gradcheck(nd.ndf_beckmann_aniso, (hx, hy, c, a, ay))
    # Exactly at the singular points the gradient exists and is finite.
    one = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    gam = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    nd.gtr_normalization(one, gam).backward()
    assert torch.isfinite(one.grad).all() and torch.isfinite(gam.grad).all()
