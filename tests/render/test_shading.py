"""shade / plan / Shader / GBuffer / lights / analytic g-buffers."""

import math

import pytest
import torch

import torchbrdf
from torchbrdf._math import safe_normalize
from torchbrdf.brdf.lambert import LambertBRDF, lambert
from torchbrdf.brdf.principled import PrincipledBRDF, principled
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.geometry import pinhole_rays, plane_gbuffer, sphere_gbuffer
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, PointLight
from torchbrdf.render.shading import Shader, ShadingPlan, plan, shade

D = torch.float64


def rand(*shape, seed=0, dtype=D, lo=0.0, hi=1.0):
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64).to(dtype)


def full_material(b, h, w, dtype=D, seed=0):
    """Every principled parameter as a random map."""
    names = list(torchbrdf.PRINCIPLED_DEFAULTS)  # the ten scalar parameters
    mat = {"base_color": rand(b, 3, h, w, seed=seed, dtype=dtype)}
    for i, k in enumerate(names):
        mat[k] = rand(b, 1, h, w, seed=seed + i + 1, dtype=dtype, lo=0.05, hi=0.95)
    return mat


def direct_reference(g: GBuffer, lights, brdf=principled):
    """Per-pixel evaluation with the contract's formulas, written independently of shade()."""
    b, h, w = g.shape
    out = torch.zeros(b, h, w, 3, dtype=g.dtype)
    cam = g.camera_position.expand(b, 3) if g.camera_position.dim() == 2 else g.camera_position.expand(b, 3)
    for bi in range(b):
        p = g.position[bi].permute(1, 2, 0)
        n = safe_normalize(g.normal[bi].permute(1, 2, 0))
        v = safe_normalize(cam[bi] - p)
        x = y = None
        if g.tangent is not None and "anisotropic" in g.material:
            t = g.tangent[bi].permute(1, 2, 0)
            x = safe_normalize(t - (t * n).sum(-1, keepdim=True) * n)
            y = torch.linalg.cross(n, x, dim=-1)
        mat = {
            k: (m[min(bi, m.shape[0] - 1)].permute(1, 2, 0) if torch.is_tensor(m) and m.dim() == 4 else m)
            for k, m in g.material.items()
        }
        for light in lights:
            if isinstance(light, PointLight):
                q = light.position if light.position.dim() == 1 else light.position[bi]
                inten = light.intensity if light.intensity.dim() == 1 else light.intensity[bi]
                d = q.to(g.dtype) - p
                dist2 = (d * d).sum(-1, keepdim=True)
                l = d / dist2.sqrt()
                cos = (n * l).sum(-1, keepdim=True).clamp(min=0)
                out[bi] += brdf(l, v, n, x, y, **mat) * inten.to(g.dtype) * cos / dist2
            else:
                dd = light.direction if light.direction.dim() == 1 else light.direction[bi]
                e = light.irradiance if light.irradiance.dim() == 1 else light.irradiance[bi]
                l = safe_normalize(dd.to(g.dtype)).expand_as(n)
                cos = (n * l).sum(-1, keepdim=True).clamp(min=0)
                out[bi] += brdf(l, v, n, x, y, **mat) * e.to(g.dtype) * cos
    img = out.permute(0, 3, 1, 2)
    if g.mask is not None:
        img = img * g.mask
    return img


LIGHTS = [
    PointLight([1.0, 2.0, 3.0], [5.0, 6.0, 7.0]),
    PointLight([-2.0, 0.5, 1.5], 3.0),
    DirectionalLight([0.3, -0.2, 1.0], [1.0, 0.5, 0.25]),
]


# ------------------------------------------------------------------ agreement with direct evaluation


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_sphere_point_and_directional_equal_direct_evaluation(dtype, rtol):
    g = sphere_gbuffer(10, 10, material=full_material(1, 10, 10, dtype), dtype=dtype)
    img = shade(g, LIGHTS)
    ref = direct_reference(g, LIGHTS)
    assert img.dtype == dtype and img.shape == (1, 3, 10, 10)
    torch.testing.assert_close(img, ref, rtol=rtol, atol=rtol * float(ref.abs().max()))


def test_lambert_and_module_brdfs_equal_direct_evaluation():
    g = sphere_gbuffer(8, 8, dtype=D, material={"base_color": rand(1, 3, 8, 8), "roughness": 0.3})
    for brdf, ref_brdf in ((lambert, lambert), (LambertBRDF(), lambert), (PrincipledBRDF(), principled)):
        torch.testing.assert_close(
            shade(g, LIGHTS, brdf), direct_reference(g, LIGHTS, ref_brdf), rtol=1e-12, atol=1e-12
        )


