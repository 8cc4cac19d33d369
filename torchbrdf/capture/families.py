"""Procedural material families beyond :func:`~torchbrdf.capture.synthetic.make_material`'s recipes.

Each family is a class of real surfaces with its own parameter ranges, drawn from fractal
noise, grooves and soft fronts (the building blocks of :mod:`torchbrdf.capture.synthetic`):

============== =============================================================================
family         what it is (roughness / specular / metallic)
============== =============================================================================
cloth          woven rough dielectric: 0.7–0.9 / 0.2–0.45 / 0
plaster        bright, bumpy, rough high-specular dielectric: 0.55–0.8 / 0.4–0.55 / 0
rubber         dark rough dielectric with fine grain: 0.55–0.75 / 0.25–0.5 / 0
raw_wood       unfinished wood, grain stripes: 0.6–0.85 / 0.2–0.45 / 0
ceramic_tiles  glossy tile faces 0.15–0.35 / 0.3–0.7, rough grout grooves / 0
lacquer        dark glossy lacquer, sparse bumps: 0.15–0.3 / 0.4–0.6 / 0
brushed_metal  metal with streaks along one direction: 0.25–0.45 / 0.5 / 1
rusted_metal   steel with a soft rust front (rust 0.7–0.9): metallic ramps 1 → 0
patina_copper  copper with a rough green patina (0.65–0.85), soft edges
mixed          enamel paint over metal, chipped with soft edges, metal studs
============== =============================================================================

:func:`make_family_material` returns exactly :func:`~torchbrdf.capture.synthetic.make_material`'s
layout, deterministic in ``(family, seed, size)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.capture.synthetic import (
    METAL_F0,
    fractal_noise,
    hsv_color,
    inlay_sdf,
    metal_color,
    pack_maps,
    pick_uniform,
    pixel_coords,
    random_color,
    scratch_mask,
    smoothstep,
    soft_step,
    tile_grid,
)

__all__ = ["FAMILIES", "DIELECTRIC_FAMILIES", "make_family_material"]

_Fields = tuple[Tensor, Tensor, Tensor, Tensor, Tensor]  # base (3,S,S), rough, metal, spec, height (S,S)


def _cloth(gen: torch.Generator, size: int) -> _Fields:
    x, y = pixel_coords(size)
    freq = pick_uniform(gen, 40.0, 70.0)
    warp, weft = torch.sin(freq * x), torch.sin(freq * y)
    over = (torch.sin(freq * 0.5 * (x + y)) > 0).float()  # which thread lies on top
    weave = over * warp.abs() + (1 - over) * weft.abs()
    c0, c1 = random_color(gen, (0.3, 0.8), (0.15, 0.7)), random_color(gen, (0.3, 0.8), (0.15, 0.7))
    t = smoothstep(-0.4, 0.4, fractal_noise(gen, size, 3))[None]
    base = (c0[:, None, None] * t + c1[:, None, None] * (1 - t)) * (0.8 + 0.2 * weave)[None]
    rough = pick_uniform(gen, 0.75, 0.85) + 0.05 * fractal_noise(gen, size, 8)
    spec = pick_uniform(gen, 0.25, 0.4) + 0.05 * fractal_noise(gen, size, 5)
    height = 0.004 * weave + 0.002 * fractal_noise(gen, size, 6, 3)
    return base, rough, torch.zeros(size, size), spec, height


def _plaster(gen: torch.Generator, size: int) -> _Fields:
    col = random_color(gen, (0.0, 0.15), (0.6, 0.85))
    n = fractal_noise(gen, size, 10, 5, 0.6)
    base = col[:, None, None] * (1 + 0.08 * fractal_noise(gen, size, 6))[None]
    rough = pick_uniform(gen, 0.6, 0.75) + 0.05 * n
    spec = pick_uniform(gen, 0.42, 0.52) + 0.03 * fractal_noise(gen, size, 4)
    height = 0.015 * n
    return base, rough, torch.zeros(size, size), spec, height


def _rubber(gen: torch.Generator, size: int) -> _Fields:
    col = random_color(gen, (0.0, 0.5), (0.04, 0.15))
    grain = fractal_noise(gen, size, 32, 2)
    base = col[:, None, None] * (1 + 0.1 * grain)[None]
    rough = pick_uniform(gen, 0.6, 0.7) + 0.05 * fractal_noise(gen, size, 6)
    spec = torch.full((size, size), pick_uniform(gen, 0.3, 0.45))
    height = 0.002 * grain + 0.003 * fractal_noise(gen, size, 4, 2)
    return base, rough, torch.zeros(size, size), spec, height


def _raw_wood(gen: torch.Generator, size: int) -> _Fields:
    x, y = pixel_coords(size)
    ang = pick_uniform(gen, -0.3, 0.3)
    u = x * math.sin(ang) + y * math.cos(ang)
    rings = torch.sin(pick_uniform(gen, 14.0, 24.0) * (u + 0.2 * fractal_noise(gen, size, 3))
                      + 2 * fractal_noise(gen, size, 8))
    t = (rings * 0.5 + 0.5)[None]
    c0, c1 = hsv_color(pick_uniform(gen, 0.06, 0.1), pick_uniform(gen, 0.35, 0.6), pick_uniform(gen, 0.45, 0.7)), \
        hsv_color(pick_uniform(gen, 0.05, 0.09), pick_uniform(gen, 0.5, 0.75), pick_uniform(gen, 0.2, 0.35))
    base = c0[:, None, None] * t + c1[:, None, None] * (1 - t)
    rough = pick_uniform(gen, 0.65, 0.75) + 0.08 * t[0] * 2 - 0.08
    spec = pick_uniform(gen, 0.25, 0.4) + 0.05 * fractal_noise(gen, size, 4)
    height = 0.003 * t[0] + 0.002 * fractal_noise(gen, size, 16, 2)
    return base, rough, torch.zeros(size, size), spec, height


def _ceramic_tiles(gen: torch.Generator, size: int) -> _Fields:
    n_tiles = int(torch.randint(2, 5, (1,), generator=gen))
    tid, edge = tile_grid(size, n_tiles)
    grout_w = pick_uniform(gen, 0.03, 0.06)
    tile = smoothstep(grout_w, grout_w + 0.05, edge)
    k = n_tiles * n_tiles
    cols = torch.stack([random_color(gen, (0.1, 0.6), (0.25, 0.8)) for _ in range(k)])
    rough_t = torch.tensor([pick_uniform(gen, 0.18, 0.32) for _ in range(k)])
    spec_t = torch.tensor([pick_uniform(gen, 0.3, 0.7) for _ in range(k)])
    grout = random_color(gen, (0.0, 0.15), (0.2, 0.4))
    base = cols[tid].permute(2, 0, 1) * tile + grout[:, None, None] * (1 - tile)
    rough = (rough_t[tid] + 0.02 * fractal_noise(gen, size, 6)) * tile + 0.85 * (1 - tile)
    spec = spec_t[tid] * tile + 0.35 * (1 - tile)
    # a glaze slightly domed toward each tile's centre: glints move across the faces
    height = 0.02 * tile + 0.01 * smoothstep(0.0, 0.5, edge) + 0.001 * fractal_noise(gen, size, 12, 3)
    return base, rough, torch.zeros(size, size), spec, height


def _lacquer(gen: torch.Generator, size: int) -> _Fields:
    col = random_color(gen, (0.3, 0.9), (0.03, 0.12))
    base = col[:, None, None].expand(3, size, size) * (1 + 0.05 * fractal_noise(gen, size, 4))[None]
    rough = pick_uniform(gen, 0.17, 0.28) + 0.03 * fractal_noise(gen, size, 5)
    spec = torch.full((size, size), pick_uniform(gen, 0.4, 0.6))
    # sparse low bumps (brush marks): few pixels tilt toward a light's mirror direction
    bumps = F.relu(fractal_noise(gen, size, 6, 3) - 0.25)
    height = 0.03 * bumps + 0.001 * fractal_noise(gen, size, 20, 2)
    return base, rough, torch.zeros(size, size), spec, height


def _brushed_metal(gen: torch.Generator, size: int) -> _Fields:
    x, y = pixel_coords(size)
    ang = pick_uniform(gen, 0.0, math.pi)
    streaks = scratch_mask(gen, x, y, 120, (0.3, 1.2), angle=ang)
    mcol = metal_color(gen)
    base = mcol[:, None, None] * (1 + 0.04 * fractal_noise(gen, size, 8))[None]
    rough = pick_uniform(gen, 0.28, 0.38) + 0.08 * streaks + 0.03 * fractal_noise(gen, size, 8)
    height = -0.002 * streaks + 0.001 * fractal_noise(gen, size, 16, 2)
    return base, rough, torch.ones(size, size), torch.full((size, size), 0.5), height


def _rusted_metal(gen: torch.Generator, size: int) -> _Fields:
    mcol = torch.tensor(METAL_F0["iron"])
    rust_col = hsv_color(pick_uniform(gen, 0.02, 0.07), pick_uniform(gen, 0.6, 0.85), pick_uniform(gen, 0.15, 0.4))
    field = fractal_noise(gen, size, 4, 5) + 0.3 * fractal_noise(gen, size, 16, 3)
    rust = soft_step(field, pick_uniform(gen, 0.35, 0.6), pick_uniform(gen, 0.08, 0.14))
    pits = fractal_noise(gen, size, 24, 2)
    base = mcol[:, None, None] * (1 - rust) + rust_col[:, None, None] * (1 + 0.2 * pits)[None] * rust
    rough = (pick_uniform(gen, 0.25, 0.35) + 0.04 * fractal_noise(gen, size, 8)) * (1 - rust) \
        + pick_uniform(gen, 0.75, 0.85) * rust
    height = 0.004 * rust + 0.003 * pits * rust
    return base, rough, 1 - rust, torch.full((size, size), 0.5), height


def _patina_copper(gen: torch.Generator, size: int) -> _Fields:
    mcol = torch.tensor(METAL_F0["copper"])
    pat_col = hsv_color(pick_uniform(gen, 0.42, 0.5), pick_uniform(gen, 0.3, 0.55), pick_uniform(gen, 0.3, 0.55))
    field = fractal_noise(gen, size, 3, 5) + 0.3 * fractal_noise(gen, size, 10, 3)
    patina = soft_step(field, pick_uniform(gen, 0.3, 0.55), pick_uniform(gen, 0.1, 0.15))
    base = mcol[:, None, None] * (1 - patina) \
        + pat_col[:, None, None] * (1 + 0.15 * fractal_noise(gen, size, 12))[None] * patina
    rough = (pick_uniform(gen, 0.3, 0.4) + 0.05 * fractal_noise(gen, size, 8)) * (1 - patina) \
        + (pick_uniform(gen, 0.7, 0.8) + 0.05 * fractal_noise(gen, size, 6)) * patina
    height = 0.004 * patina + 0.003 * fractal_noise(gen, size, 12, 3) * patina
    return base, rough, 1 - patina, torch.full((size, size), 0.5), height


def _mixed(gen: torch.Generator, size: int) -> _Fields:
    x, y = pixel_coords(size)
    mcol = metal_color(gen)
    paint = random_color(gen, (0.4, 0.9), (0.2, 0.7))
    chips = soft_step(fractal_noise(gen, size, 6, 4), pick_uniform(gen, 0.15, 0.3), pick_uniform(gen, 0.06, 0.1))
    studs = (inlay_sdf(gen, x, y, (2, 5), 0.7, (0.08, 0.16)) < 0).float()
    studs = F.avg_pool2d(studs[None, None], 3, 1, 1)[0, 0]  # filtered edges
    metal = torch.maximum(chips, studs)
    base = mcol[:, None, None] * metal + paint[:, None, None] * (1 - metal)
    rough = (pick_uniform(gen, 0.25, 0.4) + 0.04 * fractal_noise(gen, size, 8)) * metal \
        + pick_uniform(gen, 0.4, 0.6) * (1 - metal)
    spec = torch.full((size, size), pick_uniform(gen, 0.4, 0.6))
    height = 0.004 * (1 - chips) + 0.008 * studs + 0.001 * fractal_noise(gen, size, 16, 2)
    return base, rough, metal, spec, height


_FAMILY_FUNCS: dict[str, Callable[[torch.Generator, int], _Fields]] = {
    "cloth": _cloth,
    "plaster": _plaster,
    "rubber": _rubber,
    "raw_wood": _raw_wood,
    "ceramic_tiles": _ceramic_tiles,
    "lacquer": _lacquer,
    "brushed_metal": _brushed_metal,
    "rusted_metal": _rusted_metal,
    "patina_copper": _patina_copper,
    "mixed": _mixed,
}

#: Families understood by :func:`make_family_material`.
FAMILIES: tuple[str, ...] = tuple(_FAMILY_FUNCS)
#: The families with metallic 0 everywhere (where any pixel called metal is a false metal).
DIELECTRIC_FAMILIES: tuple[str, ...] = ("cloth", "plaster", "rubber", "raw_wood", "ceramic_tiles", "lacquer")


def make_family_material(family: str, seed: int = 0, size: int = 256) -> dict[str, Tensor]:
    """Ground-truth SVBRDF maps of one material of a family.

    Args:
        family: one of :data:`FAMILIES`.
        seed: random seed; the maps are a deterministic function of ``(family, seed, size)``.
        size: output resolution (square), >= 4.

    Returns:
        dict with ``base_color (3, H, W)``, ``roughness``, ``metallic``, ``specular``
        ``(1, H, W)`` and ``normal (3, H, W)`` (tangent-space unit vectors, z > 0), float32 on
        the CPU: :func:`~torchbrdf.capture.synthetic.make_material`'s layout.

    Example:
        >>> m = make_family_material("cloth", seed=1, size=32)
        >>> sorted(m), tuple(m["roughness"].shape)
        (['base_color', 'metallic', 'normal', 'roughness', 'specular'], (1, 32, 32))
    """
    if family not in _FAMILY_FUNCS:
        raise ValueError(f"make_family_material: unknown family {family!r}; choose one of {FAMILIES}")
    if size < 4:
        raise ValueError(f"make_family_material: size must be >= 4, got {size}")
    gen = torch.Generator().manual_seed(int(seed) * 104_729 + 31 * FAMILIES.index(family) + 5)
    return pack_maps(*_FAMILY_FUNCS[family](gen, size))
