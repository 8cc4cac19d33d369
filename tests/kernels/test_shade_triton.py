"""``shade``'s fused light loop printed as Triton (kernels/light_loop.py), run by Triton's CPU interpreter.

The same light-loop schedule as the C kernel (pixel-level terms once, the lights in a loop,
the backward's boundary adjoints accumulated across lights) printed as one Triton program per
block of pixels. Values and gradients equal the per-light eager shader's.
"""

import importlib

import pytest
import torch

import torchbrdf

triton = pytest.importorskip("triton")

ct = importlib.import_module("torchbrdf.kernels.codegen_triton")
shade_ops = importlib.import_module("torchbrdf.kernels.shade_ops")
codegen_shade = importlib.import_module("torchbrdf.kernels.codegen_shade")
backend_mod = importlib.import_module("torchbrdf.kernels.backend")


@pytest.fixture(scope="module", autouse=True)
def interpreter(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("TRITON_INTERPRET", "1")
    mp.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path_factory.mktemp("kernels")))
    mp.delenv("TORCHBRDF_BACKEND", raising=False)
    mp.delenv("TORCHBRDF_EAGER", raising=False)
    yield
    torchbrdf.set_backend(None)
    mp.undo()


@pytest.fixture
def light_loop_kernels(monkeypatch):
    """The kinds of the Triton light-loop kernels built or fetched (proves the fused loop ran)."""
    calls = []
    real = shade_ops._triton_kernel

    def spy(spec, kind, wide):
        calls.append(kind)
        return real(spec, kind, wide)

    monkeypatch.setattr(shade_ops, "_triton_kernel", spy)
    return calls


def _lights(dtype, batch=1):
    g = torch.Generator().manual_seed(3)
    pts = [torchbrdf.PointLight(position=torch.tensor([1.0, 2.0, 3.0], dtype=dtype) + (
               0.5 * torch.randn(batch, 3, generator=g, dtype=dtype) if batch > 1 else 0.0),
           intensity=torch.tensor([5.0, 4.0, 3.0], dtype=dtype)),
           torchbrdf.PointLight(position=torch.tensor([-2.0, 0.5, 2.0], dtype=dtype),
                                intensity=torch.tensor([2.0, 3.0, 4.0], dtype=dtype))]
    dirs = [torchbrdf.DirectionalLight(direction=torch.tensor([0.3, -0.2, 1.0], dtype=dtype),
                                       irradiance=torch.tensor([1.0, 0.8, 1.2], dtype=dtype))]
    return pts + dirs


def _shade(backend, dtype, batch=1, size=12):
    from torchbrdf.render.geometry import sphere_gbuffer

    g = torch.Generator().manual_seed(5)
    rough = (0.2 + 0.6 * torch.rand(batch, 1, size, size, generator=g, dtype=dtype)).requires_grad_()
    base = torch.rand(batch, 3, size, size, generator=g, dtype=dtype).requires_grad_()
    metal = torch.rand(batch, 1, size, size, generator=g, dtype=dtype).requires_grad_()
    gb = sphere_gbuffer(size, size, dtype=dtype)
    gb = torchbrdf.GBuffer(position=gb.position.expand(batch, -1, -1, -1),
                           normal=gb.normal.expand(batch, -1, -1, -1),
                           camera_position=gb.camera_position,
                           material={"roughness": rough, "base_color": base, "metallic": metal,
                                     "clearcoat": 0.3, "sheen": 0.2})
    old = backend_mod.get_backend()
    torchbrdf.set_backend(backend)
    try:
        img = torchbrdf.shade(gb, _lights(dtype, batch))
        go = torch.linspace(-1.0, 2.0, img.numel(), dtype=dtype).reshape(img.shape)
        img.backward(go)
    finally:
        torchbrdf.set_backend(old)
    return img.detach(), rough.grad, base.grad, metal.grad


