"""Batch recovery (``python -m training.recover_many``): Ray tasks, skip/resume, failures, fallback.

Tiny captures (16 px, 8 lights, 5 iterations) keep this CI-sized; Ray is started once for the
module (2 CPUs, no dashboard) and the Ray tests are skipped when Ray is not installed.
"""

import _thread
import csv
import json
import sys
import threading
import time

import pytest
import torch

from torchbrdf.capture import generate_capture
from torchbrdf.io import read_exr
from torchbrdf.recovery import RecoveryConfig, recover
from torchbrdf.recovery.config import Settings
from torchbrdf.recovery.batch import _parser, config_from_args, find_captures, main, run_batch

MAPS = ("base_color", "roughness", "metallic", "specular", "normal")
CFG = dict(iters=5, seed=3)


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Three good captures and one whose second image is not an EXR."""
    root = tmp_path_factory.mktemp("captures")
    for i, recipe in enumerate(("tiles", "metal_inlay", "painted")):
        generate_capture(root / f"cap{i}", recipe=recipe, seed=i, size=16, lights=8)
    generate_capture(root / "broken", recipe="stone", seed=5, size=16, lights=8)
    (root / "broken" / "img_001.exr").write_bytes(b"not an exr")
    return root


@pytest.fixture(scope="module")
def good(captures):
    """The three good capture folders."""
    return [captures / f"cap{i}" for i in range(3)]


@pytest.fixture(scope="module")
def single(good, tmp_path_factory):
    """Maps of the single-capture API with the same options (1 thread, as each task)."""
    root = tmp_path_factory.mktemp("single")
    maps = {}
    for c in good:
        recover(c, root / c.name, RecoveryConfig(**CFG, threads=1), gt=c / "gt", progress=False)
        maps[c.name] = {k: read_exr(root / c.name / f"{k}.exr") for k in MAPS}
        maps[c.name]["iterations"] = json.loads((root / c.name / "report.json").read_text())["iterations"]
    return maps


@pytest.fixture
def ctrl_c_reaches_python():
    """Ctrl-C handled as Python's default during the test.

    A shell that starts a job in the background without job control (``bash .ci/run &``)
    hands it SIGINT *ignored*, and then no simulated Ctrl-C (``_thread.interrupt_main``)
    reaches the test at all.
    """
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture(scope="module")
def ray_local(tmp_path_factory):
    """Ray with 2 CPUs, and the kill switch of the retry tests (armed by creating the file).

    TORCHBRDF_* variables reach the tasks in their runtime environment; set once, before the
    first task, every test gets the same environment and so reuses the same warm workers.
    """
    ray = pytest.importorskip("ray")
    kill = tmp_path_factory.mktemp("kill") / "kill_once"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TORCHBRDF_BATCH_KILL_ONCE", str(kill))
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        yield kill
        ray.shutdown()


def _assert_same_maps(out, single):
    for name, ref in single.items():
        for k in MAPS:
            got = read_exr(out / name / f"{k}.exr")
            assert torch.equal(got, ref[k]), f"{name}/{k}.exr differs from the single-capture run"


def _status(rows):
    return {r["name"]: r["status"] for r in rows}


def test_ray_batch_matches_single_runs_and_rerun_skips(ray_local, captures, good, single, tmp_path):
    """Two Ray workers: single-run maps, the broken capture reported, summaries, rerun skips."""
    out = tmp_path / "out"
    rows = run_batch(good + [captures / "broken"], out, RecoveryConfig(**CFG), workers=2, progress=False)
    assert _status(rows) == {"cap0": "done", "cap1": "done", "cap2": "done", "broken": "failed"}
    _assert_same_maps(out, single)
    # The broken capture: one line naming the file, and no effect on the others.
    bad = rows[-1]
    assert "img_001.exr" in bad["error"] and "\n" not in bad["error"]
    # The summary files: one row per capture, numbers and errors (gt/ exists) included.
    listed = json.loads((out / "summary.json").read_text())
    assert [r["name"] for r in listed] == ["cap0", "cap1", "cap2", "broken"]
    for r in listed[:3]:
        assert r["iterations"] == single[r["name"]]["iterations"]
        assert r["final_loss"] > 0 and r["held_out_psnr"] > 10 and r["seconds"] > 0
        assert r["errors"]["base_color_rmse"] < 0.2
    with open(out / "summary.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["status"] for r in table] == ["done", "done", "done", "failed"]
    rmse = listed[0]["errors"]["base_color_rmse"]
    assert float(table[0]["base_color_rmse"]) == pytest.approx(rmse, rel=1e-5)
    assert (out / "overview.png").stat().st_size > 1000
    # Rerun: the completed captures are skipped (outputs untouched), the broken one fails again.
    stamp = {c.name: (out / c.name / "report.json").stat().st_mtime_ns for c in good}
    again = run_batch(good + [captures / "broken"], out, RecoveryConfig(**CFG), workers=2, progress=False)
    assert _status(again) == {"cap0": "skipped", "cap1": "skipped", "cap2": "skipped", "broken": "failed"}
    assert {c.name: (out / c.name / "report.json").stat().st_mtime_ns for c in good} == stamp
    assert again[0]["final_loss"] == rows[0]["final_loss"]


def test_killed_worker_is_retried(ray_local, good, single, tmp_path):
    """The first task to start removes the armed file and kills its worker; the retry finishes."""
    armed = ray_local
    armed.touch()
    rows = run_batch(good, tmp_path / "out", RecoveryConfig(**CFG), retries=2, progress=False)
    assert not armed.exists(), "no worker was killed"
    assert _status(rows) == {"cap0": "done", "cap1": "done", "cap2": "done"}
    _assert_same_maps(tmp_path / "out", single)


def test_worker_death_without_retries_is_reported(ray_local, good, tmp_path):
    """With --retries 0 a killed worker's capture is failed, with a one-line reason."""
    armed = ray_local
    armed.touch()
    rows = run_batch(good[:1], tmp_path / "out", RecoveryConfig(**CFG), retries=0, progress=False)
    assert rows[0]["status"] == "failed" and "task lost" in rows[0]["error"]


