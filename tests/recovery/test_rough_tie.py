"""The glossy/rough ties, checked on held-out lights.

``rough_basin_tie`` runs after the class choice, ``soft_rough_tie`` in the final stage (metallic
free).

A rough dielectric (or rough, partly metal rim) whose fit landed in the glossy basin is moved to
the rough one; a glossy dielectric whose highlight the images show stays glossy.
"""

import pytest
import torch

from torchbrdf.capture.format import load_capture, write_capture
from torchbrdf.capture.synthetic import light_layout, normals_from_height, render_capture
from torchbrdf.recovery import lm, soft_metal
from torchbrdf.recovery.classes import rough_basin_tie
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.params import decode, encode
from torchbrdf.recovery.soft_metal import soft_rough_tie
from torchbrdf.recovery.svbrdf import RecoveryConfig, RecoveryError, check_config


def _maps(size: int, left: float, right: float, specular: float = 0.5) -> dict:
    """A flat dielectric, roughness ``left`` in the left half and ``right`` in the right half."""
    rough = torch.full((1, size, size), left)
    rough[..., size // 2:] = right
    return {"base_color": torch.tensor([0.5, 0.45, 0.4])[:, None, None] * torch.ones(1, size, size),
            "roughness": rough, "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), specular),
            "normal": normals_from_height(torch.zeros(size, size))}


def _flat(x):
    """``(C, S, S)`` maps as ``(S², C)`` rows."""
    return x.reshape(x.shape[0], -1).T


def _capture(tmp_path, truth: dict, left: float, right: float, seed: int):
    """``truth`` rendered under 12 ring lights with 1 % noise and written as a capture.

    Returns ``(images, the same without the specular lobe, LevelData of all lights)``; ``left``
    and ``right`` are the halves' roughness (for the diffuse-only images).
    """
    size = truth["roughness"].shape[-1]
    pos, inten = light_layout(12)
    with torch.no_grad():
        img = render_capture(truth, (pos, inten), noise=0.01, seed=seed)
        diffuse_only = render_capture(_maps(size, left, right, specular=0.0), (pos, inten))
    write_capture(tmp_path, img, (pos, inten), torch.tensor([0.0, 0.0, 3.0]))
    cap = load_capture(tmp_path)
    eps = float(0.01 * cap.images.clamp(min=0).mean())
    return img, diffuse_only, LevelData(cap, size, list(range(len(cap))), eps)


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
    img, diffuse_only, data = _capture(tmp_path, truth, 0.9, 0.06, seed=4)

    start = dict(truth)
    start["roughness"] = torch.full_like(truth["roughness"], 0.05)  # the glossy basin
    start["roughness"][..., size // 2:] = 0.06
    start["roughness"][:, 0, : size // 2] = 0.3  # above the glossy end: left alone
    theta = encode({k: _flat(start[k]) for k in ("base_color", "specular", "roughness", "normal")})
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
    """Bad tie settings are refused.

    A NaN margin, a glossy threshold above 1 (the final stage's: above ½, where no fit could stay
    rough above twice it) or a rough start below the roughness floor.
    """
    for bad in ({"rough_tie": float("nan")}, {"rough_tie_glossy": 1.5}, {"rough_tie_start": 0.0},
                {"soft_rough_tie": float("nan")}, {"soft_rough_tie_glossy": 0.5},
                {"soft_rough_tie_glossy": 0.45, "rough_tie_start": 0.85}):
        with pytest.raises(RecoveryError, match=list(bad)[-1]):
            check_config(Settings(**bad))


def test_the_final_stage_tie_moves_a_glossy_fit_of_a_rough_partly_metal_rim(tmp_path, monkeypatch):
    """``soft_rough_tie`` moves a glossy fit of a rough, partly metal region to the rough basin.

    A rough, 20 %-metal region started as a glossy dielectric (the final stage's firefly on
    dusty_metal 162) moves to a rough fit with a fractional metallic, and a rough dielectric
    started the same way to a rough fit with metallic snapped to exactly 0; a glossy dielectric
    whose highlight the images show stays; metals, pixels above the glossy threshold and pixels
    not listed are untouched. The rough side starts from the blend's coverage where known (½
    where NaN).

    Fails with the tie always taking or inverted, with metallic held at 0 on the rough side (a
    dielectric's F0 cannot reach the blend's), with the rough fit's roughness left unchecked
    (a rough start that slid back to glossy would count as moved), without the snap, or with the
    coverage ignored.
    """

    size = 16
    truth = _maps(size, 0.8, 0.06)
    truth["metallic"][..., : size // 2] = 0.2
    truth["metallic"][:, 12:, : size // 2] = 0.0  # a rough dielectric below the rim
    img, diffuse_only, data = _capture(tmp_path, truth, 0.8, 0.06, seed=5)

    start = dict(truth)
    start["roughness"] = torch.full_like(truth["roughness"], 0.08)  # the glossy basin...
    start["specular"] = torch.full_like(truth["specular"], 0.95)  # ... with a strong lobe
    start["specular"][..., size // 2:] = 0.5
    start["roughness"][..., size // 2:] = 0.06
    start["roughness"][:, 0, : size // 2] = 0.4  # above the glossy end: left alone
    theta = encode({k: _flat(start[k]) for k in ("base_color", "specular", "roughness", "normal")})
    metal = torch.zeros(size * size, 1)
    metal.view(size, size)[1, : size // 2] = 1.0  # a metal row: not tested
    rows = torch.arange(size * size)
    rows = rows[rows % size != 1]  # column 1 is not listed
    coverage = torch.full((size * size, 1), float("nan"))
    coverage.view(size, size)[2:8, : size // 2] = 0.3  # the blend known on part of the rim
    starts: list = []
    real_lm = lm.soft_lm

    def spy(jvp, cost, x, iters, **kw):
        starts.append(x.clone())
        return real_lm(jvp, cost, x, iters, **kw)

    monkeypatch.setattr(soft_metal, "soft_lm", spy)
    names = ("base_color", "specular", "roughness", "normal")
    with torch.no_grad():
        theta_true = encode({k: _flat(truth[k]) for k in names})
        r_true = data.residual(theta_true, _flat(truth["metallic"]), data.train_idx)
        sigma2 = float(r_true.pow(2).mean())  # the noise variance of one residual
        out, m_out, moved = soft_rough_tie(data, theta, metal, rows, data.train_idx, "principled",
                                           32 * sigma2, 2 * sigma2, coverage=coverage)
    tested = rows[(decode(theta[rows], metal[rows])["roughness"][:, 0] < 0.2) & (metal[rows, 0] < 1)]
    u = coverage[tested, 0]
    # One LM call holds both fits, each pixel twice: glossy (held) first, then the rough start;
    # a second call refits the pixels whose metallic was snapped, metallic held.
    n = tested.numel()
    assert len(starts) >= 1 and starts[0].shape[0] == 2 * n
    assert torch.equal(starts[0][:n], torch.cat((theta[tested], metal[tested]), -1))
    assert torch.equal(starts[0][n:, 7], torch.where(torch.isnan(u), 0.5, u))
    assert bool((u == 0.3).any()) and bool(torch.isnan(u).any())
    moved = moved.reshape(size, size)
    rough = decode(out, m_out)["roughness"][:, 0].reshape(size, size)
    mo = m_out[:, 0].reshape(size, size)
    left = torch.zeros(size, size, dtype=torch.bool)
    left[2:, : size // 2] = True
    left[:, 1] = False
    rim, below = left.clone(), left.clone()
    rim[12:], below[:12] = False, False
    assert float(moved[left].float().mean()) > 0.9 and float(rough[left].median()) > 0.6
    assert bool((rough[moved] > 0.4).all())  # every move is to the rough basin
    # the rim fractional, not a dielectric (metallic trades against base colour along a valley:
    # 0.3 here); the dielectric below it lower (0.2: the same valley)
    assert 0.05 < float(mo[rim].median()) < 0.6 and float(mo[below].median()) < float(mo[rim].median())
    assert not bool(moved[0:2, : size // 2].any()) and not bool(moved[:, 1].any())
    seen = ((img / diffuse_only.clamp(min=1e-6)).amax(dim=(0, 1)) > 1.3)[:, size // 2:]
    assert int(seen.sum()) >= 4, "the test needs glossy pixels whose highlight is seen"
    assert not bool(moved[:, size // 2:][seen].any())
    keep = ~moved.reshape(-1)
    assert torch.equal(out[keep], theta[keep]) and torch.equal(m_out[keep], metal[keep])
    # A metallic within ``snap`` of 0 or 1 is set to it (a wide snap here, so that it matters).
    with torch.no_grad():
        _, m_snap, moved_s = soft_rough_tie(data, theta, metal, rows, data.train_idx, "principled",
                                            32 * sigma2, 2 * sigma2, coverage=coverage, snap=0.3)
    ms = m_snap[moved_s, 0]
    assert bool(moved_s.any()) and bool(((ms == 0) | (ms == 1) | ((ms >= 0.3) & (ms <= 0.7))).all())
