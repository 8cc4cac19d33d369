"""Tests of the Smits Wall-E/Up model (``torchbrdf.smits``).

The float64 NumPy reference below is written from the equations of Smits' notes (and the
choices documented in the module docstring); it does not call the library.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchbrdf.brdf.smits import (
    MIN_CONE_DEG,
    SmitsBRDF,
    SmitsLayeredBRDF,
    smits,
    smits_composite,
    smits_cone_power,
    smits_distribution,
    smits_evaluate,
    smits_highlight_lobe,
    smits_layered,
    smits_lobes,
)

# --------------------------------------------------------------------------- NumPy reference

LOBE_SCALES = (
    "diffuse_scale",
    "specular_scale",
    "reflection_scale",
    "transmit_diffuse_scale",
    "transmit_specular_scale",
    "refraction_scale",
)
DEFAULTS = dict(
    metallic=0.0,
    roughness=0.5,
    clear=0.0,
    back=0.0,
    fresnel_normal_scale=1.0,
    fresnel_grazing_scale=1.0,
    highlight_tint=1.0,
    transmit_tint=1.0,
    specular_cone_scale=1.0,
    reflection_cone_scale=1.0,
    transmit_specular_cone_scale=1.0,
    refraction_cone_scale=1.0,
    **{k: 1.0 for k in LOBE_SCALES},
)


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _d(a, b):
    return np.sum(a * b, axis=-1, keepdims=True)


def np_mix(a, b, t):
    return a + (b - a) * t


def np_frnl(norm, grazing, cos):
    return np_mix(norm, grazing, (1.0 - np.clip(cos, 0.0, 1.0)) ** 5)


def np_power(cone_deg):
    """-Log[0.1] / Sin[cone]^2, the cone in degrees."""
    return -np.log(0.1) / np.sin(np.radians(cone_deg)) ** 2


def np_dist(sin2, p):
    return p / (1.0 - np.exp(-p)) * np.exp(-p * sin2) / np.pi


def np_cones(p):
    r = np.clip(p["roughness"], 0, 1)

    def c(deg, scale):
        return np.clip(deg * scale, MIN_CONE_DEG, 90.0)

    spec_deg, refl_deg = 30.0 * r + 5.0, 10.0 * r
    return dict(
        specular=c(spec_deg, p["specular_cone_scale"]),
        reflection=c(refl_deg, p["reflection_cone_scale"]),
        transmit_specular=c(spec_deg, p["transmit_specular_cone_scale"]),
        refraction=c(refl_deg, p["refraction_cone_scale"]),
    )


def np_weights(v, n, p):
    """The notes' twelve weights (typos fixed as documented), per lobe: (normal, grazing)."""
    c = p["base_color"]
    m = np.clip(p["metallic"], 0, 1)
    r = np.clip(p["roughness"], 0, 1)
    clear = np.clip(p["clear"], 0, 1)
    back = np.clip(p["back"], 0, 1)
    vn = _d(v, n)
    nrefl = np.clip(np_mix(0.05, 1.0, m) * p["fresnel_normal_scale"], 0, 1)
    grefl = np.clip(1.0 * p["fresnel_grazing_scale"], 0, 1)
    dn = np_mix((1 - clear) * (1 - nrefl) * np_frnl(1 - nrefl, 1 - grefl, vn), 1.0, r)
    dg = np_mix((1 - clear) * (1 - grefl) * np_frnl(1 - nrefl, 1 - grefl, vn), 1.0, r)
    w = {
        "diffuse": (c * dn * (1 - back), c * dg * (1 - back)),
        "transmit_diffuse": (c * dn * back, c * dg * back),
    }
    refl_ratio = np.maximum(1 - 2 * r, 0.0) ** 3
    nrefl = np.clip(np_mix(0.05, c, m) * p["fresnel_normal_scale"], 0, 1)
    w["specular"] = ((1 - refl_ratio) * nrefl * (1 - r), (1 - refl_ratio) * grefl * (1 - r))
    w["reflection"] = (refl_ratio * nrefl * (1 - r), refl_ratio * grefl * (1 - r))
    w["transmit_specular"] = (
        c * (1 - refl_ratio) * (1 - nrefl) * (1 - r) * clear,
        c * (1 - refl_ratio) * (1 - grefl) * (1 - r) * clear,
    )
    w["refraction"] = (
        c * refl_ratio * (1 - nrefl) * (1 - r) * clear,
        c * refl_ratio * (1 - grefl) * (1 - r) * clear,
    )
    tint = {
        "specular": p["highlight_tint"],
        "reflection": p["highlight_tint"],
        "transmit_specular": p["transmit_tint"],
        "refraction": p["transmit_tint"],
    }
    out = {}
    for k, (wn, wg) in w.items():
        s = p[k + "_scale"] * tint.get(k, 1.0)
        out[k] = (wn * s, wg * s)
    return out


