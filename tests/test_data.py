"""torchbrdf.data: deterministic samples per seed and worker, consistent symmetries, the renderings."""

import sys
import types

import pytest
import torch
from torch.utils.data import DataLoader

from torchbrdf.capture.synthetic import DEFAULT_CAMERA, MAP_NAMES, light_layout, make_material, render_capture
from torchbrdf.data import (
    SYMMETRIES,
    FamilySource,
    MaterialDataset,
    MaterialStream,
    RecipeSource,
    transform_maps,
)


def _same(a, b):
    assert a["index"] == b["index"]
    for k in ("maps", "images", "light_positions", "light_intensities"):
        assert torch.equal(a[k], b[k]), k


def test_samples_depend_on_seed_and_index_only():
    a = MaterialDataset(length=10, size=12, seed=3, extra_lights=1)
    b = MaterialDataset(length=50, size=12, seed=3, extra_lights=1)
    _same(a[7], b[7])
    _same(a[7], a[7])
    assert not torch.equal(a[7]["images"], a[6]["images"])
    assert not torch.equal(a[7]["images"], MaterialDataset(length=10, size=12, seed=4, extra_lights=1)[7]["images"])


def test_dataloader_with_two_workers_gets_the_samples_of_one_process():
    stream = MaterialStream(length=10, size=8, seed=2, variants=2)
    one = [s for b in DataLoader(stream, batch_size=None, num_workers=0) for s in [b]]
    two = list(DataLoader(stream, batch_size=None, num_workers=2))
    assert sorted(s["index"] for s in two) == list(range(10))  # every index once, none twice
    by_index = {s["index"]: s for s in one}
    for s in two:
        _same(s, by_index[s["index"]])
    ds = MaterialDataset(length=10, size=8, seed=2, variants=2)
    _same(ds[5], by_index[5])


def test_sample_is_the_capture_rendering_of_its_material():
    ds = MaterialDataset(length=4, size=16, seed=1, variants=1, noise=0.0, source=RecipeSource(["tiles"]))
    s = ds[2]
    maps = make_material("tiles", 1 * 1_000_003 + 2, 16)
    assert torch.equal(s["maps"], torch.cat([maps[k] for k in MAP_NAMES]))
    pos, inten = light_layout(0, near_camera=True)
    torch.testing.assert_close(s["light_positions"], pos)
    torch.testing.assert_close(s["images"], render_capture(maps, (pos, torch.full((1, 3), 15.0)), DEFAULT_CAMERA))
    assert s["camera_position"].tolist() == list(DEFAULT_CAMERA)


def _lights_transformed(pos, code):
    x, y, z = pos.unbind(-1)
    if code & 1:
        x = -x
    if code & 2:
        y = -y
    if code & 4:
        x, y = -y, -x
    return torch.stack((x, y, z), -1)


@pytest.mark.parametrize("code", range(SYMMETRIES))
def test_symmetries_keep_the_normal_map_consistent(code):
    maps = make_material("stone", 3, 12)  # strong relief: a wrong normal transform changes the shading
    pos = torch.tensor([[1.2, -0.7, 2.0], [-0.4, 1.5, 1.2]])
    inten = torch.full((2, 3), 20.0)
    camera = (0.0, 0.0, 3.0)
    want = transform_maps({"img": render_capture(maps, (pos, inten), camera)[0]}, code)["img"]
    got = render_capture(transform_maps(maps, code), (_lights_transformed(pos, code), inten), camera)[0]
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)


def test_samples_render_with_the_fused_kernels_below_the_lane_threshold(monkeypatch):
    """A dataset renders sample after sample: its small renderings take the fused kernels."""
    from torchbrdf.brdf import principled as P
    from torchbrdf.kernels import c_runner

    calls = []
    real = c_runner.run_fwd
    monkeypatch.setattr(c_runner, "run_fwd", lambda plan, *a, **k: (calls.append(plan.N), real(plan, *a, **k))[1])
    ds = MaterialDataset(length=2, size=16, extra_lights=1)
    fused = ds[0]["images"]
    assert calls == [2 * 16 * 16] and 2 * 16 * 16 < P.FAST_PATH_MIN_LANES
    P.set_fast_path(False)  # the switch still wins
    try:
        eager = ds[0]["images"]
    finally:
        P.set_fast_path(None)
    assert len(calls) == 1
    torch.testing.assert_close(fused, eager, rtol=2e-6, atol=1e-7)