def test_plane_with_normal_map_follows_capture_convention():
    """Contract §3: pixel (i, j) sees p = (-1 + (j+.5) 2/W, 1 - (i+.5) 2/H, 0).

    The frame follows by Gram–Schmidt from +X.
    """
    nm = torch.cat((rand(1, 2, 6, 8, seed=3, lo=-0.4, hi=0.4), torch.ones(1, 1, 6, 8, dtype=D)), 1)
    mat = {
        "base_color": rand(1, 3, 6, 8, seed=4),
        "roughness": rand(1, 1, 6, 8, seed=5, lo=0.2, hi=0.8),
        "anisotropic": rand(1, 1, 6, 8, seed=6),
    }
    g = plane_gbuffer(6, 8, normal_map=nm, material=mat, camera_position=(0.2, -0.1, 3.0))
    i, j = 2, 5
    assert torch.allclose(
        g.position[0, :, i, j], torch.tensor([-1 + (j + 0.5) * 2 / 8, 1 - (i + 0.5) * 2 / 6, 0.0], dtype=D)
    )
    light = PointLight([0.5, -0.3, 2.0], [10.0, 10.0, 10.0])
    img = shade(g, light)
    p = g.position[0, :, i, j]
    n = safe_normalize(nm[0, :, i, j])
    x = safe_normalize(torch.tensor([1.0, 0, 0], dtype=D) - n[0] * n)
    y = torch.linalg.cross(n, x, dim=-1)
    v = safe_normalize(torch.tensor([0.2, -0.1, 3.0], dtype=D) - p)
    d = torch.tensor([0.5, -0.3, 2.0], dtype=D) - p
    l = d / d.norm()
    f = principled(l, v, n, x, y, **{k: m[0, :, i, j] for k, m in mat.items()})
    expect = f * 10.0 * torch.clamp(n @ l, min=0) / (d @ d)
    torch.testing.assert_close(img[0, :, i, j], expect, rtol=1e-12, atol=0)


def test_lights_add_and_single_light_accepted():
    g = sphere_gbuffer(6, 6, dtype=D)
    total = shade(g, LIGHTS)
    parts = sum(shade(g, light) for light in LIGHTS)
    torch.testing.assert_close(total, parts, rtol=1e-12, atol=1e-14)
    assert torch.equal(shade(g, []), torch.zeros_like(total))


def test_per_batch_light_and_camera_parameters():
    b = 2
    g = sphere_gbuffer(
        6, 6, batch_size=b, dtype=D, material={"base_color": rand(b, 3, 6, 6), "roughness": 0.4}
    )
    g = g.replace(camera_position=torch.tensor([[0.0, 0.0, 4.0], [0.5, 0.2, 3.5]], dtype=D))
    lights = [
        PointLight(
            torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 2.0]], dtype=D),
            torch.tensor([[5.0, 5, 5], [1.0, 2, 3]], dtype=D),
        ),
        DirectionalLight(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]], dtype=D), [1.0, 1.0, 1.0]),
    ]
    img = shade(g, lights)
    torch.testing.assert_close(img, direct_reference(g, lights), rtol=1e-12, atol=1e-14)
    for bi in range(b):
        gi = GBuffer(
            g.position[bi : bi + 1],
            g.normal[bi : bi + 1],
            g.camera_position[bi],
            {k: m[bi : bi + 1] if torch.is_tensor(m) else m for k, m in g.material.items()},
            g.tangent[bi : bi + 1],
            g.mask[bi : bi + 1],
        )
        li = [
            PointLight(lights[0].position[bi], lights[0].intensity[bi]),
            DirectionalLight(lights[1].direction[bi], lights[1].irradiance),
        ]
        torch.testing.assert_close(img[bi : bi + 1], shade(gi, li), rtol=1e-12, atol=1e-14)


# ------------------------------------------------------------------ pruning


def pruning_scene(dtype):
    b, h, w = 2, 8, 8
    z = lambda: torch.zeros(b, 1, h, w, dtype=dtype)  # noqa: E731
    mat = {
        "base_color": rand(b, 3, h, w, dtype=dtype),
        "roughness": rand(b, 1, h, w, seed=1, dtype=dtype, lo=0.2, hi=0.9),
        "metallic": torch.full((b, 1, h, w), 0.25, dtype=dtype),
        "sheen": z(),
        "clearcoat": z(),
        "subsurface": z(),
        "anisotropic": z(),
        "specular_tint": z(),
    }
    g = sphere_gbuffer(h, w, batch_size=b, dtype=dtype, material=mat)
    normal = g.normal.clone()
    normal[:, :, 3, 3] = -normal[:, :, 3, 3]  # a back-facing pixel inside the mask
    mask = g.mask.clone()
    mask[1, :, 4, 4] = False
    return g.replace(normal=normal, mask=mask)


@pytest.mark.parametrize("strategy", ["mc", "split_sum"])
def test_pruned_equals_full_evaluation(strategy):
    g = pruning_scene(torch.float32)
    gt = g.replace(tangent=None)  # keep the MC proposal's frame identical in both modes
    lights = LIGHTS + [EnvironmentLight(rand(3, 8, 16, seed=9, dtype=torch.float32) * 2)]
    for gb in (g, gt):
        pruned = shade(gb, lights, env_strategy=strategy, env_samples=16)
        full = shade(gb, lights, env_strategy=strategy, env_samples=16, prune=False)
        torch.testing.assert_close(pruned, full, rtol=1e-6, atol=1e-6 * float(full.abs().max()))
    p = plan(g, lights, env_strategy=strategy)
    assert p.lobes == ("diffuse", "specular")
    assert set(p.pruned_lobes) == {"subsurface", "sheen", "clearcoat"}
    assert "constant 0.25" in p.material["metallic"] and "Python 0.0" in p.material["sheen"]
    assert p.frames.startswith("none")
    assert p.pixels_backfacing == 2 and p.pixels_masked == int((~g.mask).sum())
    full_plan = plan(g, lights, prune=False, env_strategy=strategy)
    assert full_plan.pixels_shaded == 2 * 8 * 8 and full_plan.frames.startswith("Gram")


