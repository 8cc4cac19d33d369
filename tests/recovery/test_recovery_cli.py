"""Recovery driver: fingerprinted checkpoints, outputs as one unit, refusals, clear I/O
messages, prompt stop, the Python API (issues 14 and 15).
"""

import contextlib
import errno
import json
import os
import shutil
import signal
from pathlib import Path

import pytest
import torch

import torchbrdf.recovery.outputs as outputs
import torchbrdf.recovery.svbrdf as svbrdf
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery import engine
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.svbrdf import CHECKPOINT, main

from tests.recovery.recovery_fixtures import FAST, cap, done, stopped  # noqa: F401  (fixtures)
from tests.recovery.recovery_fixtures import copy_out as _copy
from tests.recovery.recovery_fixtures import file_hashes as _hashes
from tests.recovery.recovery_fixtures import one_line_error as _one_line_error


@pytest.fixture(scope="module")
def other_cap(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap16b")
    generate_capture(folder, recipe="metal_inlay", seed=5, size=16, lights=6, noise=0.01)
    return folder


# --------------------------------------------------------------------------------------
# A checkpoint knows what it belongs to
# --------------------------------------------------------------------------------------


def test_resume_with_another_capture_is_refused(stopped, other_cap, tmp_path, capsys):
    out = _copy(stopped, tmp_path)
    before = _hashes(out)
    rc = main(["--capture", str(other_cap), "--out", str(out), "--resume", "--force", *FAST])
    assert rc == 2
    err = _one_line_error(capsys)
    assert "another capture" in err and "img_000.exr" in err and CHECKPOINT in err
    assert _hashes(out) == before


def test_resume_with_other_settings_is_refused_unless_forced(stopped, cap, tmp_path, capsys):
    out = _copy(stopped, tmp_path)
    changes = (("--lr", "0.5"), ("--seed", "3"), ("--prior-roughness", "0.01"), ("--model", "svbrdf_ggx"))
    for flag, value in changes:
        argv = ["--capture", str(cap), "--out", str(out), "--resume", *FAST, flag, value]
        assert main(argv) == 2, flag
        err = _one_line_error(capsys)
        assert flag.lstrip("-").replace("-", "_") in err and "--force" in err
    # The schedule (iterations) cannot change, even with --force.
    assert main(["--capture", str(cap), "--out", str(out), "--resume", "--force", *FAST, "--iters", "6"]) == 2
    assert "schedule" in _one_line_error(capsys)
    # --force continues with the new setting and says so in the report.
    assert main(["--capture", str(cap), "--out", str(out), "--resume", "--force", *FAST, "--lr", "0.5"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["completed"] and rep["fingerprint"]["settings"]["lr"] == 0.5
    assert any(e["event"] == "resumed with --force" for e in rep["events"])


def test_fingerprint_ignores_threads_and_checkpoint_frequency(stopped, cap, tmp_path):
    out = _copy(stopped, tmp_path)
    argv = ["--capture", str(cap), "--out", str(out), "--resume", "--iters", "4", "--quiet",
            "--threads", "2", "--checkpoint-every", "2"]
    assert main(argv) == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_resume_on_another_thread_count_warns_that_the_rounding_differs(stopped, cap, tmp_path, threads):
    # Another thread count reorders torch's reductions: the resumed maps are not the
    # uninterrupted run's bit for bit, which the docs promise only for the same count.
    out = _copy(stopped, tmp_path)  # made with one thread
    logged: list[str] = []
    before = torch.get_num_threads()
    try:
        recover(cap, RecoveryConfig(iters=4, threads=threads), out=out, resume=True, log=logged.append,
                progress=False)
    finally:
        torch.set_num_threads(before)
    warnings = [m for m in logged if "made with 1 thread(s), this run has 2" in m]
    assert len(warnings) == (threads == 2), logged


# --------------------------------------------------------------------------------------
# Outputs are one unit
# --------------------------------------------------------------------------------------


def test_failure_during_output_write_leaves_the_previous_run(done, cap, tmp_path, monkeypatch, capsys):
    out = _copy(done, tmp_path)
    before = _hashes(out)
    calls = []
    real = outputs.write_exr

    def failing(path, *a, **k):
        calls.append(path)
        if len(calls) == 2:  # the second map: the first one is already written
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, *a, **k)

    monkeypatch.setattr(outputs, "write_exr", failing)
    assert main(["--capture", str(cap), "--out", str(out), *FAST[:-1], "7"]) == 1
    err = _one_line_error(capsys)
    assert "no space left on device while writing roughness.exr" in err
    assert _hashes(out) == before
    svbrdf.load_outputs(out)  # consistent: every file matches report.json
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".out.")]  # no staging left