def test_noise_and_gamma():
    clean = MaterialDataset(length=2, size=16, noise=0.0)[0]["images"]
    noisy = MaterialDataset(length=2, size=16, noise=0.05)[0]["images"]
    rel = ((noisy - clean) / (clean.abs() + 1e-3)).std()
    assert 0.02 < float(rel) < 0.08
    g = MaterialDataset(length=2, size=16, noise=0.0, gamma=2.2)[0]["images"]
    torch.testing.assert_close(g, clean.clamp(0, 1) ** (1 / 2.2))


def test_family_source_plugs_in_lazily(monkeypatch):
    calls = []

    def make_family_material(family, seed, size):
        calls.append((family, seed, size))
        return make_material("painted", seed, size)

    fake = types.SimpleNamespace(FAMILIES=("paint", "metal"), make_family_material=make_family_material)
    monkeypatch.setitem(sys.modules, "torchbrdf.capture.families", fake)
    ds = MaterialDataset(length=4, size=8, source=FamilySource(["metal"]), variants=1)
    ds[1]
    assert calls == [("metal", 1_000_003 * 0 + 1, 8)]
    with pytest.raises(ValueError, match="subset"):
        FamilySource(["wood"])
    monkeypatch.setitem(sys.modules, "torchbrdf.capture.families", None)  # absent: a clear ImportError
    with pytest.raises(ImportError, match="RecipeSource"):
        FamilySource()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="variants"):
        MaterialDataset(variants=9)
    with pytest.raises(ValueError, match="noise"):
        MaterialDataset(noise=(0.1, 0.0))
    with pytest.raises(ValueError, match="recipes"):
        RecipeSource(["marble"])
    with pytest.raises(IndexError, match="out of range"):
        MaterialDataset(length=3, size=8)[3]
    with pytest.raises(ValueError, match="code"):
        transform_maps({}, 8)
    with pytest.raises(ValueError, match=r"MaterialStream: size must be >= 4, got 0"):
        MaterialStream(size=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_renders_on_the_gpu_when_asked():
    cpu = MaterialDataset(length=2, size=16, noise=0.0)[1]
    gpu = MaterialDataset(length=2, size=16, noise=0.0, device="cuda")[1]
    assert gpu["images"].is_cuda and gpu["maps"].is_cuda
    torch.testing.assert_close(gpu["images"].cpu(), cpu["images"], rtol=1e-4, atol=1e-6)


def test_ring_lights_without_extra_lights_is_refused():
    with pytest.raises(ValueError, match="ring_lights needs extra_lights"):
        MaterialDataset(length=2, size=8, ring_lights=True)


def test_ring_lights_are_the_capture_layout_in_a_random_order():
    ds = MaterialDataset(length=6, size=8, seed=5, extra_lights=3, ring_lights=True)
    ring, ring_inten = light_layout(3, near_camera=False)
    flash, _ = light_layout(0)
    orders = set()
    for k in range(6):
        s = ds[k]
        torch.testing.assert_close(s["light_positions"][0], flash[0])  # the flash first
        got = s["light_positions"][1:]
        match = [int((ring - p).norm(dim=-1).argmin()) for p in got]
        assert sorted(match) == [0, 1, 2]  # each ring light once, not random lights
        torch.testing.assert_close(got, ring[match])
        torch.testing.assert_close(s["light_intensities"][1:], ring_inten)  # twice the flash's, as light_layout's
        orders.add(tuple(match))
    assert len(orders) > 1  # the order changes from sample to sample
    random_ds = MaterialDataset(length=1, size=8, seed=5, extra_lights=3)
    assert not torch.allclose(random_ds[0]["light_positions"][1:].sort(0).values, ring.sort(0).values)


@pytest.mark.parametrize("kwargs, named", [
    ({"size": 16.5}, "size must be an integer, got 16.5"),
    ({"size": "64"}, "size must be an integer, got '64'"),
    ({"seed": "a"}, "seed must be an integer, got 'a'"),
    ({"length": 2.0}, "length must be an integer, got 2.0"),
    ({"extra_lights": 1.5}, "extra_lights must be an integer, got 1.5"),
])
def test_a_count_or_seed_that_is_not_an_integer_is_refused_by_name(kwargs, named):
    # size=16.5 was truncated to 16 silently, size='64' and seed='a' were a bare TypeError/ValueError
    with pytest.raises(TypeError, match="MaterialDataset: " + named):
        MaterialDataset(**{"length": 2, "size": 8, **kwargs})
    with pytest.raises(TypeError, match="MaterialStream: " + named):
        MaterialStream(**{"size": 8, **kwargs})
