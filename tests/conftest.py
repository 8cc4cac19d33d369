"""Shared fixtures: device (CPU, plus CUDA when present) and random geometry helpers."""

import os

import numpy as np
import pytest
import torch

# Under pytest-xdist every worker is a process; one torch thread each keeps the workers from
# oversubscribing the cores (measured: 10-15x slowdowns otherwise on a 2-core machine).
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def random_unit(rng: np.random.Generator, shape) -> np.ndarray:
    """Uniform random unit vectors, shape ``shape + (3,)``, float64."""
    v = rng.normal(size=tuple(shape) + (3,))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_frame(rng: np.random.Generator, count: int):
    """Random orthonormal frames (x, y, n), each ``(count, 3)`` float64."""
    n = random_unit(rng, (count,))
    t = random_unit(rng, (count,))
    x = t - (t * n).sum(-1, keepdims=True) * n
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(n, x)
    return x, y, n


def hemisphere_pairs(rng: np.random.Generator, count: int, min_cos: float = 0.0):
    """Frames plus l, v in the upper hemisphere of n with cosines above ``min_cos``."""
    x, y, n = random_frame(rng, count)

    def upper():
        w = np.empty((0, 3))
        while len(w) < count:
            cand = random_unit(rng, (count * 3,))
            cand = cand[cand[:, 2] > min_cos]
            w = np.concatenate([w, cand])
        w = w[:count]
        return w[:, :1] * x + w[:, 1:2] * y + w[:, 2:3] * n

    return x, y, n, upper(), upper()
