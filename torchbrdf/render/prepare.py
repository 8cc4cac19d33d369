"""The preparation of :func:`torchbrdf.shade`: what to shade, decided once before any pass.

The steps run in this order, each a function of the one before:

1. :func:`validate` checks every argument up front (errors name the argument);
2. :func:`select_pixels` drops masked-out and back-facing pixels (``n·v <= 0``, where every
   BRDF of the library is 0);
3. :func:`inspect_material` reduces material maps that need no gradient (all zeros -> the
   Python float ``0.0``, so the BRDF skips the lobe it weights; uniform -> a float) and
   decides the active lobes and whether tangent frames are needed;
4. :func:`schedule` splits the lights by kind, picks the fused light route, the pixel chunk
   and the Monte Carlo sample patterns.

Under ``torch.compile`` the value-dependent decisions of steps 2 and 3 are skipped (each
would be a graph break and a guard on the data, i.e. a recompile per new input): every
pixel and map is evaluated, as with ``prune=False``, and Python-float material values become
0-d tensors, so a new value is a new input rather than a new graph.
"""

from __future__ import annotations

import inspect
import numbers
import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import torch
from torch import Tensor, nn

from torchbrdf._checks import (check_finite, check_nonnegative, constant_while_tracing, forward_mode_active,
                               validation_enabled)
from torchbrdf._math import is_zero
from torchbrdf._types import BRDF
from torchbrdf.brdf.principled import LOBES
from torchbrdf.render.env import MCSetup, brdf_kind, check_env_sampling
from torchbrdf.render.fused_lights import fused_lights_wanted, light_loop_brdf
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, Light, PointLight

__all__ = [
    "ENV_STRATEGIES",
    "ShadingRequest",
    "PixelSet",
    "PixelSelection",
    "MaterialUse",
    "ShadingSchedule",
    "validate",
    "select_pixels",
    "inspect_material",
    "schedule",
    "brdf_name",
]

ENV_STRATEGIES = ("mc", "split_sum")


# --------------------------------------------------------------------------------------
# 1. Validate
# --------------------------------------------------------------------------------------


@dataclass
class ShadingRequest:
    """The validated arguments of one :func:`torchbrdf.shade` / :func:`torchbrdf.plan` call."""

    gbuf: GBuffer
    lights: list[Light]
    brdf: BRDF
    kind: str  # brdf_kind(brdf): "principled", "lambert" or "custom"
    env_strategy: str
    env_samples: int
    env_sampling: str
    seed: int | None
    chunk: int | None
    prune: bool


def _default_brdf():
    from torchbrdf.brdf.principled import principled

    return principled


def brdf_name(brdf: BRDF) -> str:
    """A BRDF's name for messages and plans: the module's class or the function's name."""
    if isinstance(brdf, nn.Module):
        return type(brdf).__name__
    return getattr(brdf, "__name__", type(brdf).__name__)


@constant_while_tracing
def _material_names(fn) -> frozenset[str] | None:
    """The keyword parameters ``fn`` takes besides the geometry; None when it takes ``**kwargs``
    or its signature cannot be read.

    Run once while tracing (:func:`~torchbrdf._checks.constant_while_tracing`). Traced,
    ``inspect.signature`` would make Dynamo track the BRDF's defaults, and under
    ``dynamic=True`` hand its float defaults to the BRDF as float64 tensors.
    """
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return None
    if any(p.kind == p.VAR_KEYWORD for p in params):
        return None
    geometry = {"self", "l", "v", "n", "x", "y"}  # passed positionally: never a material key
    return frozenset(p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)) - geometry



def _check_material_fits(brdf, material: Mapping) -> None:
    """Refuse a material whose keys ``brdf`` does not take (they are passed as keywords).

    A BRDF whose signature cannot be read, or that takes ``**kwargs``, is not checked.
    """
    fn = type(brdf).forward if isinstance(brdf, nn.Module) else brdf
    if torch.compiler.is_compiling() and not isinstance(fn, types.FunctionType):
        return  # Dynamo runs the marked function on plain functions only; the call itself checks
    names = _material_names(fn)
    if names is None:
        return
    unknown = sorted(set(material) - names)
    if unknown:
        takes = sorted(names)
        raise ValueError(
            f"shade: the g-buffer's material has {unknown}, which brdf={brdf_name(brdf)} does not take; "
            f"its material parameters are {takes}"
        )


