"""Fused shading (point and directional lights in one kernel) against the eager shader.

The eager shader (``set_fast_path(False)``) evaluates one checkpointed pass per light with the
eager principled BRDF; the fused path (``set_fast_path(True)``) runs the kernel generated from
the same formula. Values and gradients w.r.t. material maps, normals and positions must agree.
"""

import math

import pytest
import torch

import torchbrdf
from torchbrdf import DirectionalLight, GBuffer, PointLight, PrincipledBRDF, plan, shade
from torchbrdf.brdf import formula
from torchbrdf.kernels import fused

pytestmark = pytest.mark.skipif(not fused.available(), reason="no C compiler for the fused kernels")

NAMES = tuple(torchbrdf.PRINCIPLED_DEFAULTS)  # the ten scalar parameters
TOL = {torch.float32: 1e-4, torch.float64: 1e-10}


@pytest.fixture(autouse=True)
def _restore_fast_path():
    old = torchbrdf.fast_path_enabled()
    yield
    torchbrdf.set_fast_path(old)


def rand(*shape, seed=0, dtype=torch.float64, lo=0.0, hi=1.0):
    g = torch.Generator().manual_seed(seed)
    return (lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)).to(dtype)


def scene(dtype, b=1, h=12, w=10, params=("roughness", "metallic"), tangent=False, mask=None, seed=0):
    """A bumpy plane under a camera: leaves (requiring grad) and the g-buffer."""
    pos = torch.stack(
        torch.meshgrid(
            torch.linspace(-1, 1, h, dtype=torch.float64),
            torch.linspace(-1, 1, w, dtype=torch.float64),
            indexing="ij",
        )
    )
    pos = torch.cat([pos, 0.1 * rand(1, h, w, seed=seed + 1)]).unsqueeze(0).expand(b, 3, h, w)
    normal = torch.cat(
        [0.3 * rand(b, 2, h, w, seed=seed + 2, lo=-1), torch.ones(b, 1, h, w, dtype=torch.float64)], 1
    )
    leaves = {"position": pos.to(dtype).clone().requires_grad_(), "normal": normal.to(dtype).requires_grad_()}
    mat = {"base_color": rand(b, 3, h, w, seed=seed + 3, dtype=dtype).requires_grad_()}
    for i, k in enumerate(params):
        mat[k] = rand(b, 1, h, w, seed=seed + 10 + i, dtype=dtype, lo=0.05, hi=0.95).requires_grad_()
    leaves.update(mat)
    kw = {}
    if tangent:
        kw["tangent"] = torch.cat(
            [torch.ones(b, 1, h, w), 0.2 * rand(b, 2, h, w, seed=seed + 4, lo=-1)], 1
        ).to(dtype)
    if mask is not None:
        kw["mask"] = mask
    g = GBuffer(leaves["position"], leaves["normal"], torch.tensor([0.2, -0.1, 3.0], dtype=dtype), mat, **kw)
    return g, leaves


def points(dtype, k=3, batch=None):
    out = []
    for i in range(k):
        a = 2 * math.pi * i / k
        q = torch.tensor([1.5 * math.cos(a), 1.5 * math.sin(a), 2.0], dtype=dtype)
        inten = torch.tensor([4.0, 3.0 + i, 2.0], dtype=dtype)
        if batch:
            q = q + 0.3 * rand(batch, 3, seed=20 + i, dtype=dtype)
            inten = inten * (1 + rand(batch, 3, seed=30 + i, dtype=dtype))
        out.append(PointLight(q, inten))
    return out


def dirs(dtype, k=2):
    return [
        DirectionalLight(
            torch.tensor([0.3 * (i + 1), -0.2, 1.0], dtype=dtype),
            torch.tensor([1.0, 0.5, 0.25 + i], dtype=dtype),
        )
        for i in range(k)
    ]


def both(g, leaves, lights, brdf=None, tol=None, weights_seed=7):
    """Shade eagerly and fused; compare the images and the gradients of a weighted sum."""
    res = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        img = shade(g, lights, brdf)
        wts = rand(*img.shape, seed=weights_seed, dtype=img.dtype)
        grads = torch.autograd.grad(
            (img * wts).sum(), list(leaves.values()), retain_graph=True, allow_unused=True
        )
        res[fast] = (img.detach(), grads)
    tol = tol or TOL[g.dtype]
    (e_img, e_g), (f_img, f_g) = res[False], res[True]
    scale = e_img.abs().max().clamp_min(1e-30)
    assert ((e_img - f_img).abs().max() / scale).item() <= tol
    for name, a, b in zip(leaves, e_g, f_g):
        if a is None:
            assert b is None or not b.any(), name
            continue
        err = ((a - b).abs().max() / a.abs().max().clamp_min(1e-30)).item()
        assert err <= tol, (name, err)
    return res


