"""The Python blocks of the reference pages run as written (the README's: tests/test_readme.py).

A page's blocks run in order in one namespace, as a reader pastes them, in an empty folder (plus,
for docs/recovery.md, the small synthetic capture ``cap/`` its example reads). docs/shading.md's
blocks are left out: its first is the README's shading example at 256², its second runs the
environment benchmarks (tests/bench)."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run_blocks(page: str) -> None:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / page).read_text(), re.S)
    assert blocks, page
    namespace = {"__name__": "__doc_block__"}
    for block in blocks:
        exec(compile(block, page, "exec"), namespace)


@pytest.mark.parametrize("page", ["neural.md", "recovery.md"])
def test_doc_python_blocks_run_verbatim(page, tmp_path, monkeypatch):
    from torchbrdf.capture import generate_capture

    monkeypatch.chdir(tmp_path)
    if page == "recovery.md":
        generate_capture("cap", recipe="tiles", seed=7, size=16, lights=6)
    _run_blocks(page)


def test_capture_format_blocks_write_captures_the_recovery_loads(tmp_path, monkeypatch, capsys):
    from torchbrdf.capture import load_capture

    monkeypatch.chdir(tmp_path)
    _run_blocks("capture_format.md")
    assert capsys.readouterr().out.strip() == "32 32 ('img_000.exr', 'img_001.exr')"  # the comment's output
    synthetic = load_capture(tmp_path / "synthetic")
    assert (synthetic.width, synthetic.height) == (64, 64)
    assert sorted(p.name for p in (tmp_path / "synthetic" / "gt").iterdir()) == [
        "base_color.exr", "metallic.exr", "normal.exr", "roughness.exr", "specular.exr"]
