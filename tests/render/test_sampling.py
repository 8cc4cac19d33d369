"""Samplers of torchbrdf.sampling: each density integrates to 1 and matches its samples."""

import math

import pytest
import torch

from torchbrdf.render.sampling import (
    LatLongSampler,
    hammersley,
    latlong_directions,
    latlong_row_solid_angles,
    latlong_texel_index,
    pdf_cosine_hemisphere,
    pdf_ggx_reflection,
    pdf_ggx_vndf,
    pdf_gtr1,
    reflect,
    rotated_hammersley,
    sample_cosine_hemisphere,
    sample_ggx_vndf,
    sample_gtr1,
    stratified_samples,
)

D = torch.float64


def sphere_grid(n_theta: int, n_phi: int, sub: int = 1):
    """Cell-centre directions of an equal-solid-angle (cos θ, φ) grid on the sphere.

    Returns directions ``(n_theta * sub, n_phi * sub, 3)`` and the solid angle of one sub-cell.
    """
    ct = 1.0 - (torch.arange(n_theta * sub, dtype=D) + 0.5) * (2.0 / (n_theta * sub))
    phi = (torch.arange(n_phi * sub, dtype=D) + 0.5) * (2.0 * math.pi / (n_phi * sub))
    st = torch.sqrt(1.0 - ct * ct)
    d = torch.stack(
        (
            st[:, None] * torch.cos(phi)[None],
            st[:, None] * torch.sin(phi)[None],
            ct[:, None].expand(-1, n_phi * sub),
        ),
        -1,
    )
    return d, 4.0 * math.pi / (n_theta * sub * n_phi * sub)


def integrate_sphere(pdf_fn, n=300):
    """∫ pdf dω over the sphere, midpoint rule in (θ, φ) (fine near the poles, where lobes peak)."""
    theta = (torch.arange(n, dtype=D) + 0.5) * (math.pi / n)
    phi = (torch.arange(2 * n, dtype=D) + 0.5) * (math.pi / n)
    st = torch.sin(theta)
    d = torch.stack(
        (
            st[:, None] * torch.cos(phi)[None],
            st[:, None] * torch.sin(phi)[None],
            torch.cos(theta)[:, None].expand(-1, 2 * n),
        ),
        -1,
    )
    p = pdf_fn(d.reshape(-1, 3)).reshape(n, 2 * n)
    return float((p * st[:, None]).sum() * (math.pi / n) ** 2)


def chi2_against_pdf(samples: torch.Tensor, pdf_fn, n_theta=12, n_phi=16, sub=24):
    """Chi-square statistic of sample counts in (cos θ, φ) cells against the integrated pdf.

    Cells with expected count < 5 are pooled. Returns (statistic, degrees of freedom, total
    mass); the mass is a coarse check, :func:`integrate_sphere` the accurate one.
    """
    d, dw = sphere_grid(n_theta, n_phi, sub)
    p = pdf_fn(d.reshape(-1, 3)).reshape(n_theta, sub, n_phi, sub).sum(dim=(1, 3)) * dw
    ct = samples[:, 2].clamp(-1, 1)
    phi = torch.remainder(torch.atan2(samples[:, 1], samples[:, 0]), 2 * math.pi)
    it = torch.clamp(((1.0 - ct) / 2.0 * n_theta).long(), 0, n_theta - 1)
    ip = torch.clamp((phi / (2 * math.pi) * n_phi).long(), 0, n_phi - 1)
    counts = torch.zeros(n_theta * n_phi, dtype=D).index_add_(
        0, it * n_phi + ip, torch.ones(len(samples), dtype=D)
    )
    expected = p.reshape(-1) * len(samples)
    big = expected >= 5
    obs = torch.cat((counts[big], counts[~big].sum()[None]))
    exp = torch.cat((expected[big], expected[~big].sum()[None]))
    keep = exp > 0
    stat = float((((obs - exp) ** 2)[keep] / exp[keep]).sum())
    return stat, int(keep.sum()) - 1, float(p.sum())


def assert_chi2(stat, dof):
    # Normal approximation of the chi-square quantile far in the tail (~5 sigma): a wrong
    # density (even by a few percent in one region) overshoots this by a wide margin.
    assert stat < dof + 5.0 * math.sqrt(2.0 * dof), (stat, dof)


def uniform(n, seed):
    return torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=D)


