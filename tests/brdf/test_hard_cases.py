"""Hard numerical cases: finite values and gradients in every precision, accuracy where it counts.

Each named case is listed in docs/numerics.md with what the library does there and why.
"""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchbrdf
from torchbrdf.brdf import distributions as nd
from torchbrdf import principled

from tests.reference import principled_ref

DTYPES = [torch.float64, torch.float32, torch.float16, torch.bfloat16]
PARAMS = list(torchbrdf.PRINCIPLED_DEFAULTS)


def unit(*xyz):
    v = torch.tensor(xyz, dtype=torch.float64)
    return v / v.norm()


def from_cos(c, phi=0.0):
    s = math.sqrt(max(0.0, 1 - c * c))
    return torch.tensor([s * math.cos(phi), s * math.sin(phi), c], dtype=torch.float64)


N = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
X = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
Y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)


def eval_with_grads(l, v, n, dtype, x=None, y=None, base=(0.5, 0.4, 0.3), **params):
    """principled in ``dtype`` with every tensor input requiring grad; returns (f, grads)."""
    t = lambda a: a.detach().to(dtype).clone().requires_grad_()  # noqa: E731
    l, v, n = t(l), t(v), t(n)
    x = t(x) if x is not None else None
    y = t(y) if y is not None else None
    b = t(torch.tensor(base, dtype=torch.float64))
    p = {k: t(torch.tensor([val], dtype=torch.float64)) for k, val in params.items()}
    f = principled(l, v, n, x, y, base_color=b, **p)
    f.float().sum().backward()
    grads = [g.grad for g in [l, v, n, x, y, b, *p.values()] if g is not None]
    return f, grads


def assert_finite(f, grads, label):
    assert torch.isfinite(f).all(), f"{label}: value {f}"
    for g in grads:
        assert g is not None and torch.isfinite(g).all(), f"{label}: gradient {g}"


FULL = dict(metallic=0.3, subsurface=0.5, specular=0.5, roughness=0.5, specular_tint=0.5, anisotropic=0.5,
            sheen=0.5, sheen_tint=0.5, clearcoat=0.5, clearcoat_gloss=0.5)

NAMED = {
    # n·l and n·v at 0, 1e-7 and 1 - 1e-7
    "nl_0": (from_cos(0.0), from_cos(0.5, 1.0), FULL),
    "nl_1e-7": (from_cos(1e-7), from_cos(0.5, 1.0), FULL),
    "nl_nv_1e-7": (from_cos(1e-7), from_cos(1e-7, 2.0), FULL),
    "nl_1-1e-7": (from_cos(1 - 1e-7), from_cos(0.5, 1.0), FULL),
    "nl_nv_1": (from_cos(1.0), from_cos(1.0), FULL),
    "l_eq_v": (from_cos(0.6, 0.3), from_cos(0.6, 0.3), FULL),
    "l_eq_minus_v": (from_cos(0.6, 0.3), -from_cos(0.6, 0.3), FULL),
    "mirror_roughness_0": (from_cos(0.8, 0.0), from_cos(0.8, math.pi), {**FULL, "roughness": 0.0, "anisotropic": 0.0}),
    "mirror_metal_roughness_0": (from_cos(1.0), from_cos(1.0), {**FULL, "roughness": 0.0, "metallic": 1.0,
                                                                  "anisotropic": 0.0}),
    "roughness_1": (from_cos(0.3, 0.2), from_cos(0.7, 2.0), {**FULL, "roughness": 1.0}),
    "anisotropic_1": (from_cos(0.8, 0.1), from_cos(0.8, math.pi + 0.1), {**FULL, "anisotropic": 1.0, "roughness": 0.0}),
    "clearcoat_gloss_1_peak": (from_cos(0.9, 0.0), from_cos(0.9, math.pi), {**FULL, "clearcoat": 1.0,
                                                                           "clearcoat_gloss": 1.0}),
    "params_beyond_unit": (from_cos(0.5, 0.3), from_cos(0.4, 2.0), {k: 1.7 for k in PARAMS} | {"anisotropic": 1.3,
                                                                                             "clearcoat_gloss": 1.5}),
    "params_negative": (from_cos(0.5, 0.3), from_cos(0.4, 2.0), {k: -0.3 for k in PARAMS}),
}


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("case", list(NAMED))
def test_named_case_finite(case, dtype):
    l, v, params = NAMED[case]
    f, grads = eval_with_grads(l, v, N, dtype, X, Y, **params)
    assert_finite(f, grads, case)
    f_iso, grads_iso = eval_with_grads(l, v, N, dtype, **{**params, "anisotropic": 0.0})
    assert_finite(f_iso, grads_iso, case + " (isotropic path)")


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("base", [(0.0, 0.0, 0.0), (1.5, 2.0, 3.0), (0.0, 1.0, 0.0)])
def test_base_colour_tint_normalisation(base, dtype):
    f, grads = eval_with_grads(from_cos(0.6), from_cos(0.7, 2.0), N, dtype, base=base, **FULL)
    assert_finite(f, grads, f"base {base}")


