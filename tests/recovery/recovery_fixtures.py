"""Shared fixtures and helpers of the recovery driver's tests: a tiny capture, a completed
run, a stopped run, and checks on output folders and one-line errors."""

import hashlib
import math
import shutil

import pytest
import torch

from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.recovery.levels import LevelData
from torchbrdf.recovery.params import encode
from torchbrdf.recovery import recover
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.svbrdf import CHECKPOINT, main

#: A recovery small enough for CI: 4 iterations, one thread, no progress output, seed 0.
FAST = ["--iters", "4", "--threads", "1", "--quiet", "--seed", "0"]


@pytest.fixture(scope="module")
def cap(tmp_path_factory):
    """A 16 px capture, 6 lights and the flash, with metal inlays."""
    folder = tmp_path_factory.mktemp("cap16")
    generate_capture(folder, recipe="metal_inlay", seed=2, size=16, lights=6, noise=0.01)
    return folder


@pytest.fixture(scope="module")
def done(cap, tmp_path_factory):
    """A completed run (CLI, FAST settings)."""
    out = tmp_path_factory.mktemp("done") / "out"
    assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 0
    return out


@pytest.fixture(scope="module")
def stopped(cap, tmp_path_factory):
    """A run stopped by SIGTERM after one iteration (checkpoint + partial outputs)."""
    out = tmp_path_factory.mktemp("stopped") / "out"
    res = recover(cap, Settings(iters=4, threads=1, signal_at=1), out, progress=False)
    assert not res.report["completed"] and (out / CHECKPOINT).is_file()
    return out


def file_hashes(folder):
    """``{name: SHA-256}`` of the files directly in ``folder``."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def copy_out(src, tmp_path):
    """A copy of the output folder ``src`` at ``tmp_path / "out"``."""
    dst = tmp_path / "out"
    shutil.copytree(src, dst)
    return dst


def one_line_error(capsys):
    """The captured stderr, checked to be one ``error: ...`` line without a traceback."""
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    return err


def flat_level(size=16, lights=8, normal_tilt_deg=0.0):
    """A LevelData of a uniform glossy dielectric (or a tilted normal everywhere)."""
    from torchbrdf.capture.format import Capture
    from torchbrdf.capture.synthetic import light_layout, render_capture

    n = torch.tensor([math.sin(math.radians(normal_tilt_deg)), 0.0, math.cos(math.radians(normal_tilt_deg))])
    maps = {"base_color": torch.tensor([0.5, 0.3, 0.2])[:, None, None].expand(3, size, size),
            "roughness": torch.full((1, size, size), 0.3), "metallic": torch.zeros(1, size, size),
            "specular": torch.full((1, size, size), 0.5), "normal": n[:, None, None].expand(3, size, size)}
    pos, inten = light_layout(lights)
    imgs = render_capture(maps, (pos, inten), backend="compact")
    cap = Capture(images=imgs, light_positions=pos, light_intensities=inten,
                  camera_position=torch.tensor([0.0, 0.0, 3.0]), width=size, height=size,
                  files=tuple(f"{k}.exr" for k in range(len(pos))))
    data = LevelData(cap, size, list(range(len(pos))), float(0.01 * imgs.mean()))
    p = {k: v.reshape(v.shape[0], -1).T.contiguous() for k, v in maps.items()}
    metal = p.pop("metallic")
    return data, encode(p), metal


def recovery_at_polish(capture, cfg):
    """A :class:`Recovery` of ``capture`` run up to the start of its polish stage, and that stage's index."""
    from torchbrdf.capture.format import load_capture
    from torchbrdf.recovery.engine import Recovery

    rec = Recovery(load_capture(capture), cfg, log=lambda m: None)
    polish = next(i for i, (_, k, _) in enumerate(rec.plan) if k == "polish")
    with torch.no_grad():
        rec.init_state()
        while rec.state["stage"] < polish:
            rec.tick()
    return rec, polish
