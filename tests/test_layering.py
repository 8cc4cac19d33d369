"""Imports run one way between the subpackages, as each package's docstring states.

Every ``import``/``from ... import`` of a ``torchbrdf`` subpackage in a module's source (at the
top or inside a function: a lazy import is still a dependency) is checked against the
package's "Never"/"May import" list.
"""

import ast
from pathlib import Path

import pytest

import torchbrdf

ROOT = Path(torchbrdf.__file__).parent
# package -> subpackages it must never import (from the packages' docstrings)
FORBIDDEN = {
    "brdf": {"render", "analysis", "capture", "recovery", "bench"},
    "kernels": {"render", "analysis", "capture", "recovery", "bench"},
    "render": {"analysis", "capture", "recovery", "bench"},
    "analysis": {"capture", "recovery", "bench"},
    "capture": {"recovery", "kernels", "analysis", "bench"},
    "recovery": {"analysis", "kernels", "bench"},
}


def _imported_subpackages(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "torchbrdf" and len(parts) > 1:
                out.add(parts[1])
    return out


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_imports_run_one_way(package):
    bad = {}
    for path in sorted((ROOT / package).glob("*.py")):
        hit = _imported_subpackages(path) & FORBIDDEN[package]
        if hit:
            bad[path.name] = sorted(hit)
    assert not bad, f"torchbrdf.{package} imports what its docstring forbids: {bad}"


def test_the_check_sees_lazy_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from torchbrdf.kernels.ops import capture_fast\n    import torchbrdf.analysis.plots\n")
    assert _imported_subpackages(f) == {"kernels", "analysis"}