def test_plan_is_readable():
    g = pruning_scene(torch.float32)
    lights = LIGHTS + [EnvironmentLight(torch.ones(3, 4, 8))]
    text = str(plan(g, lights, env_samples=32))
    for needle in (
        "lobes    : diffuse, specular",
        "pruned   : subsurface, sheen, clearcoat",
        "point light",
        "directional light",
        "environment",
        "BRDF evaluations",
        "constant map: no map sampling",
    ):
        assert needle in text, (needle, text)
    p = plan(g, lights, env_samples=32)
    assert isinstance(p, ShadingPlan)
    assert p.brdf_evaluations == p.pixels_shaded * (3 + 32)
    text = str(plan(g, [EnvironmentLight(rand(3, 4, 8))], env_samples=32))
    assert "16 BRDF-sampled" in text and "16 map-sampled" in text
    assert "GGX visible normals" in text
    text = str(plan(g, LIGHTS, lambert))
    assert "lobes    : diffuse" in text


def test_anisotropy_builds_frames_only_when_needed():
    g = sphere_gbuffer(6, 6, dtype=D, material={"base_color": rand(1, 3, 6, 6), "anisotropic": 0.5})
    assert plan(g, LIGHTS).frames.startswith("Gram")
    assert plan(g.replace(tangent=None), LIGHTS).frames.startswith("built from the normal")
    assert plan(g.replace(material={"base_color": 1.0}), LIGHTS).frames.startswith("none")
    torch.testing.assert_close(shade(g, LIGHTS), direct_reference(g, LIGHTS), rtol=1e-12, atol=1e-14)


def test_environment_only_when_present():
    g = sphere_gbuffer(4, 4)
    assert plan(g, LIGHTS).environment is None
    assert plan(g, [EnvironmentLight(torch.ones(3, 4, 8))], env_strategy="split_sum").environment.startswith(
        "split sum"
    )


# ------------------------------------------------------------------ masks, back faces, gradients


def test_masked_and_backfacing_pixels_are_zero_with_finite_gradients():
    g = pruning_scene(D)
    mat = {k: (m.clone().requires_grad_() if torch.is_tensor(m) else m) for k, m in g.material.items()}
    normal = g.normal.clone().requires_grad_()
    pos = g.position.clone().requires_grad_()
    env = rand(3, 4, 8, seed=3).requires_grad_()
    gb = g.replace(material=mat, normal=normal, position=pos)
    for strategy in ("mc", "split_sum"):
        img = shade(gb, LIGHTS + [EnvironmentLight(env)], env_strategy=strategy, env_samples=8)
        dead = ~g.mask.expand_as(img)
        dead[:, :, 3, 3] = True
        assert bool((img[dead] == 0).all())
        assert bool((img[~dead] > 0).all())
        img.sum().backward()
        for t in [normal, pos, env] + [m for m in mat.values() if torch.is_tensor(m)]:
            assert t.grad is not None and bool(torch.isfinite(t.grad).all())
        for t in (normal, pos, mat["base_color"], mat["roughness"]):
            assert bool((t.grad[:, :, 3, 3] == 0).all())
            assert bool((t.grad * (~g.mask)).abs().sum() == 0)
        for t in [normal, pos, env] + [m for m in mat.values() if torch.is_tensor(m)]:
            t.grad = None


def test_fully_masked_image_is_zero_and_differentiable():
    g = sphere_gbuffer(4, 4, dtype=D)
    pos = g.position.clone().requires_grad_()
    img = shade(g.replace(position=pos, mask=torch.zeros_like(g.mask)), LIGHTS)
    assert torch.equal(img, torch.zeros_like(img))
    img.sum().backward()
    assert torch.equal(pos.grad, torch.zeros_like(pos))


def test_float_mask_weights_coverage():
    g = sphere_gbuffer(6, 6, dtype=D)
    soft = g.mask.to(D) * 0.5
    soft.requires_grad_()
    img = shade(g.replace(mask=soft), LIGHTS)
    torch.testing.assert_close(img, 0.5 * shade(g, LIGHTS))
    img.sum().backward()
    assert bool((soft.grad[g.mask] > 0).all())