def test_hammersley_is_stratified_and_rotation_stays_in_unit_square():
    pts = hammersley(0, 64, 64, dtype=D)
    assert sorted((pts[:, 0] * 64).floor().long().tolist()) == list(range(64))
    assert sorted((pts[:, 1] * 64).floor().long().tolist()) == list(range(64))
    shift = torch.rand(10, 2, dtype=D)
    u = rotated_hammersley(shift, 0, 64, 64)
    assert u.shape == (10, 64, 2) and bool((u >= 0).all()) and bool((u < 1).all())
    # Each rotated set is still one point per stratum of the first coordinate.
    for row in u:
        assert sorted((row[:, 0] * 64).floor().long().tolist()) == list(range(64))
    # Chunked generation equals generation in one go.
    assert torch.equal(
        torch.cat((rotated_hammersley(shift, 0, 40, 64), rotated_hammersley(shift, 40, 24, 64)), 1), u
    )


def test_stratified_samples_seeded():
    a = stratified_samples(5, 16, seed=3, dtype=D)
    b = stratified_samples(5, 16, seed=3, dtype=D)
    c = stratified_samples(5, 16, seed=4, dtype=D)
    assert torch.equal(a, b) and not torch.equal(a, c)
    g = torch.Generator().manual_seed(3)
    assert torch.equal(stratified_samples(5, 16, generator=g, dtype=D), a)


def test_cosine_hemisphere():
    w = sample_cosine_hemisphere(uniform(40000, 0))
    assert torch.allclose(w.norm(dim=-1), torch.ones(len(w), dtype=D))
    stat, dof, _ = chi2_against_pdf(w, lambda d: pdf_cosine_hemisphere(d)[:, 0])
    assert abs(integrate_sphere(lambda d: pdf_cosine_hemisphere(d)[:, 0]) - 1.0) < 1e-4
    assert_chi2(stat, dof)


@pytest.mark.parametrize("ax, ay, vz", [(0.3, 0.3, 0.9), (0.5, 0.15, 0.4), (0.8, 0.8, 0.15)])
def test_ggx_vndf_half_vectors_and_reflections(ax, ay, vz):
    v = torch.tensor([math.sqrt(1 - vz * vz) * 0.6, math.sqrt(1 - vz * vz) * 0.8, vz], dtype=D)
    n = 40000
    h = sample_ggx_vndf(v.expand(n, 3), ax, ay, uniform(n, 1))
    assert torch.allclose(h.norm(dim=-1), torch.ones(n, dtype=D))
    pdf_h = lambda d: pdf_ggx_vndf(v.expand_as(d), d, ax, ay)[:, 0]  # noqa: E731
    stat, dof, _ = chi2_against_pdf(h, pdf_h)
    assert abs(integrate_sphere(pdf_h) - 1.0) < 1e-3
    assert_chi2(stat, dof)
    # Reflected directions: the density over the whole sphere integrates to 1 too.
    l = reflect(v.expand(n, 3), h)
    pdf_l = lambda d: pdf_ggx_reflection(v.expand_as(d), d, ax, ay)[:, 0]  # noqa: E731
    stat, dof, _ = chi2_against_pdf(l, pdf_l)
    # This density jumps to 0 where h = normalize(v + l) leaves the upper hemisphere, so the
    # midpoint rule is only first-order accurate there.
    assert abs(integrate_sphere(pdf_l) - 1.0) < 4e-3
    assert_chi2(stat, dof)


@pytest.mark.parametrize("alpha", [0.1, 0.25, 0.6, 1.0])
def test_gtr1(alpha):
    n = 40000
    h = sample_gtr1(alpha, uniform(n, 2))
    assert bool((h[:, 2] > 0).all())
    stat, dof, _ = chi2_against_pdf(h, lambda d: pdf_gtr1(d, alpha)[:, 0])
    assert abs(integrate_sphere(lambda d: pdf_gtr1(d, alpha)[:, 0]) - 1.0) < 1e-3
    assert_chi2(stat, dof)


def test_gtr1_alpha_one_limit_is_continuous():
    u = uniform(100, 3)
    a = sample_gtr1(1.0, u)
    b = sample_gtr1(1.0 - 1e-3, u)
    assert torch.allclose(a, b, atol=1e-3)
    assert torch.allclose(pdf_gtr1(a, 1.0), pdf_gtr1(a, 1.0 - 1e-3), rtol=1e-3)


