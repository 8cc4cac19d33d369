"""List the public callables of torchbrdf that are not fully annotated.

Public means: a module-level ``def`` whose name does not start with ``_``, and the methods
of module-level public classes whose names do not start with ``_`` (dunder methods other
than ``__init__`` and ``__call__`` are skipped). Fully annotated means every parameter but a
leading ``self``/``cls`` (including ``*args``/``**kwargs``) has an annotation, and there is
a return annotation (``__init__`` may omit it). Modules whose own name starts with ``_`` are
still checked (``torchbrdf._math`` holds helpers the public modules re-export).

Usage: ``python tools/check_annotations.py [PACKAGE_DIR]`` prints one ``path:line: name``
per offender and exits 1 when there is any.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

_CHECKED_DUNDERS = {"__init__", "__call__"}


def _missing(fn: ast.FunctionDef | ast.AsyncFunctionDef, is_method: bool) -> list[str]:
    """Names of the parts of ``fn``'s signature that lack an annotation."""
    a = fn.args
    params = [*a.posonlyargs, *a.args]
    static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list)
    if is_method and not static and params and params[0].arg in ("self", "cls"):
        params = params[1:]
    params += a.kwonlyargs
    params += [p for p in (a.vararg, a.kwarg) if p is not None]
    out = [p.arg for p in params if p.annotation is None]
    if fn.returns is None and fn.name != "__init__":
        out.append("return")
    return out


def _public(name: str) -> bool:
    return not name.startswith("_") or name in _CHECKED_DUNDERS


def check_file(path: Path) -> list[tuple[int, str, list[str]]]:
    """``(line, qualified name, missing parts)`` for each unannotated public callable in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[int, str, list[str]]] = []
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            if miss := _missing(node, is_method=False):
                found.append((node.lineno, node.name, miss))
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and _public(item.name):
                    if miss := _missing(item, is_method=True):
                        found.append((item.lineno, f"{node.name}.{item.name}", miss))
    return found


def unannotated(package_dir: str | Path) -> list[str]:
    """One ``path:line: name (missing: ...)`` line per unannotated public callable under ``package_dir``."""
    root = Path(package_dir)
    lines = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        for line, name, miss in check_file(path):
            lines.append(f"{rel}:{line}: {name} (missing: {', '.join(miss)})")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Print the offenders under the package directory (default: this checkout's torchbrdf/)."""
    args = sys.argv[1:] if argv is None else argv
    pkg = Path(args[0]) if args else Path(__file__).resolve().parent.parent / "torchbrdf"
    bad = unannotated(pkg)
    print("\n".join(bad) if bad else "all public callables are annotated")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
