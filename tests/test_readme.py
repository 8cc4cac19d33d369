"""The README's examples run as written: each Python block in a fresh namespace, and every
``python -m`` command it shows answers ``--help``."""

import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def test_readme_python_blocks_run_verbatim(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {"__name__": "__readme__"})  # no names given: imports must be there


def _readme_commands() -> list[tuple[str, ...]]:
    text = "\n".join(re.findall(r"```bash\n(.*?)```", README.read_text(), re.S))
    modules = [["-m", m] for m in re.findall(r"python -m ((?:torchbrdf|training)[\w.]*)", text)]
    files = [[f] for f in re.findall(r"python ((?:datasets|training)/\w+\.py)", text)]
    return sorted({tuple(c) for c in modules + files})


@pytest.mark.parametrize("command", _readme_commands(), ids=" ".join)
def test_readme_commands_exist(command):
    res = subprocess.run([sys.executable, *command, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower()
