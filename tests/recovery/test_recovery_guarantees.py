"""What a recovery promises about its ``--out``, its checkpoints and impossible captures.

Nothing the run did not write is moved, copied over or deleted (mount points included);
``--out`` is locked while a run uses it; a checkpoint is resumed only when its checksum,
schema and values check out; a completed run leaves no ``checkpoint.pt``; a final state
that is not finite never replaces good outputs; a capture that cannot determine the maps
is reported. Tiny captures (16 px, 4 iterations) keep this CI-sized.
"""

import contextlib
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

from torchbrdf.recovery.engine import Recovery
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.recovery import RecoveryConfig, load_outputs, recover
from torchbrdf.recovery.batch import run_batch
from torchbrdf.recovery.checkpoint import state_checksum
from torchbrdf.recovery.svbrdf import CHECKPOINT, main

from tests.recovery.recovery_fixtures import FAST, cap, done, stopped  # noqa: F401  (fixtures)
from tests.recovery.recovery_fixtures import copy_out as _copy
from tests.recovery.recovery_fixtures import file_hashes as _hashes
from tests.recovery.recovery_fixtures import one_line_error as _one_line_error


@contextlib.contextmanager
def _mounted(path: Path, tmp_path: Path):
    """A tmpfs mounted at ``path`` (root only), or a bind mount of a folder of ours where tmpfs is refused."""
    if os.geteuid() != 0:
        pytest.skip("mounting a file system needs root (CI runs as root)")
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2M", "tmpfs", str(path)], capture_output=True, text=True)
    if r.returncode != 0:  # the stand-in: a bind mount is a mount point all the same
        (tmp_path / "bind_source").mkdir()
        r = subprocess.run(["mount", "--bind", str(tmp_path / "bind_source"), str(path)], capture_output=True,
                           text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount here: {r.stderr.strip()}")
    try:
        yield
    finally:  # wherever a faulty commit moved it: every mount under tmp_path
        with open("/proc/self/mounts") as table:
            points = [line.split()[1] for line in table]
        for point in points:
            if point.startswith(str(tmp_path)):
                subprocess.run(["umount", "-l", point], check=False)


# --------------------------------------------------------------------------------------
# Nothing lost: files the run did not write
# --------------------------------------------------------------------------------------


def test_a_mount_inside_out_is_refused_and_with_the_switch_left_mounted_and_whole(done, cap, tmp_path, capsys):
    out = _copy(done, tmp_path)
    photos = out / "photos"
    with _mounted(photos, tmp_path):
        (photos / "raw_0001.txt").write_text("data")
        assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 2
        err = _one_line_error(capsys)
        assert "photos (a mount point)" in err and "--allow-other-files" in err
        assert os.path.ismount(photos) and (photos / "raw_0001.txt").read_text() == "data"

        assert main(["--capture", str(cap), "--out", str(out), *FAST[:-1], "5", "--allow-other-files"]) == 0
        assert os.path.ismount(photos) and os.listdir(photos) == ["raw_0001.txt"]
        assert (photos / "raw_0001.txt").read_text() == "data"
        assert load_outputs(out).report["fingerprint"]["settings"]["seed"] == 5  # the new run, whole
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]  # no staging left


def test_other_files_are_refused_unless_allowed_then_never_moved(done, cap, tmp_path, capsys):
    out = _copy(done, tmp_path)
    (out / "notes.txt").write_text("mine")
    (out / "sub").mkdir()
    (out / "sub" / "a.txt").write_text("a")
    ino = (out / "notes.txt").stat().st_ino
    assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 2
    assert "notes.txt" in _one_line_error(capsys)
    assert main(["--capture", str(cap), "--out", str(out), *FAST, "--allow-other-files"]) == 0
    assert (out / "notes.txt").read_text() == "mine" and (out / "notes.txt").stat().st_ino == ino  # not copied
    assert (out / "sub" / "a.txt").read_text() == "a"
    load_outputs(out)


def test_a_completed_run_leaves_no_checkpoint(done, stopped, cap, tmp_path):
    assert not (done / CHECKPOINT).exists()
    out = _copy(stopped, tmp_path)
    assert main(["--capture", str(cap), "--out", str(out), "--resume", *FAST]) == 0
    assert not (out / CHECKPOINT).exists() and json.loads((out / "report.json").read_text())["completed"]


# --------------------------------------------------------------------------------------
# The lock
# --------------------------------------------------------------------------------------

_HOLD_LOCK = ("import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDONLY); fcntl.flock(fd, fcntl.LOCK_EX); "
              "print('locked', flush=True); sys.stdin.read()")


def test_a_busy_out_is_refused_and_the_lock_dies_with_its_process(done, cap, tmp_path, capsys):
    out = _copy(done, tmp_path)
    before = _hashes(out)
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(out)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 2
        assert "another recovery is writing it" in _one_line_error(capsys)
        assert _hashes(out) == before
    finally:
        holder.kill()
        holder.wait()
    assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 0


# --------------------------------------------------------------------------------------
# Checkpoints that load but are wrong
# --------------------------------------------------------------------------------------


def _edit_checkpoint(out, edit, rechecksum=True):
    path = out / CHECKPOINT
    blob = torch.load(path, weights_only=True)
    edit(blob)
    if rechecksum:  # as the run that wrote it would have: only the values are wrong
        blob["fingerprint"]["state_sha256"] = state_checksum(blob["state"], blob["plan"], blob["torch_rng"])
    torch.save(blob, path)


