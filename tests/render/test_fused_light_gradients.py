"""Gradients w.r.t. the lights and the camera through the fused light loop (C kernels).

The reference is the eager per-light shader (``set_fast_path(False)``, float64): the fused
backward must give the same gradients w.r.t. point-light positions and intensities,
directional-light directions and irradiances and the camera position, per image when they are
batched, and the kernel that computes them must be the one that ran.
"""

import pytest
import torch

import torchbrdf
from torchbrdf import GBuffer, shade
from torchbrdf.kernels import fused, shade_ops
from torchbrdf.kernels.shade_ops import make_cfg, shade_lights_fwd
from tests.render.test_fused_shading import NAMES, TOL, dirs, points, rand, scene, uses_fused

pytestmark = pytest.mark.skipif(not fused.available(), reason="no C compiler for the fused kernels")


@pytest.fixture(autouse=True)
def _restore_fast_path():
    old = torchbrdf.fast_path_enabled()
    yield
    torchbrdf.set_fast_path(old)


@pytest.fixture
def uniform_kernels(monkeypatch):
    """The backward kernels built or fetched with the uniforms' gradient (proves the fused loop
    computed the light gradients instead of an eager fallback)."""
    calls = []
    real = shade_ops.load

    def spy(spec, backward):
        if backward:
            calls.append(spec.uniform_grad)
        return real(spec, backward)

    monkeypatch.setattr(shade_ops, "load", spy)
    return calls


def light_leaves(lights):
    """The lights' tensors, made leaves that require grad."""
    out = []
    for light in lights:
        for t in light._light_tensors():
            out.append(t.requires_grad_())
    return out


def compare(g, wrt, lights, tol, weights_seed=7, **kw):
    """Shade eagerly and fused; the gradients of a weighted sum w.r.t. ``wrt`` must agree."""
    res = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        img = shade(g, lights, **kw)
        wts = rand(*img.shape, seed=weights_seed, dtype=img.dtype)
        res[fast] = torch.autograd.grad((img * wts).sum(), wrt)
    for i, (a, b) in enumerate(zip(res[False], res[True])):
        err = ((a - b).abs().max() / a.abs().max().clamp_min(1e-30)).item()
        assert err <= tol, (i, err)
        assert a.abs().max() > 0
    return res


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_light_and_camera_gradients_match_eager(dtype, uniform_kernels):
    g, leaves = scene(dtype)
    cam = g.camera_position.clone().requires_grad_()
    g = GBuffer(g.position, g.normal, cam, g.material)
    lights = points(dtype, 2) + dirs(dtype, 2)
    wrt = [cam, *light_leaves(lights), leaves["roughness"]]
    assert uses_fused(g, lights)
    compare(g, wrt, lights, TOL[dtype])
    assert True in uniform_kernels


def test_light_gradient_summed_per_image(uniform_kernels):
    """Per-image lights and cameras (one uniform row per image, segments that chunks straddle):
    each image's light gets the sum over its own pixels only, and a light shared by the images
    the sum over all of them."""
    dtype = torch.float64
    g, _ = scene(dtype, b=2, params=("roughness", "metallic"))
    cam = torch.tensor([[0.2, -0.1, 3.0], [-0.3, 0.2, 2.5]], dtype=dtype, requires_grad=True)
    g = GBuffer(g.position, g.normal, cam, g.material)
    lights = points(dtype, 2, batch=2) + points(dtype, 1) + dirs(dtype, 1)
    wrt = [cam, *light_leaves(lights)]
    for kw in ({}, {"chunk": 37}):
        uniform_kernels.clear()
        res = compare(g, wrt, lights, TOL[dtype], **kw)
        assert True in uniform_kernels
    per_image = res[True][1]  # the first point light's position, (2, 3)
    assert per_image.shape == (2, 3) and (per_image[0] - per_image[1]).abs().max() > 1e-3


def test_only_the_lights_require_grad(uniform_kernels):
    """A fixed g-buffer and material (light calibration): the backward writes no per-pixel
    gradient, only the lights'."""
    dtype = torch.float64
    g, _ = scene(dtype)
    detached = {k: v.detach() for k, v in g.material.items()}
    g = GBuffer(g.position.detach(), g.normal.detach(), g.camera_position, detached)
    lights = points(dtype, 3)
    compare(g, light_leaves(lights), lights, TOL[dtype])
    assert uniform_kernels == [True]


def _op_case(dtype, P=9, split=4):
    """The operator's inputs: two segments with their own camera and lights (1 point, 1 sun)."""
    pos = rand(P, 3, seed=1, dtype=dtype) * 0.3
    up = torch.tensor([0, 0, 2.0], dtype=dtype)
    n = torch.nn.functional.normalize(rand(P, 3, seed=2, dtype=dtype) + up, dim=-1)
    bc = rand(P, 3, seed=3, dtype=dtype)
    r = rand(P, 1, seed=4, dtype=dtype, lo=0.2, hi=0.8)
    floats = [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 1.0]
    uniforms = torch.tensor(
        [[0.1, 0.0, 3.0, 1.0, 0.5, 2.0, 4.0, 3.0, 2.0, 0.3, -0.2, 1.0, 1.0, 0.8, 1.2],
         [-0.2, 0.3, 2.5, -1.0, 0.4, 1.5, 2.0, 5.0, 3.0, -0.1, 0.4, 1.0, 0.5, 1.0, 0.7]], dtype=dtype)
    names = [k for k in NAMES if k != "roughness"]
    cfg = make_cfg(["pos", "n", "base_color", "roughness"], names, ("diffuse", "specular"), False, False, True,
                   1, 1)
    return [pos, n, bc, r], floats, uniforms, [0, split, P], cfg


