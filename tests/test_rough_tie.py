"""The glossy/rough tie of dielectrics (issue 18's wider held-out check): ``rough_basin_tie``.

A rough dielectric whose fit landed in the glossy basin is moved to the rough one; a glossy
dielectric whose highlight the images show stays glossy.
"""

import pytest
import torch

from torchbrdf.capture.format import load_capture, write_capture
from torchbrdf.capture.synthetic import light_layout, normals_from_height, render_capture
from torchbrdf.recovery.solver import LevelData, decode, encode, rough_basin_tie
from torchbrdf.recovery.svbrdf import RecoveryConfig, RecoveryError, check_config


def _maps(size: int, left: float, right: float, specular: float = 0.5) -> dict:
    """A flat dielectric, roughness ``left`` in the left half and ``right`` in the right half."""
    rough = torch.full((1, size, size), left)
    rough[..., size // 2:] = right
    return {"base_color": torch.tensor([0.5, 0.45, 0.4])[:, None, None] * torch.ones(1, size, size),
            "roughness": rough, "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), specular),
            "normal": normals_from_height(torch.zeros(size, size))}


def test_a_glossy_fit_of_a_rough_dielectric_moves_and_a_seen_highlight_stays(tmp_path):
    """A rough fit that landed glossy moves to the rough basin; a seen highlight stays glossy.

    Left: roughness 0.9, started glossy (0.05), as a dust speck the coarse levels sent there;
    right: truly glossy (0.06). The left half is moved to the rough basin; a right-half pixel
    whose images show its highlight (a light at least 30 % brighter than without the specular
    lobe) stays glossy, and there are such pixels; a row started at roughness 0.3 (not at the
    glossy end) is not tested. Fails with the tie off or inverted, with a rule that moves every
    glossy pixel, or without the rough side's refit of the other unknowns (base colour and
    specular take up the difference between the basins).
    """
    size = 16
    truth = _maps(size, 0.9, 0.06)
    pos, inten = light_layout(12)
    with torch.no_grad():
        img = render_capture(truth, (pos, inten), noise=0.01, seed=4)
        diffuse_only = render_capture(_maps(size, 0.9, 0.06, specular=0.0), (pos, inten))
    write_capture(tmp_path, img, (pos, inten), torch.tensor([0.0, 0.0, 3.0]))
    cap = load_capture(tmp_path)
    data = LevelData(cap, size, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))

    def flat(x):
        return x.reshape(x.shape[0], -1).T

    start = dict(truth)
    start["roughness"] = torch.full_like(truth["roughness"], 0.05)  # the glossy basin
    start["roughness"][..., size // 2:] = 0.06
    start["roughness"][:, 0, : size // 2] = 0.3  # above the glossy end: left alone
    theta = encode({k: flat(start[k]) for k in ("base_color", "specular", "roughness", "normal")})
    metal = torch.zeros(size * size, 1)
    with torch.no_grad():
        out, moved = rough_basin_tie(data, theta, metal, data.train_idx, "principled", 2.0)
    rough = decode(out, metal)["roughness"][:, 0].reshape(size, size)
    moved = moved.reshape(size, size)
    left = moved[1:, : size // 2]
    assert float(left.float().mean()) > 0.9 and float(rough[1:, : size // 2].median()) > 0.6
    assert not bool(moved[0, : size // 2].any())
    seen = ((img / diffuse_only.clamp(min=1e-6)).amax(dim=(0, 1)) > 1.3)[:, size // 2:]  # (S, S/2)
    assert int(seen.sum()) >= 4, "the test needs glossy pixels whose highlight is seen"
    assert not bool(moved[:, size // 2:][seen].any())
    assert torch.equal(out[~moved.reshape(-1)], theta[~moved.reshape(-1)])  # the others untouched
    # Off for metals: the same pixels called metal are not tested.
    _, none = rough_basin_tie(data, theta, torch.ones_like(metal), data.train_idx, "principled", 2.0)
    assert not bool(none.any())
    # At most max_pixels are tested, the glossiest first.
    _, few = rough_basin_tie(data, theta, metal, data.train_idx, "principled", 2.0, max_pixels=5)
    assert int(few.sum()) <= 5


def test_the_tie_settings_are_checked():
    """A NaN margin, a glossy threshold above 1 or a rough start below the roughness floor is refused."""
    for bad in ({"rough_tie": float("nan")}, {"rough_tie_glossy": 1.5}, {"rough_tie_start": 0.0}):
        with pytest.raises(RecoveryError, match=next(iter(bad))):
            check_config(RecoveryConfig(**bad))
