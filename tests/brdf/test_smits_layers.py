"""Tests of the Smits Wall-E/Up model: reciprocity, gradients, the API and layering (the float64
NumPy reference and shared helpers live in :mod:`tests.brdf.test_smits`)."""

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


from tests.brdf.test_smits import (  # the reference and helpers
    DEFAULTS,
    LOBE_SCALES,
    _d,
    _unit,
    diffuse_albedo,
    highlight_albedo,
    np_back_view,
    np_cones,
    np_frnl,
    np_params,
    np_weights,
    random_dirs,
    random_params,
    t64,
    torch_params,
    view_dirs,
)


# --------------------------------------------------------------------------- reciprocity


def test_reciprocity():
    rng = np.random.default_rng(6)
    count = 400
    l, v = random_dirs(rng, count, True), random_dirs(rng, count, True)
    n = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    p = torch_params(random_params(rng, count, extras=False))
    # the diffuse lobe is reciprocal for every parameter value
    off = dict(specular_scale=0.0, reflection_scale=0.0)
    torch.testing.assert_close(smits(t64(l), t64(v), n, **p, **off), smits(t64(v), t64(l), n, **p, **off))
    # the whole reflection is reciprocal when normal and grazing reflectance agree
    q = dict(p, metallic=t64(0.0), fresnel_grazing_scale=t64(0.05))
    torch.testing.assert_close(smits(t64(l), t64(v), n, **q), smits(t64(v), t64(l), n, **q))


# --------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("below", [False, True])
def test_gradcheck(below):
    rng = np.random.default_rng(7 + below)
    count = 6
    l = random_dirs(rng, count, upper=not below)
    v = random_dirs(rng, count, True)
    l[:, 2] = np.sign(l[:, 2]) * np.maximum(np.abs(l[:, 2]), 0.2)
    v[:, 2] = np.maximum(v[:, 2], 0.2)
    l, v = _unit(l), _unit(v)
    n = np.array([[0.1, -0.05, 1.0]]).repeat(count, 0)
    n = _unit(n)
    inputs = [
        t64(l),
        t64(v),
        t64(n),
        t64(rng.uniform(0.1, 0.9, (count, 3))),
        t64(rng.uniform(0.1, 0.9, (count, 1))),
        t64(rng.uniform(0.3, 0.45, (count, 1))),  # cones: refl 3-4.5 deg, spec 14-18.5 deg
        t64(rng.uniform(0.1, 0.9, (count, 1))),
        t64(rng.uniform(0.1, 0.9, (count, 1))),
        t64(rng.uniform(0.5, 0.9, (count, 1))),
    ]
    for t in inputs:
        t.requires_grad_(True)

    def fn(l, v, n, c, m, r, cl, bk, sg):
        return smits(
            l, v, n, base_color=c, metallic=m, roughness=r, clear=cl, back=bk, fresnel_grazing_scale=sg
        )

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