def test_gradcheck_uniforms_float64(uniform_kernels):
    tensors, floats, uniforms, seg, cfg = _op_case(torch.float64)
    uniforms.requires_grad_()
    bc = tensors[2].requires_grad_()

    def f(u, b):
        return shade_lights_fwd([tensors[0], tensors[1], b, tensors[3]], floats, u, seg, cfg)

    assert torch.autograd.gradcheck(f, (uniforms, bc), eps=1e-6, atol=1e-7, rtol=1e-6)
    assert True in uniform_kernels


def test_uniform_gradient_is_deterministic():
    """Per-block partial sums, added by torch: the same gradient, bit for bit, on every run and
    with any thread count."""
    dtype = torch.float32
    tensors, floats, uniforms, _, cfg = _op_case(dtype, P=5000)
    seg = [0, 2000, 5000]
    go = rand(5000, 3, seed=9, dtype=dtype)
    first = None
    threads = torch.get_num_threads()
    try:
        for nt in (1, 2, 1, 2):
            torch.set_num_threads(nt)
            u = uniforms.clone().requires_grad_()
            (gu,) = torch.autograd.grad(shade_lights_fwd(tensors, floats, u, seg, cfg), [u], go)
            if first is None:
                first = gu
            assert torch.equal(gu, first)
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_light_gradients(dtype, uniform_kernels):
    """Half-precision lights and g-buffer: shaded in float32, each light's gradient in its dtype."""
    g, _ = scene(dtype)
    lights = points(dtype, 2) + dirs(dtype, 1)
    wrt = light_leaves(lights)
    res = compare(g, wrt, lights, 1e-2)
    assert all(t.dtype == dtype for t in res[True]) and True in uniform_kernels


def test_opcheck_with_uniforms_requiring_grad():
    tensors, floats, uniforms, seg, cfg = _op_case(torch.float64)
    tensors = [t.requires_grad_() for t in tensors]
    torch.library.opcheck(
        torch.ops.torchbrdf.shade_lights_fwd.default,
        (tensors, floats, uniforms.requires_grad_(), seg, cfg),
        test_utils=("test_schema", "test_faketensor", "test_autograd_registration"),
    )


def test_compile_fullgraph_uniform_gradients():
    tensors, floats, uniforms, seg, cfg = _op_case(torch.float32, P=300, split=120)

    def loss(u):
        return (shade_lights_fwd(tensors, floats, u, seg, cfg) ** 2).sum()

    compiled = torch.compile(loss, fullgraph=True)
    u1, u2 = uniforms.clone().requires_grad_(), uniforms.clone().requires_grad_()
    a, b = loss(u1), compiled(u2)
    torch.testing.assert_close(b, a)
    torch.testing.assert_close(torch.autograd.grad(b, [u2])[0], torch.autograd.grad(a, [u1])[0])


def test_torch_func_grad_wrt_a_light(uniform_kernels):
    dtype = torch.float64
    g, _ = scene(dtype)
    g = GBuffer(g.position.detach(), g.normal.detach(), g.camera_position,
                {k: v.detach() for k, v in g.material.items()})
    q0 = torch.tensor([1.0, 0.5, 2.0], dtype=dtype)

    def loss(q):
        return shade(g, [torchbrdf.PointLight(q, torch.tensor([4.0, 3.0, 2.0], dtype=dtype))]).square().sum()

    res = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        res[fast] = torch.func.grad(loss)(q0)
    torch.testing.assert_close(res[True], res[False], rtol=1e-10, atol=0)
    assert uniform_kernels == [True]


def test_without_a_kernel_the_op_differentiates_the_formula(monkeypatch):
    """No kernel (no compiler): the operator's backward evaluates the formula's gradient itself,
    for the per-pixel tensors and the uniforms alike."""
    tensors, floats, uniforms, seg, cfg = _op_case(torch.float64)
    go = rand(9, 3, seed=9)
    ref = None
    for kernel in (True, False):
        if not kernel:
            monkeypatch.setattr(shade_ops, "load", lambda spec, backward: None)
        u, b = uniforms.clone().requires_grad_(), tensors[2].clone().requires_grad_()
        out = shade_lights_fwd([tensors[0], tensors[1], b, tensors[3]], floats, u, seg, cfg)
        got = torch.autograd.grad(out, [u, b], go)
        if ref is None:
            ref = got
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_second_order_through_a_light():
    """Differentiating the light gradient again: the formula's differentiable gradient, as eager."""
    dtype = torch.float64
    g, leaves = scene(dtype)
    lights = points(dtype, 2) + dirs(dtype, 1)
    q, irradiance = lights[0].position.requires_grad_(), lights[2].irradiance.requires_grad_()
    res = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        (gq,) = torch.autograd.grad(shade(g, lights).square().sum(), [q], create_graph=True)
        res[fast] = torch.autograd.grad(gq.sum(), [q, irradiance, leaves["roughness"]])
    for a, b in zip(res[False], res[True]):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)


def test_compiled_shade_light_gradients(uniform_kernels):
    """shade under torch.compile(fullgraph=True) with a light and the camera requiring grad."""
    dtype = torch.float32
    g, _ = scene(dtype, h=16, w=16)
    material = {k: v.detach() for k, v in g.material.items()}
    lights = points(dtype, 2)
    q = lights[1].position.requires_grad_()

    def image(cam):
        return shade(GBuffer(g.position.detach(), g.normal.detach(), cam, material), lights)

    torchbrdf.set_fast_path(True)
    compiled = torch.compile(image, fullgraph=True)
    grads = []
    for fn in (image, compiled):
        cam = g.camera_position.clone().requires_grad_()
        grads.append(torch.autograd.grad(fn(cam).square().sum(), [cam, q]))
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)
    assert True in uniform_kernels
