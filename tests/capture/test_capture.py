"""datasets.capture: contract §3 capture folders — round trip, malformed input, pixel mapping."""

import json
import os

import numpy as np
import pytest
import torch

from torchbrdf.capture import CAPTURE_JSON, Capture, load_capture, pixel_points, write_capture
from torchbrdf.capture.format import check_capture
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import write_exr

H, W, L = 6, 8, 3


def _images(seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(L, 3, H, W, generator=g) * 60.0 - 0.02  # HDR highlights, slight negative noise


def _lights():
    positions = torch.tensor([[0.5, -0.3, 2.0], [-1.0, 0.2, 1.5], [0.0, 0.0, 3.0]])
    intensities = torch.tensor([[10.0, 10.0, 10.0], [5.0, 6.0, 7.0], [0.0, 1.0, 2.0]])
    return positions, intensities


@pytest.fixture
def capture_dir(tmp_path):
    folder = tmp_path / "cap"
    write_capture(folder, _images(), _lights(), [0.0, 0.0, 3.0])
    return folder


def _edit_json(folder, edit):
    path = folder / CAPTURE_JSON
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


# --------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------


def test_round_trip(capture_dir):
    cap = load_capture(capture_dir)
    assert isinstance(cap, Capture) and len(cap) == L
    assert (cap.width, cap.height) == (W, H)
    assert cap.files == ("img_000.exr", "img_001.exr", "img_002.exr")
    assert torch.equal(cap.images, _images())  # float32 EXRs are lossless
    positions, intensities = _lights()
    assert torch.equal(cap.light_positions, positions)
    assert torch.equal(cap.light_intensities, intensities)
    assert torch.equal(cap.camera_position, torch.tensor([0.0, 0.0, 3.0]))
    assert sorted(os.listdir(capture_dir)) == sorted([CAPTURE_JSON, *cap.files])  # no temp files


def test_json_matches_contract_layout(capture_dir):
    meta = json.loads((capture_dir / CAPTURE_JSON).read_text())
    assert meta["width"] == W and meta["height"] == H
    assert meta["camera"] == {"position": [0.0, 0.0, 3.0]}
    first = meta["images"][0]
    assert first["file"] == "img_000.exr"
    assert first["light"]["type"] == "point"
    np.testing.assert_allclose(first["light"]["position"], [0.5, -0.3, 2.0], rtol=1e-7)
    assert first["light"]["intensity"] == [10.0, 10.0, 10.0]


def test_load_dtype_device(capture_dir, device):
    cap = load_capture(capture_dir, device=device, dtype=torch.float64)
    for t in (cap.images, cap.light_positions, cap.light_intensities, cap.camera_position):
        assert t.dtype == torch.float64 and t.device.type == device.type
    assert cap.to(dtype=torch.float32).images.dtype == torch.float32
    assert cap.points().shape == (H, W, 3)


@pytest.mark.parametrize(
    "lights",
    [
        "pairs",
        "mappings",
        "objects",
        "dict_of_tables",
    ],
)
def test_write_accepts_light_forms(tmp_path, lights):
    positions, intensities = _lights()
    if lights == "pairs":
        arg = [(p, i) for p, i in zip(positions, intensities)]
    elif lights == "mappings":
        arg = [
            {"type": "point", "position": p.tolist(), "intensity": i.tolist()}
            for p, i in zip(positions, intensities)
        ]
    elif lights == "objects":

        class Light:  # duck-typed like torchbrdf.PointLight
            def __init__(self, position, intensity):
                self.position, self.intensity = position, intensity

        arg = [Light(p, i) for p, i in zip(positions, intensities)]
    else:
        arg = {"position": positions.numpy(), "intensity": intensities.numpy()}
    files = ["a.exr", "b.exr", "c.exr"]
    write_capture(tmp_path, list(_images()), arg, torch.tensor([0.0, 0.0, 3.0]), files=files)
    cap = load_capture(tmp_path)
    assert cap.files == ("a.exr", "b.exr", "c.exr")
    assert torch.equal(cap.light_positions, positions) and torch.equal(cap.light_intensities, intensities)


def test_write_half(tmp_path):
    write_capture(tmp_path, _images(), _lights(), [0, 0, 3], half=True)
    cap = load_capture(tmp_path)
    torch.testing.assert_close(cap.images, _images(), rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"images": torch.zeros(L, 4, H, W)}, r"\(L, 3, H, W\)"),
        ({"images": torch.full((L, 3, H, W), float("nan"))}, "non-finite"),
        ({"lights": (torch.zeros(2, 3), torch.zeros(2, 3))}, "3 images but 2"),
        ({"lights": (torch.zeros(L, 3), -torch.ones(L, 3))}, "negative intensity"),
        ({"lights": (torch.zeros(L, 2), torch.ones(L, 3))}, "shape"),
        ({"camera_position": [0, 0]}, "camera_position"),
        ({"files": ["a.exr", "a.exr", "b.exr"]}, "distinct"),
        # a mapping with other keys was a bare KeyError naming neither the argument nor the keys
        ({"lights": {"positions": torch.ones(L, 3), "intensity": torch.ones(L, 3)}},
         r"lights must have the keys 'position' and 'intensity'; 'position' missing "
         r"\(it has \['intensity', 'positions'\]\)"),
        ({"lights": [{"position": [0, 0, 2.0], "intensity": [1.0] * 3}] * 2 + [{"position": [0, 0, 2.0]}]},
         r"lights\[2\] must have the keys 'position' and 'intensity'; 'intensity' missing"),
    ],
)
def test_write_errors(tmp_path, kwargs, match):
    args = {"images": _images(), "lights": _lights(), "camera_position": [0, 0, 3.0]}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        write_capture(tmp_path / "out", **args)
    assert not (tmp_path / "out" / CAPTURE_JSON).exists()


