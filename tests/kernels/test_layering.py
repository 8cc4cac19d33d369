"""The kernels package's imports: one way from the BRDF formulas, and no other file's private names."""

import ast
import pathlib

KERNELS = pathlib.Path(__file__).resolve().parents[2] / "torchbrdf" / "kernels"


def _imports(path: pathlib.Path):
    """``(module, name)`` of every ``from torchbrdf... import name`` and ``(module, None)`` of ``import``."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("torchbrdf"):
            for alias in node.names:
                yield node.module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("torchbrdf"):
                    yield alias.name, None


def test_kernels_take_the_formula_not_the_brdf_dispatch():
    # brdf.principled dispatches to the kernels; the kernels take only the formula and its
    # constants (brdf.formula), so the two modules do not import each other.
    offenders = [f"{p.name}: {m}" for p in sorted(KERNELS.glob("*.py")) for m, name in _imports(p)
                 if m.startswith("torchbrdf.brdf") and m not in ("torchbrdf.brdf", "torchbrdf.brdf.formula")
                 or (m == "torchbrdf.brdf" and name not in (None, "formula"))]
    assert not offenders, offenders


def test_kernels_import_no_private_names_of_other_files():
    offenders = [f"{p.name}: from {m} import {name}" for p in sorted(KERNELS.glob("*.py"))
                 for m, name in _imports(p) if name is not None and name.startswith("_")]
    assert not offenders, offenders