def test_gradcheck_through_shade():
    h = w = 3
    base = rand(1, 3, h, w, seed=1, lo=0.2, hi=0.9)
    rough = rand(1, 1, h, w, seed=2, lo=0.3, hi=0.8)
    metal = rand(1, 1, h, w, seed=3, lo=0.1, hi=0.9)
    nm = torch.cat((rand(1, 2, h, w, seed=4, lo=-0.3, hi=0.3), torch.ones(1, 1, h, w, dtype=D)), 1)
    g0 = plane_gbuffer(h, w, normal_map=nm)
    pos0, normal0 = g0.position.clone(), g0.normal.clone()
    q = torch.tensor([0.4, -0.3, 1.5], dtype=D)
    inten = torch.tensor([3.0, 2.0, 1.0], dtype=D)
    env = rand(3, 4, 8, seed=5, lo=0.2, hi=2.0)
    inputs = [t.clone().requires_grad_() for t in (pos0, normal0, base, rough, metal, q, inten, env)]

    def f(pos, normal, base, rough, metal, q, inten, env):
        g = GBuffer(
            pos,
            normal,
            torch.tensor([0.1, 0.2, 2.5], dtype=D),
            {"base_color": base, "roughness": rough, "metallic": metal},
        )
        lights = [
            PointLight(q, inten),
            DirectionalLight([0.2, 0.1, 1.0], [1.0, 1.0, 1.0]),
            EnvironmentLight(env),
        ]
        return shade(g, lights, env_strategy="split_sum")

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gradcheck_point_and_directional_full():
    h = w = 2
    nm = torch.cat((rand(1, 2, h, w, seed=4, lo=-0.3, hi=0.3), torch.ones(1, 1, h, w, dtype=D)), 1)
    g0 = plane_gbuffer(h, w, normal_map=nm)
    inputs = [
        t.clone().requires_grad_()
        for t in (
            g0.position,
            g0.normal,
            rand(1, 3, h, w, seed=1, lo=0.2, hi=0.9),
            rand(1, 1, h, w, seed=2, lo=0.3, hi=0.8),
            rand(1, 1, h, w, seed=3),
            torch.tensor([0.4, -0.3, 1.5], dtype=D),
            torch.tensor([3.0, 2.0, 1.0], dtype=D),
            torch.tensor([0.2, 0.1, 1.0], dtype=D),
            torch.tensor([0.1, 0.2, 2.5], dtype=D),
        )
    ]

    def f(pos, normal, base, rough, aniso, q, inten, d, cam):
        g = GBuffer(
            pos,
            normal,
            cam,
            {"base_color": base, "roughness": rough, "anisotropic": aniso, "clearcoat": 0.5, "sheen": 0.3},
            tangent=g0.tangent,
        )
        return shade(g, [PointLight(q, inten), DirectionalLight(d, [1.0, 1.0, 1.0])])

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_reach_every_input():
    h = w = 6
    mat = full_material(1, h, w, torch.float32)
    mat = {k: m.requires_grad_() for k, m in mat.items()}
    g = sphere_gbuffer(h, w, material=mat)
    pos = g.position.clone().requires_grad_()
    normal = g.normal.clone().requires_grad_()
    tangent = g.tangent.clone().requires_grad_()
    cam = g.camera_position.clone().requires_grad_()
    q, i_p = (
        torch.tensor([1.0, 2.0, 3.0], requires_grad=True),
        torch.tensor([5.0, 5.0, 5.0], requires_grad=True),
    )
    d, e = (
        torch.tensor([0.3, 0.2, 1.0], requires_grad=True),
        torch.tensor([1.0, 1.0, 1.0], requires_grad=True),
    )
    env = (torch.rand(3, 4, 8) + 0.5).requires_grad_()
    gb = g.replace(position=pos, normal=normal, tangent=tangent, camera_position=cam)
    for strategy in ("mc", "split_sum"):
        img = shade(
            gb,
            [PointLight(q, i_p), DirectionalLight(d, e), EnvironmentLight(env)],
            env_strategy=strategy,
            env_samples=8,
        )
        img.sum().backward()
        for name, t in [
            ("pos", pos),
            ("normal", normal),
            ("tangent", tangent),
            ("cam", cam),
            ("q", q),
            ("i", i_p),
            ("d", d),
            ("e", e),
            ("env", env),
        ] + list(mat.items()):
            assert t.grad is not None and bool(torch.isfinite(t.grad).all()), name
            if not (strategy == "split_sum" and name in ("tangent", "anisotropic")):  # split sum is isotropic
                assert float(t.grad.abs().sum()) > 0, (strategy, name)
            t.grad = None


def test_memory_saved_for_backward_does_not_grow_with_light_count():
    """Everything a light computes is recomputed in backward.

    The per-pixel tensors autograd keeps after the forward pass are the same few (shared)
    ones for 1 and for 8 lights.
    """
    g = sphere_gbuffer(
        16, 16, material={"base_color": torch.rand(1, 3, 16, 16).requires_grad_(), "roughness": 0.5}
    )
    g = g.replace(normal=g.normal.clone().requires_grad_(), position=g.position.clone().requires_grad_())

    def saved_storages(n_lights):
        seen = {}

        def pack(t):
            if t.numel() >= 100:  # per-pixel tensors (light parameters are 3 numbers each)
                seen[(t.untyped_storage().data_ptr(), t.numel())] = t.numel() * t.element_size()
            return t

        lights = [PointLight([math.cos(k), math.sin(k), 2.0], [1.0, 1.0, 1.0]) for k in range(n_lights)]
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            img = shade(g, lights)
        img.sum().backward()
        return len(seen), sum(seen.values())

    one, eight = saved_storages(1), saved_storages(8)
    assert eight == one, (one, eight)


# ------------------------------------------------------------------ options, dtypes, modules