def _shade_ggx(backend, dtype, size=12):
    from torchbrdf.brdf.svbrdf_ggx import SVBRDFGGX
    from torchbrdf.render.geometry import sphere_gbuffer

    g = torch.Generator().manual_seed(6)
    maps = {"diffuse_albedo": torch.rand(1, 3, size, size, generator=g, dtype=dtype),
            "specular_albedo": 0.9 * torch.rand(1, 3, size, size, generator=g, dtype=dtype),
            "roughness": 0.1 + 0.8 * torch.rand(1, 1, size, size, generator=g, dtype=dtype)}
    for t in maps.values():
        t.requires_grad_()
    gb = sphere_gbuffer(size, size, dtype=dtype)
    gb = torchbrdf.GBuffer(position=gb.position, normal=gb.normal, camera_position=gb.camera_position,
                           material=maps)
    old = backend_mod.get_backend()
    torchbrdf.set_backend(backend)
    try:
        img = torchbrdf.shade(gb, _lights(dtype), SVBRDFGGX(roughness_floor=0.05))
        img.backward(torch.linspace(-1.0, 2.0, img.numel(), dtype=dtype).reshape(img.shape))
    finally:
        torchbrdf.set_backend(old)
    return (img.detach(), *(t.grad for t in maps.values()))


@pytest.mark.parametrize("render", [_shade, _shade_ggx], ids=["principled", "svbrdf_ggx"])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-11), (torch.float32, 2e-5)])
def test_triton_light_loop_matches_per_light_eager(dtype, tol, render, light_loop_kernels):
    got = render("triton", dtype)
    assert light_loop_kernels.count("fwd") >= 1 and light_loop_kernels.count("bwd") >= 1
    ref = render("eager", dtype)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)


def test_triton_light_loop_per_image_lights(light_loop_kernels):
    # lights that differ between the images of a batch: one launch (uniform row) per image
    got = _shade("triton", torch.float64, batch=2, size=8)
    assert "fwd" in light_loop_kernels
    ref = _shade("eager", torch.float64, batch=2, size=8)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-11)


def test_triton_light_loop_source_loops_over_lights():
    # The printed kernel has one loop per light kind over a runtime count, reading the light's
    # uniforms inside it, and the pixel-level terms (view vector, ...) before the loops.
    from torchbrdf.brdf.principled import SCALAR_PARAMS

    tensors = [("pos", "full", 3), ("n", "full", 3), ("base_color", "b1", 3)]
    spec = codegen_shade.ShadeSpec("float", tensors, SCALAR_PARAMS, ("diffuse", "specular"), False, False,
                                   ("point", "directional"))
    src = codegen_shade.generate_triton(spec, "fwd")
    assert "for j in range(0, 0 + Lp):" in src and "for j in range(Lp, Lp + Ld):" in src
    assert src.count("tl.load(u + 0)") == 2
    head = src.split("for j in range(0")[0]
    assert "tl.load(U + 0)" in head  # the camera (view vector) before the light loops