# --------------------------------------------------------------------------------------
# Malformed folders: every error names the file
# --------------------------------------------------------------------------------------


def test_missing_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_capture(tmp_path / "nowhere")


def test_missing_capture_json(capture_dir):
    (capture_dir / CAPTURE_JSON).unlink()
    with pytest.raises(FileNotFoundError, match=r"cap/capture\.json"):
        load_capture(capture_dir)


def test_bad_json(capture_dir):
    (capture_dir / CAPTURE_JSON).write_text('{"width": 8, "height": 6,,}')
    with pytest.raises(ValueError, match=r"capture\.json: invalid JSON at line 1, column"):
        load_capture(capture_dir)
    (capture_dir / CAPTURE_JSON).write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"capture\.json: the top level must be a JSON object"):
        load_capture(capture_dir)


def _drop(*keys):
    def edit(meta):
        obj = meta
        for k in keys[:-1]:
            obj = obj[k]
        del obj[keys[-1]]

    return edit


def _set(value, *keys):
    def edit(meta):
        obj = meta
        for k in keys[:-1]:
            obj = obj[k]
        obj[keys[-1]] = value

    return edit


@pytest.mark.parametrize(
    "edit, match",
    [
        (_drop("width"), "the capture is missing the key 'width'"),
        (_drop("camera"), "missing the key 'camera'"),
        (_drop("camera", "position"), "camera is missing the key 'position'"),
        (_drop("images"), "missing the key 'images'"),
        (_drop("images", 1, "file"), r"images\[1\] is missing the key 'file'"),
        (_drop("images", 2, "light"), r"images\[2\] is missing the key 'light'"),
        (_drop("images", 0, "light", "type"), r"images\[0\].light is missing the key 'type'"),
        (_drop("images", 0, "light", "intensity"), r"images\[0\].light is missing the key 'intensity'"),
        (_set(0, "width"), "width must be a positive integer"),
        (_set(6.5, "height"), "height must be a positive integer"),
        (_set([], "images"), "images must be a non-empty list"),
        (_set("spot", "images", 1, "light", "type"), r"images\[1\].light has unsupported type 'spot'"),
        (_set([1.0, 2.0], "images", 0, "light", "position"), r"images\[0\].light.position must be a list"),
        (_set("0 0 1", "images", 0, "light", "position"), r"images\[0\].light.position must be a list of 3"),
        (_set([0, 0, float("nan")], "images", 0, "light", "position"), "must be finite"),
        (_set([1.0, -0.5, 1.0], "images", 2, "light", "intensity"), r"images\[2\].light.intensity must be"),
        (_set([0, 0], "camera", "position"), "camera.position must be a list of 3"),
    ],
)
def test_malformed_json_entries(capture_dir, edit, match):
    _edit_json(capture_dir, edit)
    with pytest.raises(ValueError, match=match) as e:
        load_capture(capture_dir)
    assert "capture.json" in str(e.value)


