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
    """Every command in the bash blocks of the README and the recovery pages, as arguments after python."""
    pages = (README, ROOT / "docs" / "recovery.md", ROOT / "docs" / "recovery_measurements.md")
    text = "\n".join(b for p in pages for b in re.findall(r"```bash\n(.*?)```", p.read_text(), re.S))
    modules = [["-m", m] for m in re.findall(r"python -m ((?:torchbrdf|training)[\w.]*)", text)]
    files = [[f] for f in re.findall(r"python ((?:datasets|training)/\w+\.py)", text)]
    scripts = [["-c", f"import sys; sys.argv[0] = {s!r}; from {t.split(':')[0]} import main; sys.exit(main())"]
               for s, t in _SCRIPTS.items() if re.search(rf"(?m)^{s}\b", text)]
    return sorted({tuple(c) for c in modules + files + scripts})


_SCRIPTS = {"torchbrdf-recover-many": "torchbrdf.recovery.batch:main", "torchbrdf-recover": "torchbrdf.recovery.svbrdf:main",
            "torchbrdf-fit-merl": "torchbrdf.recovery.fit_measured:main", "torchbrdf-explore": "torchbrdf.analysis.explore:main",
            "torchbrdf-bench": "torchbrdf.bench.brdf:main"}


@pytest.mark.parametrize("command", _readme_commands(), ids=lambda c: " ".join(c)[:60])
def test_readme_commands_exist(command):
    res = subprocess.run([sys.executable, *command, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower()


def _table_rows(text: str, header_start: str) -> dict[str, list[str]]:
    """The rows of the first Markdown table whose header starts with ``header_start``, by first cell + seed."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = {}
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[" ".join(cells[:2])] = cells[2:]
    return rows


def test_readme_accuracy_table_is_the_recovery_docs_table():
    """The README's recovery accuracy figures are the reference page's, cell for cell."""
    header = "| material | seed | base RMSE"
    readme = _table_rows(README.read_text(), header)
    docs = _table_rows((ROOT / "docs" / "recovery.md").read_text(), header)
    assert len(readme) == 5
    assert readme == docs


def test_readme_states_each_demo_time_once():
    """Every time of the ``--demo`` recovery is in the one table, and no sentence restates one."""
    text = README.read_text()
    table = _table_rows(text, "| load on the 2 cores |")
    assert len(table) >= 2 and len({len(r) for r in table.values()}) == 1 and len(next(iter(table.values()))) >= 2
    times = re.compile(r"\d+(?:\.\d+)?\s?s\b")
    for line in text.splitlines():
        if line.startswith("|"):
            continue
        if "demo" in line.lower():
            assert not times.search(line.replace("the fit alone", "")) or "2.6–2.7 s" in line, line
    # busier machines never look faster for the default thread count
    default = [float(re.match(r"[\d.]+", r[0]).group(0)) for r in table.values()]
    assert default == sorted(default)


def test_readme_names_every_console_script():
    import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    text = README.read_text()
    assert [s for s in scripts if f"`{s}`" not in text] == []


def test_readme_layout_lists_every_script_and_folder():
    layout = README.read_text().split("## Layout", 1)[1]
    for folder in ("training", "datasets", "tools"):
        for f in sorted((ROOT / folder).glob("*.py")):
            assert f.name in layout, f"{folder}/{f.name} missing from the README's layout"


def test_docs_have_no_work_log():
    """Reference pages, not a lab notebook: no issue numbers, clock times or dated narration."""
    pattern = re.compile(r"issue[ -]\d+|\d{2}:\d{2} UTC|\bsession\b|latest round|previous round"
                         r"|before the last|\bused before|was landed|\| now \| before \|", re.I)
    pages = [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
    hits = [f"{p.name}: {m.group(0)}" for p in pages if p.exists() for m in pattern.finditer(p.read_text())]
    assert hits == []
    assert len((ROOT / "docs" / "recovery.md").read_text().splitlines()) <= 800


def _anchor(heading: str, seen: dict[str, int]) -> str:
    """GitHub's anchor of a heading: lower case, punctuation and backticks dropped, spaces to dashes."""
    slug = "".join(c for c in heading.strip().lower() if c.isalnum() or c in " -_").replace(" ", "-")
    n = seen.get(slug, 0)
    seen[slug] = n + 1
    return slug if n == 0 else f"{slug}-{n}"


def test_docs_relative_links_and_anchors_resolve():
    """Every relative link of the README and docs/*.md names an existing file, and an anchor its page has."""
    pages = [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
    anchors = {}
    for p in pages:
        seen: dict[str, int] = {}
        text = re.sub(r"```.*?```", "", p.read_text(), flags=re.S)
        anchors[p.resolve()] = {_anchor(h, seen) for h in re.findall(r"(?m)^#{1,6} (.+)$", text)}
    broken = []
    for p in pages:
        for target in re.findall(r"\]\(([^)\s]+)\)", p.read_text()):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            file = (p.parent / path).resolve() if path else p.resolve()
            if not file.exists() or (anchor and file.suffix == ".md" and anchor not in anchors.get(file, ())):
                broken.append(f"{p.name}: {target}")
    assert broken == []


def test_recovery_options_table_matches_the_config_and_the_cli(capsys):
    """docs/recovery.md's options table: every RecoveryConfig field with its true default, every flag."""
    import dataclasses

    from torchbrdf.recovery import RecoveryConfig
    from torchbrdf.recovery.svbrdf import main

    text = (ROOT / "docs" / "recovery.md").read_text()
    rows = _table_rows(text, "| option | default | CLI flag | effect |")
    table = {k.split(" ", 1)[0].strip("`"): k.rsplit(" ", 1)[1] for k in rows}  # option -> stated default
    defaults = RecoveryConfig()
    groups = ("schedule", "priors", "calibration", "classes")
    options = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(RecoveryConfig) if f.name not in groups}
    for g in groups:
        options.update({f"{g}.{f.name}": getattr(getattr(defaults, g), f.name)
                        for f in dataclasses.fields(getattr(defaults, g))})
    assert sorted(table) == sorted(options)
    for name, stated in table.items():
        assert stated == f"`{options[name]!r}`", name
    assert main(["--help"]) == 0
    flags = set(re.findall(r"(--[a-z][a-z-]*)", capsys.readouterr().out))
    stated = set(re.findall(r"`(--[a-z][a-z-]*)`", text))
    assert flags - {"--help"} <= stated


@pytest.mark.parametrize("script, target", [
    ("torchbrdf-recover", "torchbrdf.recovery.svbrdf:main"),
    ("torchbrdf-recover-many", "torchbrdf.recovery.batch:main"),
    ("torchbrdf-fit-merl", "torchbrdf.recovery.fit_measured:main"),
    ("torchbrdf-explore", "torchbrdf.analysis.explore:main"),
    ("torchbrdf-bench", "torchbrdf.bench.brdf:main"),
])
def test_console_script_help_names_the_command(script, target, capsys):
    """``--help`` starts with the command a user typed, not ``python -m ...``."""
    import importlib

    module, func = target.split(":")
    try:
        rc = getattr(importlib.import_module(module), func)(["--help"])
    except SystemExit as e:
        rc = e.code
    assert rc in (0, None)
    assert capsys.readouterr().out.startswith(f"usage: {script} ")
