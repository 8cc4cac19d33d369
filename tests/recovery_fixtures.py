"""Shared fixtures and helpers of the recovery driver's tests: a tiny capture, a completed
run, a stopped run, and checks on output folders and one-line errors."""

import hashlib
import shutil

import pytest

from torchbrdf.capture.synthetic import generate_capture
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
