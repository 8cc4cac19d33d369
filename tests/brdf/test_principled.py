"""The principled BRDF against an independent float64 reference, plus its physical checks."""

import math

import numpy as np
import pytest
import torch

import torchbrdf
from torchbrdf import PrincipledBRDF, principled

from tests.conftest import hemisphere_pairs
from tests.reference import principled_ref

SCALARS = ["metallic", "subsurface", "specular", "roughness", "specular_tint", "anisotropic",
           "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss"]


def random_case(seed, count=4096, min_cos=0.0):
    rng = np.random.default_rng(seed)
    x, y, n, l, v = hemisphere_pairs(rng, count, min_cos)
    params = {k: rng.uniform(0, 1, (count, 1)) for k in SCALARS}
    base = rng.uniform(0, 1, (count, 3))
    return dict(l=l, v=v, n=n, x=x, y=y), base, params


def to_t(d, dtype, device="cpu"):
    return {k: torch.as_tensor(a, dtype=dtype, device=device) for k, a in d.items()}


def rel_err(a, b):
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-30)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference_float64(seed):
    vec, base, params = random_case(seed)
    ref = principled_ref(vec["l"], vec["v"], vec["n"], vec["x"], vec["y"], base, **params)
    out = principled(**to_t(vec, torch.float64), base_color=torch.as_tensor(base),
                     **to_t(params, torch.float64)).numpy()
    assert rel_err(out, ref).max() <= 1e-6


def test_module_matches_reference_float64():
    vec, base, params = random_case(7)
    ref = principled_ref(vec["l"], vec["v"], vec["n"], vec["x"], vec["y"], base, **params)
    out = PrincipledBRDF()(**to_t(vec, torch.float64), base_color=torch.as_tensor(base),
                           **to_t(params, torch.float64)).numpy()
    assert rel_err(out, ref).max() <= 1e-6


def test_matches_reference_float32_on_rounded_inputs():
    # Away from grazing (cosines >= 0.05); the reference sees the float32-rounded inputs.
    vec, base, params = random_case(3, min_cos=0.05)
    vec32, base32 = to_t(vec, torch.float32), torch.as_tensor(base, dtype=torch.float32)
    p32 = to_t(params, torch.float32)
    out = principled(**vec32, base_color=base32, **p32).numpy().astype(np.float64)
    up = lambda d: {k: t.double().numpy() for k, t in d.items()}  # noqa: E731
    v64 = up(vec32)
    ref = principled_ref(v64["l"], v64["v"], v64["n"], v64["x"], v64["y"], base32.double().numpy(), **up(p32))
    assert rel_err(out, ref).max() <= 1e-4


def test_beyond_unit_range_stays_finite_and_matches():
    # Burley's principle 4: parameters past [0, 1] where that still makes sense.
    vec, base, params = random_case(11, count=512)
    params = {k: p * 2.0 for k, p in params.items()}
    params["anisotropic"] = np.clip(params["anisotropic"], 0, 1)   # sqrt(1 - 0.9a) needs a <= 1.11
    params["clearcoat_gloss"] = np.clip(params["clearcoat_gloss"], 0, 1)
    ref = principled_ref(vec["l"], vec["v"], vec["n"], vec["x"], vec["y"], base * 2, **params)
    out = principled(**to_t(vec, torch.float64), base_color=torch.as_tensor(base * 2),
                     **to_t(params, torch.float64)).numpy()
    assert np.isfinite(out).all()
    assert rel_err(out, ref).max() <= 1e-6


def test_isotropic_path_equals_anisotropic_form():
    vec, base, params = random_case(4, count=1024)
    t = to_t(vec, torch.float64)
    p = to_t(params, torch.float64)
    p["anisotropic"] = 0.0
    iso = principled(t["l"], t["v"], t["n"], base_color=torch.as_tensor(base), **p)
    ani = principled(t["l"], t["v"], t["n"], t["x"], t["y"], base_color=torch.as_tensor(base), **p)
    torch.testing.assert_close(iso, ani, rtol=1e-10, atol=0)


def test_own_frame_for_tensor_anisotropy_and_error_for_float():
    vec, base, params = random_case(5, count=64)
    t = to_t(vec, torch.float64)
    out = principled(t["l"], t["v"], t["n"], base_color=torch.as_tensor(base),
                     anisotropic=torch.full((64, 1), 0.5, dtype=torch.float64))
    assert torch.isfinite(out).all()
    with pytest.raises(ValueError, match="anisotropic"):
        principled(t["l"], t["v"], t["n"], base_color=torch.as_tensor(base), anisotropic=0.5)


def test_helmholtz_reciprocity():
    vec, base, params = random_case(6)
    t, p = to_t(vec, torch.float64), to_t(params, torch.float64)
    b = torch.as_tensor(base)
    a = principled(t["l"], t["v"], t["n"], t["x"], t["y"], base_color=b, **p)
    r = principled(t["v"], t["l"], t["n"], t["x"], t["y"], base_color=b, **p)
    torch.testing.assert_close(a, r, rtol=1e-12, atol=0)


def test_zero_below_horizon_with_zero_gradients():
    vec, base, params = random_case(8, count=256)
    vec["l"][:128, :] *= -1.0  # first half: light flipped below the horizon (checked next)
    t = {k: a.requires_grad_() for k, a in to_t(vec, torch.float64).items()}
    p = {k: a.requires_grad_() for k, a in to_t(params, torch.float64).items()}
    b = torch.as_tensor(base).requires_grad_()
    below = (t["n"] * t["l"]).sum(-1) <= 0
    assert below.any() and (~below).any()
    f = principled(t["l"], t["v"], t["n"], t["x"], t["y"], base_color=b, **p)
    assert (f[below] == 0).all()
    f.sum().backward()
    for g in [t["l"].grad, t["v"].grad, t["n"].grad, b.grad] + [q.grad for q in p.values()]:
        assert torch.isfinite(g).all()
    assert (b.grad[below] == 0).all() and (p["roughness"].grad[below] == 0).all()