def np_eta(p):
    rr = np.clip(0.05 * p["fresnel_normal_scale"], 0, 0.9)
    return (1 + np.sqrt(rr)) / (1 - np.sqrt(rr))


def np_back_view(v, n, eta):
    """Refract -v by Snell's law (angles), then mirror the result about the normal axis."""
    cos_i = np.clip(_d(v, n), 0, 1)
    sin_t = np.sqrt(1 - cos_i**2) / eta
    cos_t = np.sqrt(1 - sin_t**2)
    tang = v - cos_i * n
    tl = np.linalg.norm(tang, axis=-1, keepdims=True)
    tang = np.where(tl > 1e-300, tang / np.maximum(tl, 1e-300), 0.0)
    return sin_t * tang - cos_t * n


def np_highlight(l, v, n, p):
    """Distribution-based lobe with the documented denominator 4 (v.h) max(n.l, n.v) / (n.h)."""
    h = _unit(l + v)
    nl, nv, nh, vh = _d(n, l), _d(n, v), _d(n, h), _d(v, h)
    return np_dist(1 - nh**2, p) * nh / (4 * vh * np.maximum(nl, nv))


def np_params(shape_n, **kw):
    p = dict(DEFAULTS)
    p.update(kw)
    out = {}
    for k, x in p.items():
        x = np.asarray(x, dtype=np.float64)
        out[k] = x if x.ndim else np.full((shape_n, 1), float(x))
    return out


def np_smits(l, v, n, p):
    """f(l, v) of the Smits model, (N, 3); p from np_params."""
    w = np_weights(v, n, p)
    cones = np_cones(p)
    nl, nv = _d(n, l), _d(n, v)
    up = (nl > 0) & (nv > 0)
    down = (nl < 0) & (nv > 0)
    with np.errstate(all="ignore"):
        refl = np_frnl(*w["diffuse"], nl) / np.pi
        for k in ("specular", "reflection"):
            refl = refl + np_frnl(*w[k], nv) * np_highlight(l, v, n, np_power(cones[k]))
        vt = np_back_view(v, n, np_eta(p))
        tran = np_frnl(*w["transmit_diffuse"], -nl) / np.pi
        for k in ("transmit_specular", "refraction"):
            tran = tran + np_frnl(*w[k], nv) * np_highlight(l, vt, -n, np_power(cones[k]))
    out = np.where(up, refl, np.where(down, tran, 0.0))
    return np.broadcast_to(out, (l.shape[0], 3))


# --------------------------------------------------------------------------- helpers


def t64(a):
    return torch.tensor(np.asarray(a), dtype=torch.float64)


def torch_params(p):
    return {k: t64(x) for k, x in p.items()}


def random_dirs(rng, count, upper=None):
    d = _unit(rng.normal(size=(count, 3)))
    if upper is True:
        d[:, 2] = np.abs(d[:, 2])
    elif upper is False:
        d[:, 2] = -np.abs(d[:, 2])
    return d


def random_params(rng, count, extras=True):
    p = dict(
        base_color=rng.uniform(0, 1, (count, 3)),
        metallic=rng.uniform(0, 1, (count, 1)),
        roughness=rng.uniform(0, 1, (count, 1)),
        clear=rng.uniform(0, 1, (count, 1)),
        back=rng.uniform(0, 1, (count, 1)),
    )
    if extras:
        p.update(
            fresnel_normal_scale=rng.uniform(0.5, 1.5, (count, 1)),
            fresnel_grazing_scale=rng.uniform(0.0, 1.2, (count, 1)),
            highlight_tint=rng.uniform(0, 1, (count, 3)),
            transmit_tint=rng.uniform(0, 1, (count, 3)),
            specular_cone_scale=rng.uniform(0.3, 2, (count, 1)),
            reflection_cone_scale=rng.uniform(0.3, 2, (count, 1)),
            transmit_specular_cone_scale=rng.uniform(0.3, 2, (count, 1)),
            refraction_cone_scale=rng.uniform(0.3, 2, (count, 1)),
            **{k: rng.uniform(0, 1.5, (count, 1)) for k in LOBE_SCALES},
        )
    return p


