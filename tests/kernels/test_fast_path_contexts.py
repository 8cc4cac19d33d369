"""The ways a training loop calls the BRDF and the shader keep the fused kernels: autocast,
no_grad, inference_mode, nn.Parameter inputs, channel-last views of BCHW maps."""

import contextlib

import pytest
import torch

import torchbrdf
from torchbrdf.kernels import c_runner, shade_ops
from torchbrdf.render.geometry import sphere_gbuffer

SIZE = 96  # 9216 pixels: above the automatic threshold


def _spy(monkeypatch, module, name):
    calls = []
    real = getattr(module, name)
    monkeypatch.setattr(module, name, lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    return calls


CONTEXTS = {
    "autocast_bf16": lambda: torch.autocast("cpu", dtype=torch.bfloat16),
    "no_grad": torch.no_grad,
    "inference_mode": torch.inference_mode,
    "plain": contextlib.nullcontext,
}


def _maps():
    """A network's outputs: (1, 6, H, W) maps and a unit normal map."""
    g = torch.Generator().manual_seed(0)
    maps = torch.rand(1, 6, SIZE, SIZE, generator=g)
    normal = torch.nn.functional.normalize(torch.randn(1, 3, SIZE, SIZE, generator=g)
                                           + torch.tensor([0.0, 0.0, 3.0]).view(1, 3, 1, 1), dim=1)
    return maps, normal


@pytest.mark.parametrize("context", list(CONTEXTS))
def test_principled_on_channel_last_views_stays_fused(context, monkeypatch):
    maps, normal = _maps()
    rough = torch.nn.Parameter(torch.tensor([0.4]))
    l = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0]), dim=0).expand(1, SIZE, SIZE, 3)
    fwd = _spy(monkeypatch, c_runner, "run_fwd")
    with CONTEXTS[context]():
        out = torchbrdf.principled(l, l, normal.permute(0, 2, 3, 1), base_color=maps[:, :3].permute(0, 2, 3, 1),
                                   roughness=rough, metallic=maps[:, 3:4].permute(0, 2, 3, 1))
    assert len(fwd) == 1
    torchbrdf.set_fast_path(False)
    try:
        eager = torchbrdf.principled(l, l, normal.permute(0, 2, 3, 1), base_color=maps[:, :3].permute(0, 2, 3, 1),
                                     roughness=rough.detach(), metallic=maps[:, 3:4].permute(0, 2, 3, 1))
    finally:
        torchbrdf.set_fast_path(None)
    torch.testing.assert_close(out.float(), eager, rtol=2e-6, atol=1e-7)


@pytest.mark.parametrize("context", list(CONTEXTS))
def test_shade_keeps_the_light_loop_kernel(context, monkeypatch):
    maps, _ = _maps()
    gb = sphere_gbuffer(SIZE, SIZE)
    gbuf = torchbrdf.GBuffer(position=gb.position, normal=gb.normal, camera_position=gb.camera_position,
                             material={"base_color": maps[:, :3], "roughness": maps[:, 3:4]}, mask=gb.mask)
    lights = [torchbrdf.PointLight([0.0, 0.0, 4.0], 16.0), torchbrdf.DirectionalLight([0.0, 0.6, 0.8], 2.0)]
    fwd = _spy(monkeypatch, shade_ops, "_run_fwd")
    with CONTEXTS[context]():
        torchbrdf.shade(gbuf, lights, torchbrdf.PrincipledBRDF())
    assert len(fwd) == 1
