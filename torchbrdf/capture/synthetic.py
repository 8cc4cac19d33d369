"""Synthetic multi-light captures with known ground truth (the formats of docs/capture_format.md).

Three pieces:

* **Procedural materials** (:func:`make_material`): several named recipes built from fractal
  value noise, tiles, scratches, metal inlays and height fields. Each returns ground-truth
  maps ``base_color (3, H, W)``, ``roughness``, ``metallic``, ``specular (1, H, W)`` and a
  tangent-space ``normal (3, H, W)`` (unit, z > 0), all float32 in the capture's pixel layout
  (row 0 is the +y edge). Deterministic in ``(recipe, seed, size)``.
* **Light layouts** (:func:`light_layout`, :func:`random_lights`): a ring of point lights
  plus one beside the camera (a flash), and random lights for held-out evaluation.
* **The renderer** (:func:`render_capture`): the capture format's image formation (docs/capture_format.md),
  ``radiance(p) = f(l, v) · I · max(n·l, 0) / |q − p|²`` with ``f`` the principled BRDF evaluated
  in the normal-mapped frame (tangent by Gram–Schmidt from +X). Both backends
  call :func:`torchbrdf.principled` (the one definition of the formula): ``"principled"``
  one light at a time on the image grid, ``"compact"`` (:func:`render_points`, what the
  recovery fits with) every light and pixel in one call, which the fused kernels evaluate;
  they agree to float rounding (pinned by ``tests/capture/test_synthetic.py``).

:func:`generate_capture` ties them together and writes a capture folder plus ``gt/`` maps
named as in the recovery's output layout (docs/capture_format.md).
"""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeAlias, cast
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.brdf import capture_residual
from torchbrdf.brdf.principled import principled
from torchbrdf.io import cache_root, write_exr, write_png

from torchbrdf.capture.format import (Capture, check_capture_destination, default_file_names, pixel_points,
                                      write_capture)

# Point lights as render_capture takes them: a pair (positions, intensities) of (L, 3), a mapping
# {"position", "intensity"}, or a Capture (its light_positions / light_intensities).
Lights: TypeAlias = tuple[Tensor, Tensor] | Sequence | Mapping | Capture

__all__ = [
    "RECIPES",
    "SOFT_RECIPES",
    "MAP_NAMES",
    "DEFAULT_CAMERA",
    "make_material",
    "pack_maps",
    "fractal_noise",
    "pixel_coords",
    "smoothstep",
    "scratch_mask",
    "hsv_color",
    "pick_uniform",
    "random_color",
    "METAL_F0",
    "metal_color",
    "soft_step",
    "inlay_sdf",
    "tile_grid",
    "normals_from_height",
    "light_layout",
    "random_lights",
    "render_capture",
    "render_points",
    "light_geometry",
    "add_noise",
    "generate_capture",
    "write_maps",
    "default_capture",
]

#: Recipes understood by :func:`make_material`.
RECIPES = ("tiles", "metal_inlay", "scratched_metal", "painted", "stone", "circuit")
#: Recipes with soft metal/dielectric transitions (5–15 % of pixels with metallic in [0.05, 0.95]):
#: selectable by name only, so ``recipe=None`` keeps picking from :data:`RECIPES` as before.
SOFT_RECIPES = ("rusted_metal", "dusty_metal", "aa_inlay")
#: Map names and channel counts of the recovery's output layout.
MAP_NAMES = {"base_color": 3, "roughness": 1, "metallic": 1, "specular": 1, "normal": 3}
#: Default camera of the generated captures.
DEFAULT_CAMERA = (0.0, 0.0, 3.0)



# --------------------------------------------------------------------------------------
# Procedural building blocks
# --------------------------------------------------------------------------------------


def fractal_noise(gen: torch.Generator, size: int, cells: int, octaves: int = 4, persistence: float = 0.5) -> Tensor:
    """Fractal value noise in about [-1, 1], ``(size, size)``; ``cells`` = coarsest grid size."""
    out = torch.zeros(size, size)
    amp, total = 1.0, 0.0
    c = cells
    for _ in range(octaves):
        grid = torch.rand(1, 1, c + 1, c + 1, generator=gen) * 2 - 1
        up = F.interpolate(grid, size=(size, size), mode="bicubic", align_corners=True)[0, 0]
        out += amp * up
        total += amp
        amp *= persistence
        c *= 2
        if c > size:
            break
    return out / total


def pixel_coords(size: int) -> tuple[Tensor, Tensor]:
    """World x (columns) and y (rows, +y at row 0) of every pixel, each ``(size, size)``."""
    p = pixel_points(size, size)
    return p[..., 0], p[..., 1]


def smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    """Hermite ramp of ``x`` (any shape) from 0 at ``e0`` to 1 at ``e1``, same shape."""
    t = torch.clamp((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _segments_distance(x: Tensor, y: Tensor, seg: Tensor) -> Tensor:
    """Distance from each pixel to the nearest of ``seg (N, 4)`` segments, ``(H, W)``."""
    a = seg[:, None, None, 0:2]
    b = seg[:, None, None, 2:4]
    p = torch.stack((x, y), dim=-1)[None]
    ab = b - a
    t = ((p - a) * ab).sum(-1, keepdim=True) / (ab * ab).sum(-1, keepdim=True).clamp(min=1e-12)
    q = a + t.clamp(0, 1) * ab
    return (p - q).norm(dim=-1).min(dim=0).values


def scratch_mask(gen: torch.Generator, x: Tensor, y: Tensor, count: int, length: tuple[float, float],
                 angle: float | None = None) -> Tensor:
    """Groove mask ``(H, W)`` in [0, 1] (1 on a scratch), about 1.5 px wide at 256².

    ``x``, ``y``: :func:`pixel_coords`; ``count`` straight scratches of a length in ``length``,
    at random angles or within ±0.15 rad of ``angle``.
    """
    start = torch.rand(count, 2, generator=gen) * 2 - 1
    if angle is None:
        ang = torch.rand(count, generator=gen) * math.pi
    else:
        ang = angle + (torch.rand(count, generator=gen) - 0.5) * 0.3
    ln = length[0] + torch.rand(count, generator=gen) * (length[1] - length[0])
    end = start + torch.stack((ang.cos(), ang.sin()), -1) * ln[:, None]
    d = _segments_distance(x, y, torch.cat((start, end), -1))
    width = 0.012
    return torch.exp(-((d / width) ** 2))


def normals_from_height(height: Tensor) -> Tensor:
    """Tangent-space unit normals ``(3, H, W)`` of a height field ``(H, W)`` over [-1, 1]².

    Heights are in world units; +x runs along columns and +y up the image (toward row 0), so
    ``n ∝ (-∂h/∂x, -∂h/∂y, 1)`` with central differences (one-sided at the borders).
    """
    h, w = height.shape
    hp = F.pad(height[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    dx = (hp[1:-1, 2:] - hp[1:-1, :-2]) / (2 * 2.0 / w)
    dy = -(hp[2:, 1:-1] - hp[:-2, 1:-1]) / (2 * 2.0 / h)
    n = torch.stack((-dx, -dy, torch.ones_like(dx)), 0)
    return n / n.norm(dim=0, keepdim=True)


def hsv_color(h: float, s: float, v: float) -> Tensor:
    """Linear RGB ``(3,)`` from HSV-like parameters in [0, 1] (colour picking only)."""
    k = torch.tensor([5.0, 3.0, 1.0])
    c = v - v * s * torch.clamp(torch.minimum((k + h * 6) % 6, 4 - (k + h * 6) % 6), 0, 1)
    return c


def pick_uniform(gen: torch.Generator, lo: float, hi: float) -> float:
    """One uniform draw in ``[lo, hi)`` from ``gen``."""
    return lo + (hi - lo) * float(torch.rand((), generator=gen))


def random_color(gen: torch.Generator, sat: tuple[float, float] = (0.2, 0.8),
                 val: tuple[float, float] = (0.15, 0.8)) -> Tensor:
    """A random linear RGB colour ``(3,)``: any hue, saturation in ``sat``, value in ``val``."""
    return hsv_color(pick_uniform(gen, 0, 1), pick_uniform(gen, *sat), pick_uniform(gen, *val))


#: Linear RGB normal-incidence reflectance (F0) of common metals (approximate).
METAL_F0 = {
    "gold": (1.0, 0.77, 0.34),
    "copper": (0.95, 0.64, 0.54),
    "silver": (0.95, 0.93, 0.88),
    "aluminium": (0.91, 0.92, 0.92),
    "iron": (0.56, 0.57, 0.58),
    "brass": (0.91, 0.78, 0.42),
}


def metal_color(gen: torch.Generator) -> Tensor:
    """The F0 ``(3,)`` of a metal of :data:`METAL_F0` picked from ``gen``."""
    names = list(METAL_F0)
    k = int(torch.randint(len(names), (1,), generator=gen))
    return torch.tensor(METAL_F0[names[k]])


def tile_grid(size: int, n_tiles: int) -> tuple[Tensor, Tensor]:
    """An ``n_tiles`` × ``n_tiles`` grid over the sample: each pixel's tile index ``(S, S)``
    (long, row-major from the +y edge) and its distance to the tile's nearest edge ``(S, S)`` in
    tile units (0 on an edge, 0.5 at the centre)."""
    x, y = pixel_coords(size)
    gx, gy = (x + 1) * n_tiles / 2, (1 - y) * n_tiles / 2
    fx, fy = gx - gx.floor(), gy - gy.floor()
    tid = (gy.floor() * n_tiles + gx.floor()).long().clamp(0, n_tiles * n_tiles - 1)
    return tid, torch.minimum(torch.minimum(fx, 1 - fx), torch.minimum(fy, 1 - fy))


# --------------------------------------------------------------------------------------
# Recipes: each returns (base (3,H,W), rough (H,W), metal (H,W), spec (H,W), height (H,W))
# --------------------------------------------------------------------------------------


def _recipe_tiles(gen, size):
    n_tiles = int(torch.randint(3, 7, (1,), generator=gen))
    tid, edge = tile_grid(size, n_tiles)
    grout_w = pick_uniform(gen, 0.04, 0.08)
    tile = smoothstep(grout_w, grout_w + 0.06, edge)  # 0 in grout, 1 on tile top
    cols = torch.stack([random_color(gen, (0.1, 0.7), (0.2, 0.75)) for _ in range(n_tiles * n_tiles)])
    rough_t = torch.tensor([pick_uniform(gen, 0.15, 0.45) for _ in range(n_tiles * n_tiles)])
    spec_t = torch.tensor([pick_uniform(gen, 0.3, 0.7) for _ in range(n_tiles * n_tiles)])
    grout_col = random_color(gen, (0.0, 0.2), (0.15, 0.35))
    nz = fractal_noise(gen, size, 8)
    base = cols[tid].permute(2, 0, 1) * (1 + 0.1 * nz) * tile + grout_col[:, None, None] * (1 - tile)
    rough = (rough_t[tid] + 0.08 * fractal_noise(gen, size, 6)) * tile + 0.85 * (1 - tile)
    spec = spec_t[tid] * tile + 0.4 * (1 - tile)
    height = 0.02 * tile + 0.002 * fractal_noise(gen, size, 16, 3)
    metal = torch.zeros(size, size)
    return base, rough, metal, spec, height


def _wood(gen, size, y):
    """A wood-like dielectric (stretched noise stripes): ``base (3, S, S)``, ``rough``, ``spec``."""
    stripes = torch.sin(18 * (y + 0.15 * fractal_noise(gen, size, 4)) + 3 * fractal_noise(gen, size, 8))
    c0, c1 = random_color(gen, (0.4, 0.7), (0.25, 0.5)), random_color(gen, (0.4, 0.8), (0.1, 0.3))
    t = (stripes * 0.5 + 0.5)[None]
    base = c0[:, None, None] * t + c1[:, None, None] * (1 - t)
    rough = 0.55 + 0.12 * fractal_noise(gen, size, 6)
    spec = torch.full((size, size), pick_uniform(gen, 0.35, 0.6))
    return base, rough, spec


def inlay_sdf(gen: torch.Generator, x: Tensor, y: Tensor, count: tuple[int, int], extent: float,
              radius: tuple[float, float]) -> Tensor:
    """Signed distance ``(S, S)`` to a union of random inlays (< 0 inside): discs and bars,
    ``count`` = [low, high) of their number, centres in ``±extent``, sizes in ``radius``;
    ``x``, ``y`` are :func:`pixel_coords`."""
    sdf = torch.full(x.shape, 10.0)
    for _ in range(int(torch.randint(count[0], count[1], (1,), generator=gen))):
        cx, cy = pick_uniform(gen, -extent, extent), pick_uniform(gen, -extent, extent)
        r = pick_uniform(gen, *radius)
        if float(torch.rand((), generator=gen)) < 0.5:  # a disc
            d = ((x - cx) ** 2 + (y - cy) ** 2).sqrt() - r
        else:  # a bar
            d = torch.maximum((x - cx).abs() - r * 1.6, (y - cy).abs() - r * 0.35)
        sdf = torch.minimum(sdf, d)
    return sdf


def _recipe_metal_inlay(gen, size):
    x, y = pixel_coords(size)
    base, rough, spec = _wood(gen, size, y)
    mask = (inlay_sdf(gen, x, y, (3, 6), 0.7, (0.12, 0.3)) < 0).float()
    mcol = metal_color(gen)
    mrough = pick_uniform(gen, 0.2, 0.4) + 0.06 * fractal_noise(gen, size, 8)
    scratch = scratch_mask(gen, x, y, 25, (0.1, 0.5))
    base = base * (1 - mask) + mcol[:, None, None] * mask
    rough = rough * (1 - mask) + (mrough + 0.15 * scratch) * mask
    height = 0.01 * smoothstep(-0.5, 0.5, F.avg_pool2d(mask[None, None], 5, 1, 2)[0, 0] * 2 - 1)
    height = height - 0.004 * scratch * mask + 0.003 * fractal_noise(gen, size, 8, 3)
    return base, rough, mask, spec, height


def _recipe_scratched_metal(gen, size):
    x, y = pixel_coords(size)
    mcol = metal_color(gen)
    base = mcol[:, None, None] * (1 + 0.05 * fractal_noise(gen, size, 6))[None]
    rough = pick_uniform(gen, 0.25, 0.45) + 0.1 * fractal_noise(gen, size, 5)
    ang = pick_uniform(gen, 0, math.pi)
    scratch = torch.maximum(scratch_mask(gen, x, y, 40, (0.2, 0.9), angle=ang), scratch_mask(gen, x, y, 15, (0.1, 0.4)))
    rough = rough + 0.2 * scratch
    # Paint chips: dielectric patches where noise is high.
    paint = (fractal_noise(gen, size, 4) > 0.35).float()
    pcol = random_color(gen, (0.5, 0.9), (0.3, 0.7))
    base = base * (1 - paint) + pcol[:, None, None] * paint
    rough = rough * (1 - paint) + 0.6 * paint
    metal = 1 - paint
    spec = torch.full((size, size), 0.5)
    height = 0.006 * paint - 0.004 * scratch + 0.004 * fractal_noise(gen, size, 6, 3)
    return base, rough, metal, spec, height


def _recipe_painted(gen, size):
    n1, n2 = fractal_noise(gen, size, 3), fractal_noise(gen, size, 5)
    c = [random_color(gen, (0.4, 0.9), (0.2, 0.8)) for _ in range(3)]
    w1 = smoothstep(-0.05, 0.05, n1)[None]
    w2 = smoothstep(-0.05, 0.05, n2)[None]
    base = (c[0][:, None, None] * w1 + c[1][:, None, None] * (1 - w1)) * (1 - 0.5 * w2) + c[2][:, None, None] * 0.5 * w2
    rough = (0.5 + 0.35 * fractal_noise(gen, size, 4)).clamp(0.08, 0.95)
    spec = (0.5 + 0.25 * fractal_noise(gen, size, 3)).clamp(0, 1)
    height = 0.006 * fractal_noise(gen, size, 10, 3) + 0.004 * w1[0]
    return base, rough, torch.zeros(size, size), spec, height


def _recipe_stone(gen, size):
    c0, c1 = random_color(gen, (0.0, 0.3), (0.3, 0.7)), random_color(gen, (0.0, 0.4), (0.1, 0.4))
    t = (0.5 + 0.5 * fractal_noise(gen, size, 6, 5))[None]
    base = c0[:, None, None] * t + c1[:, None, None] * (1 - t)
    rough = (0.75 + 0.15 * fractal_noise(gen, size, 6)).clamp(0, 1)
    spec = torch.full((size, size), 0.4)
    height = 0.012 * fractal_noise(gen, size, 12, 4, 0.6)
    return base, rough, torch.zeros(size, size), spec, height


def _recipe_circuit(gen, size):
    x, y = pixel_coords(size)
    board = random_color(gen, (0.5, 0.9), (0.05, 0.25))
    base = board[:, None, None] * (1 + 0.1 * fractal_noise(gen, size, 8))[None]
    rough = torch.full((size, size), pick_uniform(gen, 0.3, 0.5)) + 0.05 * fractal_noise(gen, size, 8)
    # Traces: axis-aligned bars; pads: squares.
    mask = torch.zeros(size, size)
    for _ in range(int(torch.randint(6, 12, (1,), generator=gen))):
        cx, cy, ln = pick_uniform(gen, -0.8, 0.8), pick_uniform(gen, -0.8, 0.8), pick_uniform(gen, 0.2, 0.9)
        wd = pick_uniform(gen, 0.03, 0.06)
        if float(torch.rand((), generator=gen)) < 0.5:
            m = ((x - cx).abs() < ln / 2) & ((y - cy).abs() < wd)
        else:
            m = ((y - cy).abs() < ln / 2) & ((x - cx).abs() < wd)
        mask = torch.maximum(mask, m.float())
    mcol = torch.tensor(METAL_F0["gold" if float(torch.rand((), generator=gen)) < 0.5 else "copper"])
    base = base * (1 - mask) + mcol[:, None, None] * mask
    rough = rough * (1 - mask) + (0.3 + 0.05 * fractal_noise(gen, size, 8)) * mask
    spec = torch.full((size, size), 0.5)
    height = 0.008 * F.avg_pool2d(mask[None, None], 5, 1, 2)[0, 0] + 0.002 * fractal_noise(gen, size, 16, 2)
    return base, rough, mask, spec, height


def soft_step(field: Tensor, coverage: float, soft: float) -> Tensor:
    """A ramp in [0, 1] ``(H, W)`` over the values of ``field (H, W)``: exactly a fraction ``soft``
    of the pixels get a value in (0.05, 0.95) and about ``coverage`` of them a value ≥ 0.5.

    The band is set by quantiles of ``field`` (not fixed levels), so the soft fraction is the
    same at every resolution and seed: the values between the ``1 − coverage ∓ soft/2``
    quantiles map linearly onto [0.05, 0.95] (and on outward to 0 and 1).
    """
    q = torch.quantile(field.flatten().double(),
                       torch.tensor([1 - coverage - soft / 2, 1 - coverage + soft / 2], dtype=torch.float64))
    lo, hi = float(q[0]), float(q[1])
    return (0.05 + 0.9 * (field - lo) / max(hi - lo, 1e-9)).clamp(0.0, 1.0)


def _recipe_rusted_metal(gen, size):
    """Steel with a rust front: metallic ramps smoothly from 1 (bare) to 0 (rust) across it."""
    mcol = torch.tensor(METAL_F0["iron" if float(torch.rand((), generator=gen)) < 0.5 else "silver"])
    rust_col = hsv_color(pick_uniform(gen, 0.03, 0.08), pick_uniform(gen, 0.6, 0.85), pick_uniform(gen, 0.2, 0.45))
    field = fractal_noise(gen, size, 3, 5) + 0.25 * fractal_noise(gen, size, 12, 3)
    rust = soft_step(field, pick_uniform(gen, 0.3, 0.5), pick_uniform(gen, 0.08, 0.13))
    rust_tex = rust_col[:, None, None] * (1 + 0.15 * fractal_noise(gen, size, 16))[None]
    base = mcol[:, None, None] * (1 - rust) + rust_tex * rust
    rough = (pick_uniform(gen, 0.2, 0.35) + 0.04 * fractal_noise(gen, size, 8)) * (1 - rust) + 0.8 * rust
    spec = torch.full((size, size), 0.5)
    height = 0.003 * rust + 0.002 * fractal_noise(gen, size, 16, 3) * rust
    return base, rough, 1 - rust, spec, height


def _recipe_dusty_metal(gen, size):
    """A metal with speckles of dust: small dielectric specks with soft edges."""
    mcol = metal_color(gen)
    dust_col = hsv_color(pick_uniform(gen, 0.08, 0.14), pick_uniform(gen, 0.1, 0.3), pick_uniform(gen, 0.4, 0.6))
    field = fractal_noise(gen, size, 24, 2) + 0.5 * fractal_noise(gen, size, 4, 2)
    dust = soft_step(field, pick_uniform(gen, 0.12, 0.2), pick_uniform(gen, 0.08, 0.13))
    base = mcol[:, None, None] * (1 - dust) + dust_col[:, None, None] * dust
    rough = (pick_uniform(gen, 0.25, 0.4) + 0.05 * fractal_noise(gen, size, 8)) * (1 - dust) + 0.9 * dust
    spec = torch.full((size, size), 0.5)
    height = 0.002 * fractal_noise(gen, size, 8, 3)
    return base, rough, 1 - dust, spec, height


def _recipe_aa_inlay(gen, size):
    """metal_inlay's wood and discs/bars, with anti-aliased (filtered) inlay edges: metallic ramps
    from 0 to 1 across each edge, as in a texture magnified with bilinear filtering."""
    x, y = pixel_coords(size)
    base, rough, spec = _wood(gen, size, y)
    sdf = inlay_sdf(gen, x, y, (6, 10), 0.75, (0.1, 0.25))
    mask = soft_step(-sdf, float((sdf < 0).float().mean()), pick_uniform(gen, 0.07, 0.12))
    mcol = metal_color(gen)
    mrough = pick_uniform(gen, 0.2, 0.4) + 0.06 * fractal_noise(gen, size, 8)
    base = base * (1 - mask) + mcol[:, None, None] * mask
    rough = rough * (1 - mask) + mrough * mask
    height = 0.004 * mask + 0.002 * fractal_noise(gen, size, 8, 3)
    return base, rough, mask, spec, height


_RECIPE_FUNCS = {
    "tiles": _recipe_tiles,
    "metal_inlay": _recipe_metal_inlay,
    "scratched_metal": _recipe_scratched_metal,
    "painted": _recipe_painted,
    "stone": _recipe_stone,
    "circuit": _recipe_circuit,
    "rusted_metal": _recipe_rusted_metal,
    "dusty_metal": _recipe_dusty_metal,
    "aa_inlay": _recipe_aa_inlay,
}


def make_material(recipe: str | None = None, seed: int = 0, size: int = 256) -> dict[str, Tensor]:
    """Procedural ground-truth SVBRDF maps.

    Args:
        recipe: one of :data:`RECIPES` or :data:`SOFT_RECIPES`, or ``None`` to pick one of
            :data:`RECIPES` from ``seed``.
        seed: random seed; the maps are a deterministic function of ``(recipe, seed, size)``.
        size: output resolution (square).

    Returns:
        dict with ``base_color (3, H, W)``, ``roughness``, ``metallic``, ``specular``
        ``(1, H, W)`` and ``normal (3, H, W)`` (tangent-space unit vectors, z > 0), float32.
        Dielectric base colours stay above 0.03 and metals are bright, so the metal/dielectric
        question has one answer (a black dielectric and a dark metal render identically under
        this model); metallic is binary in :data:`RECIPES` and has 5–15 % of its pixels in
        [0.05, 0.95] in :data:`SOFT_RECIPES` (rust fronts, dust specks, filtered inlay edges).

    Example:
        >>> m = make_material("tiles", seed=1, size=32)
        >>> sorted(m), tuple(m["base_color"].shape)
        (['base_color', 'metallic', 'normal', 'roughness', 'specular'], (3, 32, 32))
    """
    if recipe is None:
        recipe = RECIPES[seed % len(RECIPES)]
    if recipe not in _RECIPE_FUNCS:
        raise ValueError(f"make_material: unknown recipe {recipe!r}; choose one of {RECIPES + SOFT_RECIPES}")
    if size < 4:
        raise ValueError(f"make_material: size must be >= 4, got {size}")
    gen = torch.Generator().manual_seed(int(seed) * 7919 + (RECIPES + SOFT_RECIPES).index(recipe))
    return pack_maps(*_RECIPE_FUNCS[recipe](gen, size))


def pack_maps(base: Tensor, rough: Tensor, metal: Tensor, spec: Tensor, height: Tensor) -> dict[str, Tensor]:
    """A recipe's raw fields as :func:`make_material`'s maps, clamped to their ranges.

    Args ``base (3, S, S)``, ``rough``, ``metal``, ``spec`` and ``height (S, S)`` (world units);
    returns ``base_color (3, S, S)`` in [0.03, 1], ``roughness`` in [0.05, 1], ``metallic`` and
    ``specular (1, S, S)`` in [0, 1] and the unit ``normal (3, S, S)`` of the height field,
    float32, contiguous.
    """
    return {
        "base_color": base.clamp(0.03, 1.0).float().contiguous(),
        "roughness": rough.clamp(0.05, 1.0)[None].float().contiguous(),
        "metallic": metal.clamp(0, 1)[None].float().contiguous(),
        "specular": spec.clamp(0, 1)[None].float().contiguous(),
        "normal": normals_from_height(height.float()).contiguous(),
    }


# --------------------------------------------------------------------------------------
# Lights
# --------------------------------------------------------------------------------------


def light_layout(
    count: int = 16,
    near_camera: bool = True,
    radius: float = 1.5,
    height: float = 2.0,
    intensity: float = 30.0,
    camera_position: Tensor | Sequence[float] = DEFAULT_CAMERA,
) -> tuple[Tensor, Tensor]:
    """A ring of ``count`` point lights, plus one beside the camera (a flash).

    The ring lights sit at ``radius`` around the z axis at ``height`` (their mirror
    highlights, seen from the default camera, form a ring of radius ~0.9 on the sample);
    the flash sits 0.1 to the side of the camera and has ``intensity * 0.5``.

    Returns:
        ``(positions (L, 3), intensities (L, 3))`` float32, ring first, flash last.
    """
    if count < 0:
        raise ValueError(f"light_layout: count must be >= 0, got {count}")
    ang = (torch.arange(count, dtype=torch.float64) + 0.25) * (2 * math.pi / max(count, 1))
    pos = torch.stack((radius * ang.cos(), radius * ang.sin(), torch.full_like(ang, height)), -1)
    inten = torch.full((count, 3), float(intensity), dtype=torch.float64)
    if near_camera:
        cam = torch.as_tensor(camera_position, dtype=torch.float64)
        pos = torch.cat((pos, (cam + torch.tensor([0.1, 0.05, 0.0], dtype=torch.float64))[None]))
        inten = torch.cat((inten, torch.full((1, 3), 0.5 * intensity, dtype=torch.float64)))
    if pos.shape[0] == 0:
        raise ValueError("light_layout: no lights (count=0 and near_camera=False)")
    return pos.float(), inten.float()


def random_lights(
    count: int, seed: int = 0, distance: tuple[float, float] = (2.0, 3.0),
    elevation_deg: tuple[float, float] = (25.0, 80.0), intensity: float = 30.0,
) -> tuple[Tensor, Tensor]:
    """Random point lights over the sample (for held-out evaluation), deterministic in ``seed``.

    Positions are uniform in azimuth, in ``elevation_deg`` above the plane and in
    ``distance`` from the origin; intensities white, scaled by ``(distance / 2.5)²`` so the
    sample stays similarly lit.
    """
    gen = torch.Generator().manual_seed(int(seed) + 1_000_003)
    az = torch.rand(count, generator=gen, dtype=torch.float64) * 2 * math.pi
    el = torch.deg2rad(
        elevation_deg[0] + torch.rand(count, generator=gen, dtype=torch.float64) * (elevation_deg[1] - elevation_deg[0])
    )
    r = distance[0] + torch.rand(count, generator=gen, dtype=torch.float64) * (distance[1] - distance[0])
    pos = torch.stack((r * el.cos() * az.cos(), r * el.cos() * az.sin(), r * el.sin()), -1)
    inten = (intensity * (r / 2.5) ** 2)[:, None].expand(count, 3)
    return pos.float(), inten.float().contiguous()


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------


def _map_hwc(value, channels: int, h: int, w: int, dtype, device) -> Tensor | float:
    """A map given as ``(C, H, W)``/``(1, C, H, W)`` tensor or float → ``(H, W, C)`` or float."""
    if isinstance(value, (int, float)):
        return float(value)
    t = torch.as_tensor(value)
    if t.dim() == 4:
        if t.shape[0] != 1:
            raise ValueError(f"render_capture: maps must be (C, H, W) or (1, C, H, W), got {tuple(t.shape)}")
        t = t[0]
    if t.dim() == 0:
        return float(t)
    if t.dim() != 3 or t.shape[0] != channels or tuple(t.shape[1:]) != (h, w):
        raise ValueError(f"render_capture: expected a ({channels}, {h}, {w}) map, got {tuple(t.shape)}")
    return t.to(device=device, dtype=dtype).permute(1, 2, 0)


def _split_lights(lights) -> tuple[Tensor, Tensor]:
    if isinstance(lights, Mapping):
        return torch.as_tensor(lights["position"]), torch.as_tensor(lights["intensity"])
    if hasattr(lights, "light_positions"):  # a datasets.Capture
        return lights.light_positions, lights.light_intensities
    pos, inten = lights
    return torch.as_tensor(pos), torch.as_tensor(inten)


def frame_from_normal_map(n: Tensor) -> tuple[Tensor, Tensor]:
    """Tangent frame of the capture format: ``x = normalize(X − (X·n) n)``, ``y = n × x``; ``(*, 3)``."""
    ex = torch.zeros_like(n)
    ex[..., 0] = 1.0
    x = ex - n[..., 0:1] * n
    x = x * torch.rsqrt(torch.clamp((x * x).sum(-1, keepdim=True), min=1e-12))
    y = torch.linalg.cross(n, x, dim=-1)
    return x, y


def light_geometry(points: Tensor, camera: Tensor, light_pos: Tensor) -> dict[str, Tensor]:
    """The normal-independent geometry of a capture (fixed for it, so a fit computes it once).

    Args ``points (P, 3)``, ``camera (3,)``, ``light_pos (L, 3)``; returns ``v (P, 3)``,
    ``l (L, P, 3)`` and ``inv_d2 (L, P, 1)`` (1 / squared light distance).
    """
    v = camera - points
    v = v * torch.rsqrt((v * v).sum(-1, keepdim=True))
    dl = light_pos[:, None, :] - points[None]
    d2 = (dl * dl).sum(-1, keepdim=True)
    return {"v": v, "l": dl * torch.rsqrt(d2), "inv_d2": 1.0 / d2}


def render_points(
    normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor, params: Mapping,
    light: dict | None = None,
) -> Tensor:
    """Capture-format radiance of a flat list of pixels under every light: ``(L, P, 3)``.

    ``radiance = f · I · max(n·l, 0) / d²`` with ``f`` :func:`torchbrdf.principled` itself (one
    call for all lights and pixels, so the fused kernels evaluate it at fit sizes).
    ``normal (P, 3)`` unit normals, ``points (P, 3)``, ``camera (3,)``, ``light_pos`` and
    ``light_int (L, 3)``; ``params`` holds ``base_color (P, 3)`` and any scalar principled
    parameters ``(P, 1)`` (tensors or floats; a ``"normal"`` entry is ignored); the others
    keep ``principled``'s defaults, Python 0 for every optional lobe, so those lobes are
    pruned. The tangent frame (:func:`frame_from_normal_map`) is built only when
    ``anisotropic`` is given and not a Python 0 (otherwise ``f`` does not depend on it).
    ``light`` optionally the precomputed :func:`light_geometry`. Differentiable (reverse and
    forward mode) w.r.t. every input.
    """
    lg = light if light is not None else light_geometry(points, camera, light_pos)
    l, n = lg["l"], normal[None]
    brdf_params = {k: v for k, v in params.items() if k != "normal"}
    x, y = (t if t is None else t[None] for t in _fit_frame(normal, brdf_params))
    f = principled(l, lg["v"][None], n, x, y, **brdf_params)
    nl = torch.clamp((n * l).sum(-1, keepdim=True), min=0.0)
    return f * (light_int[:, None, :] * nl * lg["inv_d2"])


def _fit_frame(normal: Tensor, params: Mapping) -> tuple[Tensor | None, Tensor | None]:
    """The capture format's tangent frame ``(P, 3)`` each (:func:`frame_from_normal_map`), or
    ``(None, None)`` when ``anisotropic`` is absent or a Python 0 (``f`` does not depend on it)."""
    aniso = params.get("anisotropic", 0.0)
    if isinstance(aniso, Tensor) or aniso != 0.0:
        return frame_from_normal_map(normal)
    return None, None


def log_residual_points(
    normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor, params: Mapping,
    log_obs: Tensor, eps: float, any_size: bool = False, family: str = "principled",
) -> Tensor:
    """Log residuals of a flat list of pixels under every light, ``(P, L, 3)``: what a fit minimises.

    ``log(max(radiance + ε, ε/2)) − log_obs`` with the radiance of :func:`render_points` (the
    same inputs: ``normal``, ``points (P, 3)``, ``camera (3,)``, ``light_pos``, ``light_int
    (L, 3)``, ``params``), ``log_obs (P, L, 3)`` = ``log(observed + ε)`` and ``eps`` ε. It is
    :func:`torchbrdf.brdf.formula.capture_log_residual` — the capture's image formation
    (:func:`~torchbrdf.brdf.formula.point_light` with the principled BRDF) followed by the log
    — so at fit sizes the fused kernels evaluate the whole residual, its JVPs (the fit's
    Jacobian) and its backward in one pass per lane, with no ``(P, L, 3)`` intermediates.
    Differentiable (reverse and forward mode) w.r.t. every tensor input. Every tensor must
    share ``log_obs``'s floating dtype and device (the fused kernels read raw memory in one
    dtype: a float32 ``points`` beside a float64 ``log_obs`` would be misread); the result is
    in that dtype, on that device. ``any_size``: in the automatic mode, the fused kernels at
    every lane count, not only from :data:`~torchbrdf.brdf.principled.FAST_PATH_MIN_LANES` — a
    fit's first full-size call compiles them, and its later calls on a few pixels (refits,
    converged pixels left out) then cost half as much fused as eager. ``family="svbrdf_ggx"``:
    the recovery's GGX model on the same maps (:func:`torchbrdf.brdf.formula.ggx_albedos`).
    """
    return capture_residual.log_residual(_residual_inputs(normal, points, camera, light_pos, light_int, params,
                                                          log_obs, eps, any_size, family))


def log_residual_points_jvp(
    normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor, params: Mapping,
    log_obs: Tensor, eps: float, tangents: Mapping[str, Tensor], any_size: bool = False,
    family: str = "principled",
) -> tuple[Tensor, Tensor]:
    """:func:`log_residual_points` and its derivatives along ``K`` directions at once.

    ``tangents``: ``{name: (K, P, C)}``, the directions' tangents of ``"normal"`` and of
    entries of ``params``, and ``{name: (K, L, 3)}`` of ``"light_pos"`` and ``"light_int"``
    (each the shape of its input with a leading ``K``); every other input is held. The other
    arguments (``family`` too) as for :func:`log_residual_points`. Returns ``(r (P, L, 3), dr (K, P, L, 3))`` in
    ``log_obs``'s dtype, on its device, ``dr[k]`` what ``torch.func.jvp``
    of :func:`log_residual_points` along direction ``k`` gives. On the fused kernels, one
    forward and one JVP call of the operators (:func:`torchbrdf.brdf.capture_residual.log_residual_jvp`),
    which prunes each direction to its own tangents: a fit's Gauss–Newton Jacobian without the
    ``vmap``-of-``jvp`` transforms' work per call; otherwise (no kernel, or inputs that need a
    gradient) that ``vmap`` of ``jvp``.
    """
    unknown = set(tangents) - {"normal", "light_pos", "light_int", *params}
    if unknown:
        raise ValueError(f"log_residual_points_jvp: tangents for {sorted(unknown)}: expected 'normal', "
                         f"'light_pos', 'light_int' or keys of params ({sorted(params)})")
    fused = capture_residual.log_residual_jvp(
        _residual_inputs(normal, points, camera, light_pos, light_int, params, log_obs, eps, any_size, family),
        tangents)
    if fused is not None:
        return fused
    names = list(tangents)

    held = {"normal": normal, "light_pos": light_pos, "light_int": light_int, **params}

    def res(*vals: Tensor) -> Tensor:
        given = {**held, **dict(zip(names, vals))}
        p = {k: given[k] for k in params}
        return log_residual_points(given["normal"], points, camera, given["light_pos"], given["light_int"], p,
                                   log_obs, eps, any_size, family)

    primals = tuple(held[k] for k in names)
    out_dims: Any = (None, 0)  # the residual (the primal) is not batched over the directions
    pair: Any = torch.func.vmap(lambda *tg: torch.func.jvp(res, primals, tg), out_dims=out_dims)(
        *(tangents[k] for k in names))
    return pair


def _residual_inputs(normal: Tensor, points: Tensor, camera: Tensor, light_pos: Tensor, light_int: Tensor,
                     params: Mapping, log_obs: Tensor, eps: float, any_size: bool,
                     family: str = "principled") -> capture_residual.ResidualInputs:
    """:func:`torchbrdf.brdf.capture_residual.residual_inputs` with the capture format's frame."""
    x, y = _fit_frame(normal, params)
    return capture_residual.residual_inputs(normal, points, camera, light_pos, light_int, params, log_obs, eps,
                                            x, y, any_size, family)


def render_capture(
    maps: Mapping,
    lights: Lights,
    camera_position: Tensor | Sequence[float] = DEFAULT_CAMERA,
    *,
    backend: str = "principled",
    noise: float = 0.0,
    seed: int = 0,
    brdf: Callable[..., Tensor] | None = None,
) -> Tensor:
    """Render the capture (docs/capture_format.md) of a flat sample with SVBRDF ``maps``.

    Args:
        maps: principled parameter maps ``(C, H, W)`` (or floats): ``base_color`` (3 channels,
            required), ``normal`` (3, tangent space; default +z) and any scalar principled
            parameters (``roughness``, ``metallic``, ``specular``, ``sheen``, ...; 1 channel).
        lights: ``(positions (L, 3), intensities (L, 3))``, a mapping with ``position``
            and ``intensity``, or a :class:`datasets.Capture`.
        camera_position: ``(3,)`` camera position (only the view vectors depend on it).
        backend: ``"principled"`` (one light at a time) or ``"compact"`` (all lights in one
            call, :func:`render_points`); both evaluate :func:`torchbrdf.principled`.
        noise: relative sensor noise level (0.01 = 1 %); see :func:`add_noise`.
        seed: noise seed.
        brdf: another reflectance model in place of :func:`torchbrdf.principled`, called as
            ``brdf(l, v, n, x, y, **maps)`` on ``(H, W, 3)`` vectors and ``(H, W, C)`` maps and
            returning ``(H, W, 3)`` (``"principled"`` backend only): the same image formation
            under a model the recovery does not fit with.

    Returns:
        ``(L, 3, H, W)`` linear radiance, float32 (or the maps' dtype), differentiable.
    """
    if "base_color" not in maps:
        raise ValueError("render_capture: maps needs at least 'base_color'")
    bc = torch.as_tensor(maps["base_color"])
    h, w = bc.shape[-2:]
    dtype = bc.dtype if bc.is_floating_point() else torch.float32
    device = bc.device
    pos, inten = _split_lights(lights)
    pos, inten = pos.to(device=device, dtype=dtype), inten.to(device=device, dtype=dtype)
    cam = torch.as_tensor(camera_position, dtype=dtype, device=device)
    if "normal" in maps:
        n = cast(Tensor, _map_hwc(maps["normal"], 3, h, w, dtype, device))  # a normal map is a tensor
        n = n * torch.rsqrt(torch.clamp((n * n).sum(-1, keepdim=True), min=1e-12))
    else:
        n = torch.zeros(h, w, 3, dtype=dtype, device=device)
        n[..., 2] = 1.0
    params: dict[str, Any] = {}  # Any: maps (Tensor) or numbers (float), passed on as **params
    for name, value in maps.items():
        if name == "normal":
            continue
        params[name] = _map_hwc(value, 3 if name == "base_color" else 1, h, w, dtype, device)
    p = pixel_points(w, h, device=device, dtype=dtype)
    if brdf is not None and backend != "principled":
        raise ValueError(f"render_capture: brdf= needs backend='principled', got {backend!r}")
    if backend == "compact":
        flat = {k: (v.reshape(-1, v.shape[-1]) if isinstance(v, Tensor) else v) for k, v in params.items()}
        img = render_points(n.reshape(-1, 3), p.reshape(-1, 3), cam, pos, inten, flat)
        img = img.reshape(-1, h, w, 3).permute(0, 3, 1, 2)
    elif backend == "principled":
        x, y = frame_from_normal_map(n)
        v = cam - p
        v = v / v.norm(dim=-1, keepdim=True)
        out = []
        for k in range(pos.shape[0]):
            dl = pos[k] - p
            d2 = (dl * dl).sum(-1, keepdim=True)
            l = dl / d2.sqrt()
            f = (brdf or principled)(l, v, n, x, y, **params)
            nl = torch.clamp((n * l).sum(-1, keepdim=True), min=0.0)
            out.append((f * inten[k] * nl / d2).permute(2, 0, 1))
        img = torch.stack(out)
    else:
        raise ValueError(f"render_capture: unknown backend {backend!r} (use 'principled' or 'compact')")
    if noise:
        img = add_noise(img, noise, seed)
    return img


def add_noise(images: Tensor, level: float = 0.01, seed: int = 0) -> Tensor:
    """Sensor noise: Gaussian with σ = ``level`` · (|value| + 1 % of the image mean).

    The relative part models photon noise of a well-exposed sensor; the small floor lets a
    few dark values fall slightly below 0, as real captures do. Deterministic in ``seed``.
    """
    try:
        lv = float(level)
    except (TypeError, ValueError):
        lv = math.nan
    if not (math.isfinite(lv) and lv >= 0):  # a negative level would pass as its absolute value
        raise ValueError(f"add_noise: level (the relative noise, e.g. 0.01) must be a finite number >= 0, "
                         f"got {level!r}")
    gen = torch.Generator().manual_seed(int(seed) + 17)
    z = torch.randn(images.shape, generator=gen, dtype=torch.float32).to(images)
    floor = 0.01 * images.detach().abs().mean(dim=(-3, -2, -1), keepdim=True)
    return images + level * (images.detach().abs() + floor) * z


# --------------------------------------------------------------------------------------
# Folders
# --------------------------------------------------------------------------------------


def write_maps(folder: str | os.PathLike, maps: Mapping, previews: bool = True) -> None:
    """Write SVBRDF maps as the recovery's EXRs (float32) and optional PNG previews."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, c in MAP_NAMES.items():
        if name not in maps:
            continue
        t = torch.as_tensor(maps[name]).detach().float().cpu()
        if t.dim() == 4:
            t = t[0]
        if not torch.isfinite(t).all():
            raise ValueError(f"write_maps: {name} has non-finite values; refusing to write it")
        write_exr(folder / f"{name}.exr", t)
        if previews:
            if name == "normal":
                write_png(folder / f"{name}.png", t * 0.5 + 0.5, srgb=False)
            else:
                write_png(folder / f"{name}.png", t, srgb=(name == "base_color"))


def generate_capture(
    folder: str | os.PathLike,
    recipe: str | None = None,
    seed: int = 0,
    size: int = 256,
    lights: int = 16,
    near_camera: bool = True,
    noise: float = 0.01,
    camera_position: Tensor | Sequence[float] = DEFAULT_CAMERA,
    backend: str = "principled",
    overwrite: bool = False,
) -> Path:
    """Generate a synthetic capture folder: images + ``capture.json`` + ``gt/`` maps.

    Args:
        folder: destination (created).
        recipe, seed, size: see :func:`make_material`.
        lights: number of ring lights (plus the flash when ``near_camera``).
        noise: relative sensor noise (0.01 = 1 %).
        backend: renderer for the images (``"principled"`` is the reference).
        overwrite: replace a capture already in ``folder`` (see :func:`write_capture`); without
            it such a folder is refused before anything is written.

    Returns:
        The path of ``capture.json``.

    Raises:
        ValueError: ``lights``, ``size`` or ``camera_position`` out of range (named), before
            anything is written.
    """
    _check_generate_arguments(lights, size, near_camera, camera_position)
    pos, inten = light_layout(lights, near_camera=near_camera, camera_position=camera_position)
    check_capture_destination(folder, default_file_names(len(pos)), overwrite)
    maps = make_material(recipe, seed, size)
    with torch.no_grad():
        img = render_capture(maps, (pos, inten), camera_position, backend=backend, noise=noise, seed=seed)
    folder = Path(folder)
    write_maps(folder / "gt", maps, previews=False)
    return write_capture(folder, img, (pos, inten), camera_position, overwrite=overwrite)


def _check_generate_arguments(lights: Any, size: Any, near_camera: bool, camera_position: Any) -> None:
    """Refuse :func:`generate_capture`'s arguments by name before any file is written."""
    for name, value, low in (("lights", lights, 0), ("size", size, 4)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
            raise ValueError(f"generate_capture: {name} must be an integer >= {low}, got {value!r}")
    if lights == 0 and not near_camera:
        raise ValueError("generate_capture: lights=0 with near_camera=False leaves no light; pass lights >= 1")
    try:
        cam = torch.as_tensor(camera_position, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        cam = torch.full((0,), math.nan, dtype=torch.float64)
    if cam.shape != (3,) or not bool(torch.isfinite(cam).all()):
        raise ValueError(f"generate_capture: camera_position must be 3 finite numbers (x, y, z), got {camera_position!r}")
    if cam[2] <= 0:  # the sample lies in z = 0 facing +z
        raise ValueError(f"generate_capture: camera_position {cam.tolist()} must be above the sample (z > 0)")


def default_capture(folder: str | os.PathLike | None = None, size: int = 128) -> Path:
    """The demo capture: generated deterministically on first use (no network).

    Args:
        folder: where to put it; default ``<cache>/default_capture_<size>`` where ``<cache>`` is
            ``$TORCHBRDF_CACHE_DIR``, else ``$XDG_CACHE_HOME/torchbrdf`` or ``~/.cache/torchbrdf``.
        size: resolution.

    Returns:
        The capture folder (holding ``capture.json`` and ``gt/``).
    """
    if folder is None:
        root = Path(cache_root())
        folder = root / f"default_capture_{size}"
    folder = Path(folder)
    if not (folder / "capture.json").is_file():
        # overwrite: another process may finish the same deterministic capture meanwhile
        generate_capture(folder, recipe="metal_inlay", seed=0, size=size, lights=16, noise=0.01, overwrite=True)
    return folder