def _as_light_list(lights) -> list[Light]:
    if lights is None:
        return []
    if isinstance(lights, Light):
        return [lights]
    if isinstance(lights, (list, tuple)):
        out = list(lights)
    else:
        raise TypeError(f"shade: `lights` must be a light or a list of lights, got {type(lights).__name__}")
    for i, light in enumerate(out):
        if not isinstance(light, (PointLight, DirectionalLight, EnvironmentLight)):
            raise TypeError(
                f"shade: lights[{i}] must be a PointLight, DirectionalLight or EnvironmentLight, "
                f"got {type(light).__name__}"
            )
    return out


def _check_input_values(gbuf: GBuffer, lights: list) -> None:
    """Under validation: NaN/inf in a shaded pixel's g-buffer data or in a light, or a negative
    light intensity, irradiance or radiance, raises, naming it. Pixels outside the mask are not
    shaded, so they may hold anything."""
    keep = gbuf.mask
    if keep is not None and keep.dtype != torch.bool:
        keep = keep != 0

    def inside(t):
        if keep is None or not isinstance(t, Tensor) or t.dim() != 4:
            return t
        return torch.where(keep, t, torch.zeros((), dtype=t.dtype, device=t.device))

    named = {
        "gbuf.position": inside(gbuf.position),
        "gbuf.normal": inside(gbuf.normal),
        "gbuf.tangent": inside(gbuf.tangent),
        "gbuf.camera_position": gbuf.camera_position,
        **{f"gbuf.material[{k!r}]": inside(v) for k, v in gbuf.material.items()},
    }
    for i, light in enumerate(lights):
        for attr in ("position", "intensity", "direction", "irradiance", "radiance"):
            t = getattr(light, attr, None)
            if isinstance(t, Tensor):
                named[f"lights[{i}].{attr}"] = t
    check_finite(named)
    for name, t in named.items():  # a negative emitter gives negative radiance: no physical light
        if name.startswith("lights[") and name.rsplit(".", 1)[1] in ("intensity", "irradiance", "radiance"):
            check_nonnegative(name, t)


def _is_count(value: object, minimum: int = 1) -> bool:
    return not isinstance(value, bool) and isinstance(value, numbers.Integral) and int(value) >= minimum


def _refuse_vmap(gbuf: GBuffer, lights: list[Light]) -> None:
    """Refuse a g-buffer or light batched by ``torch.func.vmap``: the shader selects pixels and
    prunes the material by their values, which vmap cannot carry (its own error names ``.item()``).
    ``jacfwd`` (a vmap over the tangents only) passes. A vmap below another transform
    (``vmap(grad(f))``, per-sample gradients) is found under that transform's wrapper."""
    from torch._C._functorch import get_unwrapped, is_batchedtensor, is_functorch_wrapped_tensor

    def batched(t: Tensor) -> bool:
        while not is_batchedtensor(t):
            # (Dynamo cannot trace the unwrapping; compiled, the outer wrapper alone is looked at.)
            if torch.compiler.is_compiling() or not is_functorch_wrapped_tensor(t):
                return False
            t = get_unwrapped(t)
        return True

    tensors = [("gbuf.position", gbuf.position), ("gbuf.normal", gbuf.normal),
               ("gbuf.camera_position", gbuf.camera_position), ("gbuf.tangent", gbuf.tangent),
               ("gbuf.mask", gbuf.mask), *((f"gbuf.material[{k!r}]", v) for k, v in gbuf.material.items())]
    for i, light in enumerate(lights):
        tensors += [(f"lights[{i}].{k}", t) for k, t in (*light.named_parameters(), *light.named_buffers())]
    for name, t in tensors:
        if isinstance(t, Tensor) and batched(t):
            raise ValueError(
                f"shade: {name} is batched by torch.func.vmap, which shade does not support (it selects "
                "pixels by their values); stack the images along the g-buffer's batch dimension B instead"
            )


