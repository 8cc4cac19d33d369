"""Tests of the SVBRDF-capture GGX model (``torchbrdf.brdf.svbrdf_ggx``).

The float64 NumPy reference is written from the published formulas (uncancelled G / (4 n.l
n.v), textbook GGX denominator); it does not call the library.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchbrdf.brdf import svbrdf_ggx as capture_model
from torchbrdf.brdf.svbrdf_ggx import ALPHA_MIN, SVBRDFGGX, svbrdf_ggx


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _d(a, b):
    return np.sum(a * b, axis=-1, keepdims=True)


def t64(a):
    return torch.tensor(np.asarray(a), dtype=torch.float64)


def np_capture(l, v, n, rho_d, rho_s, rough, alpha=None):
    """Diffuse (1 - specular) / pi + D G F / (4 n.l n.v); zero unless both cosines > 0.

    ``alpha`` overrides the default floor convention ``max(rough^2, ALPHA_MIN)``.
    """
    h = _unit(l + v)
    nl, nv, nh, vh = _d(n, l), _d(n, v), _d(n, h), _d(v, h)
    alpha = np.maximum(rough**2, ALPHA_MIN) if alpha is None else alpha
    d = alpha**2 / (np.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)
    k = alpha / 2
    with np.errstate(all="ignore"):
        g = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
        f = rho_s + (1 - rho_s) * 2.0 ** ((-5.55473 * vh - 6.98316) * vh)
        out = rho_d * (1 - rho_s) / np.pi + d * g * f / (4 * nl * nv)
    return np.where((nl > 0) & (nv > 0), out, 0.0)


def random_dirs(rng, count, upper=None):
    d = _unit(rng.normal(size=(count, 3)))
    if upper:
        d[:, 2] = np.abs(d[:, 2])
    return d


def random_maps(rng, count):
    rough = rng.uniform(0, 1, (count, 1))
    rough[:50] = rng.choice([0.0, 0.01, 1.0], (50, 1))
    return rng.uniform(0, 1, (count, 3)), rng.uniform(0, 1, (count, 3)), rough


def test_matches_numpy_reference():
    rng = np.random.default_rng(0)
    count = 4000
    n = _unit(rng.normal(size=(count, 3)) * [0.3, 0.3, 1.0] + [0, 0, 1.0])
    l, v = random_dirs(rng, count), random_dirs(rng, count)
    rho_d, rho_s, rough = random_maps(rng, count)
    got = svbrdf_ggx(
        t64(l), t64(v), t64(n), diffuse_albedo=t64(rho_d), specular_albedo=t64(rho_s), roughness=t64(rough)
    )
    expected = np_capture(l, v, n, rho_d, rho_s, rough)
    assert torch.isfinite(got).all()
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-8, atol=1e-12)
    assert ((got.numpy() > 0).all(-1) == ((_d(n, l) > 0) & (_d(n, v) > 0))[:, 0]).all()


def test_closed_form_values():
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    rho_d = torch.tensor([0.5, 0.2, 0.1], dtype=torch.float64)
    rho_s = torch.tensor([0.04, 0.5, 1.0], dtype=torch.float64)
    sg1 = 2.0 ** (-5.55473 - 6.98316)  # Fresnel factor at v.h = 1
    for r in (0.2, 0.5, 1.0):
        a = r * r
        # l = v = n: D = 1 / (pi a^2), G = 1
        expected = rho_d * (1 - rho_s) / math.pi + (rho_s + (1 - rho_s) * sg1) / (4 * math.pi * a * a)
        got = svbrdf_ggx(n, n, n, diffuse_albedo=rho_d, specular_albedo=rho_s, roughness=r)
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)
        # l, v mirrored at 60 deg: h = n, n.l = n.v = v.h = 1/2
        s, c = math.sin(math.radians(60)), 0.5
        l = torch.tensor([s, 0.0, c], dtype=torch.float64)
        v = torch.tensor([-s, 0.0, c], dtype=torch.float64)
        k = a / 2
        g1 = c / (c * (1 - k) + k)
        fr = rho_s + (1 - rho_s) * 2.0 ** ((-5.55473 * c - 6.98316) * c)
        expected = rho_d * (1 - rho_s) / math.pi + g1 * g1 * fr / (math.pi * a * a * 4 * c * c)
        got = svbrdf_ggx(l, v, n, diffuse_albedo=rho_d, specular_albedo=rho_s, roughness=r)
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)


def _hemisphere(n_mu, n_phi):
    mu, wmu = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = 0.5 * (mu + 1), 0.5 * wmu
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    m, p = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - m**2)
    d = np.stack([s * np.cos(p), s * np.sin(p), m], -1).reshape(-1, 3)
    w = (wmu[:, None] * np.ones(n_phi) * 2 * np.pi / n_phi).reshape(-1)
    return d, w, m.reshape(-1)


def _ggx_h_quadrature(alpha, n_u, n_phi):
    """H nodes distributed as D(h) (n.h): tan^2 theta = a^2 u / (1 - u), equal weights."""
    u = (np.arange(n_u) + 0.5) / n_u
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    cos2 = 1 / (1 + alpha**2 * u / (1 - u))
    ct, st = np.sqrt(cos2), np.sqrt(1 - cos2)
    h = np.stack([st[:, None] * np.cos(phi), st[:, None] * np.sin(phi), ct[:, None] * np.ones(n_phi)], -1)
    return h.reshape(-1, 3)


def test_energy():
    """Albedos: diffuse exactly rho_d (1 - rho_s); specular with F0 = 1 at most 1.

    The specular one (Smith-Schlick, k = alpha/2) equals 1 - ln 2 at alpha = 1, normal incidence.
    """
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    d, w, mu = _hemisphere(24, 8)
    rho_d, rho_s = (
        torch.tensor([0.9, 0.5, 0.1], dtype=torch.float64),
        torch.tensor([0.3, 0.1, 0.0], dtype=torch.float64),
    )
    for ang in (0.0, 45.0, 80.0):
        v = t64([math.sin(math.radians(ang)), 0.0, math.cos(math.radians(ang))]).expand(len(d), 3)
        f = svbrdf_ggx(
            t64(d),
            v,
            z,
            diffuse_albedo=rho_d,
            specular_albedo=torch.zeros(3, dtype=torch.float64),
            roughness=1.0,
        )
        f_spec = svbrdf_ggx(
            t64(d),
            v,
            z,
            diffuse_albedo=0.0,
            specular_albedo=torch.zeros(3, dtype=torch.float64),
            roughness=1.0,
        )
        alb = ((f - f_spec).numpy() * (mu * w)[:, None]).sum(0)
        np.testing.assert_allclose(alb, rho_d.numpy(), rtol=1e-12)
        f = svbrdf_ggx(t64(d), v, z, diffuse_albedo=rho_d, specular_albedo=rho_s, roughness=1.0)
        # with rho_s, diffuse part scales by (1 - rho_s)
        f_s = svbrdf_ggx(t64(d), v, z, diffuse_albedo=0.0, specular_albedo=rho_s, roughness=1.0)
        alb = ((f - f_s).numpy() * (mu * w)[:, None]).sum(0)
        np.testing.assert_allclose(alb, (rho_d * (1 - rho_s)).numpy(), rtol=1e-12)
    albedos = {}
    for r in (0.1, 0.3, 0.6, 1.0):
        alpha = max(r * r, ALPHA_MIN)
        h = _ggx_h_quadrature(alpha, 400, 64)
        for ang in (0.0, 45.0, 75.0, 88.0):
            v = np.array([math.sin(math.radians(ang)), 0.0, math.cos(math.radians(ang))])
            vh = h @ v
            l = 2 * vh[:, None] * h - v
            ok = (l[:, 2] > 0) & (vh > 0)
            vv = np.broadcast_to(v, l.shape)
            f = svbrdf_ggx(t64(l), t64(vv), z, diffuse_albedo=0.0, specular_albedo=1.0, roughness=r)
            f = f[:, 0].numpy()
            nh = h[:, 2]
            dd = alpha**2 / (np.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)
            g = np.where(ok, f * l[:, 2] * 4 * np.abs(vh) / (dd * nh), 0.0)
            albedos[r, ang] = g.mean()
    values = np.array(list(albedos.values()))
    assert values.max() <= 1.0 + 1e-3, albedos
    assert albedos[0.1, 0.0] > 0.99  # a smooth lobe at normal incidence loses almost nothing
    # alpha = 1, normal incidence: D = 1/pi, G1(mu) = 2 mu / (mu + 1), so the albedo is
    # int_0^1 mu / (mu + 1) d mu = 1 - ln 2
    assert albedos[1.0, 0.0] == pytest.approx(1 - math.log(2), abs=1e-4)


def test_reciprocity():
    rng = np.random.default_rng(1)
    count = 500
    l, v = random_dirs(rng, count, True), random_dirs(rng, count, True)
    rho_d, rho_s, rough = (t64(x) for x in random_maps(rng, count))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    a = svbrdf_ggx(t64(l), t64(v), n, diffuse_albedo=rho_d, specular_albedo=rho_s, roughness=rough)
    b = svbrdf_ggx(t64(v), t64(l), n, diffuse_albedo=rho_d, specular_albedo=rho_s, roughness=rough)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_gradcheck():
    rng = np.random.default_rng(2)
    count = 8
    l, v = random_dirs(rng, count, True), random_dirs(rng, count, True)
    l[:, 2], v[:, 2] = np.maximum(l[:, 2], 0.2), np.maximum(v[:, 2], 0.2)
    l, v = _unit(l), _unit(v)
    n = _unit(np.array([[0.1, 0.05, 1.0]]).repeat(count, 0))
    inputs = [
        t64(l),
        t64(v),
        t64(n),
        t64(rng.uniform(0.1, 0.9, (count, 3))),
        t64(rng.uniform(0.1, 0.9, (count, 3))),
        t64(rng.uniform(0.2, 0.9, (count, 1))),
    ]
    for t in inputs:
        t.requires_grad_(True)

    def fn(l, v, n, rd, rs, r):
        return svbrdf_ggx(l, v, n, diffuse_albedo=rd, specular_albedo=rs, roughness=r)

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_finite_at_grazing_and_extremes(dtype):
    z = [0.0, 0.0, 1.0]
    g = [1.0, 0.0, 0.0]
    e = math.radians(89.999)
    near = [math.sin(e), 0.0, math.cos(e)]
    mirror = [-math.sin(e), 0.0, math.cos(e)]
    pairs = [
        (z, z),
        (g, z),
        (z, g),
        (near, mirror),
        (near, near),
        (g, [-1.0, 0, 0]),
        ([0, 0, -1.0], z),
        (z, [0, 0, -1.0]),
    ]
    l = torch.tensor([p[0] for p in pairs], dtype=dtype, requires_grad=True)
    v = torch.tensor([p[1] for p in pairs], dtype=dtype, requires_grad=True)
    for r in (0.0, 1.0):
        n = torch.tensor(z, dtype=dtype).expand(len(pairs), 3).clone().requires_grad_(True)
        rd = torch.full((len(pairs), 3), 0.5, dtype=dtype, requires_grad=True)
        rs = torch.full((len(pairs), 3), 0.04, dtype=dtype, requires_grad=True)
        rr = torch.full((len(pairs), 1), r, dtype=dtype, requires_grad=True)
        f = svbrdf_ggx(l, v, n, diffuse_albedo=rd, specular_albedo=rs, roughness=rr)
        assert torch.isfinite(f).all()
        f.sum().backward()
        for t in (l, v, n, rd, rs, rr):
            assert torch.isfinite(t.grad).all()
            t.grad = None
        for i in (1, 2, 5, 6, 7):  # n.l = 0, n.v = 0 or below: exactly 0, zero gradients
            assert (f[i] == 0).all()
        f = svbrdf_ggx(l, v, n, diffuse_albedo=rd, specular_albedo=rs, roughness=rr)
        f[[1, 2, 5, 6, 7]].sum().backward()
        for t in (l, v, n, rd, rs, rr):
            assert (t.grad == 0).all()
            t.grad = None


def test_module_equals_functional_shapes_and_dtypes():
    rng = np.random.default_rng(3)
    l = torch.as_tensor(random_dirs(rng, 2 * 8 * 8, True), dtype=torch.float32).reshape(2, 8, 8, 3)
    v = torch.as_tensor(random_dirs(rng, 2 * 8 * 8, True), dtype=torch.float32).reshape(2, 8, 8, 3)
    n = torch.tensor([0.0, 0.0, 1.0])
    maps = dict(
        diffuse_albedo=torch.rand(2, 8, 8, 3),
        specular_albedo=torch.rand(1, 1, 1, 3),
        roughness=torch.rand(2, 8, 8, 1),
    )
    f = svbrdf_ggx(l, v, n, **maps)
    assert f.shape == (2, 8, 8, 3) and f.dtype == torch.float32
    torch.testing.assert_close(SVBRDFGGX()(l, v, n, **maps), f, rtol=0, atol=0)
    assert svbrdf_ggx(l, v, n, diffuse_albedo=0.5, specular_albedo=0.04, roughness=0.5).shape == (2, 8, 8, 3)
    with pytest.raises(TypeError):
        svbrdf_ggx(l, v, n, metallic=0.0, **maps)
    with pytest.raises(ValueError, match="roughness"):
        svbrdf_ggx(l, v, n, **dict(maps, roughness=torch.rand(2, 8, 8, 3)))
    with pytest.raises(TypeError, match="dtype"):
        svbrdf_ggx(l.double(), v, n, **maps)
    for dtype in (torch.float16, torch.bfloat16):
        lh, vh, nh = l.to(dtype), v.to(dtype), n.to(dtype)
        mh = {k: x.to(dtype) for k, x in maps.items()}
        got = svbrdf_ggx(lh, vh, nh, **mh)
        assert got.dtype == dtype and torch.isfinite(got).all()
        ref = svbrdf_ggx(lh.float(), vh.float(), nh.float(), **{k: x.float() for k, x in mh.items()})
        torch.testing.assert_close(got.float(), ref, rtol=2e-2, atol=1e-3)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float16)
    peak = svbrdf_ggx(z, z, z, diffuse_albedo=0.5, specular_albedo=1.0, roughness=0.0)
    assert torch.isfinite(peak).all() and (peak == torch.finfo(torch.float16).max).all()


# --------------------------------------------------------------------------------------
# Roughness floor conventions
# --------------------------------------------------------------------------------------

CODES = np.arange(0, 12)  # 8-bit roughness codes; 1..8 give alpha = 1.5e-5 .. 9.8e-4


def _floor_case(rng, count=400):
    n = _unit(rng.normal(size=(count, 3)) * [0.2, 0.2, 1.0] + [0, 0, 1.0])
    l, v = random_dirs(rng, count, upper=True), random_dirs(rng, count, upper=True)
    rough = rng.choice(CODES, (count, 1)) / 255.0
    rho_d, rho_s = rng.uniform(0, 1, (count, 3)), rng.uniform(0, 1, (count, 3))
    return l, v, n, rho_d, rho_s, rough


@pytest.mark.parametrize(
    "floors, alpha_of",
    [
        ({}, lambda r: np.maximum(r**2, 1e-3)),  # default: unchanged behaviour
        ({"alpha_floor": ALPHA_MIN}, lambda r: np.maximum(r**2, 1e-3)),
        ({"alpha_floor": 1e-6}, lambda r: np.maximum(r**2, 1e-6)),
        ({"roughness_floor": 1e-3}, lambda r: np.maximum(r, 1e-3) ** 2),  # Deschaintre's
    ],
)
def test_floor_conventions_match_reference(floors, alpha_of):
    l, v, n, rho_d, rho_s, rough = _floor_case(np.random.default_rng(7))
    got = svbrdf_ggx(
        t64(l), t64(v), t64(n), diffuse_albedo=t64(rho_d), specular_albedo=t64(rho_s), roughness=t64(rough),
        **floors,
    )
    expected = np_capture(l, v, n, rho_d, rho_s, rough, alpha=alpha_of(rough))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-8, atol=1e-12)
    module = SVBRDFGGX(**floors)(
        t64(l), t64(v), t64(n), diffuse_albedo=t64(rho_d), specular_albedo=t64(rho_s), roughness=t64(rough)
    )
    assert torch.equal(module, got)


def test_roughness_floor_keeps_every_8bit_code_distinct():
    """With the default alpha floor, codes 1..8 all render like alpha = 1e-3; with Deschaintre's
    roughness floor each code keeps its lobe, and at code 1 the peak is ~4e3 times higher."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    r = torch.tensor(CODES / 255.0, dtype=torch.float64)[:, None]

    def peak(**floors):
        return svbrdf_ggx(n, n, n, diffuse_albedo=0.0, specular_albedo=1.0, roughness=r, **floors)[:, 0]

    assert capture_model.ROUGHNESS_FLOOR_DESCHAINTRE == 1e-3  # roughness = tf.maximum(roughness, 0.001)
    default, literature = peak(), peak(roughness_floor=capture_model.ROUGHNESS_FLOOR_DESCHAINTRE)
    assert torch.all(default[:9] == default[0])  # codes 0..8: one and the same lobe
    assert torch.all(literature[1:9] < literature[:8])  # strictly narrower per code down to 0
    assert float(literature[1] / default[1]) == pytest.approx((1e-3 / (1 / 255) ** 2) ** 2, rel=1e-6)
    torch.testing.assert_close(literature[9:], default[9:])  # alpha > 1e-3: the floors agree


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_roughness_floor_finite_at_zero_roughness(dtype):
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype)
    l = torch.nn.functional.normalize(torch.tensor([[0.0, 1e-4, 1.0]], dtype=torch.float64), dim=-1).to(dtype)
    rough = torch.zeros(1, 1, dtype=dtype, requires_grad=True)
    for ll in (n, l):
        f = svbrdf_ggx(ll, n, n, diffuse_albedo=0.5, specular_albedo=0.04, roughness=rough, roughness_floor=1e-3)
        f.sum().backward()
        assert torch.isfinite(f).all() and torch.isfinite(rough.grad).all()