def frame(count, rng):
    """Random orthonormal normals (world space) and a rotation to express local vectors."""
    n = random_dirs(rng, count)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    x = _unit(np.cross(helper, n))
    y = np.cross(n, x)
    return x, y, n


# --------------------------------------------------------------------------- reference values


@pytest.mark.parametrize("extras", [False, True])
def test_matches_numpy_reference(extras):
    rng = np.random.default_rng(1 if extras else 0)
    count = 4000
    x, y, n = frame(count, rng)
    loc_l, loc_v = random_dirs(rng, count), random_dirs(rng, count, upper=True)
    to_world = lambda d: d[:, :1] * x + d[:, 1:2] * y + d[:, 2:3] * n  # noqa: E731
    l, v = to_world(loc_l), to_world(loc_v)
    p = random_params(rng, count, extras)
    # include the exact end points of every clamp/blend
    p["roughness"][:200] = rng.choice([0.0, 0.5, 1.0], (200, 1))
    p["metallic"][200:400] = rng.choice([0.0, 1.0], (200, 1))
    expected = np_smits(l, v, n, np_params(count, **p))
    got = smits(t64(l), t64(v), t64(n), **torch_params(p)).numpy()
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
    assert (np.abs(got[loc_l[:, 2] < 0]) > 0).any() and (np.abs(got[loc_l[:, 2] > 0]) > 0).any()


def test_view_below_is_zero():
    rng = np.random.default_rng(2)
    l, v = random_dirs(rng, 500), random_dirs(rng, 500, upper=False)
    n = np.array([0.0, 0, 1])
    p = torch_params(random_params(rng, 500))
    f = smits(t64(l), t64(v), t64(n), **p)
    assert (f == 0).all()


