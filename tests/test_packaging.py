"""The wheel installs one import name, ``torchbrdf``, and sits beside a package called ``datasets``.

Hugging Face ``datasets`` is the package a top-level ``datasets`` folder would clobber; a stub
distribution of that name stands in for it here (no network), installed before and after the
torchbrdf wheel.
"""

import pathlib
import subprocess
import sys
import zipfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("wheel")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out),
                          str(ROOT)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {res.stderr[-500:]}")
    (whl,) = out.glob("torchbrdf-*.whl")
    return whl


def _stub_datasets(root: pathlib.Path) -> pathlib.Path:
    """A minimal distribution named ``datasets`` with ``load_dataset``, like Hugging Face's."""
    src = root / "stub"
    (src / "datasets").mkdir(parents=True)
    (src / "datasets" / "__init__.py").write_text("def load_dataset(name):\n    return 'hf:' + name\n")
    (src / "pyproject.toml").write_text(
        '[build-system]\nrequires = ["setuptools"]\nbuild-backend = "setuptools.build_meta"\n'
        '[project]\nname = "datasets"\nversion = "99.0"\n[tool.setuptools]\npackages = ["datasets"]\n')
    return src


def test_wheel_has_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"torchbrdf"}, tops
    assert "torchbrdf/py.typed" in names
    entry = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    for script in ("torchbrdf-recover", "torchbrdf-explore", "torchbrdf-bench", "torchbrdf-fit-merl"):
        assert script in entry


@pytest.mark.parametrize("order", ["datasets_first", "torchbrdf_first"])
def test_installs_beside_a_datasets_package(wheel, tmp_path, order):
    target = tmp_path / "site"
    stub = _stub_datasets(tmp_path)
    steps = [[str(stub)], [str(wheel)]]
    if order == "torchbrdf_first":
        steps.reverse()
    for what in steps:
        res = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                              "--upgrade", "--target", str(target), *what], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr[-2000:]
    # The test run itself may have torchbrdf installed in editable mode: hide that install
    # (its import hook and the checkout on sys.path) so only the target folder is seen.
    code = (f"import sys; sys.path[:] = [p for p in sys.path if p.rstrip('/') != {str(ROOT)!r}];"
            "sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()];"
            "import datasets, torchbrdf.capture, torchbrdf.recovery;"
            "assert datasets.load_dataset('x') == 'hf:x';"
            "assert callable(torchbrdf.capture.generate_capture) and callable(torchbrdf.recovery.recover);"
            "print(torchbrdf.__file__)")
    # Run from an empty folder so the checkout's own folders are not on the path.
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr[-2000:]
    assert str(target) in res.stdout


def test_editable_install_is_visible_to_mypy(tmp_path):
    # setuptools' default editable install is an import hook, which static tools do not run:
    # mypy then types every torchbrdf name as Any. A plain path entry in the .pth they read.
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    res = subprocess.run([sys.executable, "-c", "import sys, setuptools.build_meta as b; "
                          f"print(b.build_editable({str(wheels)!r}))"], cwd=ROOT, capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot build an editable wheel here: {res.stderr[-500:]}")
    (whl,) = wheels.glob("torchbrdf-*.whl")
    zf = zipfile.ZipFile(whl)
    (pth,) = [n for n in zf.namelist() if n.endswith(".pth")]
    lines = zf.read(pth).decode().split()
    assert [pathlib.Path(x).resolve() for x in lines] == [ROOT], lines  # a path, not an "import ..." hook
    # mypy on a user's script, against a bare environment holding only that .pth
    pytest.importorskip("mypy")
    env_dir = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True)
    (site,) = env_dir.glob("lib/python*/site-packages")
    (site / pth).write_bytes(zf.read(pth))
    script = tmp_path / "user.py"
    script.write_text("import torchbrdf\nreveal_type(torchbrdf.principled)\n")
    res = subprocess.run([sys.executable, "-m", "mypy", "--python-executable", str(env_dir / "bin" / "python"),
                          "--follow-imports=silent", "--no-incremental", "--cache-dir", str(tmp_path / "cache"),
                          str(script)], cwd=tmp_path, capture_output=True, text=True)
    assert "Cannot find implementation or library stub" not in res.stdout, res.stdout[-2000:]
    assert 'Revealed type is "def (l:' in res.stdout, res.stdout[-2000:]
