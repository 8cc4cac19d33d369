"""Every model of the library renders through the one shader interface."""

import pytest
import torch

import torchbrdf
from torchbrdf.render.geometry import sphere_gbuffer
from torchbrdf.render.lights import DirectionalLight, PointLight

from tests.render.test_shading import direct_reference, rand

LIGHTS = [PointLight(torch.tensor([2.0, 1.5, 3.0]), torch.tensor([20.0, 18.0, 15.0])),
          DirectionalLight(torch.tensor([-0.3, 0.5, 0.8]), torch.tensor([1.0, 0.9, 0.8]))]


def maps_for(model: str, h: int, w: int, dtype=torch.float64):
    if model == "smits":
        return {"base_color": rand(1, 3, h, w, seed=1, dtype=dtype), "roughness": rand(1, 1, h, w, seed=2, dtype=dtype),
                "metallic": rand(1, 1, h, w, seed=3, dtype=dtype), "clear": 0.3}
    if model == "svbrdf_ggx":
        return {"diffuse_albedo": rand(1, 3, h, w, seed=1, dtype=dtype),
                "specular_albedo": rand(1, 3, h, w, seed=2, dtype=dtype, lo=0.02, hi=0.5),
                "roughness": rand(1, 1, h, w, seed=3, dtype=dtype, lo=0.1, hi=0.9)}
    return {"base_color": rand(1, 3, h, w, seed=1, dtype=dtype), "roughness": rand(1, 1, h, w, seed=2, dtype=dtype)}


MODELS = {
    "principled": torchbrdf.PrincipledBRDF(),
    "smits": torchbrdf.SmitsBRDF(),
    "svbrdf_ggx": torchbrdf.SVBRDFGGX(),
    "lambert": torchbrdf.LambertBRDF(),
}


@pytest.mark.parametrize("model", list(MODELS))
def test_model_renders_through_shade_like_direct_evaluation(model):
    g = sphere_gbuffer(10, 12, material=maps_for(model, 10, 12), dtype=torch.float64)
    img = torchbrdf.shade(g, LIGHTS, brdf=MODELS[model])
    ref = direct_reference(g, LIGHTS, brdf=MODELS[model])
    assert img.shape == (1, 3, 10, 12)
    assert float(img.abs().max()) > 0
    torch.testing.assert_close(img, ref, rtol=1e-9, atol=1e-12)


def test_measured_brdf_renders_through_shade():
    merl = torchbrdf.MERLBRDF.from_brdf(torchbrdf.lambert, base_color=torch.tensor([0.5, 0.25, 0.125]))
    g = sphere_gbuffer(8, 8, material={}, dtype=torch.float64)
    img = torchbrdf.shade(g, LIGHTS[1:], brdf=merl)
    lam = sphere_gbuffer(8, 8, material={"base_color": torch.tensor([0.5, 0.25, 0.125], dtype=torch.float64)
                                         .view(1, 3, 1, 1).expand(1, 3, 8, 8)}, dtype=torch.float64)
    expect = torchbrdf.shade(lam, LIGHTS[1:], brdf=torchbrdf.LambertBRDF())
    torch.testing.assert_close(img, expect, rtol=2e-2, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32])
@pytest.mark.parametrize("model", ["principled", "smits", "svbrdf_ggx"])
def test_shade_half_precision_finite_values_and_gradients(model, dtype):
    mat = {k: (m.to(dtype).requires_grad_() if torch.is_tensor(m) else m) for k, m in maps_for(model, 6, 6).items()}
    g = sphere_gbuffer(6, 6, material=mat, dtype=dtype)
    img = torchbrdf.shade(g, LIGHTS, brdf=MODELS[model])
    assert img.dtype == dtype and torch.isfinite(img).all()
    img.float().sum().backward()
    for m in mat.values():
        if torch.is_tensor(m):
            assert torch.isfinite(m.grad).all()