def test_latlong_convention():
    d = latlong_directions(4, 8, dtype=D)
    # Row 0 is near +z, column 0 near phi = -pi (pointing to -x).
    assert d[0, 0, 2] > 0.9 and d[0, 0, 0] < 0
    theta = (torch.arange(4, dtype=D) + 0.5) * math.pi / 4
    phi = -math.pi + (torch.arange(8, dtype=D) + 0.5) * 2 * math.pi / 8
    expect = torch.stack(
        (
            torch.sin(theta)[:, None] * torch.cos(phi),
            torch.sin(theta)[:, None] * torch.sin(phi),
            torch.cos(theta)[:, None].expand(4, 8),
        ),
        -1,
    )
    assert torch.allclose(d, expect)
    row, col = latlong_texel_index(d, 4, 8)
    assert torch.equal(row, torch.arange(4)[:, None].expand(4, 8))
    assert torch.equal(col, torch.arange(8)[None].expand(4, 8))
    assert abs(float(latlong_row_solid_angles(4, 8, dtype=D).sum() * 8) - 4 * math.pi) < 1e-12


def test_latlong_sampler_matches_texel_probabilities():
    g = torch.Generator().manual_seed(5)
    rad = torch.rand(3, 6, 12, generator=g, dtype=D) ** 3 * 5
    rad[:, 2] = 0.0  # a black row is never sampled
    s = LatLongSampler(rad)
    n = 60000
    d, pdf = s.sample(uniform(n, 6))
    assert torch.allclose(d.norm(dim=-1), torch.ones(n, dtype=D))
    assert torch.allclose(pdf, s.pdf(d))
    row, col = latlong_texel_index(d, 6, 12)
    assert not bool((row == 2).any())
    counts = torch.zeros(72, dtype=D).index_add_(0, row * 12 + col, torch.ones(n, dtype=D))
    omega = latlong_row_solid_angles(6, 12, dtype=D)[:, None].expand(6, 12).reshape(-1)
    p = s.texel_pdf[0].reshape(-1) * omega
    assert abs(float(p.sum()) - 1.0) < 1e-12
    big = p * n >= 5
    stat = float((((counts - p * n) ** 2)[big] / (p * n)[big]).sum())
    assert_chi2(stat, int(big.sum()) - 1)
    # Inside a texel the direction is uniform in solid angle: check cos(theta) in one texel.
    sel = (row == 0) & (col == int(p[:12].argmax()))
    ct = d[sel, 2]
    edges = torch.cos(torch.tensor([0.0, math.pi / 6], dtype=D))
    frac = (ct - edges[1]) / (edges[0] - edges[1])
    assert abs(float(frac.mean()) - 0.5) < 0.05


def test_latlong_sampler_batched_and_black_map():
    rad = torch.zeros(2, 3, 4, 8, dtype=D)
    rad[1, :, 1, 3] = 1.0
    s = LatLongSampler(rad)
    u = uniform(100, 7)
    bidx = torch.tensor([0, 1]).repeat(50)
    d, pdf = s.sample(u, bidx)
    # Map 0 is black: uniform over the sphere.
    assert torch.allclose(pdf[bidx == 0], torch.full_like(pdf[bidx == 0], 1 / (4 * math.pi)))
    row, col = latlong_texel_index(d[bidx == 1], 4, 8)
    assert bool((row == 1).all()) and bool((col == 3).all())
    with pytest.raises(ValueError, match="batch_index"):
        s.sample(u)
    with pytest.raises(ValueError, match="radiance"):
        LatLongSampler(torch.zeros(4, 4, 8))


def test_samplers_dtype_and_device_generic(device):
    for dt in (torch.float32, torch.float64):
        u = torch.rand(16, 2, dtype=dt, device=device)
        v = torch.tensor([0.3, 0.0, 0.95], dtype=dt, device=device)
        v = v / v.norm()
        for w in (
            sample_cosine_hemisphere(u),
            sample_ggx_vndf(v.expand(16, 3), 0.3, 0.2, u),
            sample_gtr1(0.2, u),
        ):
            assert w.dtype == dt and w.device == u.device and bool(torch.isfinite(w).all())
        d, p = LatLongSampler(torch.rand(3, 4, 8, dtype=dt, device=device)).sample(u)
        assert d.dtype == dt and p.dtype == dt and d.device == u.device