def test_chunking_does_not_change_the_result():
    g = sphere_gbuffer(8, 8, dtype=D, material={"base_color": rand(1, 3, 8, 8), "roughness": 0.4})
    lights = LIGHTS + [EnvironmentLight(rand(3, 4, 8, seed=2))]
    for strategy in ("mc", "split_sum"):
        a = shade(g, lights, env_strategy=strategy, env_samples=8)
        b = shade(g, lights, env_strategy=strategy, env_samples=8, chunk=7)
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_gbuffer(dtype):
    g32 = sphere_gbuffer(6, 6, material={"base_color": torch.full((1, 3, 6, 6), 0.5), "roughness": 0.5})
    g = g32.to(dtype)
    lights = LIGHTS + [EnvironmentLight(torch.ones(3, 4, 8))]
    img = shade(g, lights, env_samples=4)
    assert img.dtype == dtype and bool(torch.isfinite(img).all())
    torch.testing.assert_close(img.float(), shade(g32, lights, env_samples=4), rtol=3e-2, atol=3e-2)


def test_torch_func_grad_and_vjp_through_shade_equal_autograd():
    """torch.func's reverse transforms refuse saved-tensor hooks, so the per-light passes run
    without checkpointing there; the gradient is autograd's."""
    rough = torch.full((1, 1, 6, 6), 0.4, dtype=torch.float64)

    def image(r):
        g = sphere_gbuffer(6, 6, material={"base_color": torch.full((1, 3, 6, 6), 0.5, dtype=torch.float64),
                                           "roughness": r}, dtype=torch.float64)
        return shade(g, LIGHTS)

    leaf = rough.clone().requires_grad_()
    image(leaf).square().sum().backward()
    grad = torch.func.grad(lambda r: image(r).square().sum())(rough)
    torch.testing.assert_close(grad, leaf.grad, rtol=1e-12, atol=0)
    assert float(grad.abs().sum()) > 0
    _, pullback = torch.func.vjp(image, rough)
    torch.testing.assert_close(pullback(2 * image(rough))[0], leaf.grad, rtol=1e-12, atol=0)


def test_vmap_over_the_gbuffer_or_a_light_is_refused_naming_it():
    """shade selects pixels by their values, which vmap cannot carry: a clear error instead of
    torch's about `.item()`; jacfwd (vmap over the tangents only) still runs."""
    cam = torch.tensor([0.0, 0.0, 3.0])
    with pytest.raises(ValueError, match=r"gbuf\.position is batched by torch\.func\.vmap.*batch dimension B"):
        torch.func.vmap(lambda p: shade(GBuffer(position=p, normal=p, camera_position=cam,
                                                material={"base_color": 0.5}), LIGHTS))(torch.rand(2, 1, 3, 4, 4))
    with pytest.raises(ValueError, match=r"lights\[0\]\.position is batched by torch\.func\.vmap"):
        torch.func.vmap(lambda q: shade(sphere_gbuffer(4, 4), [PointLight(q, [20.0, 20.0, 20.0])]))(
            torch.rand(2, 3) + 3)
    g = sphere_gbuffer(4, 4, material={"base_color": torch.full((1, 3, 4, 4), 0.5), "roughness": 0.3})
    jac = torch.func.jacfwd(lambda r: shade(g.replace(material={**g.material, "roughness": r}), LIGHTS))(
        torch.full((1, 1, 4, 4), 0.4))
    assert jac.shape == (1, 3, 4, 4, 1, 1, 4, 4) and bool(jac.abs().sum() > 0)


@pytest.mark.parametrize("inner", [torch.func.grad, torch.func.jacrev, torch.func.jacfwd])
def test_vmap_below_another_transform_is_refused_naming_it(inner):
    """Per-sample derivatives, vmap over grad / jacrev / jacfwd: the batched light is found under
    the inner transform's wrapper (a shape error from deep inside the shader otherwise)."""
    g = sphere_gbuffer(4, 4)
    with pytest.raises(ValueError, match=r"lights\[0\]\.position is batched by torch\.func\.vmap"):
        torch.func.vmap(inner(lambda q: shade(g, [PointLight(q, [20.0, 20.0, 20.0])]).sum()))(torch.rand(2, 3) + 3)