def uses_fused(g, lights, brdf=None) -> bool:
    torchbrdf.set_fast_path(True)
    return any("fused kernel" in note for note in plan(g, lights, brdf).notes)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind", ["point", "directional", "both"])
def test_fused_matches_eager(dtype, kind):
    g, leaves = scene(dtype)
    lights = {"point": points(dtype), "directional": dirs(dtype), "both": points(dtype, 2) + dirs(dtype, 1)}[
        kind
    ]
    assert uses_fused(g, lights)
    both(g, leaves, lights)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batched_lights_and_camera(dtype):
    g, leaves = scene(dtype, b=2)
    g = GBuffer(
        g.position, g.normal, torch.tensor([[0.2, -0.1, 3.0], [-0.3, 0.2, 2.5]], dtype=dtype), g.material
    )
    lights = points(dtype, 2, batch=2) + points(dtype, 1) + dirs(dtype, 1)
    assert uses_fused(g, lights)
    both(g, leaves, lights)


@pytest.mark.parametrize("soft", [False, True])
def test_masks(soft):
    dtype = torch.float64
    m = rand(1, 1, 12, 10, seed=5) > 0.4
    mask = m.to(dtype) * rand(1, 1, 12, 10, seed=6) if soft else m
    g, leaves = scene(dtype, mask=mask)
    res = both(g, leaves, points(dtype))
    img, grads = res[True]
    assert (img * (~m)).abs().max() == 0
    assert grads[list(leaves).index("base_color")].mul(~m).abs().max() == 0


def test_zero_pixels():
    dtype = torch.float32
    g, leaves = scene(dtype, mask=torch.zeros(1, 1, 12, 10, dtype=torch.bool))
    res = both(g, leaves, points(dtype))
    assert res[True][0].abs().max() == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["metal", "dielectric_const", "all_maps", "clearcoat_sheen", "lobes"])
def test_pruned_lobe_combinations(dtype, case):
    brdf = None
    if case == "metal":  # metallic = 1 (Python): no diffuse, subsurface or sheen
        g, leaves = scene(dtype, params=("roughness",))
        g = GBuffer(g.position, g.normal, g.camera_position, {**g.material, "metallic": 1.0})
    elif case == "dielectric_const":  # constants as runtime floats, tinted specular
        g, leaves = scene(dtype, params=("roughness",))
        g = GBuffer(
            g.position,
            g.normal,
            g.camera_position,
            {**g.material, "specular_tint": 0.5, "subsurface": 0.3, "metallic": 0.0},
        )
    elif case == "all_maps":  # every lobe and tint from maps, anisotropy with a frame from the normal
        g, leaves = scene(dtype, params=NAMES)
    elif case == "clearcoat_sheen":
        g, leaves = scene(dtype, params=("roughness", "clearcoat", "clearcoat_gloss", "sheen"))
        g = GBuffer(g.position, g.normal, g.camera_position, {**g.material, "sheen_tint": 0.7})
    else:
        g, leaves = scene(dtype, params=("roughness", "metallic", "clearcoat"))
        brdf = PrincipledBRDF(lobes=("diffuse", "clearcoat"))
    lights = points(dtype, 2) + dirs(dtype, 1)
    assert uses_fused(g, lights, brdf)
    both(g, leaves, lights, brdf)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_anisotropy_with_tangents(dtype):
    g, leaves = scene(dtype, params=("roughness", "anisotropic", "metallic"), tangent=True)
    both(g, leaves, points(dtype) + dirs(dtype, 1))


def test_light_gradients_stay_fused():
    """Gradients w.r.t. a light keep the fused light loop (its backward differentiates the
    uniforms too; tests/render/test_fused_light_gradients.py compares them with eager)."""
    dtype = torch.float64
    g, leaves = scene(dtype)
    inten = torch.tensor([4.0, 3.0, 2.0], dtype=dtype, requires_grad=True)
    lights = [PointLight(torch.tensor([0.5, 0.2, 2.0], dtype=dtype), inten)]
    assert uses_fused(g, lights)
    torchbrdf.set_fast_path(True)
    img = shade(g, lights)
    (gi,) = torch.autograd.grad(img.sum(), [inten])
    assert torch.isfinite(gi).all() and gi.abs().sum() > 0


