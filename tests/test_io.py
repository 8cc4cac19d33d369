"""torchbrdf.io: EXR round trips, PNG output, atomic writes, error messages."""

import os

import numpy as np
import pytest
import torch
from skimage import io as skio

from torchbrdf.io import atomic_path, read_exr, to_display, write_exr, write_png


def _hdr(c, h=5, w=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    # HDR range with highlights above 50 and a few small negatives, as captures have.
    return torch.rand(c, h, w, generator=g) * 60.0 - 0.05


# --------------------------------------------------------------------------------------
# EXR
# --------------------------------------------------------------------------------------


def test_exr_rgb_round_trip_exact(tmp_path):
    img = _hdr(3)
    p = tmp_path / "rgb.exr"
    write_exr(p, img)
    back, names = read_exr(p, return_names=True)
    assert names == ["R", "G", "B"]
    assert back.dtype == torch.float32 and back.shape == (3, 5, 7)
    assert torch.equal(back, img)  # float32 storage is lossless


def test_exr_batched_input_and_channel_order(tmp_path):
    # Distinct constant planes show that R, G, B land in the right channels.
    img = torch.stack([torch.full((4, 6), v) for v in (1.0, 2.0, 3.0)])[None]
    p = tmp_path / "b.exr"
    write_exr(p, img)
    back = read_exr(p)
    assert back.shape == (3, 4, 6)
    assert back[:, 0, 0].tolist() == [1.0, 2.0, 3.0]
    # Selecting and reordering channels.
    assert read_exr(p, channels=("B", "R"))[:, 0, 0].tolist() == [3.0, 1.0]


def test_exr_single_channel_is_y(tmp_path):
    img = _hdr(1)
    p = tmp_path / "rough.exr"
    write_exr(p, img)
    back, names = read_exr(p, return_names=True)
    assert names == ["Y"] and torch.equal(back, img)


def test_exr_half(tmp_path):
    img = _hdr(3)
    img[0, 0, 0] = 1e6  # beyond the half range: saturates instead of becoming inf
    p = tmp_path / "half.exr"
    write_exr(p, img, half=True)
    back = read_exr(p)
    assert back.dtype == torch.float32
    assert back[0, 0, 0] == 65504.0
    rest = torch.ones_like(img, dtype=torch.bool)
    rest[0, 0, 0] = False
    torch.testing.assert_close(back[rest], img[rest], rtol=1e-3, atol=1e-4)
    full = tmp_path / "full.exr"
    write_exr(full, img, compression="none")
    write_exr(p, img, half=True, compression="none")
    assert p.stat().st_size < full.stat().st_size  # really stored as 16-bit


def test_exr_custom_channels_dtype_device(tmp_path, device):
    img = _hdr(2).to(device=device, dtype=torch.float64).requires_grad_()
    p = tmp_path / "uv.exr"
    write_exr(p, img, channels=["U", "V"])
    back, names = read_exr(p, return_names=True, dtype=torch.float64, device=device)
    assert names == ["U", "V"] and back.dtype == torch.float64 and back.device.type == device.type
    torch.testing.assert_close(back, img.detach().float().double())


def test_exr_rgba_order(tmp_path):
    img = torch.stack([torch.full((2, 2), v) for v in (0.1, 0.2, 0.3, 1.0)])
    p = tmp_path / "rgba.exr"
    write_exr(p, img)
    back, names = read_exr(p, return_names=True)
    assert names == ["R", "G", "B", "A"]
    torch.testing.assert_close(back[:, 0, 0], torch.tensor([0.1, 0.2, 0.3, 1.0]))


def test_exr_overwrite_is_atomic_and_leaves_no_temp_files(tmp_path):
    p = tmp_path / "img.exr"
    write_exr(p, torch.zeros(3, 4, 4))
    write_exr(p, torch.ones(3, 4, 4))
    assert os.listdir(tmp_path) == ["img.exr"]
    assert torch.equal(read_exr(p), torch.ones(3, 4, 4))


def test_failed_write_keeps_old_file_and_no_temp(tmp_path):
    p = tmp_path / "keep.exr"
    write_exr(p, torch.zeros(3, 2, 2))
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("crash mid-write")
    assert os.listdir(tmp_path) == ["keep.exr"]
    assert torch.equal(read_exr(p), torch.zeros(3, 2, 2))


def test_atomic_path_keeps_suffix_and_same_folder(tmp_path):
    with atomic_path(tmp_path / "a.png") as tmp:
        assert tmp.parent == tmp_path and tmp.name.endswith(".png") and tmp.exists()
        tmp.write_bytes(b"x")
    assert (tmp_path / "a.png").read_bytes() == b"x"
    assert os.listdir(tmp_path) == ["a.png"]


@pytest.mark.parametrize(
    "image, kwargs, match",
    [
        (torch.zeros(2, 3, 4, 4), {}, "B = 1"),
        (torch.zeros(4, 4), {}, r"\(C, H, W\)"),
        (torch.zeros(2, 4, 4), {}, "no default channel names for 2"),
        (torch.zeros(3, 4, 4), {"channels": ["R", "G"]}, "2 names"),
        (torch.zeros(2, 4, 4), {"channels": ["R", "R"]}, "unique"),
        (torch.zeros(3, 4, 4), {"compression": "zstd9"}, "compression"),
        (torch.zeros(3, 0, 4), {}, "empty"),
    ],
)
def test_write_exr_errors_name_the_file(tmp_path, image, kwargs, match):
    p = tmp_path / "bad.exr"
    with pytest.raises(ValueError, match=match) as e:
        write_exr(p, image, **kwargs)
    assert "bad.exr" in str(e.value)
    assert os.listdir(tmp_path) == []


def test_write_into_missing_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        write_exr(tmp_path / "nope" / "a.exr", torch.zeros(3, 2, 2))


def test_read_exr_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr(tmp_path / "missing.exr")
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"this is not an EXR file")
    with pytest.raises(ValueError, match="junk.exr.*not an OpenEXR"):
        read_exr(junk)
    good = tmp_path / "y.exr"
    write_exr(good, torch.zeros(1, 2, 2))
    with pytest.raises(ValueError, match=r"y.exr.*no channel\(s\) \['R', 'G', 'B'\]; it has \['Y'\]"):
        read_exr(good, channels=("R", "G", "B"))