@pytest.mark.parametrize("name, value", [("roughness", 0.4), ("metallic", 0.0)], ids=["uniform", "zeros"])
def test_forward_mode_through_a_uniform_or_zero_map_keeps_its_tangent(name, value):
    """A map with a forward-mode tangent does not require grad; pruning it to a Python float
    (uniform or all-zero maps) would drop the tangent and give a zero jvp."""
    g = sphere_gbuffer(6, 6, material={"base_color": torch.full((1, 3, 6, 6), 0.5), "roughness": 0.3},
                       dtype=torch.float64)

    def image(m):
        return shade(g.replace(material={**g.material, name: m}), LIGHTS)

    m0 = torch.full((1, 1, 6, 6), value, dtype=torch.float64)
    rev = torch.func.jacrev(image)(m0)
    assert float(rev.abs().sum()) > 0
    torch.testing.assert_close(torch.func.jacfwd(image)(m0), rev, rtol=1e-10, atol=1e-12)
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(image(fwAD.make_dual(m0, torch.ones_like(m0)))).tangent
    torch.testing.assert_close(tangent, rev.sum((-4, -3, -2, -1)), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("brdf", [None, lambert], ids=["principled", "lambert"])
def test_meta_gbuffer_shades_to_its_shape(brdf):
    """Meta tensors hold no values: no decision reads them (as under torch.compile), so shade
    gives the image's shape and dtype; environment lights, whose set-up reads the map, are refused."""
    g = sphere_gbuffer(6, 8, batch_size=2, material={"base_color": torch.rand(2, 3, 6, 8)}).to("meta")
    lights = [PointLight(torch.tensor([2.0, 2.0, 3.0], device="meta"), torch.ones(3, device="meta")),
              DirectionalLight(torch.tensor([0.0, 0.0, 1.0], device="meta"), torch.ones(3, device="meta"))]
    img = shade(g, lights, brdf)
    assert img.device.type == "meta" and img.shape == (2, 3, 6, 8) and img.dtype == torch.float32
    with pytest.raises(ValueError, match="environment lights on the meta device"):
        shade(g, [EnvironmentLight(torch.ones(3, 4, 8, device="meta"))], brdf)


def test_shader_module():
    brdf = LambertBRDF()
    s = Shader(brdf, env_strategy="split_sum")
    assert dict(s.named_children())["brdf"] is brdf
    g = sphere_gbuffer(5, 5)
    lights = LIGHTS + [EnvironmentLight(torch.rand(3, 4, 8))]
    torch.testing.assert_close(s(g, lights), shade(g, lights, brdf, env_strategy="split_sum"))
    assert s.plan(g, lights).brdf == "LambertBRDF"
    assert "split_sum" in repr(s)
    torch.testing.assert_close(Shader()(g, LIGHTS), shade(g, LIGHTS))


def test_custom_brdf_callable():
    calls = []

    def my_brdf(l, v, n, x=None, y=None, *, base_color, roughness=0.5, **kw):
        calls.append(l.shape)
        return principled(l, v, n, x, y, base_color=base_color, roughness=roughness)

    g = sphere_gbuffer(5, 5, dtype=D)
    torch.testing.assert_close(shade(g, LIGHTS, my_brdf), shade(g, LIGHTS))
    assert calls and all(s[-1] == 3 and len(s) == 2 for s in calls)  # flat channel-last (P, 3)
    assert plan(g, LIGHTS, my_brdf).lobes is None
    out = shade(g, [EnvironmentLight(torch.rand(3, 4, 8, dtype=D))], my_brdf, env_samples=8)
    assert bool(torch.isfinite(out).all())
    with pytest.raises(ValueError, match="split_sum"):
        shade(g, [EnvironmentLight(torch.rand(3, 4, 8, dtype=D))], my_brdf, env_strategy="split_sum")


def test_a_material_the_brdf_does_not_take_is_refused_up_front():
    # SVBRDFGGX takes diffuse/specular albedo: a principled material (base_color) is named and
    # refused before any shading, with the parameters the BRDF does take.
    g = sphere_gbuffer(5, 5, dtype=D)  # base_color, roughness, ...
    for brdf in (torchbrdf.SVBRDFGGX(), torchbrdf.svbrdf_ggx):
        with pytest.raises(ValueError, match=r"base_color.*diffuse_albedo"):
            shade(g, LIGHTS, brdf)
    albedo = {"diffuse_albedo": torch.full((1, 3, 5, 5), 0.5, dtype=D), "specular_albedo": 0.04,
              "roughness": 0.3}
    ggx = sphere_gbuffer(5, 5, dtype=D, material=albedo)
    assert bool(torch.isfinite(shade(ggx, LIGHTS, torchbrdf.SVBRDFGGX())).all())


# ------------------------------------------------------------------ validation


def test_gbuffer_errors_name_the_argument():
    p = torch.zeros(1, 3, 4, 5)
    n = torch.zeros(1, 3, 4, 5)
    c = torch.tensor([0.0, 0.0, 3.0])
    with pytest.raises(ValueError, match="`position`"):
        GBuffer(torch.zeros(3, 4, 5), n, c, {})
    with pytest.raises(ValueError, match="`normal`.*\\[1, 3, 4, 5\\]"):
        GBuffer(p, torch.zeros(1, 3, 5, 4), c, {})
    with pytest.raises(ValueError, match="`tangent`"):
        GBuffer(p, n, c, {}, tangent=torch.zeros(1, 2, 4, 5))
    with pytest.raises(ValueError, match="`mask`"):
        GBuffer(p, n, c, {}, mask=torch.ones(1, 3, 4, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="`camera_position`"):
        GBuffer(p, n, torch.zeros(4), {})
    with pytest.raises(ValueError, match="base_color"):
        GBuffer(p, n, c, {"base_color": torch.zeros(1, 1, 4, 5)})
    with pytest.raises(ValueError, match="roughness"):
        GBuffer(p, n, c, {"roughness": torch.zeros(1, 3, 4, 5)})
    with pytest.raises(ValueError, match="metallic"):
        GBuffer(p, n, c, {"metallic": torch.zeros(1, 1, 3, 5)})
    with pytest.raises(TypeError, match="sheen"):
        GBuffer(p, n, c, {"sheen": "none"})
    with pytest.raises(TypeError, match="`normal`"):
        GBuffer(p, n.long(), c, {})
    g = GBuffer(p, n, [0.0, 0.0, 3.0], {"base_color": torch.zeros(1, 3, 1, 1), "roughness": 0.5})
    assert g.camera_position.dtype == p.dtype and g.material["roughness"] == 0.5
    assert g.to(torch.float64).position.dtype == torch.float64
    assert not g.detach().position.requires_grad


def test_light_and_shade_errors():
    with pytest.raises(ValueError, match="PointLight: `position`"):
        PointLight([0.0, 1.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="PointLight: `intensity`"):
        PointLight([0.0, 1.0, 2.0], torch.ones(2, 2))
    with pytest.raises(ValueError, match="DirectionalLight: `direction`"):
        DirectionalLight(torch.ones(2, 3, 1), 1.0)
    with pytest.raises(ValueError, match="EnvironmentLight: `radiance`"):
        EnvironmentLight(torch.ones(4, 8))
    g = sphere_gbuffer(4, 4, batch_size=2)
    with pytest.raises(ValueError, match="lights\\[1\\].*3 images.*2"):
        shade(g, [PointLight([0.0, 0.0, 3.0], 1.0), PointLight(torch.ones(3, 3), 1.0)])
    with pytest.raises(TypeError, match="lights\\[0\\]"):
        shade(g, ["sun"])
    with pytest.raises(ValueError, match="env_strategy"):
        shade(g, LIGHTS, env_strategy="mcmc")
    with pytest.raises(ValueError, match="env_samples"):
        shade(g, LIGHTS, env_samples=0)
    with pytest.raises(ValueError, match="chunk"):
        shade(g, LIGHTS, chunk=0)
    with pytest.raises(TypeError, match="gbuf"):
        shade({"position": 1}, LIGHTS)


def test_lights_are_modules_with_parameters_and_buffers():
    pos = torch.nn.Parameter(torch.tensor([0.0, 0.0, 3.0]))
    light = PointLight(pos, torch.tensor([1.0, 2.0, 3.0]))
    assert list(light.parameters()) == [pos]
    assert "intensity" in dict(light.named_buffers())
    assert light.batch_size is None and PointLight(torch.zeros(2, 3), 1.0).batch_size == 2
    assert EnvironmentLight(torch.ones(2, 3, 4, 8)).batch_size == 2
    assert light.to(torch.float64).intensity.dtype == torch.float64


# ------------------------------------------------------------------ analytic g-buffers


def test_sphere_gbuffer_geometry():
    g = sphere_gbuffer(32, 32, radius=0.7, center=(0.1, -0.2, 0.3), camera_position=(0.0, 0.0, 5.0), dtype=D)
    m = g.mask[0, 0]
    p = g.position[0].permute(1, 2, 0)[m]
    n = g.normal[0].permute(1, 2, 0)[m]
    c = torch.tensor([0.1, -0.2, 0.3], dtype=D)
    assert torch.allclose((p - c).norm(dim=-1), torch.full((len(p),), 0.7, dtype=D))
    assert torch.allclose(n, (p - c) / 0.7)
    v = safe_normalize(torch.tensor([0.0, 0.0, 5.0], dtype=D) - p)
    assert bool(((n * v).sum(-1) > 0).all())
    t = g.tangent[0].permute(1, 2, 0)[m]
    assert torch.allclose((t * n).sum(-1), torch.zeros(len(t), dtype=D), atol=1e-12)
    # Disk fraction: sphere radius fills 1/1.1 of the half field of view (in tangent space).
    frac = float(m.double().mean())
    assert 0.55 < frac < 0.7
    # Row 0 is the top (+y).
    rays = pinhole_rays(4, 4, (0.0, 0.0, 5.0), dtype=D)
    assert rays[0, 0, 1] > 0 and rays[-1, 0, 1] < 0 and rays[0, 0, 0] < 0
    with pytest.raises(ValueError, match="camera_position"):
        sphere_gbuffer(4, 4, camera_position=(0.0, 0.0, 0.5))


def test_plane_gbuffer_normal_map_and_errors():
    nm = torch.zeros(2, 3, 4, 4)
    nm[:, 2] = 2.0
    nm[:, 0] = 2.0
    g = plane_gbuffer(4, 4, normal_map=nm)
    assert g.batch_size == 2 and torch.allclose(g.normal.norm(dim=1), torch.ones(2, 4, 4))
    assert torch.allclose(g.normal[:, 0], torch.full((2, 4, 4), 1 / math.sqrt(2)))
    assert torch.equal(g.tangent[:, 0], torch.ones(2, 4, 4))
    with pytest.raises(ValueError, match="normal_map"):
        plane_gbuffer(4, 4, normal_map=torch.zeros(1, 3, 5, 4))


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: sphere_gbuffer(0, 0), "sphere_gbuffer: `height` must be a positive integer, got 0"),
        (lambda: sphere_gbuffer(4, 0), "sphere_gbuffer: `width` must be a positive integer, got 0"),
        (lambda: sphere_gbuffer(4, -2), "`width` must be a positive integer, got -2"),
        (lambda: sphere_gbuffer(4.5, 4), "`height` must be a positive integer, got 4.5"),
        (lambda: sphere_gbuffer(4, 4, batch_size=0), "`batch_size` must be a positive integer"),
        (lambda: sphere_gbuffer(4, 4, radius=0.0), "`radius` must be a positive finite number"),
        (lambda: plane_gbuffer(0, 0), "plane_gbuffer: `height` must be a positive integer, got 0"),
        (lambda: plane_gbuffer(3, 0), "plane_gbuffer: `width` must be a positive integer, got 0"),
        (lambda: plane_gbuffer(3, 3, batch_size=0), "`batch_size` must be a positive integer"),
        (lambda: pinhole_rays(0, 4, (0.0, 0.0, 3.0)), "pinhole_rays: `height` must be a positive integer"),
    ],
)
def test_gbuffer_sizes_must_be_positive_integers(make, match):
    """Zero sizes used to raise ZeroDivisionError; now a ValueError names the argument."""
    with pytest.raises(ValueError, match=match):
        make()