def test_other_brdfs_stay_eager():
    dtype = torch.float64
    g, _ = scene(dtype)
    assert not uses_fused(g, points(dtype), torchbrdf.lambert)


def ggx_scene(dtype, uniform_specular=False):
    """``scene``'s geometry with SVBRDF GGX maps (a 0-d specular albedo when ``uniform_specular``)."""
    g, leaves = scene(dtype, params=())
    b, _, h, w = g.position.shape
    specular = (torch.tensor(0.04, dtype=dtype) if uniform_specular
                else rand(b, 3, h, w, seed=41, dtype=dtype, lo=0.02, hi=0.9))
    mat = {"diffuse_albedo": rand(b, 3, h, w, seed=40, dtype=dtype).requires_grad_(),
           "specular_albedo": specular.requires_grad_(),
           "roughness": rand(b, 1, h, w, seed=42, dtype=dtype, lo=0.05, hi=0.95).requires_grad_()}
    leaves = {"position": leaves["position"], "normal": leaves["normal"], **mat}
    return GBuffer(g.position, g.normal, g.camera_position, mat), leaves


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("floor", [None, ("roughness_floor", 0.3), ("alpha_floor", 0.2)])
def test_svbrdf_ggx_takes_the_light_loop(dtype, floor):
    """The SVBRDF GGX (function or module, each floor) shades through the light-loop kernel, as its per-light passes."""
    from torchbrdf.brdf.svbrdf_ggx import SVBRDFGGX, svbrdf_ggx

    brdf = svbrdf_ggx if floor is None else SVBRDFGGX(**dict([floor]))
    for uniform in (False, True):
        g, leaves = ggx_scene(dtype, uniform_specular=uniform)
        lights = points(dtype, 2) + dirs(dtype, 1)
        assert uses_fused(g, lights, brdf)
        both(g, leaves, lights, brdf)


def test_svbrdf_ggx_subclasses_and_foreign_inputs_take_per_light_passes():
    from torchbrdf.brdf.svbrdf_ggx import SVBRDFGGX, svbrdf_ggx

    class Tinted(SVBRDFGGX):
        def forward(self, *args, **kw):
            return 2.0 * super().forward(*args, **kw)

    g, _ = ggx_scene(torch.float64)
    lights = points(torch.float64, 2)
    assert not uses_fused(g, lights, Tinted())
    torchbrdf.set_fast_path(True)
    torch.testing.assert_close(shade(g, lights, Tinted()), 2.0 * shade(g, lights, svbrdf_ggx))
    g.material["alpha_floor"] = 0.3  # a floor in the material: the per-light passes apply it
    assert not uses_fused(g, lights, svbrdf_ggx)
    torch.testing.assert_close(shade(g, lights, svbrdf_ggx), shade(g, lights, SVBRDFGGX(alpha_floor=0.3)))


def test_svbrdf_ggx_modules_changed_by_the_user_take_per_light_passes():
    """A hook, an instance forward, or floors set afterwards: what the call does, the image shows."""
    from torchbrdf.brdf.svbrdf_ggx import SVBRDFGGX

    g, _ = ggx_scene(torch.float64)
    lights = points(torch.float64, 2)
    torchbrdf.set_fast_path(True)
    plain = shade(g, lights, SVBRDFGGX()).detach()
    hooked = SVBRDFGGX()
    hooked.register_forward_hook(lambda module, args, out: 2.0 * out)
    assert not uses_fused(g, lights, hooked)
    torch.testing.assert_close(shade(g, lights, hooked).detach(), 2.0 * plain)
    replaced = SVBRDFGGX()
    replaced.forward = lambda *a, **k: 3.0 * SVBRDFGGX.forward(replaced, *a, **k)
    assert not uses_fused(g, lights, replaced)
    torch.testing.assert_close(shade(g, lights, replaced).detach(), 3.0 * plain)
    broken = SVBRDFGGX()
    broken.alpha_floor = 0.0
    with pytest.raises(ValueError, match="alpha_floor"):
        shade(g, lights, broken)