def test_missing_image(capture_dir):
    (capture_dir / "img_001.exr").unlink()
    with pytest.raises(FileNotFoundError, match=r"img_001\.exr.*images\[1\].*not found"):
        load_capture(capture_dir)


def test_image_size_mismatch(capture_dir):
    write_exr(capture_dir / "img_002.exr", torch.ones(3, H, W + 1))
    with pytest.raises(ValueError, match=r"img_002\.exr: image is 9x6 .* says 8x6"):
        load_capture(capture_dir)


def test_non_finite_pixels(capture_dir):
    img = torch.ones(3, H, W)
    img[1, 2, 5] = float("inf")
    img[0, 4, 0] = float("nan")
    write_exr(capture_dir / "img_000.exr", img)
    with pytest.raises(ValueError, match=r"img_000\.exr: 2 non-finite .* row 2, column 5, channel G"):
        load_capture(capture_dir)


def test_image_not_rgb_or_not_exr(capture_dir):
    write_exr(capture_dir / "img_001.exr", torch.ones(1, H, W))
    with pytest.raises(ValueError, match=r"img_001\.exr.*no channel"):
        load_capture(capture_dir)
    (capture_dir / "img_001.exr").write_bytes(b"garbage")
    with pytest.raises(ValueError, match=r"img_001\.exr.*not an OpenEXR"):
        load_capture(capture_dir)


# --------------------------------------------------------------------------------------
# Image names stay inside the capture folder
# --------------------------------------------------------------------------------------


@pytest.fixture
def outside_exr(tmp_path):
    """A valid RGB EXR beside (outside) the capture folder."""
    path = tmp_path / "outside.exr"
    write_exr(path, torch.ones(3, H, W))
    return path


@pytest.mark.parametrize(
    "name, match",
    [
        ("ABSOLUTE", "is an absolute path"),
        ("/etc/passwd", "is an absolute path"),
        ("../outside.exr", "contains '..'"),
        ("sub/../../outside.exr", "contains '..'"),
        ("..\\outside.exr", "contains '..'"),
        ("C:\\Windows\\x.exr", "is an absolute path"),
        ("C:x.exr", "is an absolute path"),
    ],
)
def test_image_names_must_stay_inside(capture_dir, outside_exr, name, match):
    """Absolute paths and '..' were loaded (an outside EXR even successfully); now refused."""
    name = str(outside_exr) if name == "ABSOLUTE" else name
    _edit_json(capture_dir, _set(name, "images", 1, "file"))
    with pytest.raises(ValueError, match=match) as e:
        load_capture(capture_dir)
    msg = str(e.value)
    assert r"capture.json: images[1].file" in msg and repr(name) in msg


def test_image_symlink_leading_out_is_refused(capture_dir, outside_exr):
    (capture_dir / "link.exr").symlink_to(outside_exr)
    _edit_json(capture_dir, _set("link.exr", "images", 0, "file"))
    with pytest.raises(ValueError, match=r"images\[0\]\.file: image name 'link.exr' resolves to .*outside"):
        load_capture(capture_dir)
    (capture_dir / "sub").symlink_to(outside_exr.parent, target_is_directory=True)
    _edit_json(capture_dir, _set("sub/outside.exr", "images", 0, "file"))
    with pytest.raises(ValueError, match=r"'sub/outside.exr' resolves to .*outside the capture folder"):
        load_capture(capture_dir)


def test_image_symlink_inside_and_subfolders_are_fine(capture_dir):
    (capture_dir / "alias.exr").symlink_to(capture_dir / "img_000.exr")
    (capture_dir / "raw").mkdir()
    (capture_dir / "img_002.exr").rename(capture_dir / "raw" / "img_002.exr")
    _edit_json(capture_dir, _set("alias.exr", "images", 0, "file"))
    _edit_json(capture_dir, _set("./raw/img_002.exr", "images", 2, "file"))
    cap = load_capture(capture_dir)
    assert torch.equal(cap.images, _images())


