"""The light-loop printer's carried loads (kernels/light_loop.py, ``Layout.carry_loads``).

The normal-equations kernels copy each pixel's interleaved inputs and tangents into lane-contiguous
block arrays once per block, where they were read with a stride once per pixel-light. Only where
the values are read may change: the kernels' outputs must keep their bits, on the recovery's
inputs (the decode's three tangent rows, the residuals stored) in float32 and float64. (The
Triton printer names every load its pre-loop reads there already: its source is the same.)
"""

import dataclasses
import importlib
import re

import pytest
import torch

from torchbrdf.kernels import build
from torchbrdf.kernels import codegen_normal_eq as cne
from torchbrdf.kernels.normal_eq_ops import normal_equations
from torchbrdf.recovery.params import decode_directions, decode_pattern, decode_slots

from tests.kernels.normal_eq_cases import EPS, capture_case

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")


def _recovery_call(dtype, N=37, L=5, seed=3):
    """The recovery's normal equations (7 unknowns, three tangent rows, residuals) on a case."""
    theta, metal, points, cam, lpos, lint, log_obs = capture_case(N, L, dtype, seed=seed)
    log_obs[4, 1, 2] = float("nan")  # a target the model cannot match: NaN residual and cost
    p, dp = decode_directions(theta, metal, decode_slots(7))
    pattern = decode_pattern(7)

    def run():
        return normal_equations(p, {k: dp[k] for k in pattern}, points, cam, lpos, lint, log_obs, EPS,
                                pattern, 7, residuals=True)

    return run


def _without_carried_loads(monkeypatch):
    """Print the normal-equations kernels re-reading their inputs inside the light loop, in a
    fresh kernel table (the cache keys do not name the layout)."""
    layout = cne._layout
    monkeypatch.setattr(cne, "_layout", lambda spec: dataclasses.replace(layout(spec), carry_loads=False))
    monkeypatch.setattr(ne_ops, "_kernels", {})


def _spec(dtype):
    return cne.NormalEqSpec("float" if dtype == torch.float32 else "double",
                            [("pos", 3), ("n", 3), ("base_color", 3), ("metallic", 1), ("specular", 1),
                             ("roughness", 1)],
                            ["subsurface", "specular_tint", "anisotropic", "sheen", "sheen_tint", "clearcoat",
                             "clearcoat_gloss"], ["diffuse", "specular"], False, 7,
                            [[], [(5, c, 1) for c in range(3)] + [(6, c, 2) for c in range(3)],
                             [(c, c, 0) for c in range(3)], [], [(3, 0, 0)], [(4, 0, 0)]], residuals=True)


def test_c_light_loop_reads_only_the_targets_from_memory():
    # the loop over the lights reads its per-pixel inputs and tangents from the block's arrays;
    # the only tensor it loads is the per-pixel-light targets
    src = cne.generate(_spec(torch.float32))
    loop = src.split("for (long j = 0; j < L; ++j) {", 1)[1].split("\n    }\n", 1)[0]
    assert re.findall(r"\blo\[", loop)
    assert not re.findall(r"\b[pt]\d+\[", loop)
    assert re.findall(r"\bp0\[", src.split("for (long j = 0; j < L; ++j) {", 1)[0])  # read before it


@pytest.mark.skipif(not build.available(), reason="needs the C kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_c_kernel_keeps_its_bits_with_carried_loads(monkeypatch, dtype):
    run = _recovery_call(dtype)
    carried = run()
    assert carried[0].isnan().any() and carried[1].isfinite().all()
    _without_carried_loads(monkeypatch)
    strided = run()
    assert any(k[0] == "c" for k in ne_ops._kernels)  # the C kernel, printed anew, ran
    for a, b in zip(carried, strided):
        assert torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0)) and torch.equal(a.isnan(), b.isnan())