def validate(
    gbuf: GBuffer,
    lights: Light | Sequence[Light] | None,
    brdf: BRDF | None,
    env_strategy: str,
    env_samples: int,
    seed: int | None,
    chunk: int | None,
    prune: bool,
    env_sampling: str,
) -> ShadingRequest:
    """Check the arguments of :func:`torchbrdf.shade`; raise naming the offending one.

    Returns:
        A :class:`ShadingRequest` with the lights as a list and ``brdf`` defaulted.
    """
    if not isinstance(gbuf, GBuffer):
        raise TypeError(f"shade: `gbuf` must be a torchbrdf.GBuffer, got {type(gbuf).__name__}")
    lights = _as_light_list(lights)
    _refuse_vmap(gbuf, lights)
    if env_strategy not in ENV_STRATEGIES:
        raise ValueError(f"shade: `env_strategy` must be one of {ENV_STRATEGIES}, got {env_strategy!r}")
    if not _is_count(env_samples):
        raise ValueError(f"shade: `env_samples` must be a positive int, got {env_samples!r}")
    check_env_sampling(env_sampling, "shade", "env_sampling")
    if chunk is not None and not _is_count(chunk):
        raise ValueError(f"shade: `chunk` must be None or a positive int (pixels per pass), got {chunk!r}")
    brdf = _default_brdf() if brdf is None else brdf
    if not callable(brdf):
        raise TypeError(
            f"shade: `brdf` must be callable with the principled signature, got {type(brdf).__name__}"
        )
    _check_material_fits(brdf, gbuf.material)
    b = gbuf.batch_size
    for i, light in enumerate(lights):
        lb = light.batch_size
        if lb is not None and lb not in (1, b):
            raise ValueError(
                f"shade: lights[{i}] ({type(light).__name__}) has per-batch parameters for {lb} images, "
                f"but the g-buffer holds {b}"
            )
    if validation_enabled():
        _check_input_values(gbuf, lights)
    kind = brdf_kind(brdf)
    has_env = any(isinstance(x, EnvironmentLight) for x in lights)
    if env_strategy == "split_sum" and kind == "custom" and has_env:
        raise ValueError(
            "shade: env_strategy='split_sum' supports the principled and Lambert BRDFs, "
            f"not {brdf_name(brdf)}; use 'mc'"
        )
    if has_env and gbuf.device.type == "meta":
        raise ValueError(
            "shade: environment lights on the meta device: their set-up reads the map's values; "
            "point and directional lights shade meta g-buffers (shapes and dtypes only)"
        )
    return ShadingRequest(
        gbuf, lights, brdf, kind, env_strategy, env_samples, env_sampling, seed, chunk, prune
    )


# --------------------------------------------------------------------------------------
# 2. Select pixels
# --------------------------------------------------------------------------------------


class PixelSet:
    """The shaded pixel set: gathers ``(B, C, H, W)`` maps to ``(P, C)`` and scatters back.

    Args:
        select: ``(B, H, W)`` bool, the pixels to shade.
        all_selected: whether every pixel is selected, if known (else read from ``select``).
    """

    def __init__(self, select: Tensor, all_selected: bool | None = None):
        self.b, self.h, self.w = select.shape
        self.select = select
        self.all = bool(select.all()) if all_selected is None else all_selected
        if self.all:
            self.count = self.b * self.h * self.w
            self.flat = None
            self.batch_index = torch.arange(self.b, device=select.device).repeat_interleave(self.h * self.w)
        else:
            self.flat = select.reshape(-1).nonzero().squeeze(1)
            self.count = int(self.flat.numel())
            self.batch_index = torch.div(self.flat, self.h * self.w, rounding_mode="floor")

    def gather(self, t: Tensor) -> Tensor:
        """``(B or 1, C, H, W)`` -> ``(P, C)`` over the set."""
        c = t.shape[1]
        t = t.expand(self.b, c, self.h, self.w).permute(0, 2, 3, 1)
        if self.all:
            return t.reshape(-1, c)
        return t[self.select]

    def gather_cl(self, t: Tensor) -> Tensor:
        """Gather a channel-last ``(B*H*W, C)`` tensor."""
        return t if self.all else t[self.flat]

    def scatter(self, vals: Tensor) -> Tensor:
        """``(P, 3)`` -> ``(B, 3, H, W)`` with zeros outside the set."""
        if self.all:
            full = vals
        else:
            flat = self.flat
            assert flat is not None  # set whenever not all pixels are selected
            full = vals.new_zeros(self.b * self.h * self.w, vals.shape[-1]).index_copy(0, flat, vals)
        return full.reshape(self.b, self.h, self.w, -1).permute(0, 3, 1, 2)