@pytest.mark.parametrize("name", ["../x.exr", "/tmp/x.exr", "a/../../x.exr"])
def test_write_refuses_names_outside(tmp_path, name):
    """write_capture(files=['../x.exr']) wrote outside its folder; now refused before anything is written."""
    with pytest.raises(ValueError, match=r"write_capture: files\[1\]: image name .* (absolute|'\.\.')"):
        write_capture(tmp_path / "out", _images(), _lights(), [0, 0, 3.0], files=["a.exr", name, "c.exr"])
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "x.exr").exists()


def test_write_refuses_symlink_out(tmp_path):
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (out / "sub").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(ValueError, match=r"files\[0\]: image name 'sub/a.exr' resolves to .*outside"):
        write_capture(out, _images(), _lights(), [0, 0, 3.0], files=["sub/a.exr", "b.exr", "c.exr"])
    assert os.listdir(elsewhere) == [] and sorted(os.listdir(out)) == ["sub"]


# --------------------------------------------------------------------------------------
# Impossible captures are refused up front
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, match",
    [
        (
            lambda m: [e["light"].__setitem__("position", [0.5, 0.5, -1.0]) for e in m["images"]],
            r"capture\.json: no light is above the sample plane",
        ),
        (
            lambda m: [e["light"].__setitem__("position", [1.0, 0.0, 0.0]) for e in m["images"]],
            "no light is above the sample plane",
        ),
        (_set([0.0, 0.0, 0.0], "images", 1, "light", "intensity"), r"images\[1\]\.light\.intensity is zero"),
        (
            lambda m: [e["light"].__setitem__("intensity", [0, 0, 0]) for e in m["images"]],
            r"images\[0\]\.light\.intensity is zero",
        ),
        (_set([1.0, float("inf"), 1.0], "images", 2, "light", "intensity"), r"images\[2\]\.light\.intensity must be finite"),
        (_set([1.0, float("nan"), 1.0], "images", 0, "light", "intensity"), r"images\[0\]\.light\.intensity must be finite"),
        (_set([float("-inf"), 0.0, 1.0], "images", 0, "light", "position"), r"images\[0\]\.light\.position must be finite"),
    ],
)
def test_impossible_lights_refused(capture_dir, edit, match):
    _edit_json(capture_dir, edit)
    (capture_dir / "img_002.exr").unlink()  # refused from capture.json alone, before any image is read
    with pytest.raises(ValueError, match=match):
        load_capture(capture_dir)


def test_all_zero_image_refused(capture_dir):
    write_exr(capture_dir / "img_001.exr", torch.zeros(3, H, W))
    with pytest.raises(ValueError, match=r"img_001\.exr: every pixel is 0"):
        load_capture(capture_dir)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"lights": (torch.tensor([[0.0, 0.0, -1.0]] * L), torch.ones(L, 3))}, "no light is above the sample plane"),
        ({"lights": (torch.ones(L, 3), torch.zeros(L, 3))}, "the intensity of light 0 is zero"),
        ({"images": torch.cat((_images()[:2], torch.zeros(1, 3, H, W)))}, "image 2 is all 0"),
    ],
)
def test_write_refuses_what_load_refuses(tmp_path, kwargs, match):
    args = {"images": _images(), "lights": _lights(), "camera_position": [0, 0, 3.0], **kwargs}
    with pytest.raises(ValueError, match=match):
        write_capture(tmp_path / "out", **args)
    assert not (tmp_path / "out" / CAPTURE_JSON).exists()


def test_capture_folder_that_is_a_file(tmp_path):
    (tmp_path / "cap").write_text("not a folder")
    with pytest.raises(NotADirectoryError, match="is a file, not a folder"):
        load_capture(tmp_path / "cap")


def test_image_that_is_a_folder(capture_dir):
    (capture_dir / "img_001.exr").unlink()
    (capture_dir / "img_001.exr").mkdir()
    with pytest.raises(IsADirectoryError, match=r"img_001\.exr.*images\[1\].*is a directory"):
        load_capture(capture_dir)


