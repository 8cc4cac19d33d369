"""``datasets/`` and ``training/`` are folders of scripts, not packages: from the repository root
they never shadow an installed package of the same name (Hugging Face ``datasets`` above all), and
their scripts run as files and, for ``training``, with ``python -m`` as a namespace folder."""

import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(args, cwd=ROOT, env_extra=None):
    env = dict(os.environ, **(env_extra or {}))
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("folder", ["datasets", "training"])
def test_folder_has_no_init(folder):
    assert (ROOT / folder).is_dir()
    assert not (ROOT / folder / "__init__.py").exists()


@pytest.mark.parametrize("name", ["datasets", "training"])
def test_installed_package_wins_from_the_repository_root(tmp_path, name):
    site = tmp_path / "site"
    (site / name).mkdir(parents=True)
    (site / name / "__init__.py").write_text("def load_dataset(n):\n    return 'hf:' + n\n")
    res = _run(["-c", f"import {name}; print({name}.load_dataset('x'), {name}.__file__)"],
               env_extra={"PYTHONPATH": str(site)})
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["hf:x", str(site / name / "__init__.py")]


@pytest.mark.parametrize("script", ["datasets/generate.py", "training/recover_svbrdf.py", "training/evaluate.py",
                                    "training/fit_measured.py", "training/recover_many.py"])
@pytest.mark.parametrize("where", ["root", "elsewhere"])
def test_scripts_run_as_files(tmp_path, script, where):
    res = _run([str(ROOT / script), "--help"], cwd=ROOT if where == "root" else tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower()


def test_training_runs_as_a_namespace_folder():
    res = _run(["-m", "training.recover_svbrdf", "--help"])
    assert res.returncode == 0, res.stderr[-2000:]
    assert "--capture" in res.stdout



@pytest.mark.parametrize("args, words", [(["--size", "0"], "generate_capture: size must be an integer >= 4, got 0"),
                                         (["--noise", "-0.5"], "add_noise: level")])
def test_generate_refuses_a_bad_option_in_one_line(tmp_path, args, words):
    # a bad --size ended in a ValueError traceback; now argparse's one-line error, exit status 2
    res = _run([str(ROOT / "datasets" / "generate.py"), "--out", str(tmp_path / "cap"), *args])
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert words in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "cap" / "capture.json").exists()
