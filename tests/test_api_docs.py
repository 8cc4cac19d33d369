"""``docs/api.md`` is generated from the docstrings (``python tools/gen_api_docs.py``) and is current."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_api_page_is_current():
    res = subprocess.run([sys.executable, str(ROOT / "tools" / "gen_api_docs.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:] + "\nrun: python tools/gen_api_docs.py"


def test_api_page_covers_the_three_packages():
    text = (ROOT / "docs" / "api.md").read_text()
    for name in ("torchbrdf.principled", "torchbrdf.shade", "torchbrdf.render.envmap", "torchbrdf.recovery.recover",
                 "torchbrdf.recovery.RecoveryConfig"):
        assert f"`{name}" in text, name