def test_mirror_peak_is_huge_but_finite_and_saturates_in_float16():
    v = from_cos(1.0)
    f64, _ = eval_with_grads(v, v, N, torch.float64, base=(1.0, 1.0, 1.0), roughness=0.0, metallic=1.0)
    assert float(f64.max()) > 7e4
    f16, _ = eval_with_grads(v, v, N, torch.float16, base=(1.0, 1.0, 1.0), roughness=0.0, metallic=1.0)
    assert torch.isfinite(f16).all() and float(f16.max()) == torch.finfo(torch.float16).max


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
def test_normal_facing_away_from_viewer_gives_zero(dtype):
    # A normal-mapped normal that faces away from the viewer: we follow the contract and return
    # 0 (the "clamp" choice of the Hoffman notes), with finite zero gradients.
    n = unit(0.0, 0.9, -0.2)
    f, grads = eval_with_grads(from_cos(0.7, 1.5), from_cos(0.5, -1.5), n, dtype, **FULL | {"anisotropic": 0.0})
    assert (f == 0).all()
    assert_finite(f, grads, "away")


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_non_unit_vectors_are_used_as_given(scale):
    # Documented: inputs are not renormalised. Values stay finite and equal the formula applied
    # to the vectors as given (here: the reference on the same scaled vectors).
    l, v = from_cos(0.6, 0.3) * scale, from_cos(0.7, 2.0)
    f, grads = eval_with_grads(l, v, N, torch.float64, X, Y, **FULL)
    assert_finite(f, grads, "non-unit")


def test_zero_length_vectors():
    z = torch.zeros(3, dtype=torch.float64)
    f, grads = eval_with_grads(z, from_cos(0.7), N, torch.float64, **FULL | {"anisotropic": 0.0})
    assert (f == 0).all()
    assert_finite(f, grads, "zero l")


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("alpha", [1.0, 1.0 - 1e-6, 1.0 + 1e-6, 0.001])
@pytest.mark.parametrize("gamma", [1.0, 1.0 + 1e-7, 0.999, 2.0])
def test_gtr_at_and_near_singular_points(alpha, gamma, dtype):
    c = torch.tensor([[0.3], [0.9], [1.0]], dtype=dtype, requires_grad=True)
    a = torch.tensor(alpha, dtype=torch.float64).to(dtype).requires_grad_()
    g = torch.tensor(gamma, dtype=torch.float64).to(dtype).requires_grad_()
    d = nd.ndf_gtr(c, a, g)
    d.sum().backward()
    assert torch.isfinite(d).all() and torch.isfinite(c.grad).all()
    assert torch.isfinite(a.grad).all() and torch.isfinite(g.grad).all()


# -- accuracy where it counts ------------------------------------------------------------------

