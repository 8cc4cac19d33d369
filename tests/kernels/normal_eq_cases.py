"""Cases for the normal-equations operators' tests, and spies on their calls and Triton kernels."""

from __future__ import annotations

import importlib

import pytest
import torch

import torchbrdf

ne_ops = importlib.import_module("torchbrdf.kernels.normal_eq_ops")
EPS = 1e-3


def capture_case(N, L, dtype=torch.float64, seed=0, metal_frac=0.5):
    """A case ``[theta, metal, points, camera, light_pos, light_int, log_obs]`` in ``dtype``:
    ``N`` pixels (``metal_frac`` of them metal) under ``L`` lights, every light's targets
    different, one residual clamped."""
    g = torch.Generator().manual_seed(seed)
    theta = torch.randn(N, 7, generator=g, dtype=torch.float64) * 1.5
    theta[:, 5:7] *= 0.3  # normals within ~40° of +z
    metal = (torch.rand(N, 1, generator=g, dtype=torch.float64) < metal_frac).double()
    points = torch.cat((torch.rand(N, 2, generator=g, dtype=torch.float64) * 2 - 1,
                        torch.zeros(N, 1, dtype=torch.float64)), -1)
    ang = torch.arange(L, dtype=torch.float64) * (6.283 / L)
    lpos = torch.stack((2 * ang.cos(), 2 * ang.sin(), torch.full_like(ang, 2.0)), -1)
    lint = torch.full((L, 3), 20.0, dtype=torch.float64) + torch.rand(L, 3, generator=g, dtype=torch.float64)
    cam = torch.tensor([0.1, -0.2, 3.0], dtype=torch.float64)
    obs = torch.rand(N, L, 3, generator=g, dtype=torch.float64) * 2.0
    obs[0, 0] = -0.5 * EPS  # a pixel whose log residual is clamped under one light
    log_obs = torch.log(torch.clamp(obs + EPS, min=0.5 * EPS))
    cast = [t.to(dtype) for t in (theta, metal, points, cam, lpos, lint, log_obs)]
    return cast


def interpreted_triton(monkeypatch, tmp_path, run):
    """``run()`` with the Triton kernels under the interpreter; returns its result and the
    kernels built ``[(spec, kernel or None)]``."""
    pytest.importorskip("triton")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path))
    built = []
    real = ne_ops._triton_kernel

    def spy(spec, wide):
        hit = real(spec, wide)
        built.append((spec, hit))
        return hit

    monkeypatch.setattr(ne_ops, "_triton_kernel", spy)
    torchbrdf.set_backend("triton")
    try:
        return run(), built
    finally:
        torchbrdf.set_backend(None)


def op_calls(name: str, run) -> list[tuple]:
    """The argument tuples of every call of ``normal_eq_ops.<name>`` (an operator) during ``run()``."""
    calls = []
    real = getattr(ne_ops, name)

    def spy(*args):
        calls.append(args)
        return real(*args)

    setattr(ne_ops, name, spy)
    try:
        run()
    finally:
        setattr(ne_ops, name, real)
    return calls