def test_interrupted_write_never_mixes_runs(done, cap, tmp_path, monkeypatch):
    """A kill (here: an exception that is not an OSError) while the new run writes its outputs
    leaves every output file of the previous run.
    """
    out = _copy(done, tmp_path)
    before = {k: v for k, v in _hashes(out).items() if k != CHECKPOINT}
    real = outputs.write_png

    def killed(path, *a, **k):
        if path.name == "roughness.png":
            raise KeyboardInterrupt
        return real(path, *a, **k)

    monkeypatch.setattr(outputs, "write_png", killed)
    with pytest.raises(KeyboardInterrupt):
        main(["--capture", str(cap), "--out", str(out), *FAST[:-1], "9"])
    after = {k: v for k, v in _hashes(out).items() if k != CHECKPOINT}
    assert after == before
    assert svbrdf.load_outputs(out).report["fingerprint"]["settings"]["seed"] == 0


def test_report_lists_its_files_and_readers_detect_a_mix(done, tmp_path):
    out = _copy(done, tmp_path)
    rep = json.loads((out / "report.json").read_text())
    assert rep["completed"] is True and set(rep["fingerprint"]) == {"capture_sha256", "settings"}
    assert {"base_color.exr", "normal.exr", "comparison.png", "loss.png"} <= set(rep["files"])
    res = svbrdf.load_outputs(out)
    assert res.maps["base_color"].shape == (3, 16, 16)
    m = read_exr(out / "roughness.exr")
    svbrdf.write_exr(out / "roughness.exr", m * 0.5)
    with pytest.raises(svbrdf.RecoveryError, match="roughness.exr"):
        svbrdf.load_outputs(out)


_KILL_DURING_WRITE = """
import os, signal, sys
import torchbrdf.recovery.outputs as o, torchbrdf.recovery.svbrdf as s
real = o.write_png
def write_png(path, *a, **k):
    if path.name == "roughness.png":  # base_color.exr/.png and roughness.exr are written already
        os.kill(os.getpid(), signal.SIGKILL)
    return real(path, *a, **k)
o.write_png = write_png
sys.exit(s.main(sys.argv[1:]))
"""


def test_sigkill_during_output_write_then_next_run_cleans_up(done, cap, tmp_path):
    import subprocess
    import sys

    out = _copy(done, tmp_path)
    before = _hashes(out)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", _KILL_DURING_WRITE, "--capture", str(cap), "--out", str(out),
                           *FAST[:-1], "9"], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert _hashes(out) == before  # the previous run, whole
    svbrdf.load_outputs(out)
    staging = [p for p in tmp_path.iterdir() if p.name.startswith(".out.staging-")]
    assert len(staging) == 1 and (staging[0] / "base_color.exr").is_file()  # the killed run's half
    tmp_ck = out / ".checkpoint.pt.k2j4h5g6.tmp.pt"  # what a kill during a checkpoint write leaves
    tmp_ck.write_bytes(b"half")
    mine = tmp_path / f".out.staging-{os.getpid()}-live00"  # a live process's folder stays
    mine.mkdir()
    assert main(["--capture", str(cap), "--out", str(out), *FAST]) == 0
    assert not staging[0].exists() and not tmp_ck.exists() and mine.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([mine.name, "out"])