# --------------------------------------------------------------------------------------
# Pixel mapping
# --------------------------------------------------------------------------------------


def test_pixel_points_contract_mapping():
    p = pixel_points(4, 2)
    assert p.shape == (2, 4, 3)
    # Row 0 is the +y edge; column 0 the -x edge; z = 0.
    torch.testing.assert_close(p[0, 0], torch.tensor([-0.75, 0.5, 0.0]))
    torch.testing.assert_close(p[1, 3], torch.tensor([0.75, -0.5, 0.0]))
    i, j = 1, 2
    torch.testing.assert_close(p[i, j], torch.tensor([-1 + (j + 0.5) * 2 / 4, 1 - (i + 0.5) * 2 / 2, 0.0]))


def test_pixel_points_symmetry_dtype_device(device):
    p = pixel_points(W, H, device=device, dtype=torch.float64)
    assert p.dtype == torch.float64 and p.device.type == device.type
    assert p[..., :2].abs().max() < 1 and (p[..., 2] == 0).all()
    torch.testing.assert_close(p[..., 0].mean(), torch.zeros((), dtype=torch.float64, device=device))
    torch.testing.assert_close(p.flip(0)[..., 1], -p[..., 1])  # rows mirror about y = 0
    assert (p[:, 1:, 0] > p[:, :-1, 0]).all() and (p[1:, :, 1] < p[:-1, :, 1]).all()
    with pytest.raises(ValueError, match="positive"):
        pixel_points(0, 4)


# --------------------------------------------------------------------------------------
# What cannot be a capture, or cannot be fitted in float32
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, match",
    [
        (_set([0.0, 0.0, -2.0], "images", 1, "light", "position"), r"light 1 is at z = -2, on or below the sample"),
        (_set([0.5, 0.5, 0.0], "images", 2, "light", "position"), r"light 2 is at z = 0, on or below"),
        (_set([0.0, 0.0, -3.0], "camera", "position"), r"camera\.position is at z = -3, on or below"),
        (_set([0.5, 0.0, 0.0], "camera", "position"), r"camera\.position is at z = 0"),
        (_set([1e39, 1.0, 1.0], "images", 0, "light", "intensity"), r"images\[0\]\.light\.intensity must lie within"),
        (_set([1e39, 0.0, 1e39], "images", 1, "light", "position"), r"images\[1\]\.light\.position must lie within"),
        (_set("img_000.exr", "images", 2, "file"), r"images\[2\]\.file 'img_000\.exr' is listed already"),
    ],
)
def test_impossible_geometry_and_float32_ranges_refused(capture_dir, edit, match):
    _edit_json(capture_dir, edit)
    with pytest.raises(ValueError, match=match):
        load_capture(capture_dir)


def test_pixel_beyond_float32_range_refused(capture_dir):
    img = _images()[1]
    img[0, 2, 3] = 3e38
    write_exr(capture_dir / "img_001.exr", img)
    with pytest.raises(ValueError, match=r"img_001\.exr: a pixel value reaches 3e\+38"):
        load_capture(capture_dir)


def test_wholly_negative_image_refused(capture_dir):
    write_exr(capture_dir / "img_001.exr", -_images()[1].abs() - 0.01)
    with pytest.raises(ValueError, match=r"img_001\.exr: no pixel is positive"):
        load_capture(capture_dir)


def test_the_same_exposure_under_two_names_refused(capture_dir):
    write_exr(capture_dir / "img_002.exr", _images()[0])
    with pytest.raises(ValueError, match=r"img_002\.exr .*the same pixels as img_000\.exr \(images\[0\]\)"):
        load_capture(capture_dir)


def test_deeply_nested_json_is_one_value_error(capture_dir):
    (capture_dir / CAPTURE_JSON).write_text("[" * 100_000)
    with pytest.raises(ValueError, match="nests lists or objects too deeply"):
        load_capture(capture_dir)


def test_fifo_image_is_not_reported_missing(capture_dir):
    (capture_dir / "img_001.exr").unlink()
    os.mkfifo(capture_dir / "img_001.exr")
    with pytest.raises(ValueError, match=r"img_001\.exr.*is not a regular file \(a FIFO"):
        load_capture(capture_dir)


