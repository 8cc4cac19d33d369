r"""Training losses on SVBRDF maps: the rendering loss of the learned-capture literature, and a map loss.

**Rendering loss** (Deschaintre et al. 2018, "Single-Image SVBRDF Capture with a
Rendering-Aware Deep Network"; reused by Deschaintre 2019, Gao 2019, MaterialGAN). Both the
predicted and the target maps of each batch element are rendered under the same ``N`` random
view/light configurations and the renderings are compared in log space::

    loss = mean over (b, k, c, pixel) of | log(R_pred + 0.01) - log(R_target + 0.01) |

Configurations (drawn per batch element, :func:`random_configurations`):

* ``n_diffuse`` **diffuse-lit** ones: a light direction and a view direction, drawn
  independently from the cosine-weighted hemisphere (``r = sqrt(u1)``, ``u1`` uniform in
  ``[0.001, 0.9]``, azimuth uniform), both at infinity (the same ``l`` and ``v`` at every
  pixel, no falloff);
* ``n_specular`` **specular-lit** ones: a view direction ``d`` from the same distribution and the
  mirrored light direction ``(-d_x, -d_y, d_z)``, each placed at its own distance
  ``exp(N(0.5, 0.75))`` from a shifted point ``(U(-1, 1), U(-1, 1), 1e-4)`` of the sample, so
  the mirror highlight falls somewhere on it; ``l`` and ``v`` are then per pixel, and the
  light falls off as ``1 / |q - p|^2``.

A pixel's rendering is ``pi * f(l, v) * max(n.l, 0) / d^2`` (``d = 1`` for the diffuse-lit
ones), ``f`` the BRDF of the maps' layout in the normal-mapped frame. The sample is the
capture format's flat square (``docs/capture_format.md``): pixel ``(i, j)`` sees
``(-1 + (j + 0.5) 2 / W, 1 - (i + 0.5) 2 / H, 0)``.

Map layouts (channels of a ``(B, C, H, W)`` map tensor, in this order):

* ``"principled"`` (:data:`PRINCIPLED_LAYOUT`, the recovery's maps): ``base_color`` 3,
  ``roughness`` 1, ``metallic`` 1, ``specular`` 1, ``normal`` 3 (tangent space); rendered with
  :func:`torchbrdf.principled` (the fused kernels), the other parameters at their defaults.
* ``"svbrdf_ggx"`` (:data:`GGX_LAYOUT`, Deschaintre's maps): ``normal`` 3, ``diffuse`` 3,
  ``roughness`` 1, ``specular`` 3; rendered with :func:`torchbrdf.svbrdf_ggx` and Deschaintre's
  roughness floor.

Normal maps are normalised before rendering (a network's output need not be unit length).
"""

from __future__ import annotations

import contextlib
import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchbrdf._math import dot, safe_normalize
from torchbrdf.brdf.svbrdf_ggx import ROUGHNESS_FLOOR_DESCHAINTRE, svbrdf_ggx
from torchbrdf.brdf.principled import FAST_PATH_MIN_LANES, fused_at_every_size, principled
from torchbrdf.capture.format import pixel_points
from torchbrdf.capture.synthetic import MAP_NAMES

__all__ = [
    "PRINCIPLED_LAYOUT",
    "GGX_LAYOUT",
    "LAYOUTS",
    "LOG_OFFSET",
    "Configurations",
    "random_configurations",
    "render_configurations",
    "rendering_loss",
    "RenderingLoss",
    "map_loss",
    "MapLoss",
    "split_maps",
]

PRINCIPLED_LAYOUT: dict[str, int] = dict(MAP_NAMES)
"""Channels of principled maps, in order: base_color 3, roughness 1, metallic 1, specular 1, normal 3."""

GGX_LAYOUT: dict[str, int] = {"normal": 3, "diffuse": 3, "roughness": 1, "specular": 3}
"""Channels of SVBRDF-GGX maps (Deschaintre et al.'s order): normal 3, diffuse 3, roughness 1, specular 3."""

LAYOUTS: dict[str, dict[str, int]] = {"principled": PRINCIPLED_LAYOUT, "svbrdf_ggx": GGX_LAYOUT}

LOG_OFFSET = 0.01
"""The published ``log(x + 0.01)``: compresses highlights while keeping dark pixels' differences."""

# Sampling constants of the published scheme: the hemisphere's radius-squared range avoids the
# exact normal and grazing directions; the log-normal distance puts the specular lights
# between ~0.4 and ~7 sample half-widths away.
_DIR_LOW_EPS, _DIR_HIGH_EPS = 0.001, 0.1
_DISTANCE_MEAN, _DISTANCE_STD = 0.5, 0.75
_SHIFT_Z = 1e-4


