"""Procedural materials and their renderings as ``torch.utils.data`` datasets, for training networks.

:class:`MaterialDataset` (map-style) and :class:`MaterialStream` (iterable) yield samples

* ``maps`` ``(9, S, S)``: the ground truth in :data:`torchbrdf.losses.PRINCIPLED_LAYOUT` order
  (base_color 3, roughness 1, metallic 1, specular 1, normal 3);
* ``images`` ``(L, 3, S, S)``: the sample rendered in the capture format
  (``docs/capture_format.md``) under the flash first, then ``extra_lights`` random point lights
  (or, with ``ring_lights``, the ring of :func:`torchbrdf.capture.synthetic.light_layout`, in a
  random order per sample);
* ``light_positions``, ``light_intensities`` ``(L, 3)`` and ``camera_position`` ``(3,)``;
* ``index``: the sample's index.

Sample ``k`` is a function of ``(seed, k)`` alone, whichever process or worker makes it: a
``DataLoader`` with any ``num_workers`` gets the same samples (the iterable form shards by
blocks of ``variants`` indices over the workers, so their order depends on the worker count).

Materials come from a *source*: a picklable callable ``(seed, size) -> maps`` returning the
:func:`torchbrdf.capture.synthetic.make_material` layout. :class:`RecipeSource` (default) draws
the synthetic recipes; :class:`FamilySource` the material families of
``torchbrdf.capture.families`` when that module is installed (imported when used). Each
material gives ``variants`` samples: the 8 symmetries of the square (flips and transposition,
with the normal map transformed to match) under new lights and noise, which amortises the
material's procedural synthesis.

Rendering: the flash sits beside the camera as in :func:`torchbrdf.capture.synthetic.light_layout`;
``noise`` draws a relative sensor-noise level per sample (:func:`torchbrdf.capture.synthetic.add_noise`);
``gamma`` optionally applies a camera response (clip at 1, then ``x ** (1 / gamma)``).
``device`` renders there (materials are always synthesised on the CPU); with CUDA, use
``num_workers=0`` or render in the training loop.
"""

from __future__ import annotations

import importlib
import math
import numbers
from collections.abc import Iterator, Sequence
from typing import Any, Protocol

import torch
from torch import Tensor
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from torchbrdf.brdf.principled import fused_at_every_size
from torchbrdf.capture.synthetic import (
    DEFAULT_CAMERA,
    MAP_NAMES,
    RECIPES,
    SOFT_RECIPES,
    add_noise,
    light_layout,
    make_material,
    random_lights,
    render_capture,
)

__all__ = [
    "MaterialSource",
    "RecipeSource",
    "FamilySource",
    "MaterialDataset",
    "MaterialStream",
    "transform_maps",
    "SYMMETRIES",
]

SYMMETRIES = 8
"""The symmetries of the square: ``code & 1`` flips x (columns), ``code & 2`` flips y (rows),
``code & 4`` transposes."""

# Seeds of different samples must not collide: a large odd stride per dataset seed.
_SEED_STRIDE = 1_000_003


class MaterialSource(Protocol):
    """A material generator: ``source(seed, size)`` -> maps ``(C, size, size)`` by name (:data:`MAP_NAMES`)."""

    def __call__(self, seed: int, size: int) -> dict[str, Tensor]: ...