def test_ctrl_c_cancels_ray_tasks_and_rerun_finishes(ray_local, good, tmp_path, ctrl_c_reaches_python):
    """Ctrl-C while tasks run: summary with interrupted rows, KeyboardInterrupt; the rerun finishes."""
    out = tmp_path / "out"
    # Every planned iteration (no early end of converged stages): the tasks must still be running
    # when the interrupt arrives.
    cfg = RecoveryConfig(iters=20, seed=3, checkpoint_every=1, converge_tol=0.0)

    def press_ctrl_c():  # as soon as a task has written its first checkpoint
        deadline = time.monotonic() + 120
        while not list(out.glob("*/checkpoint.pt")) and time.monotonic() < deadline:
            time.sleep(0.05)
        _thread.interrupt_main()

    threading.Thread(target=press_ctrl_c, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        run_batch(good, out, cfg, progress=False)
    rows = json.loads((out / "summary.json").read_text())
    assert "interrupted" in _status(rows).values()
    again = run_batch(good, out, cfg, progress=False)
    assert set(_status(again).values()) <= {"done", "skipped"}
    assert all((out / c.name / "report.json").is_file() for c in good)


def test_sequential_fallback_without_ray(good, single, tmp_path, monkeypatch, capsys):
    """Without Ray the same captures run in-process, to the same maps, and it says why."""
    monkeypatch.setitem(sys.modules, "ray", None)  # "import ray" raises ImportError
    rows = run_batch(good, tmp_path / "out", RecoveryConfig(**CFG), workers=2, progress=False)
    assert _status(rows) == {"cap0": "done", "cap1": "done", "cap2": "done"}
    _assert_same_maps(tmp_path / "out", single)
    assert "running sequentially in this process: Ray is not installed" in capsys.readouterr().err


def test_interrupted_capture_is_resumed(good, single, tmp_path):
    """SIGTERM (as Ctrl-C) stops the batch with a summary; the rerun resumes from the checkpoint."""
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_batch(good, out, Settings(**CFG, signal_at=2), use_ray=False, progress=False)
    rows = json.loads((out / "summary.json").read_text())
    assert _status(rows) == {"cap0": "interrupted", "cap1": "interrupted", "cap2": "interrupted"}
    assert (out / "cap0" / "checkpoint.pt").is_file() and not (out / "cap1").exists()
    rows = run_batch(good, out, RecoveryConfig(**CFG), use_ray=False, progress=False)
    assert _status(rows) == {"cap0": "done", "cap1": "done", "cap2": "done"}
    assert rows[0]["iterations"] == single["cap0"]["iterations"]
    for k in MAPS:  # resumed = uninterrupted, to the tolerance of tests/recovery/test_recovery.py
        got = read_exr(out / "cap0" / f"{k}.exr")
        torch.testing.assert_close(got, single["cap0"][k], rtol=1e-5, atol=1e-6)


def test_learned_prior_reaches_every_fit_and_a_rerun_with_another_prior_recovers_again(good, tmp_path, capsys):
    """--prior as the single command: the same maps as recover(prior=...); skip only for the same prior."""
    out, cfg = tmp_path / "out", RecoveryConfig(**CFG, threads=1)
    assert main(["--captures", str(good[0]), "--out", str(out), "--no-ray", "--quiet", "--iters", "5",
                 "--seed", "3", "--prior", "default"]) == 0
    recover(good[0], cfg, tmp_path / "single", progress=False, prior="default")
    for k in MAPS:
        torch.testing.assert_close(read_exr(out / "cap0" / f"{k}.exr"), read_exr(tmp_path / "single" / f"{k}.exr"))
    assert "learned_prior" in json.loads((out / "cap0" / "report.json").read_text())
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the check runs on other threads than the fit: the weights decide, not the maps
    try:
        rows = run_batch(good[:1], out, RecoveryConfig(**CFG), use_ray=False, progress=False, prior="default")
    finally:
        torch.set_num_threads(threads)
    assert _status(rows) == {"cap0": "skipped"}
    rows = run_batch(good[:1], out, RecoveryConfig(**CFG), use_ray=False, progress=False)
    assert _status(rows) == {"cap0": "done"}  # made with a prior: not this fit
    assert "learned_prior" not in json.loads((out / "cap0" / "report.json").read_text())
    missing = tmp_path / "nothing.pt"
    assert main(["--captures", str(good[0]), "--out", str(tmp_path / "o"), "--no-ray", "--quiet",
                 "--prior", str(missing)]) == 2
    assert f"error: --prior {missing}:" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_cli_options_and_exit_status(captures, tmp_path):
    """The single CLI's recovery flags pass through; exit status 1 when a capture failed."""
    args = _parser().parse_args(["--captures", "x", "--out", "o", "--iters", "7", "--seed", "4", "--model",
                                 "svbrdf_ggx", "--holdout", "-1", "--size", "12", "--no-soft-metal",
                                 "--no-light-position"])
    cfg = config_from_args(args)
    assert (cfg.iters, cfg.seed, cfg.model, cfg.size, cfg.holdout) == (7, 4, "svbrdf_ggx", 12, -1)
    assert (cfg.soft_metal, cfg.light_scale, cfg.light_position) == (False, True, False)
    assert cfg.threads is None  # --threads-per-task sets it per task
    with pytest.raises(SystemExit):
        _parser().parse_args(["--captures", "x", "--out", "o", "--threads", "2"])
    # A glob over the good captures plus the broken one by name: exit status 1 (one failed).
    rc = main(["--captures", str(captures / "cap[01]"), str(captures / "broken"),
               "--out", str(tmp_path / "o"), "--no-ray", "--quiet", "--iters", "2"])
    assert rc == 1
    assert [r["status"] for r in json.loads((tmp_path / "o" / "summary.json").read_text())] == [
        "done", "done", "failed"]
    assert main(["--captures", str(tmp_path / "nothing*"), "--out", str(tmp_path / "o2")]) == 2


@pytest.mark.parametrize("flags,says", [
    (["--size", "-5"], "size"), (["--levels", "0"], "levels"), (["--checkpoint-every", "0"], "checkpoint_every"),
    (["--threads-per-task", "0"], "--threads-per-task must be at least 1"),
    (["--workers", "-1"], "--workers must be at least 1"), (["--retries", "-1"], "--retries must be at least 0"),
    (["--gpus-per-task", "-1"], "--gpus-per-task must be at least 0")])
def test_impossible_options_are_refused_before_any_capture_runs(captures, tmp_path, capsys, flags, says):
    out = tmp_path / "o"
    assert main(["--captures", str(captures / "cap0"), "--out", str(out), "--no-ray", "--quiet", *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and says in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_a_cuda_device_is_for_the_workers_to_check(captures, tmp_path, monkeypatch):
    """A CPU-only head may send --device cuda to GPU nodes: the up-front checks leave the device alone."""
    from torchbrdf.recovery import batch

    seen = {}
    monkeypatch.setattr(batch, "run_batch", lambda captures, out, cfg, **kw: seen.setdefault("cfg", cfg) and [])
    assert main(["--captures", str(captures / "cap0"), "--out", str(tmp_path / "o"), "--device", "cuda",
                 "--gpus-per-task", "1", "--quiet"]) == 0
    assert seen["cfg"].device == "cuda"
    assert main(["--captures", str(captures / "cap0"), "--out", str(tmp_path / "o"), "--device", "nonsense"]) == 2


def test_is_complete_with_a_prior_needs_the_capture(tmp_path):
    from torchbrdf.recovery.batch import is_complete

    (tmp_path / "report.json").write_text(json.dumps({"completed": True, "fingerprint": {"settings": {"learned_prior": "0"}}}))
    with pytest.raises(ValueError, match="needs its capture"):
        is_complete(tmp_path, None, RecoveryConfig(), prior="default")


def test_an_out_that_is_a_file_is_one_line_and_left_alone(captures, tmp_path, capsys):
    # this was mkdir's FileExistsError traceback
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["--captures", str(captures / "cap0"), "--out", str(taken), "--no-ray", "--quiet"]) == 2
    assert f"error: --out {taken}: {taken} is a file, not a folder" in capsys.readouterr().err
    assert taken.read_text() == "mine"


def test_find_captures(captures, tmp_path):
    """Folders, parents and globs; duplicates dropped; clashing names and no capture refused."""
    assert [p.name for p in find_captures([captures])] == ["broken", "cap0", "cap1", "cap2"]
    found = find_captures([str(captures / "cap*"), captures / "cap0"])
    assert [p.name for p in found] == ["cap0", "cap1", "cap2"]
    (tmp_path / "a" / "cap0").mkdir(parents=True)
    (tmp_path / "a" / "cap0" / "capture.json").write_text("{}")
    with pytest.raises(ValueError, match="two captures are named 'cap0'"):
        find_captures([captures / "cap0", tmp_path / "a"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no folder holding capture.json"):
        find_captures([tmp_path / "empty"])


def test_an_interrupt_during_the_first_imports_waits_until_they_are_complete(monkeypatch,
                                                                             ctrl_c_reaches_python):
    """An interrupt that lands inside the first imports is raised after them.

    Ray cancels a task by interrupting its worker, then reuses the worker: a half-imported
    module would fail the next task.
    """
    import signal

    from torchbrdf.recovery import batch, previews

    done = []

    def pyplot_interrupted_midway():
        _thread.interrupt_main()  # Ray's cancel of a running task
        time.sleep(0.05)  # the interrupt would land here, inside the import
        done.append(True)

    monkeypatch.setattr(previews, "pyplot", pyplot_interrupted_midway)
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        batch._import_before_interrupts()
    assert done == [True]
    assert signal.getsignal(signal.SIGINT) is handler
    # An ignored SIGINT stays ignored: the held interrupt goes to the handler that was there.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        batch._import_before_interrupts()  # interrupted midway again; nothing raised
    finally:
        signal.signal(signal.SIGINT, handler)
    assert done == [True, True]