def test_a_grey_albedo_map_is_refused_at_every_size():
    """svbrdf_ggx takes (3,) albedos or a number; a (B, 1, H, W) map is its error, fused or not."""
    from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx

    g, _ = ggx_scene(torch.float64)
    g.material["diffuse_albedo"] = g.material["diffuse_albedo"][:, :1].detach()
    lights = points(torch.float64, 2)
    assert not uses_fused(g, lights, svbrdf_ggx)
    with pytest.raises(ValueError, match="diffuse_albedo"):
        shade(g, lights, svbrdf_ggx)


def test_one_definition_changes_both_paths(monkeypatch):
    """Doubling the point-light term in brdf/formula.py doubles the eager and the fused image."""
    dtype = torch.float64
    g, _ = scene(dtype, params=("roughness",))
    lights = points(dtype, 2)
    base = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        base[fast] = shade(g, lights).detach()
    original = formula.point_light

    def doubled(ops, *args):
        return original(ops, *args) * 2.0

    monkeypatch.setattr(formula, "point_light", doubled)
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        torch.testing.assert_close(shade(g, lights).detach(), 2.0 * base[fast], rtol=1e-12, atol=0)


def test_custom_op_registration():
    """The fused op has a fake implementation and autograd registration (what torch.compile uses)."""
    from torchbrdf.kernels.shade_ops import make_cfg

    dtype = torch.float64
    P = 7
    tensors = [
        rand(P, 3, seed=1, dtype=dtype) * 0.1,
        torch.nn.functional.normalize(
            rand(P, 3, seed=2, dtype=dtype) + torch.tensor([0, 0, 2.0], dtype=dtype), dim=-1
        ),
        rand(P, 3, seed=3, dtype=dtype),
        rand(P, 1, seed=4, dtype=dtype, lo=0.2, hi=0.8),
    ]
    tensors = [t.requires_grad_() for t in tensors]
    floats = [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 1.0]
    names = [k for k in NAMES if k != "roughness"]
    uniforms = torch.tensor([[0.0, 0.0, 3.0, 1.0, 0.5, 2.0, 4.0, 4.0, 4.0]], dtype=dtype)
    cfg = make_cfg(
        ["pos", "n", "base_color", "roughness"], names, ("diffuse", "specular"), False, False, True, 1, 0
    )
    torch.library.opcheck(
        torch.ops.torchbrdf.shade_lights_fwd.default,
        (tensors, floats, uniforms, [0, P], cfg),
        test_utils=("test_schema", "test_faketensor", "test_autograd_registration"),
    )


def test_compile_fullgraph_sees_the_op():
    """torch.compile(fullgraph=True) traces the fused op (fake impl + autograd) and matches eager."""
    from torchbrdf.kernels.shade_ops import make_cfg, shade_lights_fwd

    P = 300
    pos = rand(P, 3, seed=1, dtype=torch.float32) * 0.1
    n = torch.nn.functional.normalize(
        rand(P, 3, seed=2, dtype=torch.float32) + torch.tensor([0, 0, 2.0]), dim=-1
    )
    bc = rand(P, 3, seed=3, dtype=torch.float32).requires_grad_()
    r = rand(P, 1, seed=4, dtype=torch.float32, lo=0.2, hi=0.8).requires_grad_()
    floats = [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 1.0]
    names = [k for k in NAMES if k != "roughness"]
    uniforms = torch.tensor([[0.0, 0.0, 3.0, 1.0, 0.5, 2.0, 4.0, 4.0, 4.0]])
    cfg = make_cfg(
        ["pos", "n", "base_color", "roughness"], names, ("diffuse", "specular"), False, False, True, 1, 0
    )

    def loss(bc, r):
        return (shade_lights_fwd([pos, n, bc, r], floats, uniforms, [0, P], cfg) ** 2).sum()

    compiled = torch.compile(loss, fullgraph=True)
    a, b = loss(bc, r), compiled(bc, r)
    torch.testing.assert_close(b, a)
    for x, y in zip(torch.autograd.grad(a, [bc, r]), torch.autograd.grad(b, [bc, r])):
        torch.testing.assert_close(y, x)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chunks_across_images_and_no_pruning(dtype):
    """Pixel chunks that straddle images with per-image lights, and prune=False, match eager."""
    g, leaves = scene(dtype, b=2, params=("roughness", "metallic", "clearcoat"))
    lights = points(dtype, 2, batch=2) + dirs(dtype, 1)
    for kw in ({"chunk": 37}, {"prune": False}):
        res = {}
        for fast in (False, True):
            torchbrdf.set_fast_path(fast)
            img = shade(g, lights, **kw)
            grads = torch.autograd.grad(img.square().sum(), list(leaves.values()), retain_graph=True)
            res[fast] = (img.detach(), grads)
        for a, b in zip((res[False][0], *res[False][1]), (res[True][0], *res[True][1])):
            assert ((a - b).abs().max() / a.abs().max()).item() <= TOL[dtype]