def test_other_files_in_out_are_kept_and_mode_is_not_0700(done, cap, tmp_path):
    out = _copy(done, tmp_path)
    (out / "notes.txt").write_text("mine")
    os.chmod(out, 0o755)
    assert main(["--capture", str(cap), "--out", str(out), *FAST, "--allow-other-files"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert (out.stat().st_mode & 0o777) == 0o755


# --------------------------------------------------------------------------------------
# Refuse the impossible up front
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("extra, words", [
    (["--lr", "nan"], "--lr"), (["--lr", "inf"], "--lr"), (["--lr", "0"], "--lr"), (["--lr", "-1"], "--lr"),
    (["--iters", "-1"], "--iters"), (["--checkpoint-every", "0"], "--checkpoint-every"),
    (["--levels", "0"], "--levels"), (["--size", "0"], "--size"), (["--size", "nan"], "--size"),
    (["--prior-roughness", "nan"], "--prior-roughness"), (["--prior-specular", "-1"], "--prior-specular"),
    (["--prior-metal-base", "inf"], "--prior-metal-base"),
    (["--prior-nonlocal-base", "-0.1"], "--prior-nonlocal-base"),
    (["--seed", "-1"], "--seed"), (["--threads", "0"], "--threads"), (["--force"], "--force"),
    (["--holdout", "99"], "--holdout 99: the capture has"), (["--holdout", "-2"], "--holdout -2"),
])
def test_bad_option_is_one_line_rc2_and_no_folder(cap, tmp_path, capsys, extra, words):
    out = tmp_path / "o"
    assert main(["--capture", str(cap), "--out", str(out), "--iters", "2", "--quiet", *extra]) == 2
    assert words in _one_line_error(capsys)
    assert not out.exists()


def test_bad_gt_capture_and_out_are_refused(cap, tmp_path, capsys):
    out = tmp_path / "o"
    base = ["--out", str(out), "--iters", "2", "--quiet"]
    assert main(["--capture", str(cap), *base, "--gt", str(tmp_path / "nonexistent")]) == 2
    assert "--gt" in _one_line_error(capsys)
    (tmp_path / "empty").mkdir()
    assert main(["--capture", str(cap), *base, "--gt", str(tmp_path / "empty")]) == 2
    assert "base_color.exr" in _one_line_error(capsys)
    bad = tmp_path / "badcap"
    shutil.copytree(cap, bad)
    (bad / "capture.json").write_text("{not json")
    assert main(["--capture", str(bad), *base]) == 2
    assert "capture.json" in _one_line_error(capsys)
    assert not out.exists()
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["--capture", str(cap), "--out", str(f / "sub"), "--quiet"]) == 2
    assert "is a file" in _one_line_error(capsys)
    assert main(["--capture", str(cap), "--out", str(f), "--quiet"]) == 2
    assert "not a folder" in _one_line_error(capsys)


@pytest.mark.parametrize("name, channels, value, words", [
    ("roughness", 1, float("nan"),
     "roughness.exr: 1 non-finite value(s) (NaN or inf), first at row 2, column 3"),
    ("normal", 3, float("inf"), "normal.exr: 1 non-finite value(s)"),
    ("base_color", 4, 0.5, "base_color.exr: expected 3 channel(s) for the base_color map, got 4"),
    ("metallic", 1, "half", "metallic.exr: expected the capture's size"),
])
def test_gt_map_that_is_not_finite_or_has_other_channels_is_refused(cap, tmp_path, capsys, name,
                                                                     channels, value, words):
    # A NaN in a ground-truth map ran the whole fit and wrote NaN into report.json's errors; a
    # 4-channel base colour failed on broadcasting only after the fit.
    from torchbrdf.io import write_exr
    gt = tmp_path / "gt"
    shutil.copytree(cap / "gt", gt)
    m = read_exr(gt / f"{name}.exr")
    m = torch.cat([m, m[:1]])[:channels] if channels > m.shape[0] else m.clone()
    if value == "half":  # a truth of another size was silently resampled into another truth
        m = m[:, ::2, ::2].contiguous()
    else:
        m[0, 2, 3] = value
    write_exr(gt / f"{name}.exr", m)
    out = tmp_path / "o"
    assert main(["--capture", str(cap), "--out", str(out), "--gt", str(gt), *FAST]) == 2
    err = _one_line_error(capsys)
    assert "--gt" in err and words in err
    assert not out.exists()


def test_read_only_out_is_one_line(cap, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    monkeypatch.setattr(outputs, "_read_only", lambda p: True)
    assert main(["--capture", str(cap), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "read-only file system" in _one_line_error(capsys)


def test_lr_nan_never_runs_from_the_api(cap):
    with pytest.raises(svbrdf.RecoveryError, match=r"lr \(--lr\) must be"):  # the field and its flag
        recover(cap, RecoveryConfig(lr=float("nan")))


@pytest.mark.parametrize("kw", [{"soft_metal_smooth": float("nan")}, {"soft_metal_smooth": -1.0},
                                {"soft_metal_band": -1}, {"soft_metal_edge": float("nan")},
                                {"soft_metal_context": -0.5}, {"soft_metal_grow": 2.5},
                                {"nonlocal_fit_weight": -1.0}, {"soft_metal_passes": 1.5},
                                {"fuse_rounds": 0}, {"fuse_refit_iters": -1},
                                {"soft_metal_quiet": float("nan")}, {"soft_metal_quiet": -1.0}])
def test_soft_metal_and_fusion_settings_are_checked(kw):
    # A NaN smooth weight made every second-pass residual NaN (sqrt(nan)); a negative band
    # reached max_pool2d as a kernel size <= 0. Both are refused up front, naming the setting.
    name = next(iter(kw))
    with pytest.raises(svbrdf.RecoveryError, match=f"Settings.{name}"):  # a constant of the method
        svbrdf.check_config(Settings(**kw))


# --------------------------------------------------------------------------------------
# Clear messages
# --------------------------------------------------------------------------------------


def test_corrupt_checkpoint_names_the_file(stopped, cap, tmp_path, capsys):
    out = _copy(stopped, tmp_path)
    data = (out / CHECKPOINT).read_bytes()
    (out / CHECKPOINT).write_bytes(data[: len(data) // 2])
    assert main(["--capture", str(cap), "--out", str(out), "--resume", *FAST]) == 2
    err = _one_line_error(capsys)
    assert str(out / CHECKPOINT) in err and "corrupt" in err
    # torch's reason, cut to its first sentence: it was cut mid-word at 160 characters
    (out / CHECKPOINT).write_bytes(data[:100])
    assert main(["--capture", str(cap), "--out", str(out), "--resume", *FAST]) == 2
    err = _one_line_error(capsys)
    assert "failed finding central directory); delete it" in err and "If you are seeing" not in err


def test_disk_full_during_checkpoint(done, cap, tmp_path, monkeypatch, capsys):
    out = _copy(done, tmp_path)
    before = _hashes(out)

    @contextlib.contextmanager
    def full(path):
        raise OSError(errno.ENOSPC, "No space left on device")
        yield

    monkeypatch.setattr(engine, "atomic_path", full)
    assert main(["--capture", str(cap), "--out", str(out), *FAST[:-1], "5", "--checkpoint-every", "1"]) == 1
    err = _one_line_error(capsys)
    assert "no space left on device while writing" in err and CHECKPOINT in err
    assert _hashes(out) == before


def test_checkpoint_write_reports_enospc_as_oserror(tmp_path, monkeypatch):
    """Torch's own writer turns ENOSPC into an opaque RuntimeError; the checkpoint is
    serialised in memory and written by Python, so the errno survives.
    """
    rec = engine.Recovery.__new__(engine.Recovery)
    rec.out, rec.state, rec.plan, rec.cfg = tmp_path, {"x": torch.zeros(3)}, [], Settings()
    real_open = open

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, b):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.f.close()

    monkeypatch.setattr("builtins.open", lambda p, m="r", *a, **k: Full(real_open(p, m, *a, **k)) if m == "wb"
                        else real_open(p, m, *a, **k))
    with pytest.raises(OSError) as e:
        rec.save_checkpoint()
    assert e.value.errno == errno.ENOSPC
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------
# Prompt stop
# --------------------------------------------------------------------------------------


def test_sigterm_is_honoured_within_one_inner_step_and_resumes_exactly(cap, tmp_path, monkeypatch):
    cfg = dict(iters=4, threads=1, seed=0, checkpoint_every=10)
    full = recover(cap, RecoveryConfig(**cfg), tmp_path / "full", progress=False)
    real = engine.lm_step
    calls = []

    def spy(*a, **k):
        calls.append(1)
        if len(calls) == 3:  # second iteration (dual stage), first hypothesis
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*a, **k)

    monkeypatch.setattr(engine, "lm_step", spy)
    part = recover(cap, RecoveryConfig(**cfg), tmp_path / "part", progress=False)
    assert len(calls) == 3  # the step in progress was abandoned, nothing after it ran
    assert not part.report["completed"] and part.report["iterations"] == 1
    monkeypatch.setattr(engine, "lm_step", real)
    resumed = recover(cap, RecoveryConfig(**cfg), tmp_path / "part", resume=True, progress=False)
    assert resumed.report["completed"]
    for k in full.maps:
        torch.testing.assert_close(resumed.maps[k], full.maps[k], rtol=0, atol=0)


# --------------------------------------------------------------------------------------
# API, help, progress
# --------------------------------------------------------------------------------------


def test_api_reproduces_the_cli_maps_exactly(done, cap):
    res = recover(cap, RecoveryConfig(iters=4, threads=1, seed=0), progress=False)
    assert isinstance(res, svbrdf.RecoveryResult) and res.out is None
    assert res.confidence is None or res.confidence.shape == (1, 16, 16)
    for name, t in res.maps.items():
        assert torch.equal(t, read_exr(done / f"{name}.exr")), name
    assert res["maps"] is res.maps and res["completed"] is True  # the old dict-style access


def test_every_option_has_help_and_no_contract_references():
    p = svbrdf._parser()
    for a in p._actions:
        assert a.help, a.option_strings
    text = p.format_help()
    assert "contract" not in text.lower() and "§" not in text


def test_loss_history_states_both_hypotheses(done):
    rep = json.loads((done / "report.json").read_text())
    assert rep["final_fit_loss"] > 0
    hist = rep["loss_history"]
    dual = [h["fit"] for h in hist if h["stage"] == "dual"]
    assert dual and all({"dielectric", "metal", "best"} <= set(f) for f in dual)
    assert all(f["best"] <= min(f["dielectric"], f["metal"]) + 1e-12 for f in dual)
    assert all("chosen" in h["fit"] for h in hist if h["stage"] != "dual")


def test_cli_prints_stages_and_its_output_folder(cap, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["--capture", str(cap), "--out", str(out), *[a for a in FAST if a != "--quiet"]]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["out"] == str(out.resolve())
    err = captured.err
    assert f"outputs written to {out.resolve()}" in err
    assert "stage 1/3: 16×16 px" in err and "both hypotheses" in err and "stage 3/3" in err
    assert "fit loss (bar and loss.png) = mean squared log residual" in err  # the bar's loss, stated


def test_command_line_exit_status_and_output_reach_the_caller(cap, tmp_path):
    # The command line ends the process without the interpreter's teardown (svbrdf.cli): its
    # exit status and everything it printed must still arrive.
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "training.recover_svbrdf"]
    bad = subprocess.run([*cmd, "--capture", str(tmp_path / "none"), "--out", str(tmp_path / "o1")],
                         capture_output=True, text=True, cwd=root, env=env)
    assert bad.returncode == 2 and bad.stderr.startswith("error: ") and "none" in bad.stderr
    ok = subprocess.run([*cmd, "--capture", str(cap), "--out", str(tmp_path / "o2"), *FAST],
                        capture_output=True, text=True, cwd=root, env=env)
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert json.loads(ok.stdout)["completed"] is True
    assert (tmp_path / "o2" / "report.json").is_file()
    # The interpreter's teardown is skipped, its exit handlers are not (a private kernel folder's removal).
    code = ("import atexit, sys; atexit.register(print, 'exit handler ran'); "
            f"sys.argv = ['torchbrdf-recover', '--capture', {str(tmp_path / 'none')!r}, '--out', 'o']; "
            "from torchbrdf.recovery.svbrdf import cli; cli()")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, env=env)
    assert run.returncode == 2 and "exit handler ran" in run.stdout


def test_holdout_minus_one_holds_no_light_out(cap):
    """``holdout=-1``: every light trains the fit and no validation PSNR is reported."""
    from torchbrdf.recovery.svbrdf import recover

    cfg = RecoveryConfig(iters=2, threads=1, seed=0, holdout=-1)
    res = recover(cap, cfg, progress=False, log=lambda m: None)
    assert res.report["held_out_light"] is None
