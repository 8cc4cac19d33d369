"""docs/capture_format.md's Python blocks run as written, and what they write is a capture the recovery loads."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_capture_format_python_blocks_run_verbatim(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "capture_format.md").read_text(), re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, "capture_format.md", "exec"), {"__name__": "__doc_block__"})
    assert capsys.readouterr().out.strip() == "32 32 ('img_000.exr', 'img_001.exr')"  # the comment's output

    from torchbrdf.capture import load_capture

    synthetic = load_capture(tmp_path / "synthetic")
    assert (synthetic.width, synthetic.height) == (64, 64)
    assert sorted(p.name for p in (tmp_path / "synthetic" / "gt").iterdir()) == [
        "base_color.exr", "metallic.exr", "normal.exr", "roughness.exr", "specular.exr"]
