"""Synthetic capture generator: determinism, formats, compact renderer == principled."""

import json

import pytest
import torch

from torchbrdf.capture.format import load_capture
from torchbrdf.capture.synthetic import (
    DEFAULT_CAMERA,
    MAP_NAMES,
    RECIPES,
    generate_capture,
    light_layout,
    make_material,
    random_lights,
    render_capture,
)
from torchbrdf.io import read_exr


@pytest.mark.parametrize("recipe", RECIPES)
def test_material_maps_valid_and_deterministic(recipe):
    a = make_material(recipe, seed=3, size=32)
    b = make_material(recipe, seed=3, size=32)
    c = make_material(recipe, seed=4, size=32)
    assert set(a) == set(MAP_NAMES)
    for k, ch in MAP_NAMES.items():
        assert a[k].shape == (ch, 32, 32) and a[k].dtype == torch.float32
        assert torch.equal(a[k], b[k])
        assert torch.isfinite(a[k]).all()
    assert any(not torch.equal(a[k], c[k]) for k in a)
    n = a["normal"]
    assert torch.allclose(n.norm(dim=0), torch.ones(32, 32), atol=1e-5) and (n[2] > 0).all()
    for k in ("roughness", "metallic", "specular", "base_color"):
        assert a[k].min() >= 0 and a[k].max() <= 1


def test_unknown_recipe_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown recipe"):
        make_material("velvet")


@pytest.mark.parametrize("noise", [-0.01, float("nan"), float("inf")])
def test_negative_or_non_finite_noise_is_refused(tmp_path, noise):
    # noise=-1 wrote a capture with 100 % noise (the sign of a Gaussian does not matter)
    with pytest.raises(ValueError, match=r"add_noise: level \(the relative noise, e\.g\. 0\.01\) must be"):
        generate_capture(tmp_path / "cap", recipe="tiles", seed=1, size=8, lights=2, noise=noise)
    assert not (tmp_path / "cap" / "capture.json").exists()


