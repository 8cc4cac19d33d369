"""The photo-derived evaluation set's forward model (training/photo_set.py)."""

import math

import pytest
import torch

from torchbrdf.capture.format import pixel_points
from training.photo_set import DEFAULT_CAMERA, render_other_model

F64 = torch.float64


def _maps(rough: float, metal: float, s: int = 4):
    g = torch.Generator().manual_seed(0)
    return {"base_color": 0.2 + 0.6 * torch.rand(3, s, s, generator=g),
            "normal": torch.nn.functional.normalize(torch.randn(3, s, s, generator=g) * 0.2
                                                    + torch.tensor([0.0, 0.0, 1.0])[:, None, None], dim=0),
            "roughness": torch.full((1, s, s), rough), "metallic": torch.full((1, s, s), metal),
            "specular": torch.full((1, s, s), 0.5)}


@pytest.mark.parametrize("rough", [0.1, 0.5, 0.9])
def test_burley_diffuse_differs_from_lambert_by_burleys_retro_factor(rough):
    """Only the diffuse lobe changes: ``burley − lambert = base/π (Fd − 1) E n·l``, with Burley's
    ``Fd = (1 + (FD90 − 1)(1 − n·l)^5)(1 + (FD90 − 1)(1 − n·v)^5)``, ``FD90 = ½ + 2 r (l·h)²``
    written out here on its own."""
    maps = _maps(rough, 0.0)
    pos = torch.tensor([[0.8, -0.5, 1.6], [-1.2, 0.3, 0.9]])
    inten = torch.tensor([[30.0, 30.0, 30.0], [10.0, 20.0, 30.0]])
    lam = render_other_model(maps, (pos, inten)).double()
    bur = render_other_model(maps, (pos, inten), diffuse="burley").double()
    s = maps["base_color"].shape[-1]
    p = pixel_points(s, s).reshape(-1, 3).double()
    n = maps["normal"].reshape(3, -1).T.double()
    base = maps["base_color"].reshape(3, -1).T.double()
    v = torch.nn.functional.normalize(torch.as_tensor(DEFAULT_CAMERA, dtype=F64) - p, dim=-1)
    for k in range(pos.shape[0]):
        dl = pos[k].double() - p
        d2 = (dl * dl).sum(-1, keepdim=True)
        l = dl / d2.sqrt()
        h = torch.nn.functional.normalize(l + v, dim=-1)
        nl, nv, lh = ((n * l).sum(-1, keepdim=True), (n * v).sum(-1, keepdim=True), (l * h).sum(-1, keepdim=True))
        fd90 = 0.5 + 2 * rough * lh**2
        fd = (1 + (fd90 - 1) * (1 - nl) ** 5) * (1 + (fd90 - 1) * (1 - nv) ** 5)
        expect = base / math.pi * (fd - 1) * inten[k].double() * nl.clamp(min=0) / d2
        got = (bur[k] - lam[k]).reshape(3, -1).T
        assert torch.allclose(got, expect, rtol=1e-4, atol=1e-6)


def test_a_metal_has_no_diffuse_in_either_model():
    maps = _maps(0.4, 1.0)
    lights = (torch.tensor([[0.8, -0.5, 1.6]]), torch.tensor([[30.0, 30.0, 30.0]]))
    assert torch.equal(render_other_model(maps, lights), render_other_model(maps, lights, diffuse="burley"))


def test_an_unknown_diffuse_is_refused():
    with pytest.raises(ValueError, match="diffuse must be 'lambert' or 'burley', got 'oren'"):
        render_other_model(_maps(0.4, 0.0), (torch.zeros(1, 3), torch.ones(1, 3)), diffuse="oren")