def test_check_capture_warns_about_too_few_lights_and_a_degenerate_layout():
    images = _images().abs() + 0.1
    positions, intensities = _lights()
    few = Capture(images[:2], positions[:2], intensities[:2], torch.tensor([0.0, 0.0, 3.0]), W, H, ("a", "b"))
    assert "2 light(s) for 5 unknowns per pixel" in " ".join(check_capture(few))
    n = 6
    line = torch.stack([torch.linspace(-1, 1, n), torch.zeros(n), torch.full((n,), 2.0)], 1)  # one plane: y = 0
    flat = Capture(images[[0] * n], line, torch.ones(n, 3), torch.tensor([0.0, 0.0, 3.0]), W, H,
                   tuple(str(k) for k in range(n)))
    assert "span only 2 dimension(s)" in " ".join(check_capture(flat))
    spread = torch.tensor([[1.0, 0, 2], [-1, 0, 2], [0, 1, 2], [0, -1, 2], [0, 0, 3], [0.7, 0.7, 1]])
    good = Capture(images[[0] * n], spread, torch.ones(n, 3), torch.tensor([0.0, 0.0, 3.0]), W, H,
                   tuple(str(k) for k in range(n)))
    assert check_capture(good) == []


@pytest.mark.parametrize("inside", ["", "sub"])
def test_write_capture_refuses_a_folder_that_is_a_file_by_name(tmp_path, inside):
    # this was mkdir's FileExistsError/NotADirectoryError traceback (generate_capture's and
    # datasets/generate.py's too), for --out naming a file or a folder under one
    taken = tmp_path / "taken"
    taken.write_text("mine")
    folder = taken / inside if inside else taken
    with pytest.raises(ValueError, match=f"write_capture: {taken} is a file, not a folder"):
        write_capture(folder, _images(1), _lights(), [0.0, 0.0, 3.0])
    with pytest.raises(ValueError, match=f"write_capture: {taken} is a file, not a folder"):
        generate_capture(folder, recipe="tiles", size=8, lights=2)
    assert taken.read_text() == "mine"


def test_write_capture_refuses_an_existing_capture_and_overwrite_replaces_it_whole(capture_dir):
    # Writing over a capture silently replaced it and left its other images behind.
    before = {p.name: p.read_bytes() for p in capture_dir.iterdir()}
    with pytest.raises(ValueError, match=r"capture\.json already exists; pass overwrite=True"):
        write_capture(capture_dir, _images(1), _lights(), [0.0, 0.0, 3.0])
    with pytest.raises(ValueError, match=r"img_000\.exr already exists"):  # an image alone is refused too
        (capture_dir / CAPTURE_JSON).unlink()
        write_capture(capture_dir, _images(1), _lights(), [0.0, 0.0, 3.0])
    (capture_dir / CAPTURE_JSON).write_bytes(before[CAPTURE_JSON])
    assert {p.name: p.read_bytes() for p in capture_dir.iterdir()} == before
    (capture_dir / "notes.txt").write_text("mine")
    write_capture(capture_dir, _images(1)[:2], (_lights()[0][:2], _lights()[1][:2]), [0.0, 0.0, 3.0],
                  files=["a.exr", "img_001.exr"], overwrite=True)
    assert sorted(p.name for p in capture_dir.iterdir()) == ["a.exr", CAPTURE_JSON, "img_001.exr", "notes.txt"]
    cap = load_capture(capture_dir)
    assert len(cap) == 2 and torch.allclose(cap.images, _images(1)[:2], atol=1e-6)


def test_generate_capture_refuses_an_existing_capture_before_writing(tmp_path):
    from torchbrdf.capture import generate_capture
    folder = tmp_path / "cap"
    generate_capture(folder, recipe="tiles", seed=1, size=16, lights=3)
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match="overwrite=True"):
        generate_capture(folder, recipe="painted", seed=2, size=16, lights=3)
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before  # gt/ untouched too
    generate_capture(folder, recipe="painted", seed=2, size=16, lights=3, overwrite=True)
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} != before