@pytest.mark.parametrize("kwargs, named", [
    ({"lights": 2.5}, "lights must be an integer >= 0, got 2.5"),
    ({"lights": -2}, "lights must be an integer >= 0, got -2"),
    ({"lights": 0, "near_camera": False}, "lights=0 with near_camera=False leaves no light"),
    ({"size": 2}, "size must be an integer >= 4, got 2"),
    ({"size": "64"}, "size must be an integer >= 4, got '64'"),
    ({"camera_position": (0.0, 0.0)}, r"camera_position must be 3 finite numbers"),
    ({"camera_position": (0.0, 0.0, float("nan"))}, r"camera_position must be 3 finite numbers"),
    ({"camera_position": (0.0, 0.0, -3.0)}, r"camera_position .* above the sample"),
])
def test_generate_capture_refuses_bad_arguments_by_name_before_writing(tmp_path, kwargs, named):
    # these reached torch (a size mismatch, a float shape) or refused a light the user never
    # placed, after gt/ was already written
    with pytest.raises(ValueError, match="generate_capture: " + named):
        generate_capture(tmp_path / "cap", **{"recipe": "tiles", "size": 8, "lights": 2, **kwargs})
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("recipe", ["metal_inlay", "tiles", "scratched_metal"])
def test_compact_renderer_equals_principled(recipe, fast):
    # The fit's renderer (all lights in one torchbrdf.principled call) against the per-light
    # reference, eager and through the fused kernels: equal to float32 rounding.
    import torchbrdf
    from torchbrdf.kernels import fused

    if fast and not fused.available():
        pytest.skip("no C compiler: the fused path is unavailable")
    maps = make_material(recipe, seed=1, size=24)
    lights = light_layout(8)
    ref = render_capture(maps, lights, backend="principled")
    torchbrdf.set_fast_path(fast)
    try:
        fit = render_capture(maps, lights, backend="compact")
    finally:
        torchbrdf.set_fast_path(None)
    assert torch.allclose(fit, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fast", [False, True])
def test_fit_residual_is_the_log_of_the_rendered_capture(fast):
    # The recovery minimises log_residual_points (formula.capture_log_residual: the point light,
    # the principled BRDF and the log in one kernel family). It must be log(render + eps) - log_obs
    # of the per-light reference renderer, with every principled parameter, eager and fused.
    import torchbrdf
    from torchbrdf.capture.synthetic import log_residual_points, pixel_points

    maps = make_material("metal_inlay", seed=2, size=20)
    gen = torch.Generator().manual_seed(1)
    for name in ("subsurface", "sheen", "clearcoat", "anisotropic", "specular_tint"):
        maps[name] = torch.rand(1, 20, 20, generator=gen)
    pos, inten = light_layout(7)
    ref = render_capture(maps, (pos, inten), backend="principled")  # (L, 3, H, W)
    eps = 0.01
    obs = ref * (1 + 0.05 * torch.randn(ref.shape, generator=gen)).clamp(min=0)
    log_obs = torch.log(obs + eps).permute(2, 3, 0, 1).reshape(-1, ref.shape[0], 3)  # (P, L, 3)
    flat = {k: v.permute(1, 2, 0).reshape(-1, v.shape[0]) for k, v in maps.items() if k != "normal"}
    n = maps["normal"].permute(1, 2, 0).reshape(-1, 3)
    n = n / n.norm(dim=-1, keepdim=True)
    pts = pixel_points(20, 20).reshape(-1, 3)
    torchbrdf.set_fast_path(fast)
    try:
        r = log_residual_points(n, pts, torch.as_tensor(DEFAULT_CAMERA, dtype=torch.float32), pos, inten, flat,
                                log_obs, eps)
    finally:
        torchbrdf.set_fast_path(None)
    want = torch.log(ref + eps).permute(2, 3, 0, 1).reshape(-1, ref.shape[0], 3) - log_obs
    assert r.shape == want.shape
    assert torch.allclose(r, want, atol=2e-5)


def test_fit_residual_on_a_few_pixels_runs_fused_with_any_size(monkeypatch):
    """``any_size``: a call below the fused path's lane threshold runs on the fused kernels.

    As the fit's refits of a few pixels do, with the eager path's values; without it, eagerly.
    (Without a derivative taken the fused residual is the light-loop kernel's.)
    """
    import torchbrdf.kernels.normal_eq_ops as normal_eq_ops
    import torchbrdf.kernels.ops as ops
    from torchbrdf.brdf.principled import FAST_PATH_MIN_LANES
    from torchbrdf.capture.synthetic import log_residual_points, pixel_points

    maps = make_material("metal_inlay", seed=2, size=6)
    pos, inten = light_layout(4)
    assert 36 * pos.shape[0] < FAST_PATH_MIN_LANES
    flat = {k: v.permute(1, 2, 0).reshape(-1, v.shape[0]) for k, v in maps.items() if k != "normal"}
    n = maps["normal"].permute(1, 2, 0).reshape(-1, 3)
    n = n / n.norm(dim=-1, keepdim=True)
    pts = pixel_points(6, 6).reshape(-1, 3)
    log_obs = torch.full((36, pos.shape[0], 3), -1.0)
    cam = torch.as_tensor(DEFAULT_CAMERA, dtype=torch.float32)
    calls = []
    fast, loop = ops.capture_fast, normal_eq_ops.normal_equations
    monkeypatch.setattr(ops, "capture_fast", lambda *a, **k: calls.append("lane") or fast(*a, **k))
    monkeypatch.setattr(normal_eq_ops, "normal_equations",
                        lambda *a, **k: calls.append("loop") or loop(*a, **k))
    eager = log_residual_points(n, pts, cam, pos, inten, flat, log_obs, 0.01)
    assert calls == []
    fused = log_residual_points(n, pts, cam, pos, inten, flat, log_obs, 0.01, any_size=True)
    assert calls == ["loop"]
    assert torch.allclose(fused, eager, atol=2e-5)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fit_residual_jvp_is_the_vmapped_jvp_of_the_residual(monkeypatch, dtype):
    """``log_residual_points_jvp``: the residual and its derivatives along K directions at once.

    K = 5 directions, each moving some of base colour, roughness, metallic, the normal and the
    lights' positions and intensities (``(K, L, 3)`` tangents, L ≠ P; one direction all of
    them, one none), against ``torch.func.jvp`` of :func:`log_residual_points` one direction at
    a time, on the eager formula. The fused path is one call of each operator
    (``capture_jvp``); inputs that need a gradient, or no fused kernel, take the transforms. A
    tangent of an input that is not there is refused by name.
    """
    import torchbrdf
    import torchbrdf.kernels.ops as ops
    from torchbrdf.capture.synthetic import log_residual_points, log_residual_points_jvp, pixel_points

    maps = make_material("rusted_metal", seed=4, size=12)
    pos, inten = light_layout(5)
    pos, inten = pos.to(dtype), inten.to(dtype)
    gen = torch.Generator().manual_seed(2)
    flat = {k: v.permute(1, 2, 0).reshape(-1, v.shape[0]).to(dtype) for k, v in maps.items() if k != "normal"}
    flat["metallic"] = torch.rand(144, 1, generator=gen, dtype=dtype)  # fractional: both lobes count
    n = maps["normal"].permute(1, 2, 0).reshape(-1, 3).to(dtype)
    n = n / n.norm(dim=-1, keepdim=True)
    pts, cam = pixel_points(12, 12, dtype=dtype).reshape(-1, 3), torch.as_tensor(DEFAULT_CAMERA, dtype=dtype)
    log_obs = torch.randn(144, pos.shape[0], 3, generator=gen, dtype=dtype) * 0.3 - 1.0
    K, moved = 5, ("base_color", "roughness", "metallic", "normal", "light_pos", "light_int")
    rows = {"light_pos": pos.shape[0], "light_int": pos.shape[0]}
    tangents = {k: torch.zeros(K, rows.get(k, 144), 1 if k in ("roughness", "metallic") else 3, dtype=dtype)
                for k in moved}
    tangents["base_color"][0] = torch.rand(144, 3, generator=gen, dtype=dtype)
    tangents["roughness"][1] = 1.0
    tangents["light_int"][1] = inten
    tangents["normal"][2] = torch.randn(144, 3, generator=gen, dtype=dtype)
    tangents["light_pos"][2, :, 1] = 1.0
    for k in moved:
        tangents[k][3] = torch.randn(tangents[k][3].shape, generator=gen, dtype=dtype)
    #                                   direction 4: nothing moves

    def res(b, r, m, nn, lp, li):
        mat = {**flat, "base_color": b, "roughness": r, "metallic": m}
        return log_residual_points(nn, pts, cam, lp, li, mat, log_obs, 0.01, any_size=True)

    primals = tuple({"normal": n, "light_pos": pos, "light_int": inten}.get(k, flat.get(k)) for k in moved)
    torchbrdf.set_fast_path(False)
    try:
        want_r = res(*primals)
        want = torch.stack([torch.func.jvp(res, primals, tuple(tangents[k][j] for k in moved))[1]
                            for j in range(K)])
    finally:
        torchbrdf.set_fast_path(None)
    calls = []
    direct = ops.capture_jvp
    monkeypatch.setattr(ops, "capture_jvp", lambda *a, **k: calls.append(1) or direct(*a, **k))
    tol = {"rtol": 1e-9, "atol": 1e-10} if dtype == torch.float64 else {"rtol": 2e-4, "atol": 2e-4}
    r, dr = log_residual_points_jvp(n, pts, cam, pos, inten, flat, log_obs, 0.01, tangents, any_size=True)
    assert calls == [1] and dr.shape == (K, 144, pos.shape[0], 3)
    torch.testing.assert_close(r, want_r, **tol)
    torch.testing.assert_close(dr, want, **tol)
    assert float(dr[4].abs().max()) == 0.0
    # an input that needs a gradient: the transforms (capture_jvp is not differentiable)
    needs_grad = {**flat, "specular": flat["specular"].requires_grad_()}
    r2, dr2 = log_residual_points_jvp(n, pts, cam, pos, inten, needs_grad, log_obs, 0.01, tangents,
                                      any_size=True)
    assert calls == [1]
    torch.testing.assert_close(dr2.detach(), want, **tol)
    with pytest.raises(ValueError, match="sheen"):
        log_residual_points_jvp(n, pts, cam, pos, inten, flat, log_obs, 0.01,
                                {"sheen": tangents["roughness"]})


def test_compact_renderer_is_the_library_formula_for_every_parameter():
    # The fit renders through torchbrdf.principled, so it takes every principled parameter (the
    # old hand-written diffuse + GGX copy refused them) and keeps the capture format's frame:
    # tangent from +X by Gram–Schmidt, which the anisotropic lobe depends on.
    maps = make_material("painted", seed=3, size=16)
    gen = torch.Generator().manual_seed(0)
    for name in ("subsurface", "sheen", "clearcoat", "anisotropic", "specular_tint"):
        maps[name] = torch.rand(1, 16, 16, generator=gen)
    maps["clearcoat_gloss"] = 0.7
    lights = light_layout(6)
    ref = render_capture(maps, lights, backend="principled")
    fit = render_capture(maps, lights, backend="compact")
    assert torch.allclose(fit, ref, rtol=1e-5, atol=1e-6)
    iso = render_capture({**maps, "anisotropic": 0.0}, lights, backend="compact")
    assert (iso - fit).abs().max() > 1e-3  # the frame matters: the check above is not vacuous


def test_render_follows_contract_formula_for_a_lambertian_pixel():
    # Flat, rough-free diffuse check at one pixel against the contract formula by hand.
    maps = {"base_color": torch.full((3, 2, 2), 0.5), "roughness": torch.full((1, 2, 2), 0.5),
            "specular": torch.zeros(1, 2, 2)}
    pos = torch.tensor([[0.0, 0.0, 2.0]])
    img = render_capture(maps, (pos, torch.ones(1, 3)), (0.0, 0.0, 2.0), backend="principled")
    from torchbrdf import principled

    p = torch.tensor([-0.5, 0.5, 0.0])  # pixel (0, 0) of a 2x2 capture
    d = pos[0] - p
    l = d / d.norm()
    n = torch.tensor([0.0, 0.0, 1.0])
    f = principled(l[None], l[None], n[None], base_color=torch.full((1, 3), 0.5), roughness=0.5, specular=0.0)
    want = f[0] * l[2] / (d @ d)
    assert torch.allclose(img[0, :, 0, 0], want, rtol=1e-5)


def test_lights_layouts():
    for count in (4, 8, 16, 32):
        pos, inten = light_layout(count)
        assert pos.shape == (count + 1, 3) and inten.shape == (count + 1, 3)
        assert (pos[:, 2] > 0).all()
    p1, _ = random_lights(5, seed=2)
    p2, _ = random_lights(5, seed=2)
    assert torch.equal(p1, p2) and (p1[:, 2] > 0).all()


def test_generate_capture_roundtrip_and_determinism(tmp_path):
    a = generate_capture(tmp_path / "a", recipe="circuit", seed=5, size=16, lights=4, noise=0.01)
    generate_capture(tmp_path / "b", recipe="circuit", seed=5, size=16, lights=4, noise=0.01)
    cap = load_capture(a.parent)
    assert len(cap) == 5 and cap.width == 16
    capb = load_capture(tmp_path / "b")
    assert torch.equal(cap.images, capb.images)
    for name, ch in MAP_NAMES.items():
        assert read_exr(tmp_path / "a" / "gt" / f"{name}.exr").shape == (ch, 16, 16)
    meta = json.loads(a.read_text())
    assert meta["camera"]["position"] == [0.0, 0.0, 3.0]
    # noise is relative ~1 %
    clean = render_capture(make_material("circuit", 5, 16), cap, backend="principled")
    rel = ((cap.images - clean) / clean.clamp(min=1e-3)).std()
    assert 0.005 < rel < 0.02


@pytest.mark.parametrize("fast", [False, True])
def test_fit_residual_refuses_mixed_dtypes(fast):
    # The fused kernels read every input's memory in log_obs's dtype: a float32 `points` beside a
    # float64 `log_obs` was misread (residuals ~1e19), so a mismatch is an error naming the argument.
    import torchbrdf
    from torchbrdf.capture.synthetic import log_residual_points, pixel_points

    pos, inten = light_layout(4)
    P, L = 16, pos.shape[0]
    n = torch.zeros(P, 3)
    n[:, 2] = 1.0
    pts = pixel_points(4, 4).reshape(-1, 3)
    cam = torch.as_tensor(DEFAULT_CAMERA, dtype=torch.float32)
    params = {"base_color": torch.full((P, 3), 0.5), "roughness": torch.full((P, 1), 0.4)}
    log_obs = torch.zeros(P, L, 3, dtype=torch.float64)
    torchbrdf.set_fast_path(fast)
    try:
        with pytest.raises(TypeError, match="normal"):
            log_residual_points(n, pts, cam, pos.float(), inten.float(), params, log_obs, 0.01)
    finally:
        torchbrdf.set_fast_path(None)


def test_fused_kernel_refuses_mixed_dtypes():
    # The internal invariant behind every fused entry point: one dtype for all inputs.
    from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS, active_lobes
    from torchbrdf.kernels.ops import capture_fast

    P, L = 4, 3
    c = {**PRINCIPLED_DEFAULTS, "pos": torch.zeros(P, 1, 3), "n": torch.zeros(P, 1, 3), "camera": torch.ones(3),
         "light_pos": torch.ones(1, L, 3), "light_int": torch.ones(1, L, 3),
         "log_obs": torch.zeros(P, L, 3, dtype=torch.float64), "eps": 0.01, "base_color": 0.5}
    with pytest.raises(TypeError, match="log_obs"):
        capture_fast(c, active_lobes(PRINCIPLED_DEFAULTS), False, False)
