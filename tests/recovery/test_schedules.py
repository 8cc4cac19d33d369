"""The schedules a user chooses by name: fast / default / thorough, from Python and the command lines."""

import pytest

from torchbrdf.recovery import RecoveryConfig, ScheduleConfig
from torchbrdf.recovery import cli
from torchbrdf.recovery.batch import _parser as batch_parser
from torchbrdf.recovery.batch import config_from_args
from torchbrdf.recovery.engine import _schedule


def test_presets_resolve_to_their_settings():
    assert ScheduleConfig.preset("default") == ScheduleConfig()
    assert ScheduleConfig.preset("fast") == ScheduleConfig(iters=18, converge_tol=0.03)
    assert ScheduleConfig.preset("thorough") == ScheduleConfig(iters=78, converge_tol=0.002, converge_min_iters=4)
    with pytest.raises(ValueError, match="fast, default, thorough.*'quick'"):
        ScheduleConfig.preset("quick")


def test_presets_plan_fewer_and_more_iterations_than_the_default():
    def planned(name):
        return sum(n for _, _, n in _schedule(128, RecoveryConfig(schedule=name).settings()))

    assert planned("default") == 39
    assert planned("fast") == 18
    assert planned("thorough") == 78
    # the plan's stages are the same, only longer or shorter
    stages = [[k for _, k, _ in _schedule(128, RecoveryConfig(schedule=s).settings())]
              for s in ("fast", "default", "thorough")]
    assert stages[0] == stages[1] == stages[2]


def test_a_named_schedule_is_adjusted_by_flat_keywords():
    cfg = RecoveryConfig(schedule="thorough", iters=50)
    assert (cfg.iters, cfg.converge_tol, cfg.converge_min_iters) == (50, 0.002, 4)
    assert RecoveryConfig(schedule="fast").settings().converge_tol == 0.03
    with pytest.raises(ValueError, match="schedule"):
        RecoveryConfig(schedule="slow")


def _cli_config(monkeypatch, tmp_path, *flags):
    seen = {}

    def fake_recover(capture, cfg, out, **kw):
        seen["cfg"] = cfg
        raise cli.RecoveryError("stop here")

    monkeypatch.setattr(cli, "recover", fake_recover)
    assert cli.main(["--demo", "--out", str(tmp_path / "out"), "--threads", "1", *flags]) != 0
    return seen["cfg"]


def test_command_line_schedule_and_explicit_flags(monkeypatch, tmp_path):
    monkeypatch.setattr("torchbrdf.capture.synthetic.default_capture", lambda size: tmp_path / "cap")
    cfg = _cli_config(monkeypatch, tmp_path)
    assert cfg.schedule == ScheduleConfig()
    cfg = _cli_config(monkeypatch, tmp_path, "--schedule", "fast")
    assert cfg.schedule == ScheduleConfig.preset("fast")
    cfg = _cli_config(monkeypatch, tmp_path, "--schedule", "fast", "--iters", "10", "--converge-tol", "0")
    assert (cfg.iters, cfg.converge_tol) == (10, 0.0)
    # recover_many takes the same flag
    args = batch_parser().parse_args(["--captures", "x", "--out", "y", "--schedule", "thorough", "--levels", "2"])
    assert config_from_args(args).schedule == ScheduleConfig(iters=78, converge_tol=0.002, converge_min_iters=4,
                                                             levels=2)