def test_lobe_pruning_is_exact():
    vec, base, params = random_case(9, count=512)
    t, b = to_t(vec, torch.float32), torch.as_tensor(base, dtype=torch.float32)
    p = to_t(params, torch.float32)
    for lobe, key in [("clearcoat", "clearcoat"), ("sheen", "sheen"), ("subsurface", "subsurface")]:
        q = dict(p)
        q[key] = torch.zeros_like(p[key])
        full = principled(**t, base_color=b, **q)
        q[key] = 0.0
        pruned = principled(**t, base_color=b, **q)
        dropped = PrincipledBRDF(lobes=[x for x in torchbrdf.LOBES if x != lobe])(**t, base_color=b, **q)
        assert torch.equal(full, pruned), lobe
        assert torch.equal(full, dropped), lobe
    q = dict(p, metallic=1.0)
    full = principled(**t, base_color=b, **dict(p, metallic=torch.ones_like(p["metallic"])))
    assert torch.allclose(principled(**t, base_color=b, **q), full, rtol=1e-6, atol=0)


def test_lobes_argument_selects_single_lobe():
    vec, base, params = random_case(10, count=256)
    t, b, p = to_t(vec, torch.float64), torch.as_tensor(base), to_t(params, torch.float64)
    total = principled(**t, base_color=b, **p)
    parts = sum(PrincipledBRDF(lobes=[lobe])(**t, base_color=b, **p) for lobe in torchbrdf.LOBES)
    torch.testing.assert_close(parts, total, rtol=1e-10, atol=1e-14)
    with pytest.raises(ValueError, match="lobes"):
        PrincipledBRDF(lobes=["glitter"])


def test_gradcheck_float64():
    vec, base, params = random_case(12, count=6, min_cos=0.1)
    t = {k: a.requires_grad_() for k, a in to_t(vec, torch.float64).items()}
    p = {k: (a * 0.8 + 0.1).requires_grad_() for k, a in to_t(params, torch.float64).items()}
    b = torch.as_tensor(base).requires_grad_()
    names = list(p)

    def fn(l, v, n, x, y, b, *ps):
        return principled(l, v, n, x, y, base_color=b, **dict(zip(names, ps)))

    assert torch.autograd.gradcheck(fn, (t["l"], t["v"], t["n"], t["x"], t["y"], b, *p.values()))


def test_white_furnace_energy_bound():
    # A white, smooth-ish dielectric must not reflect more than it receives (diffuse +
    # specular of the principled model are not strictly energy conserving, Burley 2012 §5.3,
    # but stay within ~10 % at normal incidence for roughness 0.5).
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    u = (torch.arange(256, dtype=torch.float64) + 0.5) / 256
    ct, ph = torch.meshgrid(u, u * 2 * math.pi, indexing="ij")
    st = torch.sqrt(1 - ct ** 2)
    l = torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], -1).reshape(-1, 3)
    v = n.expand_as(l)
    f = principled(l, v, n.expand_as(l), base_color=torch.ones(3, dtype=torch.float64), roughness=0.5, specular=0.5)
    albedo = (f[:, 0] * l[:, 2]).mean() * 2 * math.pi
    assert 0.9 < float(albedo) < 1.12


def test_dtype_and_device_follow_input(device):
    vec, base, params = random_case(13, count=32)
    for dtype in (torch.float64, torch.float32, torch.float16, torch.bfloat16):
        t = to_t(vec, dtype, device)
        out = principled(**t, base_color=torch.as_tensor(base, dtype=dtype, device=device),
                         **to_t(params, dtype, device))
        assert out.dtype == dtype and out.device.type == device.type and out.shape == (32, 3)
        assert torch.isfinite(out).all()


def test_broadcast_scalars_and_batches():
    n = torch.tensor([0.0, 0.0, 1.0])
    l = torch.nn.functional.normalize(torch.randn(4, 5, 3).abs(), dim=-1)
    out = principled(l, n.expand(1, 1, 3), n, base_color=torch.tensor([0.5, 0.4, 0.3]),
                     roughness=torch.full((4, 1, 1), 0.3), metallic=0.5)
    assert out.shape == (4, 5, 3)
    grey = principled(l, n.expand(1, 1, 3), n, base_color=0.5)
    assert grey.shape == (4, 5, 3)


def test_bad_input_messages():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="roughness"):
        principled(n, n, n, base_color=torch.ones(1, 3), roughness=torch.ones(1, 2))
    with pytest.raises(TypeError, match="l: expected a floating-point"):
        principled(n.long(), n, n, base_color=torch.ones(1, 3))
    with pytest.raises(TypeError, match="dtype"):
        principled(n, n.double(), n, base_color=torch.ones(1, 3))
    with pytest.raises(ValueError, match="base_color"):
        principled(n, n, n, base_color=torch.ones(1, 4))
    with pytest.raises(ValueError, match="broadcast"):
        principled(torch.ones(2, 3), torch.ones(5, 3), n, base_color=torch.ones(1, 3))
    with pytest.raises(TypeError):
        principled(n, n, n)  # base_color is required
    with torchbrdf.validation(True), pytest.raises(ValueError, match="metallic"):
        principled(n, n, n, base_color=torch.ones(1, 3), metallic=torch.tensor([[float("nan")]]))