def test_read_truncated_exr(tmp_path):
    p = tmp_path / "cut.exr"
    write_exr(p, _hdr(3, 32, 32), compression="none")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cut.exr"):
        read_exr(p)


def test_truncated_exr_prints_nothing_and_its_error_carries_the_library_text(tmp_path, capfd):
    """OpenEXR prints its own lines about a damaged file; they belong in the one error, not on the terminal."""
    p = tmp_path / "cut.exr"
    write_exr(p, _hdr(3, 64, 64))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    with pytest.raises(ValueError, match=r"cut\.exr.*\(OpenEXR: .*\)") as e:
        read_exr(p)
    assert "\n" not in str(e.value)
    printed = capfd.readouterr()
    assert printed.out == "" and printed.err == ""


# --------------------------------------------------------------------------------------
# Display and PNG
# --------------------------------------------------------------------------------------


def test_to_display_srgb_matches_formula():
    x = torch.tensor([0.0, 0.001, 0.0031308, 0.18, 0.5, 1.0, 2.0]).view(1, 7, 1).expand(3, 7, 1)
    out = to_display(x)
    lin = x.clamp(0, 1)
    ref = torch.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    torch.testing.assert_close(out, ref, atol=1e-6, rtol=0)


def test_to_display_exposure_tonemaps_and_range():
    x = torch.tensor([0.0, 0.25, 1.0, 10.0, 1e4, float("nan"), -0.1]).view(1, 1, 7)
    torch.testing.assert_close(to_display(x, exposure=1.0, srgb=False), to_display(2 * x, srgb=False))
    reinhard = to_display(x, tonemap="reinhard", srgb=False).flatten()
    torch.testing.assert_close(reinhard[:4], torch.tensor([0.0, 0.2, 0.5, 10 / 11]))
    for tm in (None, "clip", "reinhard", "aces"):
        y = to_display(x, tonemap=tm)
        assert torch.isfinite(y).all() and y.min() >= 0 and y.max() <= 1
        assert y.flatten()[5] == 0 and y.flatten()[6] == 0  # NaN and negative noise show black
    aces = to_display(x, tonemap="aces", srgb=False).flatten()
    assert (aces[1:5].diff() > 0).all()  # monotone
    with pytest.raises(ValueError, match="tonemap"):
        to_display(x, tonemap="drago")