def test_non_finite_gbuffer_or_light_under_validation():
    """A NaN position gave a silent 0 even under validation; now it raises, naming the map.
    Masked-out pixels are not shaded, so they may hold NaN."""
    import torchbrdf

    light = PointLight(torch.tensor([0.0, 0.0, 5.0], dtype=D), torch.tensor([1.0, 1.0, 1.0], dtype=D))
    g = sphere_gbuffer(4, 4, dtype=D)
    g.position[0, 0, 1, 1] = float("nan")
    assert torch.isfinite(shade(g, light)).all()  # validation off: no data read
    with torchbrdf.validation(True), pytest.raises(ValueError, match=r"^gbuf\.position: contains 1 non-finite"):
        shade(g, light)
    g = sphere_gbuffer(4, 4, dtype=D)
    g.position[0, :, 0, 0] = float("nan")  # a corner pixel: outside the sphere's mask
    assert not bool(g.mask[0, 0, 0, 0])
    with torchbrdf.validation(True):
        assert torch.isfinite(shade(g, light)).all()
        bad = PointLight(torch.tensor([0.0, float("inf"), 5.0], dtype=D), torch.ones(3, dtype=D))
        with pytest.raises(ValueError, match=r"^lights\[1\]\.position: contains 1 non-finite"):
            shade(g, [light, bad])
        g.material["roughness"] = float("nan")
        with pytest.raises(ValueError, match=r"^gbuf\.material\['roughness'\]: expected a finite number"):
            shade(g, light)


