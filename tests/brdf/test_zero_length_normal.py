"""A zero-length shading normal: f = 0 with finite gradients in every lobe, dtype and backend.

The NDF's denominator α² (n·h)² + |n × h|² vanishes when n does; the masked lane must not
carry an inf whose backward turns into NaN (docs/numerics.md, "zero-length vectors").
"""

import pytest
import torch

import torchbrdf
from torchbrdf._checks import validation


@pytest.mark.parametrize("backend", ["eager", "cpu"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
@pytest.mark.parametrize("anisotropic, with_frame", [(None, False), (0.5, True), (0.5, False)])  # None: isotropic
def test_zero_length_normal_gives_zero_and_finite_gradients(backend, dtype, anisotropic, with_frame):
    previous = torchbrdf.get_backend()
    torchbrdf.set_backend(backend)
    try:
        l = torch.tensor([0.3, 0.2, 0.9], dtype=torch.float64)
        v = torch.tensor([-0.2, 0.1, 0.95], dtype=torch.float64)
        l, v = (l / l.norm()).to(dtype).requires_grad_(), (v / v.norm()).to(dtype).requires_grad_()
        n = torch.zeros(3, dtype=dtype, requires_grad=True)
        x = torch.tensor([1.0, 0.0, 0.0], dtype=dtype) if with_frame else None
        y = torch.tensor([0.0, 1.0, 0.0], dtype=dtype) if with_frame else None
        roughness = torch.tensor([0.3], dtype=dtype, requires_grad=True)
        inputs = [l, v, n, roughness]
        lobe = {}
        if anisotropic is not None:
            lobe["anisotropic"] = torch.tensor([anisotropic], dtype=dtype, requires_grad=True)
            inputs.append(lobe["anisotropic"])
        with validation(True):
            f = torchbrdf.principled(l, v, n, x, y, base_color=torch.full((3,), 0.5, dtype=dtype), metallic=1.0,
                                     roughness=roughness, **lobe)
        grads = torch.autograd.grad(f.sum(), inputs)
    finally:
        torchbrdf.set_backend(previous)
    assert (f == 0).all()
    for name, g in zip(("l", "v", "n", "roughness", "anisotropic"), grads):
        assert torch.isfinite(g).all(), f"non-finite gradient for {name}: {g}"