def test_shade_under_torch_compile():
    """``shade`` compiled (graph breaks allowed) runs the fused op with its fake implementation
    (contiguous gradients, as the kernels return them) and matches eager, values and gradients."""
    dtype = torch.float32
    g, leaves = scene(dtype, h=16, w=16)
    lights = points(dtype, 2)
    torchbrdf.set_fast_path(True)
    ref = shade(g, lights)
    (gref,) = torch.autograd.grad(ref.sum(), [leaves["base_color"]], retain_graph=True)
    compiled = torch.compile(lambda g: shade(g, lights))
    for _ in range(2):
        out = compiled(g)
        (gout,) = torch.autograd.grad(out.sum(), [leaves["base_color"]], retain_graph=True)
        torch.testing.assert_close(out, ref)
        torch.testing.assert_close(gout, gref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradient_of_a_plain_sum(dtype):
    """The output gradient of ``img.sum()`` is one value for all pixels (read in place, mode 'b0')."""
    g, leaves = scene(dtype, b=2)
    lights = points(dtype, 2, batch=2) + dirs(dtype, 1)
    res = {}
    for fast in (False, True):
        torchbrdf.set_fast_path(fast)
        img = shade(g, lights)
        res[fast] = torch.autograd.grad(img.sum(), list(leaves.values()), retain_graph=True)
    for a, b in zip(res[False], res[True]):
        assert ((a - b).abs().max() / a.abs().max()).item() <= TOL[dtype]


def _count_shade_kernels(monkeypatch):
    from torchbrdf.kernels import shade_ops

    calls = {"fwd": 0, "bwd": 0}
    real_fwd, real_bwd = shade_ops._run_fwd, shade_ops._run_bwd

    def fwd(*a, **k):
        calls["fwd"] += 1
        return real_fwd(*a, **k)

    def bwd(*a, **k):
        calls["bwd"] += 1
        return real_bwd(*a, **k)

    monkeypatch.setattr(shade_ops, "_run_fwd", fwd)
    monkeypatch.setattr(shade_ops, "_run_bwd", bwd)
    return calls


def test_torch_func_grad_and_vjp_run_the_fused_light_loop(monkeypatch):
    """torch.func.grad / vjp over shade run the light-loop kernels forward and backward, and
    give autograd's gradients; a second level of differentiation (grad of grad, or autograd
    around torch.func.grad) takes the formula's differentiable gradient and matches eager."""
    dtype = torch.float64
    g, leaves = scene(dtype)
    lights = points(dtype) + dirs(dtype)
    rough = leaves["roughness"].detach()
    material = {k: v.detach() for k, v in g.material.items()}

    def image(r):
        gb = GBuffer(g.position.detach(), g.normal.detach(), g.camera_position, {**material, "roughness": r})
        return shade(gb, lights)

    torchbrdf.set_fast_path(True)
    leaf = rough.clone().requires_grad_()
    image(leaf).square().sum().backward()
    calls = _count_shade_kernels(monkeypatch)
    grad = torch.func.grad(lambda r: image(r).square().sum())(rough)
    assert calls == {"fwd": 1, "bwd": 1}
    torch.testing.assert_close(grad, leaf.grad, rtol=1e-12, atol=0)
    _, pullback = torch.func.vjp(image, rough)
    torch.testing.assert_close(pullback(2 * image(rough))[0], leaf.grad, rtol=1e-12, atol=0)

    def second(r):  # d/dr of sum(d/dr sum(image²)): differentiates the backward again
        return torch.func.grad(lambda s: torch.func.grad(lambda t: image(t).square().sum())(s).sum())(r)

    outer = rough.clone().requires_grad_()
    torch.func.grad(lambda r: image(r).square().sum())(outer).sum().backward()
    fused_second = second(rough)
    torchbrdf.set_fast_path(False)
    eager_second = second(rough)
    torch.testing.assert_close(fused_second, eager_second, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(outer.grad, eager_second, rtol=1e-9, atol=1e-12)
    assert float(eager_second.abs().sum()) > 0
