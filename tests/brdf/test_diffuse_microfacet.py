"""Diffuse models and the generic microfacet composition."""

import math

import numpy as np
import pytest
import torch

from torchbrdf.brdf import diffuse as df
from torchbrdf import microfacet, principled

from tests.conftest import hemisphere_pairs


def hemisphere_grid(n=200):
    u = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    ct, ph = torch.meshgrid(u, u * 2 * math.pi, indexing="ij")
    st = torch.sqrt(1 - ct ** 2)
    return torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], -1).reshape(-1, 3)


def test_lambert_albedo_equals_colour():
    l = hemisphere_grid()
    f = df.diffuse_lambert(torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)).expand(len(l), 3)
    albedo = (f * l[:, 2:3]).mean(0) * 2 * math.pi
    torch.testing.assert_close(albedo, torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64), rtol=1e-6, atol=0)


def test_oren_nayar_against_trig_form():
    rng = np.random.default_rng(0)
    x, y, n, l, v = hemisphere_pairs(rng, 500, 0.02)
    t = lambda a: torch.as_tensor(a)  # noqa: E731
    nl, nv, lv = (t((n * l).sum(-1, keepdims=True)), t((n * v).sum(-1, keepdims=True)),
                  t((l * v).sum(-1, keepdims=True)))
    sigma = 0.4
    out = df.diffuse_oren_nayar(nl, nv, lv, torch.ones(1, dtype=torch.float64), sigma)
    # PBRT's form with explicit angles.
    ti, to = torch.acos(nl), torch.acos(nv)
    phi_l = torch.atan2(t((l * y).sum(-1, keepdims=True)), t((l * x).sum(-1, keepdims=True)))
    phi_v = torch.atan2(t((v * y).sum(-1, keepdims=True)), t((v * x).sum(-1, keepdims=True)))
    s2 = sigma ** 2
    a, b = 1 - s2 / (2 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09)
    alpha, beta = torch.maximum(ti, to), torch.minimum(ti, to)
    ref = (a + b * torch.clamp(torch.cos(phi_l - phi_v), min=0) * torch.sin(alpha) * torch.tan(beta)) / math.pi
    torch.testing.assert_close(out, ref, rtol=1e-9, atol=1e-12)
    lam = df.diffuse_oren_nayar(nl, nv, lv, torch.ones(1, dtype=torch.float64), 0.0)
    torch.testing.assert_close(lam, torch.full_like(lam, 1 / math.pi))


def test_burley_diffuse_limits():
    one = torch.ones(1, 1, dtype=torch.float64)
    # Normal incidence both ways: FL = FV = 0 -> Fd = 1 whatever the roughness.
    assert float(df.diffuse_burley(one, one, one, 1.0, 0.7)) == pytest.approx(1 / math.pi)
    # Grazing, smooth: Fd -> 0.5 * 0.5 (Fd90 = 0.5 at roughness 0).
    z = torch.zeros(1, 1, dtype=torch.float64)
    assert float(df.diffuse_burley(z, z, one, 1.0, 0.0)) == pytest.approx(0.25 / math.pi)
    # Subsurface factor at normal incidence: 1.25 * (1 * (1/2 - 0.5) + 0.5) = 0.625.
    assert float(df.diffuse_subsurface(one, one, one, 1.0, 0.3)) == pytest.approx(0.625 / math.pi)


def test_microfacet_ggx_schlick_equals_principled_metal():
    rng = np.random.default_rng(1)
    x, y, n, l, v = hemisphere_pairs(rng, 256, 0.05)
    t = lambda a: torch.as_tensor(a)  # noqa: E731
    base = torch.tensor([0.9, 0.6, 0.3], dtype=torch.float64)
    r = 0.4
    p = principled(t(l), t(v), t(n), base_color=base, metallic=1.0, roughness=r)
    m = microfacet(t(l), t(v), t(n), alpha=r * r, f0=base, masking="smith_separable")
    torch.testing.assert_close(m, p, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann", "gtr", "blinn_phong", "abc"])
@pytest.mark.parametrize("masking", ["smith_separable", "smith_correlated", "cook_torrance", "kelemen", "implicit"])
def test_microfacet_combinations_finite_and_reciprocal(distribution, masking):
    rng = np.random.default_rng(2)
    x, y, n, l, v = hemisphere_pairs(rng, 128, 0.0)
    t = lambda a: torch.as_tensor(a).requires_grad_()  # noqa: E731
    l, v, n = t(l), t(v), t(n)
    kw = dict(alpha=0.3, distribution=distribution, masking=masking, gamma=1.5, abc_a=20.0)
    a = microfacet(l, v, n, **kw)
    b = microfacet(v, l, n, **kw)
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    a.sum().backward()
    assert torch.isfinite(a).all() and torch.isfinite(l.grad).all()


def test_microfacet_bad_choice():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="distribution"):
        microfacet(n, n, n, alpha=0.1, distribution="gaussian")