@dataclass
class PixelSelection:
    """The pixels to shade, and the counts a :class:`~torchbrdf.render.shading.ShadingPlan` reports."""

    pixels: PixelSet
    active: Tensor  # (B, H, W) bool: covered by the mask and facing the camera
    data_prune: bool  # value-dependent pruning applies (never under torch.compile)
    position: Tensor  # (B, 3, H, W) positions in the compute dtype
    camera: Tensor  # (3,) or (B, 3) camera centre in the compute dtype
    n_masked: int  # -1: not counted (under torch.compile)
    n_back: int  # back-facing pixels inside the mask; -1 as above


def select_pixels(req: ShadingRequest, cd: torch.dtype) -> PixelSelection:
    """Step 2: the masked-in, camera-facing pixels (all pixels when not pruning)."""
    gbuf = req.gbuf
    b, h, w = gbuf.shape
    pos_img = gbuf.position.to(cd)
    cam = gbuf.camera_position.to(device=gbuf.device, dtype=cd)
    with torch.no_grad():
        c4 = cam.reshape(-1, 3, 1, 1)
        facing = (gbuf.normal.detach().to(cd) * (c4 - pos_img.detach())).sum(1) > 0  # (B, H, W)
        n_total = b * h * w
        # Compiled or on the meta device, no decision reads the data (a guard, or no data).
        data_free = torch.compiler.is_compiling() or gbuf.device.type == "meta"
        data_prune = req.prune and not data_free
        counted = not data_free
        if gbuf.mask is None:  # (few whole-image ops: each costs a thread wake-up on a loaded machine)
            active = facing
            n_masked = 0
            n_facing = int(facing.sum()) if counted else -1
            n_back = n_total - n_facing if counted else -1
        else:
            covered = (gbuf.mask[:, 0] > 0).expand(b, h, w)
            active = facing & covered
            n_masked = int((~covered).sum()) if counted else -1
            n_facing = int(active.sum()) if counted else -1
            n_back = int((covered & ~facing).sum()) if counted else -1
    select = active if data_prune else torch.ones_like(active)
    pixels = PixelSet(select, (n_facing == n_total) if data_prune else True)
    return PixelSelection(pixels, active, data_prune, pos_img, cam, n_masked, n_back)


# --------------------------------------------------------------------------------------
# 3. Inspect the material
# --------------------------------------------------------------------------------------


@dataclass
class MaterialUse:
    """How each material entry reaches the BRDF, and what that leaves to evaluate.

    ``values[name]`` is a Python float, a 0-d tensor or a ``(B, C, H, W)`` map still to be
    gathered (compute dtype). ``reduction[name]`` names what was done to the entry:
    ``"constant"`` (a Python float), ``"zeros"`` (all zeros -> ``0.0``), ``"scalar"`` (0-d
    tensor -> float), ``"uniform"`` (uniform one-channel map -> float) or ``"kept"``.
    """

    values: dict[str, Any]
    reduction: dict[str, str]
    lobes: tuple[str, ...] | None  # None: decided by a custom BRDF
    pruned_lobes: tuple[str, ...]
    need_frame: bool  # tangent frames: anisotropic is not a Python 0


def _reduce_material(material: Mapping[str, Any], prune: bool, cd: torch.dtype, device: torch.device):
    values, reduction = {}, {}
    compiling = torch.compiler.is_compiling()
    # A map carrying a forward-mode tangent does not require grad: kept as a map, else its
    # tangent would be dropped with it (jvp / jacfwd of a uniform map would read 0).
    prune = prune and not forward_mode_active()
    for name, v in material.items():
        if isinstance(v, numbers.Real):
            # Compiled: a 0-d tensor (torch.full keeps the value symbolic, where as_tensor would
            # guard on it), so a new value is a new input rather than a new graph.
            values[name] = torch.full((), cast(float, v), dtype=cd, device=device) if compiling else float(v)
            reduction[name] = "constant"
            continue
        if prune and not v.requires_grad:
            vd = v.detach()
            if not bool(vd.any()):
                values[name], reduction[name] = 0.0, "zeros"
                continue
            if v.dim() == 0:
                values[name], reduction[name] = float(vd), "scalar"
                continue
            if v.shape[1] == 1 and bool(vd.amin() == vd.amax()):
                values[name], reduction[name] = float(vd.reshape(-1)[0]), "uniform"
                continue
        values[name], reduction[name] = v.to(cd), "kept"
    return values, reduction