def _nan_state(blob):
    for t in blob["state"]["theta"]:
        t.fill_(float("nan"))


@pytest.mark.parametrize("edit, words", [
    (_nan_state, "theta holds non-finite values"),
    (lambda blob: blob["state"].pop("events"), "lacks events"),
])
def test_a_wrong_checkpoint_is_refused_and_outputs_kept(stopped, cap, tmp_path, capsys, edit, words):
    out = _copy(stopped, tmp_path)
    _edit_checkpoint(out, edit)
    before = _hashes(out)
    assert main(["--capture", str(cap), "--out", str(out), "--resume", *FAST]) == 2
    err = _one_line_error(capsys)
    assert str(out / CHECKPOINT) in err and words in err
    assert _hashes(out) == before


def test_flipped_bits_in_a_checkpoint_fail_its_checksum(stopped, cap, tmp_path, capsys):
    out = _copy(stopped, tmp_path)
    path = out / CHECKPOINT
    with zipfile.ZipFile(path) as z:  # torch stores tensor records uncompressed: flip bits in the largest
        info = max((i for i in z.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    for k in range(start + info.file_size // 3, start + info.file_size // 3 + 8):
        raw[k] ^= 0x10
    path.write_bytes(bytes(raw))
    torch.load(path, weights_only=True)  # still loads: only the checksum can tell
    assert main(["--capture", str(cap), "--out", str(out), "--resume", *FAST]) == 2
    assert "checksum does not match" in _one_line_error(capsys)


def test_a_non_finite_final_state_never_replaces_good_outputs(done, cap, tmp_path, monkeypatch, capsys):
    out = _copy(done, tmp_path)
    before = _hashes(out)
    real_step = Recovery.step

    def step_then_diverge(self):
        real_step(self)
        if self.finished():
            self.state["theta"][0].fill_(float("nan"))

    monkeypatch.setattr(Recovery, "step", step_then_diverge)
    assert main(["--capture", str(cap), "--out", str(out), *FAST[:-1], "6"]) == 1
    assert "non-finite state" in _one_line_error(capsys)
    assert _hashes(out) == before


# --------------------------------------------------------------------------------------
# The batch skips only what it has done
# --------------------------------------------------------------------------------------


def test_batch_redoes_a_changed_capture_and_skips_an_unchanged_one(cap, tmp_path):
    src = tmp_path / "captures" / "c"
    shutil.copytree(cap, src)
    cfg = RecoveryConfig(iters=4, seed=0)
    out = tmp_path / "out"
    assert run_batch([src], out, cfg, use_ray=False, progress=False)[0]["status"] == "done"
    assert run_batch([src], out, cfg, use_ray=False, progress=False)[0]["status"] == "skipped"
    meta = json.loads((src / "capture.json").read_text())
    for entry in meta["images"]:
        entry["light"]["intensity"] = [2 * c for c in entry["light"]["intensity"]]
    (src / "capture.json").write_text(json.dumps(meta))
    assert run_batch([src], out, cfg, use_ray=False, progress=False)[0]["status"] == "done"
    assert run_batch([src], out, RecoveryConfig(iters=4, seed=1), use_ray=False,
                     progress=False)[0]["status"] == "done"  # other settings: not done either


def test_batch_reports_a_broken_capture_in_one_line(cap, tmp_path, capsys):
    src = tmp_path / "captures" / "broken"
    shutil.copytree(cap, src)
    meta = json.loads((src / "capture.json").read_text())
    meta["camera"]["position"] = [0.0, 0.0, -3.0]
    (src / "capture.json").write_text(json.dumps(meta))
    rows = run_batch([src], tmp_path / "out", RecoveryConfig(iters=4), use_ray=False, progress=False)
    assert rows[0]["status"] == "failed" and "below the sample plane" in rows[0]["error"]
    assert "Traceback" not in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# A capture that cannot determine the maps
# --------------------------------------------------------------------------------------


def test_too_few_lights_are_reported_and_the_confidence_map_shows_it(tmp_path):
    folder = tmp_path / "cap2"
    generate_capture(folder, recipe="metal_inlay", seed=2, size=16, lights=2, noise=0.01)
    logged = []
    res = recover(folder, RecoveryConfig(iters=4, threads=1), tmp_path / "out", progress=False, log=logged.append)
    assert res.report["completed"]
    assert any("3 light(s) for 5 unknowns per pixel" in w for w in res.report["warnings"])  # 2 + the flash
    assert any(m.startswith("warning: ") and "unknowns per pixel" in m for m in logged)
    assert res.confidence is not None and float(res.confidence.max()) == 0.0


def test_batch_waits_for_a_worker_that_still_holds_its_output_lock(cap, tmp_path):
    """A cancelled task's worker may end after the rerun starts: the rerun waits, then recovers."""
    out = tmp_path / "out"
    (out / "c").mkdir(parents=True)
    src = tmp_path / "captures" / "c"
    shutil.copytree(cap, src)
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK.replace("sys.stdin.read()", "time.sleep(3)")
                               .replace("import fcntl", "import time, fcntl"), str(out / "c")],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        rows = run_batch([src], out, RecoveryConfig(iters=4, seed=0), use_ray=False, progress=False)
    finally:
        holder.kill()
        holder.wait()
    assert rows[0]["status"] == "done", rows[0]