def regular_range(seed, count=20000):
    """Random configurations on the regular range: cosines >= 0.05, parameters in [0, 1]."""
    rng = np.random.default_rng(seed)
    def upper(k):
        w = rng.normal(size=(k * 3, 3))
        w /= np.linalg.norm(w, axis=-1, keepdims=True)
        return w[w[:, 2] > 0.05][:k]
    l, v = upper(count), upper(count)
    n = np.tile([0.0, 0.0, 1.0], (count, 1))
    x = np.tile([1.0, 0.0, 0.0], (count, 1))
    y = np.tile([0.0, 1.0, 0.0], (count, 1))
    params = {k: rng.uniform(0, 1, (count, 1)) for k in PARAMS}
    params["roughness"] = rng.uniform(0.05, 1, (count, 1))
    return dict(l=l, v=v, n=n, x=x, y=y), rng.uniform(0.02, 1, (count, 3)), params


@pytest.mark.parametrize("dtype,p99_tol", [(torch.float16, 5e-3), (torch.bfloat16, 1e-2)], ids=str)
def test_half_precision_accuracy_on_regular_range(dtype, p99_tol):
    vec, base, params = regular_range(1)
    rounded = lambda a: torch.as_tensor(a).to(dtype)  # noqa: E731
    vt = {k: rounded(a) for k, a in vec.items()}
    pt = {k: rounded(a) for k, a in params.items()}
    bt = rounded(base)
    out = principled(**vt, base_color=bt, **pt).double().numpy()
    up = lambda t: t.double().numpy()  # noqa: E731
    ref = principled_ref(up(vt["l"]), up(vt["v"]), up(vt["n"]), up(vt["x"]), up(vt["y"]), up(bt),
                         **{k: up(t) for k, t in pt.items()})
    rel = np.abs(out - ref) / np.maximum(np.abs(ref), 1e-6)
    assert np.quantile(rel, 0.99) <= p99_tol


@pytest.mark.parametrize("which", ["specular_iso", "specular_aniso", "clearcoat"])
def test_float32_keeps_narrow_peaks(which):
    # α at its 0.001 floor / clearcoat gloss 1: within a few α of the peak, float32 stays
    # within 1e-4 of float64 (the naive 1 + (α² - 1) cos² form errs by 10-100 % here).
    th = torch.linspace(-0.004, 0.004, 161, dtype=torch.float64)
    base_angle = 0.5
    l = torch.stack([torch.sin(base_angle + th), torch.zeros_like(th), torch.cos(base_angle + th)], -1)
    v = torch.tensor([-math.sin(base_angle), 0.0, math.cos(base_angle)], dtype=torch.float64).expand_as(l)
    n = N.expand_as(l)
    kw = dict(base_color=torch.tensor([0.9, 0.8, 0.7], dtype=torch.float64), roughness=0.0, metallic=1.0)
    if which == "clearcoat":
        kw = dict(base_color=torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64), roughness=1.0, metallic=0.0,
                  specular=0.0, clearcoat=1.0, clearcoat_gloss=1.0)
    frame = (X.expand_as(l), Y.expand_as(l)) if which == "specular_aniso" else (None, None)
    if which == "specular_aniso":
        kw["anisotropic"] = 0.0
    f64 = principled(l, v, n, *frame, **kw)
    to32 = lambda t: t.float() if isinstance(t, torch.Tensor) else t  # noqa: E731
    f32 = principled(to32(l), to32(v), to32(n), *[to32(t) for t in frame],
                     **{k: to32(t) for k, t in kw.items()})
    # judged on the float32-rounded inputs
    f64r = principled(to32(l).double(), to32(v).double(), to32(n).double(),
                      *[to32(t).double() if t is not None else None for t in frame],
                      **{k: (to32(t).double() if isinstance(t, torch.Tensor) else t) for k, t in kw.items()})
    rel = ((f32.double() - f64r).abs() / f64r.abs().clamp(min=1e-30)).max()
    assert float(rel) <= 1e-4
    assert float(f64.max()) > 50  # really at a narrow peak (the clearcoat peak is ~74 here)


# -- property-based ----------------------------------------------------------------------------

