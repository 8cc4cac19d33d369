"""The renderer's modules hold one concept each: sizes, private names and the envmap re-export."""

import ast
import pathlib

import torchbrdf
from torchbrdf.render import envmap

RENDER = pathlib.Path(torchbrdf.__file__).parent / "render"
MODULES = sorted(RENDER.rglob("*.py"))


def _tree(path):
    return ast.parse(path.read_text(), filename=str(path))


def test_no_render_module_over_900_lines():
    long = [f"{p.relative_to(RENDER)}: {len(p.read_text().splitlines())}" for p in MODULES
            if len(p.read_text().splitlines()) > 900]
    assert not long, long


def test_no_render_function_over_120_lines():
    long = [
        f"{p.relative_to(RENDER)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for p in MODULES
        for node in ast.walk(_tree(p))
        if isinstance(node, ast.FunctionDef) and node.end_lineno - node.lineno + 1 > 120
    ]
    assert not long, long


def test_render_modules_import_no_private_names_of_each_other():
    # Names one render module uses from another are public within the package (e.g. the
    # shader's Monte Carlo pass is env.mc_pass, not envmap._mc_pass).
    bad = [
        f"{p.relative_to(RENDER)}:{node.lineno} {node.module}.{alias.name}"
        for p in MODULES
        for node in ast.walk(_tree(p))
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("torchbrdf.render")
        for alias in node.names
        if alias.name.startswith("_")
    ]
    assert not bad, bad


def test_one_is_zero():
    # "a Python number equal to 0" is defined once (torchbrdf._math.is_zero) and imported.
    package = pathlib.Path(torchbrdf.__file__).parent
    defs = [
        f"{p.relative_to(package)}:{node.lineno}"
        for p in sorted(package.rglob("*.py"))
        for node in ast.walk(_tree(p))
        if isinstance(node, ast.FunctionDef) and node.name.lstrip("_") == "is_zero"
    ]
    assert defs == ["_math.py:" + defs[0].split(":")[1]], defs


def test_envmap_keeps_its_public_names():
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