@pytest.mark.parametrize("make, name", [
    (lambda: PointLight(torch.tensor([0.0, 0.0, 5.0], dtype=D), torch.tensor([1.0, -0.5, 1.0], dtype=D)),
     "intensity"),
    (lambda: DirectionalLight(torch.tensor([0.0, 0.0, 1.0], dtype=D), -1.0), "irradiance"),
    (lambda: EnvironmentLight(-torch.ones(3, 4, 8, dtype=D)), "radiance"),
])
def test_negative_light_under_validation(make, name):
    """numerics.md promised negative intensities are refused under validation; they shaded."""
    good = PointLight(torch.tensor([0.0, 0.0, 5.0], dtype=D), torch.ones(3, dtype=D))
    g = sphere_gbuffer(4, 4, dtype=D)
    shade(g, [good, make()])  # validation off: no data read
    with torchbrdf.validation(True), pytest.raises(ValueError,
                                                    match=rf"^lights\[1\]\.{name}: expected non-negative"):
        shade(g, [good, make()])


def test_shade_under_torch_compile_has_no_graph_break_and_no_recompile():
    # Value-dependent pruning (which pixels, constant maps) is skipped while compiling: each
    # decision would be a graph break and a guard on the data (a recompile per new input).
    from torch._dynamo.utils import counters

    import torchbrdf

    b, h, w = 1, 12, 16

    def inputs(seed):
        mat = {"base_color": rand(b, 3, h, w, seed=seed, dtype=torch.float32).requires_grad_(),
               "roughness": rand(b, 1, h, w, seed=seed + 1, dtype=torch.float32, lo=0.1).requires_grad_(),
               "metallic": torch.zeros(b, 1, h, w)}  # all zeros: pruned eagerly, evaluated compiled
        mask = (rand(b, 1, h, w, seed=seed + 2, dtype=torch.float32) > 0.2).float()
        pos = torch.stack(torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")[::-1]
                          + (torch.zeros(h, w),))[None]
        nrm = torch.tensor([0.1, -0.1, 1.0]).view(1, 3, 1, 1) + 0.2 * rand(b, 3, h, w, seed=seed + 3,
                                                                             dtype=torch.float32)
        nrm = torch.nn.functional.normalize(nrm, dim=1)
        gb = GBuffer(position=pos, normal=nrm, camera_position=torch.tensor([0.0, 0.0, 3.0]), material=mat,
                     mask=mask)
        lights = [PointLight(torch.tensor([0.5, -0.3, 2.0]) + 0.1 * seed, torch.tensor([10.0, 8.0, 6.0])),
                  DirectionalLight(safe_normalize(torch.tensor([0.2, 0.1, 1.0])), torch.ones(3))]
        return gb, lights, mat

    counters.clear()
    fn = torch.compile(torchbrdf.shade, backend="eager")
    for seed in range(3):
        gb, lights, mat = inputs(seed)
        img = fn(gb, lights)
        (g,) = torch.autograd.grad(img.sum(), mat["roughness"])
        ref = shade(gb, lights)
        (ge,) = torch.autograd.grad(ref.sum(), mat["roughness"])
        torch.testing.assert_close(img, ref, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(g, ge, rtol=1e-4, atol=1e-6)
    assert not counters["graph_break"], dict(counters["graph_break"])
    assert counters["stats"]["unique_graphs"] == 1