def test_gradcheck_layered():
    rng = np.random.default_rng(9)
    count = 4
    l, v = random_dirs(rng, count, True), random_dirs(rng, count, True)
    l[:, 2], v[:, 2] = np.maximum(l[:, 2], 0.3), np.maximum(v[:, 2], 0.3)
    l, v = _unit(l), _unit(v)
    n = t64(np.array([0.0, 0, 1]))
    n2 = t64(_unit(np.array([[0.2, 0.1, 1.0]])).repeat(count, 0)).requires_grad_(True)
    c1 = t64(rng.uniform(0.1, 0.9, (count, 3))).requires_grad_(True)
    r2 = t64(rng.uniform(0.6, 0.9, (count, 1))).requires_grad_(True)
    a = t64(rng.uniform(0.2, 0.8, (count, 1))).requires_grad_(True)

    def fn(l, v, n2, c1, r2, a):
        top = dict(base_color=c1, roughness=0.3)
        bottom = dict(base_color=torch.ones(3, dtype=torch.float64), roughness=r2, normal=n2)
        return smits_layered(l, v, n, layers=[top, bottom], layer_weights=[a, 1.0])

    assert torch.autograd.gradcheck(fn, (t64(l), t64(v), n2, c1, r2, a), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_finite_at_grazing_and_extreme_parameters():
    z = np.array([0.0, 0, 1])
    g = math.radians(89.99)
    dirs = [
        (z, z),
        (np.array([1.0, 0, 0]), z),  # light exactly grazing
        (z, np.array([1.0, 0, 0])),  # view exactly grazing -> 0
        (view_dirs([89.99])[0], -view_dirs([89.99])[0] * [1, 1, -1]),  # mirror pair at grazing
        (view_dirs([89.99])[0], view_dirs([89.99])[0]),  # l = v grazing
        (np.array([1.0, 0, 0]), np.array([-1.0, 0, 0])),  # l = -v: h undefined
        (np.array([math.sin(g), 0, -math.cos(g)]), z),  # light just below, transmission
        (-z, z),  # straight through
        (-z, view_dirs([60.0])[0]),
        (z, -z),  # view below
    ]
    l = np.stack([d[0] for d in dirs])
    v = np.stack([d[1] for d in dirs])
    for dtype in (torch.float32, torch.float64):
        for r in (0.0, 1.0, 0.5):
            for m in (0.0, 1.0):
                lt = torch.as_tensor(l, dtype=dtype).requires_grad_(True)
                vt = torch.as_tensor(v, dtype=dtype).requires_grad_(True)
                nt = torch.tensor([0.0, 0, 1], dtype=dtype).expand(len(l), 3).clone().requires_grad_(True)
                c = torch.full((len(l), 3), 0.8, dtype=dtype, requires_grad=True)
                rr = torch.full((len(l), 1), r, dtype=dtype, requires_grad=True)
                f = smits(lt, vt, nt, base_color=c, roughness=rr, metallic=m, clear=0.5, back=0.5)
                assert torch.isfinite(f).all()
                f.sum().backward()
                for t in (lt, vt, nt, c, rr):
                    assert torch.isfinite(t.grad).all()
                # exactly zero (value and gradients) for grazing/below views and n.l = 0
                for i in (1, 2, 5, 9):
                    assert (f[i] == 0).all()
                    assert (c.grad[i] == 0).all() and (rr.grad[i] == 0).all()
                for i in (2, 9):
                    assert (lt.grad[i] == 0).all()


# --------------------------------------------------------------------------- API


def test_module_equals_functional_and_shapes():
    rng = np.random.default_rng(10)
    l = torch.as_tensor(random_dirs(rng, 2 * 4 * 5), dtype=torch.float32).reshape(2, 4, 5, 3)
    v = torch.as_tensor(random_dirs(rng, 2 * 4 * 5, True), dtype=torch.float32).reshape(2, 4, 5, 3)
    n = torch.tensor([0.0, 0.0, 1.0])
    material = dict(
        base_color=torch.rand(2, 4, 5, 3),
        roughness=torch.rand(2, 4, 5, 1),
        metallic=0.3,
        clear=torch.tensor(0.2),
        back=torch.rand(1, 1, 1, 1),
        highlight_tint=torch.rand(3),
    )
    f = smits(l, v, n, **material)
    assert f.shape == (2, 4, 5, 3) and f.dtype == torch.float32
    torch.testing.assert_close(SmitsBRDF()(l, v, n, None, None, **material), f, rtol=0, atol=0)
    # scalar base colour still gives RGB
    assert smits(l, v, n, base_color=0.5).shape == (2, 4, 5, 3)
    with pytest.raises(TypeError):
        smits(l, v, n, base_color=0.5, sheen=1.0)


def test_defaults_agree():
    """One set of defaults: smits, smits_lobes and the NumPy reference's DEFAULTS."""
    import inspect

    def defaults(fn):
        return {
            k: q.default
            for k, q in inspect.signature(fn).parameters.items()
            if q.kind == q.KEYWORD_ONLY and q.default is not q.empty and k != "lobes"
        }

    assert defaults(smits) == defaults(smits_lobes) == DEFAULTS
    assert list(inspect.signature(smits).parameters)[:5] == ["l", "v", "n", "x", "y"]


def test_lobe_selection_pruning_and_argument_checks():
    rng = np.random.default_rng(15)
    count = 300
    l, v = t64(random_dirs(rng, count)), t64(random_dirs(rng, count, True))
    n = t64(np.array([0.0, 0, 1]))
    p = torch_params(random_params(rng, count))
    keep = ("diffuse", "refraction")
    only = dict(p, **{s: p[s] * float(s[: -len("_scale")] in keep) for s in LOBE_SCALES})
    expected = smits(l, v, n, **only)
    torch.testing.assert_close(smits(l, v, n, **p, lobes=keep), expected, rtol=0, atol=0)
    torch.testing.assert_close(SmitsBRDF(lobes=keep)(l, v, n, **p), expected, rtol=0, atol=0)
    # Python zeros are skipped, with the same result as zero tensors
    q = dict(p, clear=0.0, back=0.0, roughness=0.7, specular_scale=0.0)
    q_t = dict(q, clear=t64(0.0), back=t64(0.0), roughness=t64(0.7), specular_scale=t64(0.0))
    torch.testing.assert_close(smits(l, v, n, **q), smits(l, v, n, **q_t), rtol=0, atol=0)
    assert smits_lobes(v, n, **q).pruned == {
        "specular",
        "transmit_diffuse",
        "transmit_specular",
        "reflection",
        "refraction",
    }
    with pytest.raises(ValueError, match="unknown lobe"):
        SmitsBRDF(lobes=("sheen",))
    with pytest.raises(ValueError, match="base_color"):
        smits(l, v, n, base_color=torch.ones(count, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="roughness"):
        smits(l, v, n, base_color=1.0, roughness=torch.ones(count, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="dtype"):
        smits(l.float(), v, n, base_color=1.0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision(dtype):
    rng = np.random.default_rng(11)
    l = torch.as_tensor(random_dirs(rng, 200), dtype=torch.float32)
    v = torch.as_tensor(random_dirs(rng, 200, True), dtype=torch.float32)
    n = torch.tensor([0.0, 0.0, 1.0])
    c, r = torch.rand(200, 3), torch.rand(200, 1) * 0.9 + 0.1
    ref = smits(l, v, n, base_color=c, roughness=r, clear=0.5, back=0.3)
    got = smits(
        l.to(dtype),
        v.to(dtype),
        n.to(dtype),
        base_color=c.to(dtype),
        roughness=r.to(dtype),
        clear=0.5,
        back=0.3,
    )
    assert got.dtype == dtype and torch.isfinite(got).all()
    # inputs were rounded to the half type; compare loosely on the float32 result of those
    ref_h = smits(
        l.to(dtype).float(),
        v.to(dtype).float(),
        n,
        base_color=c.to(dtype).float(),
        roughness=r.to(dtype).float(),
        clear=0.5,
        back=0.3,
    )
    torch.testing.assert_close(got.float(), ref_h, rtol=2e-2, atol=1e-3)
    assert torch.isfinite(ref).all()
    # a roughness-0 peak stays finite in float16 (saturated, never inf)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    assert torch.isfinite(smits(z, z, z, base_color=torch.ones(3, dtype=dtype), roughness=0.0)).all()


# --------------------------------------------------------------------------- layering


def _lobe_fields(lobes):
    names = [
        f"{k}_{s}"
        for k in ("diffuse", "specular", "reflection", "transmit_diffuse", "transmit_specular", "refraction")
        for s in "ng"
    ]
    return {k: getattr(lobes, k) for k in names}


def test_single_layer_equals_smits_and_presence_scales():
    rng = np.random.default_rng(12)
    count = 300
    l, v = t64(random_dirs(rng, count)), t64(random_dirs(rng, count, True))
    n = t64(np.array([0.0, 0, 1]))
    p = torch_params(random_params(rng, count))
    f = smits(l, v, n, **p)
    torch.testing.assert_close(smits_layered(l, v, n, layers=[p], layer_weights=[1.0]), f)
    torch.testing.assert_close(SmitsLayeredBRDF()(l, v, n, layers=[p], layer_weights=[0.3]), 0.3 * f)
    # the same material twice covers 0.4 + 0.6 * 1 = 1 of the pixel: unchanged
    torch.testing.assert_close(smits_layered(l, v, n, layers=[p, p], layer_weights=[0.4, 1.0]), f)
    # presence below 1 on both: coverage 0.5 + 0.5 * 0.5 = 0.75
    torch.testing.assert_close(smits_layered(l, v, n, layers=[p, p], layer_weights=[0.5, 0.5]), 0.75 * f)


def test_composite_weights_cones_and_normals():
    rng = np.random.default_rng(13)
    count = 200
    v = random_dirs(rng, count, True)
    v[:, 2] = np.maximum(v[:, 2], 0.2)
    v = _unit(v)
    na = _unit(np.array([[0.2, 0.0, 1.0]])).repeat(count, 0)
    nb = _unit(np.array([[-0.1, 0.3, 1.0]])).repeat(count, 0)
    pa, pb = random_params(rng, count, extras=False), random_params(rng, count, extras=False)
    a, b = rng.uniform(0, 1, (count, 1)), rng.uniform(0, 1, (count, 1))
    la = smits_lobes(t64(v), t64(na), **torch_params(pa))
    lb = smits_lobes(t64(v), t64(nb), **torch_params(pb))
    comp = smits_composite(t64(v), [la, lb], [t64(a), t64(b)])
    ca, cb = a, (1 - a) * b  # A over B
    # lobe weights: A-over-B, checked against the NumPy weights
    wa = np_weights(v, na, np_params(count, **pa))
    wb = np_weights(v, nb, np_params(count, **pb))
    for lobe in wa:
        for i, s in enumerate("ng"):
            expected = np.broadcast_to(ca * wa[lobe][i] + cb * wb[lobe][i], (count, 3))
            np.testing.assert_allclose(getattr(comp, f"{lobe}_{s}").numpy(), expected, rtol=1e-10, atol=1e-14)

    def lum(c):
        return 0.3 * c[:, 0:1] + 0.6 * c[:, 1:2] + 0.1 * c[:, 2:3]

    def energy(w, lobe, n):
        wn, wg = w[lobe]
        share = (20 * wn + wg) / 21 if "diffuse" in lobe else np_frnl(wn, wg, _d(v, n))
        return lum(np.broadcast_to(share, (count, 3))) + 1e-6

    ca_, cb_ = np_cones(np_params(count, **pa)), np_cones(np_params(count, **pb))
    for lobe in ("specular", "reflection", "transmit_specular", "refraction"):
        ea, eb = ca * energy(wa, lobe, na), cb * energy(wb, lobe, nb)
        expected = np.radians((ea * ca_[lobe] + eb * cb_[lobe]) / (ea + eb))
        np.testing.assert_allclose(getattr(comp, lobe + "_cone").numpy(), expected, rtol=1e-9)
    ed = [
        c * (energy(w, "diffuse", nn) + energy(w, "transmit_diffuse", nn))
        for c, w, nn in ((ca, wa, na), (cb, wb, nb))
    ]
    np.testing.assert_allclose(comp.diffuse_normal.numpy(), _unit(ed[0] * na + ed[1] * nb), rtol=1e-9)
    hs = ("specular", "reflection", "transmit_specular", "refraction")
    eh = [c * sum(energy(w, k, nn) for k in hs) for c, w, nn in ((ca, wa, na), (cb, wb, nb))]
    np.testing.assert_allclose(comp.highlight_normal.numpy(), _unit(eh[0] * na + eh[1] * nb), rtol=1e-9)
    # evaluating the composite is what smits_layered does
    l = t64(random_dirs(rng, count))
    n = t64(np.array([0.0, 0, 1]))
    ref = smits_evaluate(l, t64(v), n, comp)
    got = smits_layered(
        l,
        t64(v),
        n,
        layers=[dict(torch_params(pa), normal=t64(na)), dict(torch_params(pb), normal=t64(nb))],
        layer_weights=[t64(a), t64(b)],
    )
    torch.testing.assert_close(got, ref)


def test_layered_albedo_at_most_one():
    """A layered lobe set is a coverage-weighted sum of partitions: still <= 1."""
    rng = np.random.default_rng(14)
    k = 16
    pa, pb = random_params(rng, k, extras=False), random_params(rng, k, extras=False)
    for p in (pa, pb):
        p["base_color"][:] = 1.0
    a = rng.uniform(0, 1, (k, 1))
    v_loc = view_dirs(rng.uniform(0, 85, k))
    z = torch.tensor([0.0, 0, 1], dtype=torch.float64)

    def layered_f(scale_name):
        def f(l):
            extra = (1,) * (l.ndim - 2)
            vv = np.broadcast_to(v_loc.reshape(k, *extra, 3), l.shape)

            def tp(p):
                q = {kk: t64(x.reshape(k, *extra, x.shape[-1])) for kk, x in p.items()}
                q.update({s: float(s == scale_name) for s in LOBE_SCALES})
                return q

            aa = t64(a.reshape(k, *extra, 1))
            return smits_layered(t64(l), t64(vv), z, layers=[tp(pa), tp(pb)], layer_weights=[aa, 1.0]).numpy()

        return f

    comp = smits_composite(
        t64(v_loc),
        [smits_lobes(t64(v_loc), z, **torch_params(pa)), smits_lobes(t64(v_loc), z, **torch_params(pb))],
        [t64(a), 1.0],
    )
    total = np.zeros((k, 3))
    total += diffuse_albedo(layered_f("diffuse_scale"), k)
    total += diffuse_albedo(layered_f("transmit_diffuse_scale"), k, lower=True)
    for lobe in ("specular", "reflection"):
        power = smits_cone_power(getattr(comp, lobe + "_cone")).numpy()[:, 0]
        total += highlight_albedo(layered_f(lobe + "_scale"), v_loc, power, n_u=64, n_phi=32)
    vt = np_back_view(v_loc, np.array([0.0, 0, 1]), comp.eta.numpy())
    for lobe in ("transmit_specular", "refraction"):
        power = smits_cone_power(getattr(comp, lobe + "_cone")).numpy()[:, 0]
        total += highlight_albedo(layered_f(lobe + "_scale"), vt, power, lower=True, n_u=64, n_phi=32)
    assert total.max() <= 1 + 2e-3, total.max()
    assert total.min() > 0.3
