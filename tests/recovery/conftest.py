"""Shared fixtures of the recovery tests: a tiny synthetic capture and its recovery."""

import pytest

from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.recovery.svbrdf import RecoveryConfig, recover


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap")
    generate_capture(folder, recipe="metal_inlay", seed=2, size=32, lights=8, noise=0.01)
    return folder


@pytest.fixture(scope="module")
def tiny_result(tiny):
    return recover(tiny, RecoveryConfig(seed=0, threads=2), None, gt=tiny / "gt", progress=False)