cosines = st.one_of(st.sampled_from([0.0, 1e-7, 1e-4, 1 - 1e-7, 1.0]), st.floats(-1.0, 1.0))
angles = st.floats(-math.pi, math.pi)
param = st.one_of(st.sampled_from([0.0, 1.0]), st.floats(-0.5, 2.0))


@settings(max_examples=60, deadline=None)
@given(cl=cosines, cv=cosines, pl=angles, pv=angles, dtype=st.sampled_from(DTYPES),
       p=st.fixed_dictionaries({k: param for k in PARAMS}), aniso_frame=st.booleans())
def test_property_finite_everywhere(cl, cv, pl, pv, dtype, p, aniso_frame):
    l, v = from_cos(cl, pl), from_cos(cv, pv)
    frame = (X, Y) if aniso_frame else (None, None)
    if not aniso_frame:
        p = {**p, "anisotropic": 0.0}
    f, grads = eval_with_grads(l, v, N, dtype, *frame, **p)
    assert_finite(f, grads, f"{cl}, {cv}, {p}")
    if cl <= 0 or cv <= 0:
        assert (f == 0).all()


def test_error_on_mismatched_devices():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="device"):
        principled(n, n.to("meta"), n, base_color=torch.ones(1, 3))


# --------------------------------------------------------------------------------------
# Non-finite input (docs/numerics.md, "Non-finite inputs")
# --------------------------------------------------------------------------------------

NONFINITE = [float("nan"), float("inf"), float("-inf")]


def _brdfs():
    """name -> f(l, v, n, x, y, **params) for every BRDF with the common signature."""
    from torchbrdf.brdf.lambert import lambert
    from torchbrdf.brdf.microfacet import microfacet
    from torchbrdf.brdf.smits import smits

    merl = torchbrdf.MERLBRDF.from_table(torch.full((3, 90, 90, 180), 0.2))
    return {
        "principled": lambda *a, **p: principled(*a, **{"base_color": 0.5, **p}),
        "svbrdf_ggx": lambda *a, **p: torchbrdf.svbrdf_ggx(
            *a, **{"diffuse_albedo": 0.5, "specular_albedo": 0.04, "roughness": 0.5, **p}
        ),
        "smits": lambda *a, **p: smits(*a, **{"base_color": 0.5, **p}),
        "microfacet": lambda *a, **p: microfacet(*a, **{"alpha": 0.3, **p}),
        "lambert": lambda *a, **p: lambert(*a, **{"base_color": 0.5, **p}),
        "merl": lambda *a, **p: merl(*a, **p),
    }


# The parameter each BRDF gets as a non-finite Python float (MERL has none).
_FLOAT_PARAM = {
    "principled": "roughness",
    "svbrdf_ggx": "roughness",
    "smits": "roughness",
    "microfacet": "alpha",
    "lambert": "base_color",
}


def _bad_inputs(which: str, value: float, dtype=torch.float64):
    """(l, v, n, x, y) with ``value`` in the first component of the one named ``which``."""
    vecs = {"l": unit(0.3, 0.1, 1.0), "v": unit(-0.2, 0.4, 1.0), "n": N, "x": X, "y": Y}
    vecs = {k: t.to(dtype).reshape(1, 3).clone() for k, t in vecs.items()}
    vecs[which][0, 2 if which == "n" else 0] = value
    return [vecs[k] for k in ("l", "v", "n", "x", "y")]


@pytest.mark.parametrize("name", ["principled", "svbrdf_ggx", "smits", "microfacet", "lambert", "merl"])
@pytest.mark.parametrize("which", ["l", "v", "n", "x", "y"])
@pytest.mark.parametrize("value", NONFINITE)
def test_non_finite_input_validation_on(name, which, value):
    f = _brdfs()[name]
    with torchbrdf.validation(True), pytest.raises(ValueError, match=rf"^{which}: contains 1 non-finite"):
        f(*_bad_inputs(which, value))


