"""Differentiable screen-space shading of g-buffers: :func:`shade`, :func:`plan`, :class:`Shader`.

``shade(gbuf, lights)`` turns a :class:`~torchbrdf.GBuffer` into linear radiance
``(B, 3, H, W)`` under any mix of point, directional and environment lights, with
the formulas of :mod:`torchbrdf.render.lights`. It evaluates any BRDF callable with the principled signature
``brdf(l, v, n, x, y, **material)`` (default :func:`torchbrdf.principled`).

How it works, in order:

1. **Inspect once** (:func:`plan` shows the result). Pixels that are masked out or face away
   from the camera (``n·v <= 0``, where every BRDF of the library is 0) are dropped. Each
   material map that does not require grad is reduced: all zeros -> the Python float
   ``0.0`` (the BRDF then skips the lobe it weights), uniform single-channel map -> a float.
   Tangent frames are built only when ``anisotropic`` is not a Python 0; environment
   integration runs only when an :class:`~torchbrdf.EnvironmentLight` is present. The result
   equals full evaluation (``prune=False``) to float rounding.
2. **Convert once** from ``(B, C, H, W)`` to flat channel-last ``(P, C)`` over the shaded
   pixels, call the BRDF on those, and scatter back.
3. **Accumulate per light** (per environment-sample pass, per pixel chunk), each pass
   wrapped in ``torch.utils.checkpoint`` (non-reentrant): its intermediates are dropped after
   the forward pass and recomputed during backward, so forward+backward peak memory is that of
   one pass, whatever the number of lights (measured in ``docs/shading.md``).
   With the principled BRDF (the C kernels on CPU, Triton on CUDA), all point and directional
   lights instead go through ONE fused kernel per chunk, forward and recompute-backward (the
   ``torchbrdf::shade_lights_fwd`` operator), generated from the same per-light formula the
   eager passes run (:func:`torchbrdf.brdf.formula.point_light`, ``directional_light``);
   gradients w.r.t. light parameters or the camera keep the eager passes.

Gradients reach every tensor input: material maps, normals, positions, camera position,
tangents, light positions/directions/intensities and environment maps. Masked and
back-facing pixels are exactly 0 with zero (finite) gradients.
"""

from __future__ import annotations

import inspect
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from torchbrdf import _checks
from torchbrdf._types import BRDF
from torchbrdf._checks import check_finite, validation_enabled
from torchbrdf._math import cast_back, compute_dtype, safe_normalize
from torchbrdf.brdf import formula
from torchbrdf.render.envmap import (
    ENV_SAMPLINGS,
    PREFILTER_ROUGHNESS,
    SplitSumEnvironment,
    _as_bhwc,
    _mc_pass,
    _MCSetup,
    brdf_kind,
    check_env_sampling,
    integrate_environment_split_sum,
    sampling_lobes_for,
)
from torchbrdf.brdf.frames import frame_from_normal, gram_schmidt
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, Light, PointLight
from torchbrdf.brdf.principled import LOBES, PRINCIPLED_DEFAULTS

__all__ = ["shade", "plan", "Shader", "ShadingPlan", "ENV_STRATEGIES", "ENV_SAMPLINGS", "DEFAULT_ENV_SAMPLES"]

ENV_STRATEGIES = ("mc", "split_sum")
DEFAULT_ENV_SAMPLES = 64
# Environment samples are evaluated in passes of about this many (pixel, sample) pairs, so an
# environment pass costs about as much memory as one point light over 2^18 pixels.
ENV_ELEMENTS_PER_PASS = 1 << 18
# Squared distance floor for point lights (defined with the shading formula).
DIST2_EPS = formula.DIST2_EPS

# One source of truth for the principled lobes and defaults.
_LOBES = LOBES
_DEFAULTS = PRINCIPLED_DEFAULTS
# Rough relative cost of one BRDF evaluation per lobe (diffuse = 1), for plan()'s estimate.
_LOBE_COST = {"diffuse": 1.0, "subsurface": 0.6, "specular": 2.0, "sheen": 0.4, "clearcoat": 1.2}
# Bytes of live intermediates per (pixel, sample) element and per unit of lobe cost during
# the backward of one pass, float32 (measured on the principled BRDF; see docs/shading.md).
_BYTES_PER_ELEMENT_COST = 40


# --------------------------------------------------------------------------------------
# The plan
# --------------------------------------------------------------------------------------


