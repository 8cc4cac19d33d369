"""Lights for :func:`torchbrdf.shade`: point, directional and lat-long environment lights.

Each light is an ``nn.Module`` holding its parameters as tensors. A tensor passed in is kept
as is (not copied), so gradients flow back to it; an ``nn.Parameter`` is registered as a
parameter (optimise it through ``light.parameters()``), any other tensor as a buffer (moved
by ``.to()``). Python sequences and numbers are stored exactly, as float64; every
parameter is cast to the g-buffer's dtype and device when shading.

Per-batch parameters: a leading batch axis ``B`` (matching the g-buffer's) gives each image
its own light; without it the light is shared by the whole batch.

Radiance contributed at a pixel with BRDF ``f``, normal ``n`` and position ``P`` (the screen-space shading formulas):

* :class:`PointLight` (radiant intensity ``I`` at ``q``): ``f(l, v) I max(n·l, 0) / |q - P|²``,
  ``l = normalize(q - P)``;
* :class:`DirectionalLight` (irradiance ``E`` from direction ``d``):
  ``f(d, v) E max(n·d, 0)``;
* :class:`EnvironmentLight` (lat-long radiance ``L``): ``∫ f(l, v) L(l) max(n·l, 0) dω``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["Light", "PointLight", "DirectionalLight", "EnvironmentLight"]


def _to_tensor(name: str, owner: str, value) -> Tensor:
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            raise TypeError(f"{owner}: `{name}` must be floating point, got dtype {value.dtype}")
        return value
    if isinstance(value, bool):
        raise TypeError(f"{owner}: `{name}` must be a tensor or numbers, got bool")
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(
            f"{owner}: `{name}` must be a tensor or a sequence of numbers, got {type(value).__name__}"
        ) from None


class Light(nn.Module):
    """Base class: stores tensors as parameters or buffers and reports the batch size."""

    def _store(self, name: str, value: Tensor) -> None:
        if isinstance(value, nn.Parameter):
            self.register_parameter(name, value)
        else:
            self.register_buffer(name, value)

    def _vec3(self, name: str, value, allow_scalar: bool = False) -> Tensor:
        owner = type(self).__name__
        t = _to_tensor(name, owner, value)
        if allow_scalar and t.dim() == 0:
            t = t.expand(3)
        if not (t.shape == (3,) or (t.dim() == 2 and t.shape[1] == 3 and t.shape[0] >= 1)):
            extra = ", or a scalar" if allow_scalar else ""
            raise ValueError(f"{owner}: `{name}` must have shape [3] or [B, 3]{extra}, got {list(t.shape)}")
        return t

    @property
    def batch_size(self) -> int | None:
        """Leading batch size of the parameters, or ``None`` when shared by the whole batch."""
        sizes = {t.shape[0] for t in self._light_tensors() if t.dim() == self._batched_dim()}
        return max(sizes) if sizes else None

    def _light_tensors(self) -> list[Tensor]:  # pragma: no cover - overridden
        return []

    def _batched_dim(self) -> int:
        return 2


class PointLight(Light):
    """Isotropic point light.

    Args:
        position: ``(3,)`` or ``(B, 3)`` world-space position ``q``.
        intensity: ``(3,)`` or ``(B, 3)`` linear RGB radiant intensity ``I`` (a scalar means
            grey).

    Example:
        >>> PointLight([0.0, 0.0, 3.0], [10.0, 10.0, 10.0]).position
        tensor([0., 0., 3.], dtype=torch.float64)
    """

    position: Tensor  # registered by _store (parameter or buffer); declared for the type checker
    intensity: Tensor

    def __init__(self, position: Tensor | Sequence[float], intensity: Tensor | Sequence[float] | float) -> None:
        super().__init__()
        pos = self._vec3("position", position)
        inten = self._vec3("intensity", intensity, allow_scalar=True)
        if (
            pos.dim() == 2
            and inten.dim() == 2
            and pos.shape[0] != inten.shape[0]
            and 1 not in (pos.shape[0], inten.shape[0])
        ):
            raise ValueError(
                f"PointLight: `position` batch {pos.shape[0]} and `intensity` batch {inten.shape[0]} differ"
            )
        self._store("position", pos)
        self._store("intensity", inten)

    def _light_tensors(self):
        return [self.position, self.intensity]

    def extra_repr(self) -> str:
        """Parameter shapes, for ``repr``."""
        return f"position={list(self.position.shape)}, intensity={list(self.intensity.shape)}"


class DirectionalLight(Light):
    """Distant light arriving from one direction.

    Args:
        direction: ``(3,)`` or ``(B, 3)`` unit vector from the surface toward the light
            (normalised by the shader, which keeps its gradient well defined).
        irradiance: ``(3,)`` or ``(B, 3)`` linear RGB irradiance ``E`` on a surface facing
            the light (a scalar means grey).

    Example:
        >>> DirectionalLight([0.0, 0.0, 1.0], 1.0).irradiance
        tensor([1., 1., 1.], dtype=torch.float64)
    """

    direction: Tensor  # registered by _store (parameter or buffer)
    irradiance: Tensor

    def __init__(self, direction: Tensor | Sequence[float], irradiance: Tensor | Sequence[float] | float) -> None:
        super().__init__()
        d = self._vec3("direction", direction)
        e = self._vec3("irradiance", irradiance, allow_scalar=True)
        if d.dim() == 2 and e.dim() == 2 and d.shape[0] != e.shape[0] and 1 not in (d.shape[0], e.shape[0]):
            raise ValueError(
                f"DirectionalLight: `direction` batch {d.shape[0]} and `irradiance` batch {e.shape[0]} differ"
            )
        self._store("direction", d)
        self._store("irradiance", e)

    def _light_tensors(self):
        return [self.direction, self.irradiance]

    def extra_repr(self) -> str:
        """Parameter shapes, for ``repr``."""
        return f"direction={list(self.direction.shape)}, irradiance={list(self.irradiance.shape)}"


class EnvironmentLight(Light):
    """Distant lighting from a lat-long (equirectangular) radiance map.

    The map is read as constant over each texel. Convention (z up): row ``i`` of ``He``
    has polar angle ``θ = (i + 0.5) π / He`` from +z, column ``j`` of ``We`` azimuth
    ``φ = -π + (j + 0.5) 2π / We``, direction ``(sin θ cos φ, sin θ sin φ, cos θ)``.

    Args:
        radiance: ``(3, He, We)`` or ``(B, 3, He, We)`` linear RGB radiance.

    Example:
        >>> EnvironmentLight(torch.ones(3, 8, 16)).radiance.shape
        torch.Size([3, 8, 16])
    """

    radiance: Tensor  # registered by _store (parameter or buffer)

    def __init__(self, radiance: Tensor) -> None:
        super().__init__()
        r = _to_tensor("radiance", "EnvironmentLight", radiance)
        if not (r.dim() in (3, 4) and r.shape[-3] == 3 and r.shape[-1] >= 1 and r.shape[-2] >= 1):
            raise ValueError(
                "EnvironmentLight: `radiance` must have shape [3, He, We] or [B, 3, He, We], "
                f"got {list(r.shape)}"
            )
        self._store("radiance", r)
        # Split-sum preparation of a map that does not require grad, keyed by its version.
        self._split_sum_cache: tuple | None = None

    def _light_tensors(self):
        return [self.radiance]

    def _batched_dim(self) -> int:
        return 4

    @property
    def height(self) -> int:
        """``He``."""
        return self.radiance.shape[-2]

    @property
    def width(self) -> int:
        """``We``."""
        return self.radiance.shape[-1]

    def extra_repr(self) -> str:
        """Parameter shapes, for ``repr``."""
        return f"radiance={list(self.radiance.shape)}"
