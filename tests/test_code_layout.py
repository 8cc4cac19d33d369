"""The package's code layout: small modules and functions, one-way imports, public names only.

One test module for the whole of ``torchbrdf/`` (read with ``ast``, nothing imported):

* no module over :data:`MAX_MODULE_LINES` lines, no function over :data:`MAX_FUNCTION_LINES`
  (``end_lineno - lineno + 1``) unless :data:`SINGLE_FORMULA_OR_TABLE` names it;
* every ``torchbrdf`` import (at the top or inside a function: a lazy import is still a
  dependency) of a subpackage stays within the "May import" list of that subpackage's
  ``__init__`` docstring, and the units (subpackages, top-level modules, and
  ``brdf.formula``, the formula layer under both the models and the kernels) import each
  other without a cycle;
* no module uses another file's ``_``-prefixed name (``from m import _x`` or ``m._x``);
* the renamed modules keep their old import paths (``render.envmap``, ``brdf.capture_model``).
"""

from __future__ import annotations

import ast
import importlib
import re
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "torchbrdf"
MAX_MODULE_LINES = 900
MAX_FUNCTION_LINES = 120
# "path:function" of functions allowed over MAX_FUNCTION_LINES, each a single formula or table.
SINGLE_FORMULA_OR_TABLE: dict[str, str] = {}
# Plumbing every layer may import: argument checks, gradient-safe helpers, type aliases.
PLUMBING = {"_math", "_checks", "_types"}
# Units: the formula layer is its own node (the kernels trace it; the models evaluate it).
SPLIT_UNITS = {"brdf.formula"}


def _modules(root: Path = ROOT) -> list[Path]:
    return sorted(root.rglob("*.py"))


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["torchbrdf", *parts])


def _unit(dotted: str) -> str:
    """The layering unit of ``torchbrdf.<dotted>``: ``brdf.formula``, else its first component."""
    for split in SPLIT_UNITS:
        if dotted == split or dotted.startswith(split + "."):
            return split
    return dotted.split(".")[0] if dotted else "__init__"


def _imports(path: Path, root: Path = ROOT) -> list[tuple[int, str, str | None]]:
    """``(line, module, name)`` of every import of a ``torchbrdf`` module in ``path``; ``name``
    is the imported name of a ``from`` import (None for ``import m``). Relative imports resolve."""
    me = _module_name(path, root)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, None) for a in node.names if a.name.split(".")[0] == "torchbrdf"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            if base.split(".")[0] == "torchbrdf":
                out += [(node.lineno, base, a.name) for a in node.names]
    return out


def _module_set(root: Path) -> set[str]:
    return {_module_name(p, root) for p in _modules(root)}


def _targets(path: Path, root: Path = ROOT) -> set[str]:
    """Units that ``path`` imports (a ``from m import sub`` of a submodule counts as ``m.sub``)."""
    modules = _module_set(root)
    out = set()
    for _, module, name in _imports(path, root):
        full = f"{module}.{name}" if name and f"{module}.{name}" in modules else module
        out.add(_unit(full.removeprefix("torchbrdf").lstrip(".")))
    return out


def _own_unit(path: Path, root: Path = ROOT) -> str:
    return _unit(_module_name(path, root).removeprefix("torchbrdf").lstrip("."))


def _may_import(package: str, root: Path = ROOT) -> set[str] | None:
    """The units the docstring of ``package/__init__.py`` lets it import (None: anything)."""
    doc = ast.get_docstring(ast.parse((root / package / "__init__.py").read_text())) or ""
    para = doc[doc.index("May import"):] if "May import" in doc else ""
    para = re.split(r"\bNever\b|Nothing above|\n\n", para)[0]
    if para.startswith("May import anything"):
        return None
    return PLUMBING | {_unit(m) for m in re.findall(r"``torchbrdf\.([\w.]+)``", para)}


def _allowed(target: str, allowed: set[str]) -> bool:
    # a whole package allows its split units too (``brdf`` allows ``brdf.formula``)
    return target in allowed or target.split(".")[0] in allowed