class Configurations(NamedTuple):
    """View/light configurations of the rendering loss, per batch element.

    Attributes:
        light: ``(B, N, 3)``; a unit direction toward the light (diffuse-lit) or the light's
            position (specular-lit).
        view: ``(B, N, 3)``; a unit direction toward the viewer or the viewer's position.
        positional: ``(N,)`` 0 for a configuration at infinity (directions), 1 for positions.
    """

    light: Tensor
    view: Tensor
    positional: Tensor


def _hemisphere(shape: tuple[int, ...], gen, dtype, device) -> Tensor:
    """Cosine-weighted directions ``(*shape, 3)`` with ``sin^2 theta`` in ``[0.001, 0.9]``."""
    u1 = _DIR_LOW_EPS + (1.0 - _DIR_HIGH_EPS - _DIR_LOW_EPS) * torch.rand(shape, generator=gen, dtype=dtype, device=device)
    phi = 2 * math.pi * torch.rand(shape, generator=gen, dtype=dtype, device=device)
    r = u1.sqrt()
    return torch.stack((r * phi.cos(), r * phi.sin(), (1.0 - u1).sqrt()), -1)


def random_configurations(
    batch: int,
    n_diffuse: int = 3,
    n_specular: int = 6,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Configurations:
    """Draw the published diffuse-lit and specular-lit configurations (see the module docstring).

    Args:
        batch: B, the number of batch elements (each gets its own configurations).
        n_diffuse: diffuse-lit configurations per element (Deschaintre et al.: 3).
        n_specular: specular-lit configurations per element (Deschaintre et al.: 6).
        generator: the random generator (on ``device``); ``None`` uses torch's global one.
        dtype: floating dtype of the result.
        device: device of the result (default the generator's, else CPU).

    Returns:
        :class:`Configurations` with ``light``/``view`` ``(B, n_diffuse + n_specular, 3)``,
        diffuse-lit first.

    Example:
        >>> c = random_configurations(2, generator=torch.Generator().manual_seed(0))
        >>> tuple(c.light.shape), c.positional.tolist()
        ((2, 9, 3), [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    """
    if batch < 1 or n_diffuse < 0 or n_specular < 0 or n_diffuse + n_specular < 1:
        raise ValueError(
            f"random_configurations: need batch >= 1 and n_diffuse, n_specular >= 0 with at least one "
            f"configuration; got batch={batch}, n_diffuse={n_diffuse}, n_specular={n_specular}"
        )
    if device is None:
        device = generator.device if generator is not None else torch.device("cpu")
    d_light = _hemisphere((batch, n_diffuse), generator, dtype, device)
    d_view = _hemisphere((batch, n_diffuse), generator, dtype, device)
    s_view = _hemisphere((batch, n_specular), generator, dtype, device)
    s_light = s_view * torch.tensor([-1.0, -1.0, 1.0], dtype=dtype, device=device)
    shift = torch.cat(
        (2.0 * torch.rand((batch, n_specular, 2), generator=generator, dtype=dtype, device=device) - 1.0,
         torch.full((batch, n_specular, 1), _SHIFT_Z, dtype=dtype, device=device)), -1)
    view_dist, light_dist = torch.exp(_DISTANCE_MEAN + _DISTANCE_STD * torch.randn(
        (2, batch, n_specular, 1), generator=generator, dtype=dtype, device=device))
    positional = torch.cat((torch.zeros(n_diffuse, dtype=dtype, device=device),
                            torch.ones(n_specular, dtype=dtype, device=device)))
    return Configurations(
        light=torch.cat((d_light, s_light * light_dist + shift), 1),
        view=torch.cat((d_view, s_view * view_dist + shift), 1),
        positional=positional,
    )


def split_maps(maps: Tensor, layout: str = "principled", *, name: str = "maps") -> dict[str, Tensor]:
    """Split ``(B, C, H, W)`` maps into named ``(B, c, H, W)`` views by :data:`LAYOUTS`.

    ``name`` is how an error calls ``maps`` (a caller's argument, e.g. ``"rendering_loss: pred"``).

    Raises:
        ValueError: if ``layout`` is unknown or ``maps`` is not ``(B, C, H, W)`` with that
            layout's channel count.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {sorted(LAYOUTS)}, got {layout!r}")
    spec = LAYOUTS[layout]
    channels = sum(spec.values())
    if not isinstance(maps, Tensor) or maps.dim() != 4 or maps.shape[1] != channels:
        shape = tuple(maps.shape) if isinstance(maps, Tensor) else type(maps).__name__
        raise ValueError(f"{name} must be (B, {channels}, H, W) for the {layout!r} layout "
                         f"({', '.join(f'{k} {c}' for k, c in spec.items())}), got {shape}")
    return dict(zip(spec, torch.split(maps, list(spec.values()), dim=1)))


def render_configurations(maps: Tensor, configs: Configurations, layout: str = "principled",
                          intensity: float = math.pi) -> Tensor:
    """Render maps under each configuration: ``(B, C, H, W)`` maps -> ``(B, N, 3, H, W)`` radiance.

    Args:
        maps: ``(B, C, H, W)`` maps of ``layout`` (floating, any device).
        configs: :class:`Configurations` with ``B`` rows (or 1, shared by the batch).
        layout: ``"principled"`` or ``"svbrdf_ggx"`` (:data:`LAYOUTS`).
        intensity: the light's intensity (the published scheme: pi).

    Returns:
        ``(B, N, 3, H, W)`` linear radiance in the maps' dtype and on their device.
    """
    named = split_maps(maps, layout)
    b, _, h, w = maps.shape
    cl = {k: t.permute(0, 2, 3, 1)[:, None] for k, t in named.items()}  # (B, 1, H, W, c)
    p = pixel_points(w, h, device=maps.device, dtype=maps.dtype)  # (H, W, 3)
    pos = configs.positional.to(maps)[None, :, None, None, None]
    to_light = configs.light.to(maps)[:, :, None, None, :] - pos * p
    to_view = configs.view.to(maps)[:, :, None, None, :] - pos * p
    d2 = dot(to_light, to_light)
    l, v = safe_normalize(to_light), safe_normalize(to_view)
    n = safe_normalize(cl["normal"])
    if layout == "principled":
        f = principled(l, v, n, base_color=cl["base_color"], roughness=cl["roughness"],
                       metallic=cl["metallic"], specular=cl["specular"])
    else:
        f = svbrdf_ggx(l, v, n, diffuse_albedo=cl["diffuse"], specular_albedo=cl["specular"],
                       roughness=cl["roughness"], roughness_floor=ROUGHNESS_FLOOR_DESCHAINTRE)
    radiance = f * (intensity * torch.clamp(dot(n, l), min=0.0) / d2)
    return radiance.permute(0, 1, 4, 2, 3)


def rendering_loss(
    pred: Tensor,
    target: Tensor,
    *,
    layout: str = "principled",
    n_diffuse: int = 3,
    n_specular: int = 6,
    generator: torch.Generator | None = None,
    configs: Configurations | None = None,
    intensity: float = math.pi,
) -> Tensor:
    """The rendering loss: L1 between ``log(R + 0.01)`` of both map sets' renderings.

    Args:
        pred: predicted maps ``(B, C, H, W)`` of ``layout``.
        target: target maps, the same shape, dtype and device.
        layout: ``"principled"`` (:data:`PRINCIPLED_LAYOUT`) or ``"svbrdf_ggx"`` (:data:`GGX_LAYOUT`).
        n_diffuse: diffuse-lit configurations per element (when ``configs`` is not given).
        n_specular: specular-lit configurations per element.
        generator: seeds the configurations (``None``: torch's global generator), on any
            device (the configurations move to ``pred``'s). Under
            ``torch.compile(fullgraph=True)`` pass ``configs`` (or no generator) instead:
            a generator argument is not traceable.
        configs: fixed :class:`Configurations` (from :func:`random_configurations`) instead of
            drawing new ones.
        intensity: the light's intensity (the published scheme: pi).

    Returns:
        A 0-d tensor in ``pred``'s dtype: the mean over elements, configurations, channels
        and pixels.

    Example:
        >>> from torchbrdf.capture.synthetic import make_material
        >>> m = make_material("tiles", seed=1, size=16)
        >>> t = torch.cat([m[k] for k in PRINCIPLED_LAYOUT])[None]
        >>> float(rendering_loss(t, t, generator=torch.Generator().manual_seed(0)))
        0.0
    """
    if not isinstance(target, Tensor) or not isinstance(pred, Tensor) or pred.shape != target.shape:
        raise ValueError(f"rendering_loss: pred and target must be tensors of one shape, got "
                         f"{getattr(pred, 'shape', type(pred).__name__)} and "
                         f"{getattr(target, 'shape', type(target).__name__)}")
    if (pred.dtype, pred.device) != (target.dtype, target.device):
        raise ValueError(f"rendering_loss: pred and target must share dtype and device, got "
                         f"{pred.dtype} on {pred.device} and {target.dtype} on {target.device}")
    split_maps(pred, layout, name="rendering_loss: pred")  # named before any rendering
    if configs is None:
        # Drawn on the generator's device (a CPU generator may seed a CUDA loss), then moved.
        where = generator.device if generator is not None else pred.device
        configs = random_configurations(pred.shape[0], n_diffuse, n_specular, generator, pred.dtype, where)
    b = pred.shape[0]
    if torch.is_grad_enabled() and pred.requires_grad and not target.requires_grad:
        # Two renderings, so that the backward (kernel and geometry) covers pred's half only;
        # dispatched as the one rendering of both would be (the same lane count decides).
        configs = Configurations(configs.light.expand(b, -1, -1), configs.view.expand(b, -1, -1), configs.positional)
        large = not torch.compiler.is_compiling() and (
            2 * b * configs.light.shape[1] * pred.shape[2] * pred.shape[3] >= FAST_PATH_MIN_LANES)
        with fused_at_every_size() if large else contextlib.nullcontext():
            rp = render_configurations(pred, configs, layout, intensity)
            rt = render_configurations(target, configs, layout, intensity)
    else:  # one rendering of both: one kernel call
        both = render_configurations(torch.cat((pred, target)), Configurations(
            configs.light.expand(b, -1, -1).repeat(2, 1, 1),
            configs.view.expand(b, -1, -1).repeat(2, 1, 1), configs.positional), layout, intensity)
        rp, rt = both.chunk(2)
    return (torch.log(rp + LOG_OFFSET) - torch.log(rt + LOG_OFFSET)).abs().mean()


class RenderingLoss(nn.Module):
    """:func:`rendering_loss` as a module holding the options and, when seeded, its own generator.

    Args:
        layout: see :func:`rendering_loss`.
        n_diffuse: see :func:`rendering_loss`.
        n_specular: see :func:`rendering_loss`.
        seed: seeds a CPU generator owned by the module (configurations drawn on CPU, then
            moved); ``None`` uses torch's global generator.
        intensity: see :func:`rendering_loss`.

    Shape:
        - Input: ``pred``, ``target`` ``(B, C, H, W)``.
        - Output: ``()``.
    """

    def __init__(self, layout: str = "principled", n_diffuse: int = 3, n_specular: int = 6,
                 seed: int | None = None, intensity: float = math.pi) -> None:
        super().__init__()
        if layout not in LAYOUTS:
            raise ValueError(f"RenderingLoss: layout must be one of {sorted(LAYOUTS)}, got {layout!r}")
        self.layout, self.n_diffuse, self.n_specular, self.intensity = layout, n_diffuse, n_specular, intensity
        self.generator = None if seed is None else torch.Generator().manual_seed(int(seed))

    def forward(self, pred: Tensor, target: Tensor, configs: Configurations | None = None) -> Tensor:
        return rendering_loss(pred, target, layout=self.layout, n_diffuse=self.n_diffuse, n_specular=self.n_specular,
                              generator=self.generator, configs=configs, intensity=self.intensity)

    def extra_repr(self) -> str:
        return f"layout={self.layout!r}, n_diffuse={self.n_diffuse}, n_specular={self.n_specular}"


def map_loss(pred: Tensor, target: Tensor, *, layout: str = "principled",
             weights: dict[str, float] | None = None) -> Tensor:
    """Weighted sum over maps of each map's mean L1 difference.

    Args:
        pred: predicted maps ``(B, C, H, W)`` of ``layout``.
        target: target maps, the same shape.
        layout: ``"principled"`` or ``"svbrdf_ggx"`` (:data:`LAYOUTS`).
        weights: map name -> weight; maps not named weigh 1 (a weight of 0 drops a map).

    Returns:
        A 0-d tensor in ``pred``'s dtype.

    Raises:
        ValueError: on a shape mismatch or a weight for a map the layout does not have.
    """
    if not isinstance(target, Tensor) or not isinstance(pred, Tensor) or pred.shape != target.shape:
        raise ValueError(f"map_loss: pred and target must be tensors of one shape, got "
                         f"{getattr(pred, 'shape', type(pred).__name__)} and "
                         f"{getattr(target, 'shape', type(target).__name__)}")
    p, t = split_maps(pred, layout, name="map_loss: pred"), split_maps(target, layout, name="map_loss: target")
    weights = dict(weights or {})
    unknown = set(weights) - set(p)
    if unknown:
        raise ValueError(f"map_loss: weights names maps {sorted(unknown)} that the {layout!r} layout "
                         f"does not have ({list(p)})")
    total = pred.new_zeros(())
    for name in p:
        total = total + weights.get(name, 1.0) * (p[name] - t[name]).abs().mean()
    return total


class MapLoss(nn.Module):
    """:func:`map_loss` as a module.

    Args:
        layout: see :func:`map_loss`.
        weights: see :func:`map_loss`.

    Shape:
        - Input: ``pred``, ``target`` ``(B, C, H, W)``.
        - Output: ``()``.
    """

    def __init__(self, layout: str = "principled", weights: dict[str, float] | None = None) -> None:
        super().__init__()
        self.layout, self.weights = layout, dict(weights or {})

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        return map_loss(pred, target, layout=self.layout, weights=self.weights)
