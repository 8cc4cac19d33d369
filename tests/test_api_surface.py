"""The public names fixed by the contract stay importable with their argument order."""

import inspect

import torch

import torchbrdf


def test_contract_names_and_signature():
    ps = list(inspect.signature(torchbrdf.principled).parameters)
    assert ps[:5] == ["l", "v", "n", "x", "y"]
    for name in ["base_color", "metallic", "subsurface", "specular", "roughness", "specular_tint",
                 "anisotropic", "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss"]:
        assert name in ps
    defaults = {k: p.default for k, p in inspect.signature(torchbrdf.principled).parameters.items()}
    assert defaults["specular"] == 0.5 and defaults["sheen_tint"] == 0.5 and defaults["clearcoat_gloss"] == 1.0
    assert issubclass(torchbrdf.PrincipledBRDF, torch.nn.Module)


def test_all_names_exist():
    for name in torchbrdf.__all__:
        assert hasattr(torchbrdf, name), name


def test_contract_shading_names():
    import inspect

    for name in ["GBuffer", "shade", "PointLight", "DirectionalLight", "EnvironmentLight"]:
        assert name in torchbrdf.__all__, name
    ps = list(inspect.signature(torchbrdf.GBuffer).parameters)
    assert ps[:6] == ["position", "normal", "camera_position", "material", "tangent", "mask"]
    assert list(inspect.signature(torchbrdf.shade).parameters)[:2] == ["gbuf", "lights"]


def test_contract_point_light_matches_formula():
    # Contract §5: radiance = f(l, v) I max(n·l, 0) / |q - P|², v = normalize(C - P).
    import torch

    P = torch.tensor([0.1, -0.2, 0.0], dtype=torch.float64).view(1, 3, 1, 1)
    N = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
    C = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    q = torch.tensor([0.5, 0.3, 2.0], dtype=torch.float64)
    I = torch.tensor([10.0, 8.0, 6.0], dtype=torch.float64)
    mat = {"base_color": torch.tensor([0.6, 0.4, 0.2], dtype=torch.float64).view(1, 3, 1, 1), "roughness": 0.4}
    img = torchbrdf.shade(torchbrdf.GBuffer(position=P, normal=N, camera_position=C, material=mat),
                          [torchbrdf.PointLight(q, I)])
    p, n = P.view(3), N.view(3)
    d = q - p
    l, v = d / d.norm(), (C - p) / (C - p).norm()
    f = torchbrdf.principled(l, v, n, base_color=mat["base_color"].view(3), roughness=0.4)
    expect = f * I * torch.clamp(l @ n, min=0) / (d @ d)
    torch.testing.assert_close(img.view(3), expect, rtol=1e-10, atol=0)


def test_import_does_not_load_the_compiler_stack():
    """``import torchbrdf`` leaves ``torch._dynamo`` (1.6 s) to users who compile."""
    import subprocess
    import sys

    code = "import sys, torchbrdf, torchbrdf.recovery.svbrdf; print('torch._dynamo' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_the_constant_result_mark_is_torchs_own():
    """The functions run once while tracing are marked the way torch.compiler marks a function."""
    from torchbrdf.brdf import principled as P

    def probe():
        return 0

    from torchbrdf.render import passes, prepare

    marked = torch.compiler.assume_constant_result(probe)
    flags = {k for k in vars(marked) if k.startswith("_dynamo")}
    for fn in (P._resolve_backend, passes._dynamic_shapes_config, prepare._material_names):
        assert flags and flags <= set(vars(fn)), (fn.__name__, flags)