def _layering_breaks(root: Path = ROOT) -> dict[str, list[str]]:
    bad = {}
    for init in sorted(root.glob("*/__init__.py")):
        package = init.parent.name
        allowed = _may_import(package, root)
        if allowed is None:
            continue
        for path in _modules(init.parent):
            own = _own_unit(path, root)
            hit = sorted(t for t in _targets(path, root) - {own}
                         if t.split(".")[0] != package and not _allowed(t, allowed))
            if hit:
                bad[str(path.relative_to(root))] = hit
    return bad


def _unit_cycles(root: Path = ROOT) -> list[list[str]]:
    graph: dict[str, set[str]] = {}
    for path in _modules(root):
        own = _own_unit(path, root)
        graph.setdefault(own, set()).update(_targets(path, root) - {own, "__init__"})
    graph.pop("__init__", None)  # the root re-exports everything; nothing below imports it
    cycles, state = [], {}

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return cycles


def _private_uses(root: Path = ROOT) -> list[str]:
    """``file:line name`` of each use of another file's ``_`` name (dunders and ``_`` modules,
    such as ``torchbrdf._math``, are not private names)."""
    modules = _module_set(root)
    bad = []
    for path in _modules(root):
        me = _module_name(path, root)
        where = path.relative_to(root)
        aliases = {}
        for line, module, name in _imports(path, root):
            if name is None:
                continue
            if f"{module}.{name}" in modules:
                aliases[name] = f"{module}.{name}"
            elif name.startswith("_") and not name.startswith("__") and module != me:
                bad.append(f"{where}:{line} from {module} import {name}")
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                for a in node.names:
                    if a.asname and a.name in aliases:
                        aliases[a.asname] = aliases[a.name]
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.asname and a.name in modules:
                        aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith("_")
                    and not node.attr.startswith("__")):
                target = aliases[node.value.id]
                if target != me and f"{target}.{node.attr}" not in modules:
                    bad.append(f"{where}:{node.lineno} {target}.{node.attr}")
    return bad


def _long_functions(root: Path = ROOT) -> list[str]:
    out = []
    for path in _modules(root):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                key = f"{path.relative_to(root)}:{node.name}"
                if length > MAX_FUNCTION_LINES and key not in SINGLE_FORMULA_OR_TABLE:
                    out.append(f"{key} ({length} lines)")
    return out


def _long_modules(root: Path = ROOT) -> list[str]:
    return [f"{p.relative_to(root)}: {n}" for p in _modules(root)
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]


# --------------------------------------------------------------------------- the package


def test_no_module_over_900_lines():
    assert not _long_modules(), _long_modules()


def test_no_function_over_120_lines():
    assert not _long_functions(), _long_functions()


def test_imports_follow_each_packages_docstring():
    assert not _layering_breaks(), _layering_breaks()


def test_every_subpackage_states_its_layering():
    for init in sorted(ROOT.glob("*/__init__.py")):
        if len(list(init.parent.glob("*.py"))) == 1 and not _imports(init):
            continue  # a folder of package data (weights/), no code
        assert "May import" in (ast.get_docstring(ast.parse(init.read_text())) or ""), init.parent.name


def test_no_import_cycle_between_units():
    assert not _unit_cycles(), _unit_cycles()


def test_the_kernels_take_the_formula_not_the_brdf_models():
    targets = set().union(*(_targets(p) for p in _modules(ROOT / "kernels")))
    assert {t for t in targets if t.startswith("brdf")} <= {"brdf.formula"}, targets


def test_no_module_uses_another_files_private_names():
    assert not _private_uses(), _private_uses()


def test_one_is_zero():
    # "a Python number equal to 0" is defined once (torchbrdf._math.is_zero) and imported.
    defs = [f"{p.relative_to(ROOT)}" for p in _modules() for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, ast.FunctionDef) and node.name.lstrip("_") == "is_zero"]
    assert defs == ["_math.py"], defs