def test_notes_diffuse_check_at_normal_incidence():
    """The notes' check: FrnlBlend[diffN, diffG, Ldir.n] with V = L = n is 0.9025 / 1."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    off = dict(specular_scale=0.0, reflection_scale=0.0)
    white = torch.ones(3, dtype=torch.float64)
    f0 = smits(n, n, n, base_color=white, roughness=0.0, **off) * math.pi
    f1 = smits(n, n, n, base_color=white, roughness=1.0, **off) * math.pi
    torch.testing.assert_close(f0, torch.full_like(f0, 0.9025), rtol=0, atol=1e-12)
    torch.testing.assert_close(f1, torch.ones_like(f1), rtol=0, atol=1e-12)


def _gauss_hemisphere(n_mu, n_phi, lower=False):
    """Cosine-free quadrature over a hemisphere: directions (k, 3) and weights of d omega."""
    mu, wmu = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = 0.5 * (mu + 1), 0.5 * wmu
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    mu_g, phi_g = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - mu_g**2)
    d = np.stack([s * np.cos(phi_g), s * np.sin(phi_g), -mu_g if lower else mu_g], -1)
    w = np.repeat(wmu[:, None], n_phi, 1) * 2 * np.pi / n_phi
    return d.reshape(-1, 3), w.reshape(-1), mu_g.reshape(-1)


def test_diffuse_hemispherical_integral_at_normal_incidence():
    """Diffuse hemispherical integral at normal incidence: 0.9025 * 20/21 at roughness 0, 1 at 1.

    int FrnlBlend(diffN, diffG, n.l) cos / pi = 0.9025 (1 - 2 B(2, 6)) = 0.9025 * 20/21 at
    roughness 0 (the notes' 0.9025 is the value at l = v = n), exactly 1 at roughness 1.
    """
    d, w, mu = _gauss_hemisphere(16, 4)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v = n.expand(len(d), 3)
    got = []
    for r in (0.0, 1.0):
        f = smits(t64(d), v, n, base_color=1.0, roughness=r, specular_scale=0.0, reflection_scale=0.0)
        got.append(float((f[:, 0].numpy() * mu * w).sum()))
    assert got[0] == pytest.approx(0.9025 * 20 / 21, abs=1e-12)
    assert got[1] == pytest.approx(1.0, abs=1e-12)


def _integrate_distribution(p):
    """2 pi int_0^{pi/2} D(theta) cos sin d theta, composite Gauss-Legendre refined at the cone."""
    theta_c = np.arcsin(np.sqrt(np.log(10) / p))
    edges = np.unique(np.clip(theta_c * 2.0 ** np.arange(-6, 8), 0, np.pi / 2))
    edges = np.concatenate([[0.0], edges[edges > 0], [np.pi / 2]])
    x, wx = np.polynomial.legendre.leggauss(24)
    total = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        th = 0.5 * (b - a) * (x + 1) + a
        s2 = torch.as_tensor(np.sin(th) ** 2)[:, None]
        d = smits_distribution(s2, torch.full_like(s2, p))[:, 0].numpy()
        total += 0.5 * (b - a) * np.sum(wx * d * np.cos(th) * np.sin(th))
    return 2 * np.pi * total


def test_distribution_integrates_to_one_for_every_exponent():
    rough = np.linspace(0, 1, 21)
    cones = np.concatenate([30 * rough + 5, np.maximum(10 * rough, MIN_CONE_DEG), [60.0, 90.0]])
    for cone in cones:
        power = smits_cone_power(torch.tensor([math.radians(cone)], dtype=torch.float64))
        p = float(power)
        assert p == pytest.approx(float(np_power(cone)), rel=1e-12)
        # the notes' check (over the hemisphere): a / ((1 - e^-a) pi) int e^{-a sin^2} cos = 1
        assert _integrate_distribution(p) == pytest.approx(1.0, abs=1e-9), cone
        # the cone angle is where the distribution falls to 10 % of its peak
        s2 = torch.tensor([[0.0], [math.sin(math.radians(cone)) ** 2]], dtype=torch.float64)
        dd = smits_distribution(s2, power.expand(2, 1))
        assert float(dd[1] / dd[0]) == pytest.approx(0.1, rel=1e-12)


def _rot_y(d, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])


def _rot_x(d, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([d[0], c * d[1] - s * d[2], s * d[1] + c * d[2]])


@pytest.mark.parametrize("lobe", ["reflection", "refraction", "specular", "transmit_specular"])
def test_highlights_peak_at_mirror_and_snell_directions(lobe):
    """Front lobes peak at the mirror direction; back lobes at the refracted direction.

    Snell with eta = (1 + sqrt 0.05) / (1 - sqrt 0.05) = 1.576, for several view angles.
    """
    eta = (1 + math.sqrt(0.05)) / (1 - math.sqrt(0.05))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # broad lobes have off-specular peaks toward grazing (as microfacet lobes do): test them
    # up to 40 deg only
    views = (0.0, 40.0, 75.0) if lobe in ("reflection", "refraction") else (0.0, 40.0)
    for view_deg in views:
        a = math.radians(view_deg)
        v = np.array([math.sin(a), 0.0, math.cos(a)])
        if lobe in ("reflection", "specular"):
            peak = np.array([-v[0], 0.0, v[2]])
        else:
            st = math.sin(a) / eta
            peak = np.array([-st, 0.0, -math.sqrt(1 - st * st)])
        offsets = [0.3, -0.3] if lobe in ("reflection", "refraction") else [3.0, -3.0]
        probes = [peak] + [_rot_y(peak, d) for d in offsets] + [_rot_x(peak, d) for d in offsets]
        l = t64(np.stack(probes))
        scales = {s: float(s == lobe + "_scale") for s in LOBE_SCALES}
        vv = t64(v).expand(len(probes), 3)
        f = smits(l, vv, z, base_color=1.0, roughness=0.1, clear=1.0, **scales)[:, 0]
        assert f[0] > 0 and (f[0] > f[1:]).all(), (view_deg, f)


# --------------------------------------------------------------------------- energy


def _h_quadrature(n_u, n_phi, power):
    """Nodes/weights for int D(h)(n.h) g(h) d omega_h = mean over (u, phi) of g (n = +z).

    The substitution u = (1 - exp(-p t)) / (1 - exp(-p)), t = sin^2 theta_h, turns the
    distribution measure into the uniform measure on [0, 1] x [0, 2 pi).
    """
    u = (np.arange(n_u) + 0.5) / n_u
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    power = np.asarray(power, dtype=np.float64).reshape(-1, 1, 1)
    t = -np.log1p(-u[None, :, None] * -np.expm1(-power)) / power
    t = np.broadcast_to(t, (power.shape[0], n_u, n_phi))
    st = np.sqrt(t)
    h = np.stack([st * np.cos(phi), st * np.sin(phi) * np.ones_like(st), np.sqrt(1 - t)], -1)
    return h  # (k, n_u, n_phi, 3), equal weights


def highlight_albedo(f_of_l, v_loc, power, lower=False, n_u=96, n_phi=48):
    """Albedo int f |cos| d omega_l of one highlight lobe around +z (or -z), v in local frame.

    f_of_l(l) -> (k, n_u, n_phi, 3) evaluated BRDF values. Uses d omega_l = 4 (v.h) d omega_h
    and the NumPy distribution as the h-density, so the integrand is bounded.
    """
    h = _h_quadrature(n_u, n_phi, power)
    if lower:
        h = h * np.array([1.0, 1.0, -1.0])
    v = v_loc[:, None, None, :]
    vh = np.sum(v * h, -1, keepdims=True)
    l = 2 * vh * h - v
    cos_l = -l[..., 2:3] if lower else l[..., 2:3]
    valid = (cos_l > 0) & (vh > 0)
    p = np.asarray(power, dtype=np.float64).reshape(-1, 1, 1, 1)
    pdf = np_dist(h[..., 0:1] ** 2 + h[..., 1:2] ** 2, p) * np.abs(h[..., 2:3])
    f = f_of_l(np.where(valid, l, np.array([0.0, 0.0, 1.0])))
    g = np.where(valid, f * cos_l * 4 * np.abs(vh) / pdf, 0.0)
    return g.mean(axis=(1, 2))  # (k, 3)


def diffuse_albedo(f_of_l, k, lower=False):
    d, w, mu = _gauss_hemisphere(16, 2, lower)
    f = f_of_l(np.broadcast_to(d, (k, len(d), 3)))
    return np.sum(f * (mu * w)[None, :, None], axis=1)


def view_dirs(angles_deg):
    a = np.radians(np.asarray(angles_deg, dtype=np.float64))
    return np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], -1)


def test_highlight_lobe_albedo_at_most_one_for_every_exponent_and_view():
    """Choice 1 of the module docstring: the lobe's albedo never exceeds 1."""
    cones = np.array([MIN_CONE_DEG, 1, 3, 5, 10, 20, 35, 60, 90.0])
    angles = np.array([0, 30, 60, 80, 89, 89.9])
    cc, aa = np.meshgrid(cones, angles, indexing="ij")
    powers = np_power(cc.reshape(-1))
    v = view_dirs(aa.reshape(-1))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)

    def f(l):
        vv = np.broadcast_to(v[:, None, None, :], l.shape)
        pp = np.broadcast_to(powers[:, None, None, None], (*l.shape[:-1], 1))
        return smits_highlight_lobe(t64(l), t64(vv), z, t64(pp)).numpy()

    alb = highlight_albedo(f, v, powers, n_u=192, n_phi=32)[:, 0].reshape(cc.shape)
    assert (alb <= 1 + 1e-6).all(), alb.max()
    # normal incidence: n.l = cos(2 theta_h) = 1 - 2t (t = sin^2 theta_h), so the albedo is
    # E[(1 - 2t) 1{t < 1/2}] under the density p e^{-pt} / (1 - e^{-p}) on [0, 1]:
    # (1 - 2 (1 - e^{-p/2}) / p) / (1 - e^{-p})
    p = powers.reshape(cc.shape)[:, 0]
    closed = (1 - 2 * -np.expm1(-p / 2) / p) / -np.expm1(-p)
    np.testing.assert_allclose(alb[:, 0], closed, rtol=5e-4)  # horizon cut: O(1/n_u) error
    assert alb[:, 0].min() > 0.45  # 90 deg cone: 0.451; 35 deg: 0.899; 5 deg: 0.997
    # the lobe matches the documented formula pointwise
    rng = np.random.default_rng(3)
    l, vv = random_dirs(rng, 300, True), random_dirs(rng, 300, True)
    pw = rng.uniform(2, 1e4, (300, 1))
    got = smits_highlight_lobe(t64(l), t64(vv), z, t64(pw)).numpy()
    np.testing.assert_allclose(got, np_highlight(l, vv, np.array([0.0, 0, 1]), pw), rtol=1e-10)