def test_to_display_keeps_dtype_and_gradient():
    x = torch.rand(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    y = to_display(x, tonemap="reinhard")
    assert y.dtype == torch.float64
    y.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert to_display(x.detach().half()).dtype == torch.float16


def test_write_png_rgb(tmp_path):
    img = torch.tensor([0.0, 0.18, 1.0, 5.0]).view(1, 1, 4).expand(3, 2, 4).clone()
    p = tmp_path / "rgb.png"
    write_png(p, img)
    px = skio.imread(p)
    assert px.shape == (2, 4, 3) and px.dtype == np.uint8
    assert px[0, :, 0].tolist() == [0, 118, 255, 255]  # sRGB(0.18) = 0.4614 -> 118
    write_png(p, img, srgb=False)
    assert skio.imread(p)[0, :, 0].tolist() == [0, 46, 255, 255]
    write_png(p, img, tonemap="reinhard", exposure=-1.0)
    assert skio.imread(p)[0, 3, 0] < 255  # highlights no longer clip
    assert os.listdir(tmp_path) == ["rgb.png"]


def test_write_png_grey_and_batched(tmp_path):
    p = tmp_path / "grey.png"
    write_png(p, torch.full((1, 1, 3, 5), 0.5), srgb=False)
    px = skio.imread(p)
    assert px.shape == (3, 5) and (px == 128).all()


def test_write_png_errors(tmp_path):
    with pytest.raises(ValueError, match=r"bad.png.*\(C, H, W\).*got shape \(2, 4, 4\)"):
        write_png(tmp_path / "bad.png", torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match="tonemap"):
        write_png(tmp_path / "bad.png", torch.zeros(3, 4, 4), tonemap="nope")
    with pytest.raises(FileNotFoundError, match="missing"):
        write_png(tmp_path / "missing" / "a.png", torch.zeros(3, 4, 4))
    assert os.listdir(tmp_path) == []


def test_read_exr_on_a_directory_or_missing_path_says_which(tmp_path):
    folder = tmp_path / "maps.exr"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match=r"maps\.exr' is a directory, not a file"):
        read_exr(folder)
    with pytest.raises(FileNotFoundError, match=r"missing\.exr' not found"):
        read_exr(tmp_path / "missing.exr")
    dangling = tmp_path / "dangling.exr"
    dangling.symlink_to(tmp_path / "gone.exr")
    with pytest.raises(FileNotFoundError, match=r"dangling\.exr' not found"):
        read_exr(dangling)


def test_a_destination_that_is_a_folder_is_named_before_any_temporary_file(tmp_path):
    # writing to a folder's path made a temporary file beside it, then failed in os.replace
    # with the temporary name in the message
    (tmp_path / "maps").mkdir()
    with pytest.raises(IsADirectoryError, match=f"cannot write '{tmp_path / 'maps'}': it is a folder"):
        write_png(tmp_path / "maps", torch.ones(3, 4, 4))
    with pytest.raises(IsADirectoryError, match="it is a folder"):
        write_exr(tmp_path / "maps", torch.ones(3, 4, 4))
    assert [p.name for p in tmp_path.iterdir()] == ["maps"]