def test_light_loop_kernels_compile_for_a_gpu_without_one(monkeypatch):
    # The interpreter accepts some things the compiler does not: compile the shading forward and
    # backward and the normal-equations kernel to PTX for sm_90 (no GPU needed).
    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler import ASTSource
    except ImportError:
        pytest.skip("this Triton has no compiler API")
    import inspect

    from torchbrdf.brdf.principled import SCALAR_PARAMS
    from torchbrdf.kernels import codegen_normal_eq

    monkeypatch.delenv("TRITON_INTERPRET")
    fl = [k for k in SCALAR_PARAMS if k != "roughness"]
    tensors = [("pos", "full", 3), ("n", "full", 3), ("base_color", "full", 3), ("roughness", "full", 1)]
    spec = codegen_shade.ShadeSpec("float", tensors, fl, ("diffuse", "specular", "clearcoat"), False, False,
                                   ("point", "directional"), grad_mask=(2, 3))
    names = [("pos", 3), ("n", 3), ("base_color", 3), ("metallic", 1), ("specular", 1), ("roughness", 1)]
    pat = [[], [(j, c, j - 4) for j in (5, 6) for c in range(3)], [(0, 0, 0), (1, 1, 0), (2, 2, 0)], [],
           [(3, 0, 0)], [(4, 0, 0)]]
    ne = codegen_normal_eq.NormalEqSpec("float", names, [k for k in SCALAR_PARAMS if k not in
                                                         ("metallic", "specular", "roughness")],
                                        ("diffuse", "specular"), False, 7, pat)
    light_grad = codegen_shade.ShadeSpec("float", tensors, fl, ("diffuse", "specular", "clearcoat"), False,
                                         False, ("point", "directional"), grad_mask=(2,), uniform_grad=True)
    sources = [(codegen_shade.generate_triton(spec, "fwd"), "tb_fwd"),
               (codegen_shade.generate_triton(spec, "bwd"), "tb_bwd"),
               (codegen_shade.generate_triton(light_grad, "bwd"), "tb_bwd"),
               (codegen_normal_eq.generate_triton(ne), "tb_ne")]
    for src, name in sources:
        kern = ct.compile_source(src, name)
        sig = {a: "constexpr" if a == "BLOCK" else "i32" if a in ("n", "Lp", "Ld", "L") else
               "*fp64" if a in ("P", "gU") else "*fp32" for a in inspect.signature(kern.fn).parameters}
        try:
            cc = triton.compile(ASTSource(fn=kern, signature=sig, constexprs={"BLOCK": 128}),
                                target=GPUTarget("cuda", 90, 32),
                                options={"enable_fp_fusion": False, "num_warps": 4})
        except (RuntimeError, FileNotFoundError) as e:  # e.g. no ptxas for this platform
            if "ptxas" in str(e):
                pytest.skip(str(e))
            raise
        ptx = cc.asm["ptx"]
        assert "div.rn.f32" in ptx and "fma.rn.f32" not in ptx


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_shade_runs_the_triton_light_loop(monkeypatch, light_loop_kernels):
    from torchbrdf.render.geometry import sphere_gbuffer

    monkeypatch.delenv("TRITON_INTERPRET")
    res = {}
    for dev in ("cuda", "cpu"):
        g = sphere_gbuffer(64, 64, dtype=torch.float32)
        rough = torch.full((1, 1, 64, 64), 0.4, device=dev, requires_grad=True)
        gb = torchbrdf.GBuffer(position=g.position.to(dev), normal=g.normal.to(dev),
                               camera_position=g.camera_position.to(dev),
                               material={"roughness": rough, "base_color": 0.6, "clearcoat": 0.3})
        torchbrdf.set_backend("auto" if dev == "cuda" else "eager")
        try:
            light = torchbrdf.PointLight(position=torch.tensor([1.0, 2.0, 3.0], device=dev),
                                         intensity=torch.tensor([5.0, 4.0, 3.0], device=dev))
            img = torchbrdf.shade(gb, [light])
            img.sum().backward()
        finally:
            torchbrdf.set_backend(None)
        res[dev] = (img.detach().cpu(), rough.grad.cpu())
    assert "fwd" in light_loop_kernels and "bwd" in light_loop_kernels
    for a, b in zip(res["cuda"], res["cpu"]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def _light_gradients(backend, dtype, batch):
    """Gradients of a weighted image sum w.r.t. the camera and every light tensor (per-image
    point lights when ``batch`` > 1) and the roughness map."""
    from torchbrdf.render.geometry import sphere_gbuffer

    g = torch.Generator().manual_seed(5)
    gb = sphere_gbuffer(9, 9, dtype=dtype)
    rough = (0.2 + 0.6 * torch.rand(batch, 1, 9, 9, generator=g, dtype=dtype)).requires_grad_()
    cam = (gb.camera_position + torch.zeros(batch, 3, dtype=dtype)).requires_grad_()
    gb = torchbrdf.GBuffer(position=gb.position.expand(batch, -1, -1, -1),
                           normal=gb.normal.expand(batch, -1, -1, -1), camera_position=cam,
                           material={"roughness": rough, "base_color": 0.6, "clearcoat": 0.3})
    lights = _lights(dtype, batch)
    leaves = [cam, rough] + [t.requires_grad_() for light in lights for t in light._light_tensors()]
    old = backend_mod.get_backend()
    torchbrdf.set_backend(backend)
    try:
        img = torchbrdf.shade(gb, lights)
        go = torch.linspace(-1.0, 2.0, img.numel(), dtype=dtype).reshape(img.shape)
        return torch.autograd.grad(img, leaves, go)
    finally:
        torchbrdf.set_backend(old)


@pytest.mark.parametrize("batch", [1, 2])
def test_triton_light_loop_light_and_camera_gradients(batch, light_loop_kernels, monkeypatch):
    # The backward sums each uniform's gradient per block (masked lanes are 0) and per image.
    specs = []
    real = shade_ops._triton_kernel
    monkeypatch.setattr(shade_ops, "_triton_kernel",
                        lambda spec, kind, wide: specs.append(spec) or real(spec, kind, wide))
    got = _light_gradients("triton", torch.float64, batch)
    assert any(s.uniform_grad for s in specs)
    ref = _light_gradients("eager", torch.float64, batch)
    for a, b in zip(got, ref):
        assert b.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