@pytest.mark.parametrize(
    "floors, match",
    [
        ({"alpha_floor": 1e-3, "roughness_floor": 1e-3}, "give at most one floor"),
        ({"alpha_floor": 0.0}, r"alpha_floor: expected a number in \(0, 1\]"),
        ({"roughness_floor": -1e-3}, "roughness_floor: expected a number"),
        ({"roughness_floor": float("nan")}, "roughness_floor: expected a number"),
        ({"alpha_floor": [1e-3] * 1000}, r"alpha_floor: expected a number in \(0, 1\], got \[0\.001, .*\.\.\.\]$"),
    ],
)
def test_bad_floors(floors, match):
    n = torch.tensor([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=match):
        svbrdf_ggx(n, n, n, diffuse_albedo=0.5, specular_albedo=0.04, roughness=0.5, **floors)
    with pytest.raises(ValueError, match=match):
        SVBRDFGGX(**floors)


def test_roughness_gradient_at_one_is_the_smooth_one():
    """The floor under ``|n x h|^2 + alpha^2 (n.h)^2`` (for ``l = -v``) must not tie with it for
    unit vectors: at roughness 1 the sum is ``|h|^2 = 1 = min(alpha^2, 1)``, so a floor of
    ``min(alpha^2, 1)`` lets rounding pick the floor's gradient (or half of each) in most lanes.
    The model is smooth there: the gradient is the limit of its neighbours'."""
    rng = np.random.default_rng(7)
    count = 400
    n = _unit(random_dirs(rng, count, upper=True) + np.array([0.0, 0.0, 1.0]))
    l, v = _unit(n + 0.6 * random_dirs(rng, count)), _unit(n + 0.6 * random_dirs(rng, count))
    maps = {"diffuse_albedo": t64(np.full((count, 3), 0.5)), "specular_albedo": t64(np.full((count, 3), 0.04))}

    def grad(r):
        rr = t64(np.full((count, 1), r)).requires_grad_()
        f = svbrdf_ggx(t64(l), t64(v), t64(n), roughness=rr, **maps)
        return torch.autograd.grad(f.sum(), rr)[0]

    torch.testing.assert_close(grad(1.0), grad(1.0 - 1e-6), rtol=1e-4, atol=0)