def test_microfacet_dispatches_on_name_tables():
    tree = ast.parse((ROOT / "brdf" / "microfacet.py").read_text())
    chains = [node.lineno for node in ast.walk(tree) if isinstance(node, ast.If)
              and isinstance(node.test, ast.Compare) and isinstance(node.test.left, ast.Name)
              and any(isinstance(c, ast.Constant) and isinstance(c.value, str) for c in node.test.comparators)
              and node.orelse and isinstance(node.orelse[0], ast.If)]
    assert not chains, f"if/elif chains on names at lines {chains}; a table does it"


# --------------------------------------------------------------------------- old import paths


def test_capture_model_is_a_deprecated_name_of_svbrdf_ggx():
    from torchbrdf.brdf import svbrdf_ggx

    sys.modules.pop("torchbrdf.brdf.capture_model", None)
    with pytest.warns(DeprecationWarning, match="svbrdf_ggx"):
        old = importlib.import_module("torchbrdf.brdf.capture_model")
    for name in svbrdf_ggx.__all__:
        assert getattr(old, name) is getattr(svbrdf_ggx, name), name


def test_envmap_keeps_its_public_names():
    import torchbrdf
    from torchbrdf.render import envmap

    names = [
        "latlong_lookup", "latlong_bilinear", "integrate_environment_mc",
        "integrate_environment_quadrature", "integrate_environment_split_sum", "prefilter_environment",
        "irradiance_environment", "extract_peaks", "UNIFORM", "split_sum_table", "SplitSumEnvironment",
        "PREFILTER_ROUGHNESS", "SPLIT_SUM_TABLE_CHANNELS", "ENV_SAMPLINGS",
    ]
    assert sorted(envmap.__all__) == sorted(names)
    also = ["PEAK_CONTRAST", "PEAK_DIRECTIONS", "sampling_lobes_for", "brdf_kind", "check_env_sampling"]
    for name in names + also:
        assert hasattr(envmap, name), name
    assert envmap.SplitSumEnvironment is torchbrdf.render.env.split_sum.SplitSumEnvironment


def test_the_bench_cli_keeps_its_entry():
    from torchbrdf.bench import brdf

    assert callable(brdf.main)
    assert "--no-env" in (ROOT / "bench" / "brdf.py").read_text()


# --------------------------------------------------------------------------- the checks can fail


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "torchbrdf"
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_the_checks_see_what_they_forbid(tmp_path):
    root = _package(tmp_path, {
        "__init__.py": "",
        "_math.py": "",
        "brdf/__init__.py": ('"""May import: ``torchbrdf._math`` and ``torchbrdf.kernels``.  '
                             'Never ``render``."""\n'),
        "brdf/formula.py": "from torchbrdf._math import dot\n",
        "brdf/model.py": ("def g():\n    from torchbrdf.render import shade\n"
                          "    from torchbrdf.kernels import ops\n    return ops._pool\n"),
        "kernels/__init__.py": '"""May import: ``torchbrdf.brdf.formula``."""\n',
        "kernels/ops.py": "from torchbrdf.brdf.model import _helper\nfrom ..brdf import formula\n",
        "render/__init__.py": '"""May import: ``torchbrdf.brdf``."""\n',
        "render/shade.py": "def f():\n" + "    x = 1\n" * 130,
    })
    assert _layering_breaks(root) == {"brdf/model.py": ["render"], "kernels/ops.py": ["brdf"]}
    assert _unit_cycles(root) and all(c[0] == c[-1] for c in _unit_cycles(root))
    assert sorted(_private_uses(root)) == ["brdf/model.py:4 torchbrdf.kernels.ops._pool",
                                           "kernels/ops.py:1 from torchbrdf.brdf.model import _helper"]
    assert _long_functions(root) == ["render/shade.py:f (131 lines)"]
    (root / "kernels" / "ops.py").write_text("from torchbrdf.brdf import formula\n")
    (root / "brdf" / "model.py").write_text("from torchbrdf.kernels import ops\n")
    assert _layering_breaks(root) == {} and _unit_cycles(root) == [] and _private_uses(root) == []


def test_no_warning_on_the_new_names():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        importlib.import_module("torchbrdf.brdf.svbrdf_ggx")