class RecipeSource:
    """Materials from :func:`torchbrdf.capture.synthetic.make_material`, the recipe chosen by seed.

    Args:
        recipes: recipe names (default every one of ``RECIPES`` and ``SOFT_RECIPES``).
    """

    def __init__(self, recipes: Sequence[str] | None = None) -> None:
        self.recipes = tuple(recipes) if recipes is not None else RECIPES + SOFT_RECIPES
        unknown = [r for r in self.recipes if r not in RECIPES + SOFT_RECIPES]
        if unknown or not self.recipes:
            raise ValueError(f"RecipeSource: recipes must be a non-empty subset of {RECIPES + SOFT_RECIPES}, "
                             f"got {list(self.recipes)}")

    def __call__(self, seed: int, size: int) -> dict[str, Tensor]:
        return make_material(self.recipes[seed % len(self.recipes)], seed // len(self.recipes), size)

    def __repr__(self) -> str:
        return f"RecipeSource({list(self.recipes)})"


class FamilySource:
    """Materials from ``torchbrdf.capture.families.make_family_material``, the family chosen by seed.

    Args:
        families: family names (default that module's ``FAMILIES``).

    Raises:
        ImportError: when ``torchbrdf.capture.families`` is not installed.
    """

    def __init__(self, families: Sequence[str] | None = None) -> None:
        module = self._module()
        self.families = tuple(families) if families is not None else tuple(module.FAMILIES)
        unknown = [f for f in self.families if f not in module.FAMILIES]
        if unknown or not self.families:
            raise ValueError(f"FamilySource: families must be a non-empty subset of {list(module.FAMILIES)}, "
                             f"got {list(self.families)}")

    @staticmethod
    def _module() -> Any:  # Any: an optional module, imported when used
        try:
            return importlib.import_module("torchbrdf.capture.families")
        except ModuleNotFoundError as err:
            raise ImportError("FamilySource needs torchbrdf.capture.families (FAMILIES, make_family_material), "
                              "which this installation does not have; use RecipeSource") from err

    def __call__(self, seed: int, size: int) -> dict[str, Tensor]:
        family = self.families[seed % len(self.families)]
        return self._module().make_family_material(family, seed // len(self.families), size)

    def __repr__(self) -> str:
        return f"FamilySource({list(self.families)})"


def transform_maps(maps: dict[str, Tensor], code: int) -> dict[str, Tensor]:
    """Apply one of the :data:`SYMMETRIES` to ``(C, H, W)`` maps, keeping the normal map consistent.

    A flip of x negates the normals' x component, a flip of y their y; the transposition
    (row ``i``, column ``j``) -> (``j``, ``i``) maps the sample's ``(x, y)`` to ``(-y, -x)``, so
    the normals' ``(x, y)`` become ``(-y, -x)``. Rendering the transformed maps under the
    transformed lights gives the transformed images (pinned by ``tests/test_data.py``).
    """
    if not 0 <= code < SYMMETRIES:
        raise ValueError(f"transform_maps: code must be in [0, {SYMMETRIES}), got {code}")
    out = {}
    for name, t in maps.items():
        if code & 1:
            t = t.flip(-1)
        if code & 2:
            t = t.flip(-2)
        if code & 4:
            t = t.transpose(-1, -2)
        if name == "normal":
            x, y, z = t[0], t[1], t[2]
            x = -x if code & 1 else x
            y = -y if code & 2 else y
            if code & 4:
                x, y = -y, -x
            t = torch.stack((x, y, z))
        out[name] = t.contiguous()
    return out


def _range(name: str, value: float | tuple[float, float]) -> tuple[float, float]:
    lo, hi = (value, value) if isinstance(value, (int, float)) else value
    if not 0 <= lo <= hi:
        raise ValueError(f"{name} must be a non-negative number or a (low, high) range, got {value!r}")
    return float(lo), float(hi)


def _check_integers(owner: str, **values: Any) -> None:
    """Refuse a count or seed that is not an integer, naming it (``int()`` would truncate 16.5)."""
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{owner}: {name} must be an integer, got {value!r}")


class MaterialDataset(Dataset):
    """Map-style dataset of procedural materials with their renderings (see the module docstring).

    Args:
        length: number of samples.
        size: S, the samples' resolution (square).
        seed: dataset seed; sample ``k`` depends on ``(seed, k)`` only.
        source: a :class:`MaterialSource` (default :class:`RecipeSource`).
        variants: samples per material (1..8, its symmetries of the square).
        extra_lights: random point lights after the flash (:func:`~torchbrdf.capture.synthetic.random_lights`).
        ring_lights: the extra lights are instead the ring of ``light_layout(extra_lights)`` (the
            capture layout an estimator is trained for), in a random order per sample: the
            estimator learns that layout, not an order a capture file may not keep.
        noise: relative sensor-noise level, or a ``(low, high)`` range drawn per sample.
        flash_intensity: the flash's radiant intensity (grey).
        gamma: camera response: ``None`` keeps linear radiance; a value clips at 1 and applies
            ``x ** (1 / gamma)``.
        device: where to render (default CPU).

    Example:
        >>> ds = MaterialDataset(length=4, size=16)
        >>> s = ds[0]
        >>> tuple(s["maps"].shape), tuple(s["images"].shape)
        ((9, 16, 16), (1, 3, 16, 16))
    """

    def __init__(
        self,
        length: int = 1000,
        size: int = 64,
        *,
        seed: int = 0,
        source: MaterialSource | None = None,
        variants: int = 4,
        extra_lights: int = 0,
        ring_lights: bool = False,
        noise: float | tuple[float, float] = (0.0, 0.02),
        flash_intensity: float = 15.0,
        gamma: float | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        _check_integers("MaterialDataset", length=length, size=size, seed=seed, variants=variants,
                        extra_lights=extra_lights)
        if length < 1 or size < 4:
            raise ValueError(f"MaterialDataset: need length >= 1 and size >= 4, got length={length}, size={size}")
        if not 1 <= variants <= SYMMETRIES:
            raise ValueError(f"MaterialDataset: variants must be in [1, {SYMMETRIES}], got {variants}")
        if extra_lights < 0 or not flash_intensity > 0 or (gamma is not None and not gamma > 0):
            raise ValueError(f"MaterialDataset: need extra_lights >= 0, flash_intensity > 0 and gamma > 0 or None; "
                             f"got {extra_lights}, {flash_intensity}, {gamma}")
        if ring_lights and extra_lights == 0:
            raise ValueError("MaterialDataset: ring_lights needs extra_lights > 0 (the ring's light count)")
        self.length, self.size, self.seed = int(length), int(size), int(seed)
        self.source: MaterialSource = source if source is not None else RecipeSource()
        self.variants, self.extra_lights, self.ring_lights = int(variants), int(extra_lights), bool(ring_lights)
        self.noise = _range("noise", noise)
        self.flash_intensity, self.gamma = float(flash_intensity), gamma
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self._cached: tuple[int, dict[str, Tensor]] | None = None

    def __len__(self) -> int:
        return self.length

    def material(self, index: int) -> dict[str, Tensor]:
        """The ``(C, S, S)`` maps of sample ``index`` (before its lights), on the CPU."""
        m = index // self.variants
        if self._cached is None or self._cached[0] != m:  # the variants of a material come together
            self._cached = (m, self.source(self.seed * _SEED_STRIDE + m, self.size))
        code = (index % self.variants) * (SYMMETRIES // self.variants)
        return transform_maps(self._cached[1], code)

    def __getitem__(self, index: int) -> dict[str, Any]:  # Any: tensors and the int index
        if not -self.length <= index < self.length:
            raise IndexError(f"MaterialDataset: index {index} out of range for length {self.length}")
        index %= self.length
        maps = {k: t.to(self.device) for k, t in self.material(index).items()}
        gen = torch.Generator().manual_seed(self.seed * _SEED_STRIDE + index + 7)
        flash_pos, _ = light_layout(0, near_camera=True)
        pos, inten = flash_pos, torch.full((1, 3), self.flash_intensity)
        if self.extra_lights and self.ring_lights:
            # light_layout's ring and flash, scaled so that its flash is this one
            ring_pos, ring_int = light_layout(self.extra_lights, intensity=2.0 * self.flash_intensity)
            order = torch.randperm(self.extra_lights, generator=gen)
            extra = (ring_pos[:-1][order], ring_int[:-1].to(torch.float32))
        elif self.extra_lights:
            extra = random_lights(self.extra_lights, seed=int(torch.randint(2**31 - 1, (), generator=gen)))
        if self.extra_lights:
            pos, inten = torch.cat((pos, extra[0])), torch.cat((inten, extra[1]))
        with fused_at_every_size():  # a dataset renders one kind of call sample after sample
            images = render_capture(maps, (pos, inten), DEFAULT_CAMERA, backend="compact")
        lo, hi = self.noise
        level = lo + (hi - lo) * float(torch.rand((), generator=gen))
        if level > 0:
            images = add_noise(images, level, seed=int(torch.randint(2**31 - 1, (), generator=gen)))
        if self.gamma is not None:
            images = images.clamp(0.0, 1.0) ** (1.0 / self.gamma)
        return {
            "maps": torch.cat([maps[k] for k in MAP_NAMES]),
            "images": images,
            "light_positions": pos.to(self.device),
            "light_intensities": inten.to(self.device),
            "camera_position": torch.tensor(DEFAULT_CAMERA, device=self.device),
            "index": index,
        }


class MaterialStream(IterableDataset):
    """Iterable form of :class:`MaterialDataset`: samples ``start, start + 1, ...`` split over workers.

    Each ``DataLoader`` worker takes whole blocks of ``variants`` consecutive indices (block
    ``b`` goes to worker ``b % num_workers``), so a material is synthesised once.

    Args:
        length: number of samples, or ``None`` for an endless stream.
        start: the first index.
        **kwargs: the options of :class:`MaterialDataset` (``size``, ``seed``, ``source``, ...).

    Example:
        >>> from torch.utils.data import DataLoader
        >>> batch = next(iter(DataLoader(MaterialStream(length=4, size=16), batch_size=2)))
        >>> tuple(batch["images"].shape)
        (2, 1, 3, 16, 16)
    """

    def __init__(self, length: int | None = None, start: int = 0, **kwargs: Any) -> None:
        # Any: MaterialDataset's keyword options, passed through
        counts = {k: kwargs[k] for k in ("size", "seed", "variants", "extra_lights") if k in kwargs}
        _check_integers("MaterialStream", **({} if length is None else {"length": length}), start=start, **counts)
        if length is not None and length < 1:
            raise ValueError(f"MaterialStream: length must be >= 1 or None, got {length}")
        self.length, self.start = length, int(start)
        if kwargs.get("size", 64) < 4:
            raise ValueError(f"MaterialStream: size must be >= 4, got {kwargs['size']}")
        self.dataset = MaterialDataset(length=2**62, **kwargs)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        v = self.dataset.variants
        end = math.inf if self.length is None else self.start + self.length
        block = worker
        while True:
            for k in range(self.start + block * v, self.start + (block + 1) * v):
                if k >= end:
                    return
                yield self.dataset[k]
            block += workers