def _lobes_for(brdf, kind: str, values: dict):
    if kind == "lambert":
        return ("diffuse",), ()
    if kind == "principled":
        from torchbrdf.brdf.principled import active_lobes

        wanted = getattr(brdf, "lobes", None)
        act = active_lobes(values, wanted)
        return act, tuple(lobe for lobe in LOBES if lobe not in act)
    return None, ()


def inspect_material(req: ShadingRequest, data_prune: bool, cd: torch.dtype) -> MaterialUse:
    """Step 3: reduce the material (when pruning) and decide the lobes and frames."""
    values, reduction = _reduce_material(req.gbuf.material, data_prune, cd, req.gbuf.device)
    lobes, pruned = _lobes_for(req.brdf, req.kind, values)
    need_frame = not is_zero(values.get("anisotropic", 0.0))
    return MaterialUse(values, reduction, lobes, pruned, need_frame)


# --------------------------------------------------------------------------------------
# 4. Schedule
# --------------------------------------------------------------------------------------


@dataclass
class ShadingSchedule:
    """Everything the passes need: the prepared steps, the lights by kind and the work split."""

    req: ShadingRequest
    cd: torch.dtype  # compute dtype
    sel: PixelSelection
    mat: MaterialUse
    points: list[PointLight]
    dirs: list[DirectionalLight]
    envs: list[EnvironmentLight]
    chunk_px: int  # pixels per pass
    fused: bool  # point and directional lights through the fused kernel
    loop_brdf: tuple[str, dict[str, float]] | None  # its BRDF family and fixed floats (light_loop_brdf)
    mc_setups: list[MCSetup]  # one per environment light under env_strategy="mc"

    @property
    def normal_in_kernel(self) -> bool:
        """The fused kernel normalises the normal (and computes ``v``) itself, unless the
        frames or the environment passes need them outside it."""
        return self.fused and not self.mat.need_frame and not self.envs


def _mc_setups(req: ShadingRequest, pixels: PixelSet, envs: list[EnvironmentLight], cd) -> list[MCSetup]:
    dev = req.gbuf.device
    b, h, w = req.gbuf.shape
    g = torch.Generator(device=dev)
    g.manual_seed(int(req.seed) if req.seed is not None else int(torch.randint(0, 2**62, (1,)).item()))
    setups = []
    for light in envs:
        # Pixel-major, so a pixel's pattern depends only on its index (not on B or masks).
        shifts = torch.rand((b * h * w, 2, 2), generator=g, dtype=cd, device=dev)
        setups.append(
            MCSetup(
                light.radiance.to(device=dev),
                int(req.env_samples),
                pixels.gather_cl(shifts[:, 0]),
                pixels.gather_cl(shifts[:, 1]),
                req.env_sampling,
            )
        )
    return setups


def schedule(req: ShadingRequest, cd: torch.dtype, sel: PixelSelection, mat: MaterialUse) -> ShadingSchedule:
    """Step 4: split the lights by kind and decide how the passes run."""
    lights = req.lights
    points = [x for x in lights if isinstance(x, PointLight)]
    dirs = [x for x in lights if isinstance(x, DirectionalLight)]
    envs = [x for x in lights if isinstance(x, EnvironmentLight)]
    p_count = sel.pixels.count
    chunk_px = p_count if req.chunk is None else min(int(req.chunk), max(p_count, 1))
    mc_setups = _mc_setups(req, sel.pixels, envs, cd) if envs and req.env_strategy == "mc" else []
    loop_brdf = light_loop_brdf(req.brdf, req.kind)
    fused = fused_lights_wanted(
        req.gbuf, loop_brdf[0] if loop_brdf else None, mat.values, points, dirs, sel.camera, req.gbuf.device,
        cd, p_count * (len(points) + len(dirs)),
    )
    return ShadingSchedule(req, cd, sel, mat, points, dirs, envs, chunk_px, fused, loop_brdf, mc_setups)