@dataclass
class ShadingPlan:
    """What :func:`shade` will compute for a scene, and roughly what it costs.

    ``str(plan)`` prints a readable summary. Fields are plain Python values.
    """

    brdf: str
    brdf_kind: str
    image: tuple[int, int, int]
    dtype: str
    pixels_total: int
    pixels_shaded: int
    pixels_masked: int
    pixels_backfacing: int
    lobes: tuple[str, ...] | None
    pruned_lobes: tuple[str, ...]
    material: dict[str, str]
    frames: str
    lights: list[str]
    environment: str | None
    passes: int
    brdf_evaluations: int
    relative_cost: float
    estimated_peak_bytes: int
    pruning: bool = True
    notes: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        b, h, w = self.image
        lines = [f"ShadingPlan: {self.brdf} ({self.brdf_kind}) on {b}x{h}x{w} {self.dtype}"]
        lines.append(
            f"  pixels   : {self.pixels_shaded} shaded of {self.pixels_total}"
            f" ({self.pixels_masked} masked, {self.pixels_backfacing} back-facing skipped)"
        )
        if self.lobes is None:
            lines.append("  lobes    : decided by the BRDF (custom callable)")
        else:
            lines.append(f"  lobes    : {', '.join(self.lobes) or 'none'}")
            if self.pruned_lobes:
                lines.append(f"  pruned   : {', '.join(self.pruned_lobes)}")
        lines.append(f"  frames   : {self.frames}")
        lines.append("  material :")
        for k, d in self.material.items():
            lines.append(f"    {k:16s} {d}")
        lines.append("  lights   :" + ("" if self.lights else " none"))
        for d in self.lights:
            lines.append(f"    {d}")
        if self.environment:
            lines.append(f"  env      : {self.environment}")
        lines.append(
            f"  cost     : {self.brdf_evaluations:,} BRDF evaluations in {self.passes} recomputed pass(es),"
            f" ~{self.relative_cost:.3g} diffuse-lobe units;"
            f" est. peak working set ~{self.estimated_peak_bytes / 2**20:.0f} MiB (forward+backward)"
        )
        for note in self.notes:
            lines.append(f"  note     : {note}")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------
# Preparation
# --------------------------------------------------------------------------------------


def _default_brdf():
    from torchbrdf.brdf.principled import principled

    return principled


def _brdf_name(brdf) -> str:
    if isinstance(brdf, nn.Module):
        return type(brdf).__name__
    return getattr(brdf, "__name__", type(brdf).__name__)


