"""Procedural material families: the layout of make_material, deterministic, in their ranges."""

import pytest
import torch

from torchbrdf.capture.families import DIELECTRIC_FAMILIES, FAMILIES, make_family_material
from torchbrdf.capture.synthetic import make_material

# The documented ranges (module docstring) of the dielectric families: (roughness, specular)
# over the whole sample, with grout/groove pixels of the tiles allowed up to 0.85 roughness.
RANGES = {
    "cloth": ((0.7, 0.9), (0.2, 0.45)),
    "plaster": ((0.55, 0.8), (0.4, 0.55)),
    "rubber": ((0.55, 0.75), (0.25, 0.5)),
    "raw_wood": ((0.55, 0.85), (0.2, 0.45)),
    "ceramic_tiles": ((0.15, 0.86), (0.3, 0.7)),
    "lacquer": ((0.14, 0.31), (0.4, 0.6)),
}


def test_at_least_eight_families_and_the_layout_of_make_material():
    assert len(FAMILIES) >= 8 and len(set(FAMILIES)) == len(FAMILIES)
    ref = make_material("tiles", 0, 24)
    for fam in FAMILIES:
        m = make_family_material(fam, 0, 24)
        assert sorted(m) == sorted(ref)
        for k, t in m.items():
            assert t.shape == ref[k].shape and t.dtype == torch.float32 and t.is_contiguous(), (fam, k)
            assert torch.isfinite(t).all(), (fam, k)
        n = m["normal"]
        assert torch.allclose(n.norm(dim=0), torch.ones(24, 24), atol=1e-5) and (n[2] > 0).all()
        assert m["base_color"].min() >= 0.03 and m["base_color"].max() <= 1


@pytest.mark.parametrize("fam", FAMILIES)
def test_deterministic_per_seed_and_seeds_differ(fam):
    a, b, c = (make_family_material(fam, s, 32) for s in (3, 3, 4))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a)


@pytest.mark.parametrize("fam", DIELECTRIC_FAMILIES)
def test_dielectric_families_in_their_ranges(fam):
    (r0, r1), (s0, s1) = RANGES[fam]
    for seed in range(4):
        m = make_family_material(fam, seed, 64)
        assert (m["metallic"] == 0).all()
        assert r0 <= m["roughness"].min() and m["roughness"].max() <= r1, (seed, m["roughness"].aminmax())
        assert s0 <= m["specular"].min() and m["specular"].max() <= s1, (seed, m["specular"].aminmax())


def test_glossy_families_glossy_and_metal_families_metal():
    tiles = make_family_material("ceramic_tiles", 1, 64)
    assert (tiles["roughness"] < 0.35).float().mean() > 0.5  # glossy faces, rough grout
    assert (tiles["roughness"] > 0.8).any()
    for fam in ("brushed_metal", "rusted_metal", "patina_copper", "mixed"):
        m = make_family_material(fam, 1, 64)["metallic"]
        assert (m > 0.95).any(), fam
    for fam in ("rusted_metal", "patina_copper", "mixed"):  # soft edges between the classes
        m = make_family_material(fam, 1, 64)["metallic"]
        assert 0.02 < ((m > 0.05) & (m < 0.95)).float().mean() < 0.3, fam
    copper = make_family_material("patina_copper", 2, 64)
    bare = copper["metallic"][0] > 0.95
    assert torch.allclose(copper["base_color"][:, bare].mean(1), torch.tensor([0.95, 0.64, 0.54]), atol=2e-3)
    patina = copper["metallic"][0] < 0.05
    assert copper["roughness"][0][patina].min() > 0.6


def test_bad_arguments_name_themselves():
    with pytest.raises(ValueError, match="unknown family 'velvet'"):
        make_family_material("velvet")
    with pytest.raises(ValueError, match="size must be >= 4"):
        make_family_material("cloth", size=2)
