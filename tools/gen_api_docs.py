"""Write ``docs/api.md``, the API reference of ``torchbrdf``, ``torchbrdf.render`` and ``torchbrdf.recovery``.

Usage: ``python tools/gen_api_docs.py [--check]``. The page is generated from the docstrings and
signatures: the names of ``torchbrdf.__all__`` and ``torchbrdf.recovery.__all__``, and the public
names each ``torchbrdf.render`` submodule defines. ``--check`` writes nothing and exits 1 when the
committed page differs from what the code gives (``tests/test_api_docs.py`` runs it).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import re
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "api.md"
RENDER_MODULES = ("gbuffer", "geometry", "lights", "shading", "envmap", "sampling")

_ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|obj|exc):`~?([^`]+)`")


def _markdown(doc: str | None) -> str:
    """A docstring as Markdown: its first paragraph as text (reST roles and double backquotes
    become code spans), the rest (arguments, shapes, examples) verbatim in a text block."""
    if not doc:
        return ""
    head, _, rest = inspect.cleandoc(doc).partition("\n\n")
    head = _ROLE.sub(lambda m: f"`{m.group(1)}`", head).replace("``", "`").replace("::", ":")
    return head + (f"\n\n```text\n{rest.strip()}\n```" if rest.strip() else "")


def _signature(name: str, obj: object) -> str:
    try:
        sig = str(inspect.signature(obj))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return name
    return name + re.sub(r" at 0x[0-9a-f]+", "", sig)


def _public_methods(cls: type) -> list[tuple[str, object]]:
    out = []
    for name, member in vars(cls).items():
        if (name.startswith("_") and name != "__call__") or name == "extra_repr":
            continue
        if isinstance(member, (staticmethod, classmethod)):
            member = member.__func__
        if inspect.isfunction(member) or isinstance(member, property):
            out.append((name, member))
    return out


def _entry(qual: str, obj: object, level: str = "###") -> list[str]:
    name = qual.rsplit(".", 1)[-1]
    if inspect.ismodule(obj):
        summary = _markdown(obj.__doc__).split("\n\n")[0]
        return [f"{level} `{qual}` (module)", "", summary, ""]
    if inspect.isclass(obj):
        lines = [f"{level} `{qual}` (class)", "", f"```python\n{_signature(name, obj)}\n```", "",
                 _markdown(obj.__doc__), ""]
        for mname, member in _public_methods(obj):
            if isinstance(member, property):
                lines += [f"- `{name}.{mname}` (property): " + _markdown(member.__doc__).split("\n\n")[0], ""]
            else:
                first = _markdown(getattr(member, "__doc__", None)).split("\n\n")[0]
                lines += [f"- `{_signature(f'{name}.{mname}', member)}`" + (f": {first}" if first else ""), ""]
        return lines
    if callable(obj):
        return [f"{level} `{qual}`", "", f"```python\n{_signature(name, obj)}\n```", "",
                _markdown(getattr(obj, "__doc__", None)), ""]
    value = repr(obj)
    value = value if len(value) <= 200 else value[:200] + " …"
    return [f"{level} `{qual}` (constant)", "", f"```python\n{name} = {value}\n```", ""]


def _section(mod: ModuleType, names: list[str], title: str) -> list[str]:
    lines = [f"## {title}", "", _markdown(mod.__doc__).split("\n\n")[0], ""]
    for n in names:
        lines += _entry(f"{mod.__name__}.{n}", getattr(mod, n))
    return lines


def _defined_here(mod: ModuleType) -> list[str]:
    names = getattr(mod, "__all__", None)
    if names is not None:
        return list(names)
    return [n for n, o in vars(mod).items() if not n.startswith("_") and not inspect.ismodule(o)
            and getattr(o, "__module__", None) == mod.__name__ and (inspect.isclass(o) or callable(o))]


def generate() -> str:
    """The page's Markdown text."""
    import torchbrdf
    import torchbrdf.recovery

    lines = ["# API reference", "",
             "Generated from the docstrings by `python tools/gen_api_docs.py`; do not edit by hand. "
             "Conventions (channel-last vectors, `(B, C, H, W)` images, dtype and device kept) are in the "
             "[README](../README.md#conventions); the fixed public contract is the part named in it.", "",
             "- [`torchbrdf`](#torchbrdf)",
             *[f"- [`torchbrdf.render.{m}`](#torchbrdfrender{m})" for m in RENDER_MODULES],
             "- [`torchbrdf.recovery`](#torchbrdfrecovery)", ""]
    lines += _section(torchbrdf, list(torchbrdf.__all__), "`torchbrdf`")
    for m in RENDER_MODULES:
        mod = importlib.import_module(f"torchbrdf.render.{m}")
        lines += _section(mod, _defined_here(mod), f"`torchbrdf.render.{m}`")
    lines += _section(torchbrdf.recovery, list(torchbrdf.recovery.__all__), "`torchbrdf.recovery`")
    text = "\n".join(lines).rstrip() + "\n"
    return re.sub(r"\n{3,}", "\n\n", text)


def main(argv: list[str] | None = None) -> int:
    """Write the page, or with ``--check`` compare it; returns the exit status."""
    p = argparse.ArgumentParser(prog="python tools/gen_api_docs.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="exit 1 if docs/api.md is not current; write nothing")
    a = p.parse_args(argv)
    text = generate()
    if a.check:
        current = PAGE.read_text() if PAGE.exists() else ""
        if current != text:
            print(f"{PAGE} is out of date: run python tools/gen_api_docs.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    print(f"wrote {PAGE} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