def _check_material_fits(brdf, material: Mapping) -> None:
    """Refuse a material whose keys ``brdf`` does not take (they are passed as keywords).

    A BRDF whose signature cannot be read, or that takes ``**kwargs``, is not checked.
    """
    fn = brdf.forward if isinstance(brdf, nn.Module) else brdf
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return
    if any(p.kind == p.VAR_KEYWORD for p in params):
        return
    geometry = {"l", "v", "n", "x", "y"}  # passed positionally: never a material key
    names = {p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)} - geometry
    unknown = sorted(set(material) - names)
    if unknown:
        takes = sorted(names)
        raise ValueError(
            f"shade: the g-buffer's material has {unknown}, which brdf={_brdf_name(brdf)} does not take; "
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


def _is_zero(p) -> bool:
    return isinstance(p, numbers.Real) and float(p) == 0.0


class _Pixels:
    """The shaded pixel set: gathers ``(B, C, H, W)`` maps to ``(P, C)`` and scatters back."""

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
class _Prepared:
    plan: ShadingPlan
    run: Callable[[], Tensor]


def _describe_value(v) -> str:
    if isinstance(v, Tensor):
        grad = ", requires grad" if v.requires_grad else ""
        return f"map {list(v.shape)}{grad}" if v.dim() else f"0-d tensor{grad}"
    return f"constant {v:g}"


def _inspect_material(material: Mapping[str, Any], prune: bool, cd: torch.dtype):
    """Decide, per material entry, how it reaches the BRDF. Returns (values, descriptions).

    ``values[name]`` is a Python float, a 0-d tensor (compute dtype) or a ``(B, C, H, W)``
    map still to be gathered.
    """
    values, desc = {}, {}
    for name, v in material.items():
        if isinstance(v, numbers.Real):
            values[name] = float(v)
            desc[name] = f"constant {float(v):g}"
            continue
        if prune and not v.requires_grad:
            vd = v.detach()
            if not bool(vd.any()):
                values[name] = 0.0
                desc[name] = f"all zeros, no grad -> Python 0.0 ({'0-d' if v.dim() == 0 else list(v.shape)})"
                continue
            if v.dim() == 0:
                values[name] = float(vd)
                desc[name] = f"0-d tensor, no grad -> constant {float(vd):g}"
                continue
            if v.shape[1] == 1 and bool(vd.amin() == vd.amax()):
                values[name] = float(vd.reshape(-1)[0])
                desc[name] = f"uniform map {list(v.shape)}, no grad -> constant {values[name]:g}"
                continue
        values[name] = v.to(cd)
        desc[name] = _describe_value(v)
    return values, desc


def _lobes_for(brdf, kind: str, values: dict):
    if kind == "lambert":
        return ("diffuse",), ()
    if kind == "principled":
        from torchbrdf.brdf.principled import active_lobes

        wanted = getattr(brdf, "lobes", None)
        act = active_lobes(values, wanted)
        return act, tuple(lobe for lobe in _LOBES if lobe not in act)
    return None, ()


def _check_finite_inputs(gbuf: GBuffer, lights: list) -> None:
    """Under validation: NaN/inf in a shaded pixel's g-buffer data or in a light raises,
    naming it. Pixels outside the mask are not shaded, so they may hold anything."""
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


def _fused_lights_wanted(gbuf, kind, values, points, dirs, cam, dev, cd, elements: int) -> bool:
    """Whether the point and directional lights go through the fused shading kernel.

    The principled BRDF, inputs the kernel reads (4-D maps or constants), no gradient wanted
    w.r.t. lights or camera (those stay on the eager shader), and the fused kernels' dispatch
    rule (``principled._fused_backend``, on ``elements`` pixel-lights) picking the C or the
    Triton kernels (the shading kernel is printed in both).
    """
    if kind != "principled" or not (points or dirs):
        return False
    if "base_color" not in values or set(values) - set(_DEFAULTS) - {"base_color"}:
        return False  # the eager call raises the error naming the argument
    from torchbrdf.brdf import principled as _pr

    tensors = []
    for k, t in [("position", gbuf.position), ("normal", gbuf.normal), *values.items()]:
        if not isinstance(t, Tensor):
            continue
        if not torch.compiler.is_compiling() and torch._C._functorch.is_functorch_wrapped_tensor(t):
            return False  # the shade ops have no vmap/jvp rule: torch.func goes eager
        channels = {"position": (3,), "normal": (3,), "base_color": (1, 3)}.get(k, (1,))
        if not (t.dim() == 0 or (t.dim() == 4 and t.shape[1] in channels)):
            return False
        tensors.append(t)
    if torch.is_grad_enabled():
        uniform = [cam] + [t for light in points + dirs for t in light._light_tensors()]
        if any(t.requires_grad for t in uniform):
            return False
    return _pr._fused_backend(dev, cd, tensors, lambda: elements) in ("c", "triton")


def _uniform_table(cam: Tensor, points, dirs, dev, cd) -> Tensor:
    """``(R, 3 + 6 L)``: camera, then ``(q, I)`` per point and ``(d, E)`` per directional light,
    one row per batch element (``R = 1`` when nothing is batched)."""
    parts = [cam.reshape(-1, 3)]
    for light in points:
        parts += [
            light.position.to(device=dev, dtype=cd).reshape(-1, 3),
            light.intensity.to(device=dev, dtype=cd).reshape(-1, 3),
        ]
    for light in dirs:
        parts += [
            light.direction.to(device=dev, dtype=cd).reshape(-1, 3),
            light.irradiance.to(device=dev, dtype=cd).reshape(-1, 3),
        ]
    rows = max(p.shape[0] for p in parts)
    return torch.cat([p.detach().expand(rows, 3) for p in parts], dim=1).contiguous()


def _fused_lights_term(
    table: Tensor, pos, n, x, y, mat, bidx, active, frame, normalize_n, n_point, n_dir
) -> Tensor:
    """All point and directional lights at ``(P, 3)`` points in one fused kernel pass
    (``normalize_n``: ``n`` is the raw normal, normalised in the kernel)."""
    from torchbrdf.brdf.principled import _need_tint
    from torchbrdf.kernels.shade_ops import shade_lights

    c = {**_DEFAULTS, **mat, "pos": pos, "n": n, "x": x, "y": y}
    if table.shape[0] == 1:
        seg = [0, pos.shape[0]]
    else:  # points are batch-major: one segment (uniform row) per image
        counts = torch.bincount(bidx, minlength=table.shape[0])
        seg = [0] + torch.cumsum(counts, 0).tolist()
    backend = "c" if pos.device.type == "cpu" and not _triton_interpreted() else "triton"
    return shade_lights(c, table, seg, active, _need_tint(c, active), frame, normalize_n, n_point, n_dir,
                        backend)


def _triton_interpreted() -> bool:
    """CPU tensors go to the Triton shading kernels when the backend resolves to Triton (its
    interpreter, ``TRITON_INTERPRET=1``: how the tests run them without a GPU)."""
    from torchbrdf.kernels import backend

    return backend.resolve(torch.device("cpu")) == "triton"


def _prepare(
    gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling="mis"
) -> _Prepared:
    if not isinstance(gbuf, GBuffer):
        raise TypeError(f"shade: `gbuf` must be a torchbrdf.GBuffer, got {type(gbuf).__name__}")
    lights = _as_light_list(lights)
    if env_strategy not in ENV_STRATEGIES:
        raise ValueError(f"shade: `env_strategy` must be one of {ENV_STRATEGIES}, got {env_strategy!r}")
    if isinstance(env_samples, bool) or not isinstance(env_samples, numbers.Integral) or env_samples < 1:
        raise ValueError(f"shade: `env_samples` must be a positive int, got {env_samples!r}")
    check_env_sampling(env_sampling, "shade", "env_sampling")
    if chunk is not None and (
        isinstance(chunk, bool) or not isinstance(chunk, numbers.Integral) or chunk < 1
    ):
        raise ValueError(f"shade: `chunk` must be None or a positive int (pixels per pass), got {chunk!r}")
    brdf = _default_brdf() if brdf is None else brdf
    if not callable(brdf):
        raise TypeError(
            f"shade: `brdf` must be callable with the principled signature, got {type(brdf).__name__}"
        )
    _check_material_fits(brdf, gbuf.material)
    b, h, w = gbuf.shape
    for i, light in enumerate(lights):
        lb = light.batch_size
        if lb is not None and lb not in (1, b):
            raise ValueError(
                f"shade: lights[{i}] ({type(light).__name__}) has per-batch parameters for {lb} images, "
                f"but the g-buffer holds {b}"
            )
    if validation_enabled():
        _check_finite_inputs(gbuf, lights)
    dt = gbuf.dtype
    cd = compute_dtype(dt)
    dev = gbuf.device
    kind = brdf_kind(brdf)
    if (
        env_strategy == "split_sum"
        and kind == "custom"
        and any(isinstance(x, EnvironmentLight) for x in lights)
    ):
        raise ValueError(
            "shade: env_strategy='split_sum' supports the principled and Lambert BRDFs, "
            f"not {_brdf_name(brdf)}; use 'mc'"
        )

    # ---- which pixels
    pos_img = gbuf.position.to(cd)
    cam = gbuf.camera_position.to(device=dev, dtype=cd)
    with torch.no_grad():
        c4 = cam.reshape(-1, 3, 1, 1)
        facing = (gbuf.normal.detach().to(cd) * (c4 - pos_img.detach())).sum(1) > 0  # (B, H, W)
        n_total = b * h * w
        # Under torch.compile the value-dependent decisions (which pixels, which maps are
        # constant) would each be a graph break and a guard on the data, i.e. a recompile per
        # new input: there every pixel and map is evaluated (as with prune=False).
        compiling = torch.compiler.is_compiling()
        data_prune = prune and not compiling
        counted = not compiling  # -1: not counted under torch.compile
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
    pixels = _Pixels(select, (n_facing == n_total) if data_prune else True)
    p_count = pixels.count

    # ---- material, lobes, frames
    values, mdesc = _inspect_material(gbuf.material, data_prune, cd)
    lobes, pruned = _lobes_for(brdf, kind, values)
    aniso = values.get("anisotropic", 0.0)
    need_frame = not _is_zero(aniso)
    if not need_frame:
        frames = "none (isotropic: anisotropic is a Python 0)"
    elif gbuf.tangent is not None:
        frames = "Gram–Schmidt from the tangent map"
    else:
        frames = "built from the normal (Duff et al. 2017)"
    for k, d in _DEFAULTS.items():
        if k not in mdesc and (kind == "principled"):
            mdesc[k] = f"default {d:g}"

    # ---- lights
    points = [x for x in lights if isinstance(x, PointLight)]
    dirs = [x for x in lights if isinstance(x, DirectionalLight)]
    envs = [x for x in lights if isinstance(x, EnvironmentLight)]
    light_desc = []
    for i, light in enumerate(lights):
        batched = "per-batch" if light.batch_size not in (None, 1) else "shared"
        if isinstance(light, PointLight):
            light_desc.append(
                f"[{i}] point light ({batched}): f·I·max(n·l,0)/|q-P|², 1 BRDF evaluation per pixel"
            )
        elif isinstance(light, DirectionalLight):
            light_desc.append(
                f"[{i}] directional light ({batched}): f·E·max(n·l,0), 1 BRDF evaluation per pixel"
            )
        else:
            light_desc.append(f"[{i}] environment {list(light.radiance.shape)} ({batched}): {env_strategy}")
    chunk_px = p_count if chunk is None else min(int(chunk), max(p_count, 1))
    n_slices = 0 if p_count == 0 else math.ceil(p_count / max(chunk_px, 1))

    # ---- environment budgets
    env_desc = None
    env_evals = 0
    env_passes = 0
    mc_setups = []
    if envs and env_strategy == "mc":
        g = torch.Generator(device=dev)
        g.manual_seed(int(seed) if seed is not None else int(torch.randint(0, 2**62, (1,)).item()))
        slobes = sampling_lobes_for(brdf, values)
        samp_names = [k for k in ("diffuse", "specular", "clearcoat") if k in slobes]
        names = {"diffuse": "cosine", "specular": "GGX visible normals", "clearcoat": "GTR1"}
        parts = []
        for light in envs:
            # Pixel-major, so a pixel's pattern depends only on its index (not on B or masks).
            shifts = torch.rand((n_total, 2, 2), generator=g, dtype=cd, device=dev)
            setup = _MCSetup(
                light.radiance.to(device=dev),
                int(env_samples),
                pixels.gather_cl(shifts[:, 0]),
                pixels.gather_cl(shifts[:, 1]),
                env_sampling,
            )
            mc_setups.append(setup)
            per_pass = max(1, ENV_ELEMENTS_PER_PASS // max(chunk_px, 1))
            for _, total, _ in setup.techniques():
                env_passes += n_slices * math.ceil(total / min(per_pass, total))
            env_evals += p_count * int(env_samples)
            proposal = " + ".join(names[k] for k in samp_names)
            if env_sampling == "mis":
                parts.append(
                    f"{setup.n_brdf} BRDF-sampled ({proposal})"
                    + (
                        f" + {setup.n_map} map-sampled, power-heuristic MIS"
                        if setup.n_map
                        else " (constant map: no map sampling)"
                    )
                )
            elif env_sampling == "brdf":
                parts.append(f"{setup.n_brdf} BRDF-sampled ({proposal}; no map sampling)")
            elif env_sampling == "map":
                parts.append(f"{setup.n_map} map-sampled (luminance × solid angle; no BRDF sampling)")
            else:
                parts.append(f"{setup.n_uniform} uniform-hemisphere (no importance sampling)")
        env_desc = "Monte Carlo, env_sampling=%r, stratified (rotated Hammersley), seed %s: %s per pixel" % (
            env_sampling,
            seed,
            "; ".join(parts),
        )
    elif envs:
        env_desc = (
            f"split sum: irradiance map + {len(PREFILTER_ROUGHNESS)} GGX-prefiltered levels"
            " + (n·v, roughness) table;"
            " no BRDF evaluations"
        )
        env_passes = n_slices * len(envs)

    brdf_evals = p_count * (len(points) + len(dirs)) + env_evals
    lobe_cost = sum(_LOBE_COST[x] for x in lobes) if lobes is not None else 4.0
    fused = _fused_lights_wanted(
        gbuf, kind, values, points, dirs, cam, dev, cd, p_count * (len(points) + len(dirs))
    )
    # Fused: all point and directional lights in one kernel pass per chunk.
    passes = n_slices * (min(1, len(points) + len(dirs)) if fused else len(points) + len(dirs)) + env_passes
    elements_per_pass = (
        chunk_px
        if not (envs and env_strategy == "mc")
        else max(chunk_px, min(ENV_ELEMENTS_PER_PASS, chunk_px * int(env_samples)))
    )
    itemsize = torch.finfo(cd).bits // 8
    est = int(elements_per_pass * lobe_cost * _BYTES_PER_ELEMENT_COST * itemsize / 4)
    est += int(p_count * itemsize * 3 * (4 + len([v for v in values.values() if isinstance(v, Tensor)])))
    notes = []
    if fused:
        notes.append(
            f"point/directional lights: fused kernel, the {len(points) + len(dirs)} light(s) looped inside"
            " one pass (forward and recompute-backward)"
        )
    if not prune:
        notes.append("pruning disabled (prune=False): every pixel and every material map is evaluated")
    the_plan = ShadingPlan(
        brdf=_brdf_name(brdf),
        brdf_kind=kind,
        image=(b, h, w),
        dtype=str(dt).replace("torch.", ""),
        pixels_total=n_total,
        pixels_shaded=p_count,
        pixels_masked=n_masked,
        pixels_backfacing=n_back,
        lobes=lobes,
        pruned_lobes=pruned,
        material=mdesc,
        frames=frames,
        lights=light_desc,
        environment=env_desc,
        passes=passes,
        brdf_evaluations=brdf_evals,
        relative_cost=brdf_evals * lobe_cost,
        estimated_peak_bytes=est,
        pruning=prune,
        notes=notes,
    )

    def run() -> Tensor:
        out_dtype = dt
        if p_count == 0:
            zero = pos_img.new_zeros(b, 3, h, w)
            # Keep the graph connected so backward() works and yields zero gradients.
            return cast_back(zero + 0.0 * pos_img.sum(), out_dtype)
        # Boundary conversion: (B, C, H, W) -> (P, C), once.
        pos = pixels.gather(pos_img)
        n = pixels.gather(gbuf.normal.to(cd))
        # The fused kernel normalises the normal and computes v itself (the same formula) unless
        # the frames or the environment passes need them here.
        n_in_kernel = fused and not need_frame and not envs
        if not n_in_kernel:
            n = safe_normalize(n)
        bidx = pixels.batch_index
        v = None
        if not (fused and not envs):
            cam_p = cam[bidx] if cam.dim() == 2 and cam.shape[0] > 1 else cam.reshape(1, 3)
            v = formula.view_direction(formula.TorchOps(cd, dev), cam_p, pos)
        x = y = None
        if need_frame:
            if gbuf.tangent is not None:
                x, y = gram_schmidt(n, pixels.gather(gbuf.tangent.to(cd)))
            else:
                x, y = frame_from_normal(n)
        mat = {
            k: (pixels.gather(val) if isinstance(val, Tensor) and val.dim() == 4 else val)
            for k, val in values.items()
        }
        table = _uniform_table(cam, points, dirs, dev, cd) if fused else None
        if fused and _checks.validation_enabled():
            _checks.check_finite({k: val for k, val in mat.items() if isinstance(val, Tensor)})
        light_params = []  # per-light eager passes (the fused kernel takes them all at once)
        for pl in [] if fused else points:
            light_params.append(
                ("point", pl.position.to(device=dev, dtype=cd), pl.intensity.to(device=dev, dtype=cd))
            )
        for dl in [] if fused else dirs:
            light_params.append(
                ("dir", dl.direction.to(device=dev, dtype=cd), dl.irradiance.to(device=dev, dtype=cd))
            )
        # (kind, radiance (*, H, W, 3) or split-sum tables, batch size, MC setup or None)
        env_inputs: list[tuple[str, Any, int, _MCSetup | None]] = []
        for i, env in enumerate(envs):
            rad = env.radiance.to(device=dev, dtype=cd)
            env_b = rad.shape[0] if rad.dim() == 4 else 1
            if env_strategy == "mc":
                env_inputs.append(("mc", _as_bhwc(rad).contiguous(), env_b, mc_setups[i]))
            else:
                env_inputs.append(("split_sum", _split_sum_env(env, rad, cd), env_b, None))

        pieces = []
        for s in range(0, p_count, chunk_px):
            e = min(s + chunk_px, p_count)

            def sl(t, s=s, e=e):
                # (one chunk: no slicing, whose backward would allocate and copy full-size gradients)
                return (
                    t[s:e]
                    if isinstance(t, Tensor)
                    and t.dim() >= 1
                    and t.shape[0] == p_count
                    and p_count > 1
                    and (s, e) != (0, p_count)
                    else t
                )

            pos_s, n_s, v_s, bidx_s = sl(pos), sl(n), sl(v), sl(bidx)
            x_s, y_s = (sl(x), sl(y)) if need_frame else (None, None)
            mat_s = {
                k: (sl(val) if isinstance(val, Tensor) and val.dim() == 2 else val) for k, val in mat.items()
            }
            # One accumulator per chunk, updated in place: a fresh sum per light would land on
            # top of the heap each time and fragment it (freed pages stay resident).
            if table is not None:  # fused (the kernel's output is a fresh buffer: accumulate into it)
                acc = _fused_lights_term(
                    table,
                    pos_s,
                    n_s,
                    x_s,
                    y_s,
                    mat_s,
                    bidx_s,
                    lobes,
                    need_frame,
                    n_in_kernel,
                    len(points),
                    len(dirs),
                )
            else:
                acc = pos_s.new_zeros(e - s, 3)
            for kind_l, p1, p2 in light_params:
                fn = _point_term if kind_l == "point" else _directional_term
                term = _pass(e - s, fn, brdf, pos_s, n_s, v_s, x_s, y_s, mat_s, p1, p2, bidx_s)
                acc.add_(term)
            for kind_e, env_data, env_b, setup in env_inputs:
                eb = bidx_s if env_b > 1 else None
                if kind_e == "mc":
                    assert setup is not None  # every "mc" entry carries its setup
                    per_pass = max(1, ENV_ELEMENTS_PER_PASS // max(e - s, 1))
                    slobes = sampling_lobes_for(brdf, mat_s)
                    for technique, total, shift in setup.techniques():
                        k = min(per_pass, max(total, 1))
                        for start in range(0, total, k):
                            count = min(k, total - start)
                            term = _pass(
                                (e - s) * count,
                                _mc_pass,
                                brdf,
                                slobes,
                                n_s,
                                v_s,
                                x_s,
                                y_s,
                                mat_s,
                                env_data,
                                eb,
                                setup,
                                technique,
                                start,
                                count,
                                sl(shift),
                            )
                            acc.add_(term)
                else:
                    term = _pass(
                        e - s,
                        integrate_environment_split_sum,
                        brdf,
                        n_s,
                        v_s,
                        env_data,
                        mat_s,
                        x=x_s,
                        y=y_s,
                        batch_index=eb,
                    )
                    acc.add_(term)
            if not acc.requires_grad and pos_s.requires_grad:
                acc = acc + 0.0 * pos_s  # no lights: keep the graph connected (zero gradients)
            pieces.append(acc)
        out = pieces[0] if len(pieces) == 1 else torch.cat(pieces, dim=0)
        img = pixels.scatter(out)
        if not data_prune:
            img = torch.where(active.unsqueeze(1), img, torch.zeros_like(img))
        if gbuf.mask is not None and gbuf.mask.is_floating_point():
            img = img * gbuf.mask.to(cd)
        return cast_back(img.contiguous(), out_dtype)

    return _Prepared(plan=the_plan, run=run)


def _split_sum_env(light: EnvironmentLight, rad: Tensor, cd) -> SplitSumEnvironment:
    """Prefilter a map for the split sum; cached on the light while the map has no grad."""
    src = light.radiance
    if src.requires_grad or rad.requires_grad:
        return SplitSumEnvironment(rad, cd)
    key = (src.data_ptr(), src._version, tuple(src.shape), cd, str(rad.device))
    cached = light._split_sum_cache
    if cached is not None and cached[0] == key:
        return cached[1]
    env = SplitSumEnvironment(rad, cd)
    light._split_sum_cache = (key, env)
    return env


def _load_malloc_trim():
    """Glibc's ``malloc_trim`` through ctypes, or ``None`` where it does not exist."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
        fn.argtypes = [ctypes.c_size_t]
        fn.restype = ctypes.c_int
        return fn
    except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows, musl)
        return None


_MALLOC_TRIM = _load_malloc_trim()
# Passes at least this large (elements) release freed heap pages before their backward.
TRIM_MIN_ELEMENTS = 1 << 16


class _ReleaseFreedMemory(torch.autograd.Function):
    """Identity whose backward first returns freed heap pages to the OS (glibc, CPU).

    glibc serves tensors below its (self-raising) mmap threshold from the heap, and the small
    long-lived autograd records of each pass land among the freed intermediates of the pass
    before, so freed pages stay resident and the next pass's large tensors go on top: the
    resident set would creep up pass after pass even though live memory does not (measured
    in docs/shading.md). ``malloc_trim`` returns those free pages.
    """

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        _MALLOC_TRIM(0)
        return grad


def _pass(elements: int, fn, *args, **kwargs):
    """Run one accumulation pass of ``elements`` BRDF evaluations.

    Under autograd the pass is checkpointed (non-reentrant): nothing inside it is stored, and
    it is recomputed during backward.
    """
    if not torch.is_grad_enabled():
        return fn(*args, **kwargs)
    out = checkpoint(fn, *args, use_reentrant=False, **kwargs)
    if (
        _MALLOC_TRIM is not None
        and out.requires_grad
        and out.device.type == "cpu"
        and elements >= TRIM_MIN_ELEMENTS
    ):
        # The small autograd records of this pass were allocated among the freed
        # intermediates; give the freed pages back now and again before its backward.
        _MALLOC_TRIM(0)
        out = _ReleaseFreedMemory.apply(out)
    return out


def _per_pixel(t: Tensor, bidx: Tensor) -> Tensor:
    """A ``(3,)`` / ``(1, 3)`` / ``(B, 3)`` light parameter broadcast to the shaded pixels."""
    if t.dim() == 2 and t.shape[0] > 1:
        return t[bidx]
    return t.reshape(1, 3)


def _point_term(brdf, pos, n, v, x, y, mat, q, intensity, bidx) -> Tensor:
    """``f(l, v) I max(n·l, 0) / |q - P|²`` at ``(P, 3)`` points (:func:`formula.point_light`)."""
    ops = formula.TorchOps(pos.dtype, pos.device)
    return formula.point_light(
        ops, pos, n, _per_pixel(q, bidx), _per_pixel(intensity, bidx), lambda l: brdf(l, v, n, x, y, **mat)
    )


def _directional_term(brdf, pos, n, v, x, y, mat, direction, irradiance, bidx) -> Tensor:
    """``f(d, v) E max(n·d, 0)`` at ``(P, 3)`` points (:func:`formula.directional_light`)."""
    ops = formula.TorchOps(n.dtype, n.device)
    return formula.directional_light(
        ops,
        n,
        _per_pixel(direction, bidx),
        _per_pixel(irradiance, bidx),
        lambda l: brdf(l.expand_as(n), v, n, x, y, **mat),
    )


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


def shade(
    gbuf: GBuffer,
    lights: Light | Sequence[Light],
    brdf: BRDF | None = None,
    *,
    env_strategy: str = "mc",
    env_samples: int = DEFAULT_ENV_SAMPLES,
    env_sampling: str = "mis",
    seed: int | None = 0,
    chunk: int | None = None,
    prune: bool = True,
) -> Tensor:
    """Shade a g-buffer: outgoing linear radiance toward the camera at every pixel.

    Args:
        gbuf: the :class:`~torchbrdf.GBuffer` (``B`` images of ``H × W``).
        lights: a light or a list of :class:`~torchbrdf.PointLight`,
            :class:`~torchbrdf.DirectionalLight` and :class:`~torchbrdf.EnvironmentLight`
            (any number of each; their contributions add).
        brdf: callable ``brdf(l, v, n, x, y, **material) -> (*, 3)`` with the principled
            signature; default :func:`torchbrdf.principled`. :func:`torchbrdf.lambert`
            ships beside it.
        env_strategy: ``"mc"`` (unbiased Monte Carlo with MIS) or ``"split_sum"``
            (prefiltered approximation; principled and Lambert only). See
            :mod:`torchbrdf.render.envmap` for their error behaviour.
        env_samples: Monte Carlo samples per pixel and environment light.
        env_sampling: the Monte Carlo proposal (:data:`ENV_SAMPLINGS`; ignored by the split
            sum): ``"mis"`` (default: half BRDF-lobe mixture, half map luminance, power
            heuristic), ``"brdf"`` (BRDF-lobe mixture only), ``"map"`` (map luminance only) or
            ``"uniform"`` (uniform hemisphere, no importance sampling). All are unbiased and
            seeded the same way; they differ in variance (``"mis"`` is the robust choice,
            ``"uniform"`` a baseline; measured in ``docs/shading.md``).
        seed: seed of the Monte Carlo sample pattern (``None``: draw one from torch's RNG).
            The same seed gives the same image.
        chunk: maximum number of pixels per pass (bounds memory further on huge images);
            default all shaded pixels in one pass.
        prune: skip masked / back-facing pixels, zero lobes and frames that are not needed
            (default). ``False`` evaluates everything; the result is the same to float
            rounding.

    Returns:
        ``(B, 3, H, W)`` linear radiance in the g-buffer's dtype and on its device; 0 at
        masked-out and back-facing pixels.

    Raises:
        TypeError / ValueError: with the offending argument named. Under
            :func:`torchbrdf.set_validation` also NaN/inf in a shaded pixel of the g-buffer
            (masked-out pixels may hold anything) or in a light; without validation such a
            pixel's value follows ``docs/numerics.md`` ("Non-finite inputs").

    Note:
        float16 / bfloat16 g-buffers are shaded in float32 and the result is cast back
        (saturating). Gradients are exact for point and directional lights and for the
        split sum; for Monte Carlo they are unbiased estimates (sample directions and
        densities are held constant).

    Example:
        >>> from torchbrdf.render.geometry import sphere_gbuffer
        >>> from torchbrdf.brdf.lambert import lambert
        >>> g = sphere_gbuffer(8, 8)
        >>> shade(g, PointLight([0.0, 0.0, 4.0], 16.0), lambert).shape
        torch.Size([1, 3, 8, 8])
    """
    return _prepare(gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling).run()


def plan(
    gbuf: GBuffer,
    lights: Light | Sequence[Light],
    brdf: BRDF | None = None,
    *,
    env_strategy: str = "mc",
    env_samples: int = DEFAULT_ENV_SAMPLES,
    env_sampling: str = "mis",
    seed: int | None = 0,
    chunk: int | None = None,
    prune: bool = True,
) -> ShadingPlan:
    """What :func:`shade` would evaluate for these arguments, without shading.

    Returns:
        A :class:`ShadingPlan`; ``print(plan(...))`` lists the active and pruned lobes, how
        each material entry reaches the BRDF, the frames, the light paths, the environment
        strategy and sample budget, and the estimated cost (BRDF evaluations, passes, peak
        working set).

    Example:
        >>> from torchbrdf.render.geometry import sphere_gbuffer
        >>> p = plan(sphere_gbuffer(8, 8), [PointLight([0.0, 0.0, 4.0], 16.0)])
        >>> p.lobes
        ('diffuse', 'specular')
    """
    return _prepare(gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling).plan


class Shader(nn.Module):
    """:func:`shade` as a module holding the BRDF and the options.

    Args:
        brdf: BRDF callable (an ``nn.Module`` BRDF is registered as a submodule, so its
            parameters train with the shader); default :func:`torchbrdf.principled`.
        env_strategy: see :func:`shade`.
        env_samples: see :func:`shade`.
        env_sampling: see :func:`shade`.
        seed: see :func:`shade`.
        chunk: see :func:`shade`.
        prune: see :func:`shade`.

    Shape:
        - Input: a :class:`~torchbrdf.GBuffer` of ``(B, ·, H, W)`` maps and lights.
        - Output: ``(B, 3, H, W)``.

    Example:
        >>> from torchbrdf.render.geometry import sphere_gbuffer
        >>> Shader()(sphere_gbuffer(8, 8), DirectionalLight([0.0, 0.0, 1.0], 1.0)).shape
        torch.Size([1, 3, 8, 8])
    """

    def __init__(
        self,
        brdf: BRDF | None = None,
        *,
        env_strategy: str = "mc",
        env_samples: int = DEFAULT_ENV_SAMPLES,
        env_sampling: str = "mis",
        seed: int | None = 0,
        chunk: int | None = None,
        prune: bool = True,
    ) -> None:
        super().__init__()
        if env_strategy not in ENV_STRATEGIES:
            raise ValueError(f"Shader: `env_strategy` must be one of {ENV_STRATEGIES}, got {env_strategy!r}")
        check_env_sampling(env_sampling, "Shader", "env_sampling")
        self.brdf = brdf
        self.env_strategy = env_strategy
        self.env_samples = env_samples
        self.env_sampling = env_sampling
        self.seed = seed
        self.chunk = chunk
        self.prune = prune

    def _kwargs(self):
        return dict(
            env_strategy=self.env_strategy,
            env_samples=self.env_samples,
            env_sampling=self.env_sampling,
            seed=self.seed,
            chunk=self.chunk,
            prune=self.prune,
        )

    def forward(self, gbuf: GBuffer, lights: Light | Sequence[Light]) -> Tensor:
        """Shade ``gbuf`` under ``lights``; see :func:`shade`."""
        return shade(gbuf, lights, self.brdf, **self._kwargs())

    def plan(self, gbuf: GBuffer, lights: Light | Sequence[Light]) -> ShadingPlan:
        """See :func:`plan`."""
        return plan(gbuf, lights, self.brdf, **self._kwargs())

    def extra_repr(self) -> str:
        """Options, for ``repr``."""
        name = "principled" if self.brdf is None else _brdf_name(self.brdf)
        return (
            f"brdf={name}, env_strategy={self.env_strategy!r}, env_samples={self.env_samples}, "
            f"env_sampling={self.env_sampling!r}, chunk={self.chunk}"
        )
