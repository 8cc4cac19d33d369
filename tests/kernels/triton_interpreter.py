"""Fixtures of the Triton-backend tests: Triton's CPU interpreter, the ``triton`` backend, launch spying.

A test module imports them (``from tests.kernels.triton_interpreter import interpreter, launches``);
``interpreter`` is module-scoped and autouse there.
"""

import importlib

import pytest

import torchbrdf

ct = importlib.import_module("torchbrdf.kernels.codegen_triton")


@pytest.fixture(scope="module", autouse=True)
def interpreter(tmp_path_factory):
    """Triton's interpreter and the ``triton`` backend for every test of the importing module."""
    mp = pytest.MonkeyPatch()
    mp.setenv("TRITON_INTERPRET", "1")
    mp.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path_factory.mktemp("kernels")))
    mp.delenv("TORCHBRDF_BACKEND", raising=False)
    mp.delenv("TORCHBRDF_EAGER", raising=False)
    torchbrdf.set_backend("triton")
    yield
    torchbrdf.set_backend(None)
    mp.undo()


@pytest.fixture
def launches(monkeypatch):
    """The kinds of the Triton kernels launched (proves the Triton path really ran)."""
    calls = []
    real = ct.launch

    def spy(kernel, kind, n, P_, args):
        calls.append(kind)
        return real(kernel, kind, n, P_, args)

    monkeypatch.setattr(ct, "launch", spy)
    return calls