@pytest.mark.parametrize("name", sorted(_FLOAT_PARAM))
@pytest.mark.parametrize("value", NONFINITE)
def test_non_finite_python_float_parameter_validation_on(name, value):
    param = _FLOAT_PARAM[name]
    l, v, n, x, y = _bad_inputs("l", 0.3)
    with torchbrdf.validation(True), pytest.raises(ValueError, match=rf"^{param}: expected a finite number"):
        _brdfs()[name](l, v, n, x, y, **{param: value})


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", ["principled", "svbrdf_ggx"])
def test_non_finite_input_validation_off(name, dtype):
    """The documented behaviour without validation: a NaN/inf direction gives 0, a NaN parameter NaN."""
    f = _brdfs()[name]
    assert not torchbrdf.validation_enabled()
    for which in ("l", "v", "n"):
        for value in NONFINITE:
            out = f(*_bad_inputs(which, value, dtype))
            if which == "n" and value == float("inf"):
                assert out.shape == (1, 3)  # undefined: NaN or a meaningless finite value
            else:
                assert (out == 0).all(), (which, value, out)
    l, v, n, x, y = _bad_inputs("l", 0.3, dtype)
    assert torch.isnan(f(l, v, n, x, y, roughness=float("nan"))).all()
    # The hidden NaN shows in the gradient (hence: validate while debugging NaN gradients).
    l = _bad_inputs("l", float("nan"), dtype)[0].requires_grad_(True)
    f(l, v, n).sum().backward()
    assert torch.isnan(l.grad).all()


def test_merl_non_finite_direction_without_validation_is_zero_not_index_error():
    l, v, n, x, y = _bad_inputs("l", float("nan"))
    out = _brdfs()["merl"](l, v, n)
    assert (out == 0).all()


def test_error_messages_excerpt_long_values():
    """A long list or array as an argument gives a short message, with an excerpt of the value."""
    n = torch.tensor([[0.0, 0.0, 1.0]])
    for bad in ([0.123456] * 4096, np.full(4096, 0.5), tuple(range(4096)), "x" * 5000):
        with pytest.raises(TypeError, match="roughness: expected a torch.Tensor or float") as e:
            principled(n, n, n, base_color=0.5, roughness=bad)
        assert len(str(e.value)) < 200, str(e.value)
    with pytest.raises(TypeError, match=r"list of length 4096 \[0\.123456, 0\.123456, .*\.\.\.\]"):
        principled(n, n, n, base_color=0.5, roughness=[0.123456] * 4096)
    with pytest.raises(TypeError) as e:
        torchbrdf.svbrdf_ggx(n, n, n, diffuse_albedo=[[1.0] * 3] * 4096, specular_albedo=0.04, roughness=0.5)
    assert len(str(e.value)) < 200, str(e.value)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=str)
def test_half_inputs_under_torch_func_transforms(dtype):
    """The saturating cast of half inputs works under torch.func.grad, jvp and vmap, and gives
    what autograd gives."""
    g = torch.Generator().manual_seed(5)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(64, 3)
    l = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) + torch.tensor([0.0, 0.0, 0.5]), dim=-1).to(dtype)
    r = torch.rand(64, 1, generator=g).to(dtype)

    def f(rough):
        return principled(l, n, n, base_color=0.5, roughness=rough)

    leaf = r.clone().requires_grad_()
    f(leaf).float().sum().backward()
    grad = torch.func.grad(lambda rough: f(rough).float().sum())(r)
    assert grad.dtype == dtype
    torch.testing.assert_close(grad, leaf.grad, rtol=0, atol=0)
    out, tangent = torch.func.jvp(f, (r,), (torch.ones_like(r),))
    assert tangent.dtype == dtype and bool(torch.isfinite(tangent).all())
    per_sample = torch.func.vmap(torch.func.grad(lambda rough: f(rough).float().sum()))(r[None].expand(2, -1, -1))
    torch.testing.assert_close(per_sample[1], leaf.grad, rtol=0, atol=0)
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():  # a dual input that also requires grad
        dual = f(fwAD.make_dual(r.clone().requires_grad_(), torch.ones_like(r)))
        torch.testing.assert_close(fwAD.unpack_dual(dual).tangent, tangent, rtol=0, atol=0)