def _smits_local(v_loc, params, only):
    """f_of_l(l) evaluating one lobe of the library in the local frame (n = +z).

    The other lobes get a Python 0 scale (skipped; ``test_lobes_sum_to_full_model`` checks
    that the lobes add up to the full model with tensor scales).
    """
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)

    def f(l):
        extra = (1,) * (l.ndim - 2)
        vv = np.broadcast_to(v_loc.reshape(len(v_loc), *extra, 3), l.shape)
        p = {k: t64(x.reshape(len(x), *extra, x.shape[-1])) for k, x in params.items()}
        p.update({s: 0.0 for s in LOBE_SCALES if s != only + "_scale"})
        return smits(t64(l), t64(vv), z, **p).numpy()

    return f


def total_albedo(v_loc, params, n_u=96, n_phi=48):
    """Reflection + transmission albedo, summing each lobe isolated by its scale."""
    k = len(v_loc)
    full = np_params(k, **params)
    cones = np_cones(full)
    eta = np_eta(full)
    vt = np_back_view(v_loc, np.array([0.0, 0, 1]), eta)
    total = np.zeros((k, 3))
    for lobe in ("diffuse", "transmit_diffuse", "specular", "reflection", "transmit_specular", "refraction"):
        p = dict(params)
        for s in LOBE_SCALES:
            p[s] = np.asarray(params.get(s, 1.0)) * np.ones((k, 1))
        f = _smits_local(v_loc, p, only=lobe)
        if lobe in ("diffuse", "transmit_diffuse"):
            total += diffuse_albedo(f, k, lower=lobe == "transmit_diffuse")
        elif lobe in ("specular", "reflection"):
            total += highlight_albedo(f, v_loc, np_power(cones[lobe]), n_u=n_u, n_phi=n_phi)
        else:
            # lobe about -z seen from the back-side view: integrate in that lobe's own frame
            total += highlight_albedo(f, vt, np_power(cones[lobe]), lower=True, n_u=n_u, n_phi=n_phi)
    return total


def test_lobes_sum_to_full_model():
    rng = np.random.default_rng(4)
    count = 500
    l, v = random_dirs(rng, count), random_dirs(rng, count, True)
    p = random_params(rng, count)
    n = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    full = smits(t64(l), t64(v), n, **torch_params(p))
    parts = 0
    for s in LOBE_SCALES:
        q = dict(p)
        for s2 in LOBE_SCALES:
            q[s2] = p[s2] * (s2 == s)
        parts = parts + smits(t64(l), t64(v), n, **torch_params(q))
    torch.testing.assert_close(parts, full, rtol=1e-12, atol=1e-12)


def test_directional_albedo_at_most_one_over_parameter_grid():
    """Reflection + transmission, every lobe, over a grid of all core parameters and views."""
    grid = (
        np.array(
            np.meshgrid(
                [0.0, 1.0],  # metallic (0.5 is covered by the random-parameter test)
                [0.0, 0.2, 0.5, 0.8, 1.0],  # roughness
                [0.0, 0.5, 1.0],  # clear
                [0.0, 1.0],  # back
                [0.0, 60.0, 85.0],  # view angle
                indexing="ij",
            )
        )
        .reshape(5, -1)
        .T
    )
    k = len(grid)
    params = dict(
        base_color=np.ones((k, 3)),
        metallic=grid[:, 0:1],
        roughness=grid[:, 1:2],
        clear=grid[:, 2:3],
        back=grid[:, 3:4],
    )
    alb = total_albedo(view_dirs(grid[:, 4]), params, n_u=64, n_phi=32)
    assert alb.max() <= 1 + 2e-3, alb.max()
    # energy is partitioned, not thrown away, where the notes say so: rough 1 is white diffuse
    rough1 = grid[:, 1] == 1
    np.testing.assert_allclose(alb[rough1], 1.0, atol=1e-9)


def test_directional_albedo_at_most_one_random_parameters():
    """All controls (colours, tints, Fresnel scales <= 1, lobe scales <= 1, cone scales)."""
    rng = np.random.default_rng(5)
    k = 32
    p = random_params(rng, k)
    p["fresnel_normal_scale"] = rng.uniform(0.2, 1.0, (k, 1))
    p["fresnel_grazing_scale"] = rng.uniform(0.0, 1.0, (k, 1))
    for s in LOBE_SCALES:
        p[s] = rng.uniform(0.5, 1.0, (k, 1))
    p["base_color"][: k // 2] = 1.0
    p["highlight_tint"][: k // 2] = 1.0
    p["transmit_tint"][: k // 2] = 1.0
    v = view_dirs(rng.uniform(0, 88, k))
    alb = total_albedo(v, p, n_u=64, n_phi=32)
    assert alb.max() <= 1 + 2e-3, alb.max()
