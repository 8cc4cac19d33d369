"""Differentiable screen-space shading of g-buffers: :func:`shade`, :func:`plan`, :class:`Shader`.

``shade(gbuf, lights)`` turns a :class:`~torchbrdf.GBuffer` into linear radiance
``(B, 3, H, W)`` under any mix of point, directional and environment lights, with
the formulas of :mod:`torchbrdf.render.lights`. It evaluates any BRDF callable with the principled signature
``brdf(l, v, n, x, y, **material)`` (default :func:`torchbrdf.principled`).

How it works, in order:

1. **Inspect once** (:mod:`torchbrdf.render.prepare`; :func:`plan` shows the result). Pixels
   that are masked out or face away from the camera (``n·v <= 0``, where every BRDF of the
   library is 0) are dropped. Each material map that does not require grad is reduced: all
   zeros -> the Python float ``0.0`` (the BRDF then skips the lobe it weights), uniform
   single-channel map -> a float. Tangent frames are built only when ``anisotropic`` is not a
   Python 0; environment integration runs only when an :class:`~torchbrdf.EnvironmentLight`
   is present. The result equals full evaluation (``prune=False``) to float rounding. Under
   ``torch.compile`` these value-dependent decisions are skipped (every pixel and map is
   evaluated) and Python-float material values enter as 0-d tensors, so ``shade`` compiles
   with ``fullgraph=True`` (and ``dynamic=True``), and neither new material values nor new
   image sizes recompile it more than once.
2. **Convert once** from ``(B, C, H, W)`` to flat channel-last ``(P, C)`` over the shaded
   pixels, call the BRDF on those, and scatter back.
3. **Accumulate per light** (per environment-sample pass, per pixel chunk), each pass
   wrapped in ``torch.utils.checkpoint`` (non-reentrant; :mod:`torchbrdf.render.passes`): its
   intermediates are dropped after the forward pass and recomputed during backward, so
   forward+backward peak memory is that of one pass, whatever the number of lights (measured
   in ``docs/shading.md``).
   With the principled BRDF (the C kernels on CPU, Triton on CUDA), all point and directional
   lights instead go through ONE fused kernel per chunk (:mod:`torchbrdf.render.fused_lights`), forward and
   recompute-backward (the ``torchbrdf::shade_lights_fwd`` operator), generated from the same
   per-light formula the eager passes run (:func:`torchbrdf.brdf.formula.point_light`,
   ``directional_light``), gradients w.r.t. the light parameters and the camera included.

Gradients reach every tensor input: material maps, normals, positions, camera position,
tangents, light positions/directions/intensities and environment maps. Masked and
back-facing pixels are exactly 0 with zero (finite) gradients.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from torchbrdf import _checks
from torchbrdf._math import cast_back, compute_dtype, safe_normalize
from torchbrdf._types import BRDF
from torchbrdf.brdf import formula
from torchbrdf.brdf.frames import frame_from_normal, gram_schmidt
from torchbrdf.render import passes
from torchbrdf.render.env import (
    ENV_SAMPLINGS,
    MCSetup,
    SplitSumEnvironment,
    as_bhwc,
    check_env_sampling,
    integrate_environment_split_sum,
    mc_pass,
    sampling_lobes_for,
)
from torchbrdf.render.fused_lights import fused_lights_term, uniform_table
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, Light, PointLight
from torchbrdf.render.prepare import (
    ENV_STRATEGIES,
    ShadingSchedule,
    brdf_name,
    inspect_material,
    schedule,
    select_pixels,
    validate,
)
from torchbrdf.render.shading_plan import ENV_ELEMENTS_PER_PASS, ShadingPlan, describe

__all__ = ["shade", "plan", "Shader", "ShadingPlan", "ENV_STRATEGIES", "ENV_SAMPLINGS", "DEFAULT_ENV_SAMPLES"]

DEFAULT_ENV_SAMPLES = 64
# Squared distance floor for point lights (defined with the shading formula).
DIST2_EPS = formula.DIST2_EPS


def _prepare(
    gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling
) -> ShadingSchedule:
    """validate -> select pixels -> inspect material -> schedule (see :mod:`torchbrdf.render.prepare`)."""
    req = validate(gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling)
    cd = compute_dtype(req.gbuf.dtype)
    sel = select_pixels(req, cd)
    mat = inspect_material(req, sel.data_prune, cd)
    return schedule(req, cd, sel, mat)


# --------------------------------------------------------------------------------------
# Running the passes
# --------------------------------------------------------------------------------------


@dataclass
class _PixelInputs:
    """Per-pixel inputs of the passes, channel-last ``(P, C)`` over the shaded pixels (or a chunk)."""

    pos: Tensor
    n: Tensor  # normalised, unless the fused kernel normalises it
    v: Tensor | None  # None: the fused kernel computes it
    x: Tensor | None  # tangent frame, when needed
    y: Tensor | None
    bidx: Tensor  # batch index of each pixel
    mat: dict[str, Any]
    size: int  # pixels
    span: tuple[int, int] | None = None  # rows of the whole set this chunk holds
    total: int = 0  # pixels of the whole set, when a chunk

    def take(self, t):
        """This chunk's rows of a per-pixel tensor of the whole set; anything else unchanged."""
        if self.span is None or not isinstance(t, Tensor) or t.dim() < 1 or t.shape[0] != self.total:
            return t
        return t[self.span[0] : self.span[1]]

    def chunk(self, start: int, stop: int) -> _PixelInputs:
        """Rows ``start:stop`` (only when chunking: a slice's backward allocates and copies
        full-size gradients)."""
        part = _PixelInputs(
            self.pos, self.n, self.v, self.x, self.y, self.bidx, self.mat,
            size=stop - start, span=(start, stop), total=self.size,
        )
        part.pos, part.n, part.v = part.take(self.pos), part.take(self.n), part.take(self.v)
        part.x, part.y, part.bidx = part.take(self.x), part.take(self.y), part.take(self.bidx)
        part.mat = {
            k: (part.take(m) if isinstance(m, Tensor) and m.dim() == 2 else m) for k, m in self.mat.items()
        }
        return part


def _gather_inputs(sch: ShadingSchedule) -> _PixelInputs:
    """Boundary conversion, once: ``(B, C, H, W)`` maps -> ``(P, C)`` at the shaded pixels."""
    gbuf, pixels, cd = sch.req.gbuf, sch.sel.pixels, sch.cd
    pos = pixels.gather(sch.sel.position)
    n = pixels.gather(gbuf.normal.to(cd))
    if not sch.normal_in_kernel:
        n = safe_normalize(n)
    bidx = pixels.batch_index
    v = None
    if not (sch.fused and not sch.envs):
        cam = sch.sel.camera
        cam_p = cam[bidx] if cam.dim() == 2 and cam.shape[0] > 1 else cam.reshape(1, 3)
        v = formula.view_direction(formula.TorchOps(cd, gbuf.device), cam_p, pos)
    x = y = None
    if sch.mat.need_frame:
        if gbuf.tangent is not None:
            x, y = gram_schmidt(n, pixels.gather(gbuf.tangent.to(cd)))
        else:
            x, y = frame_from_normal(n)
    mat = {
        k: (pixels.gather(val) if isinstance(val, Tensor) and val.dim() == 4 else val)
        for k, val in sch.mat.values.items()
    }
    if sch.fused and _checks.validation_enabled():
        _checks.check_finite({k: val for k, val in mat.items() if isinstance(val, Tensor)})
    return _PixelInputs(pos, n, v, x, y, bidx, mat, pixels.count)


@dataclass
class _LightInputs:
    """The lights, cast once: the fused kernel's table, per-light eager passes, environments."""

    table: Tensor | None  # fused_lights.uniform_table, when fused
    eager: list[tuple[str, Tensor, Tensor]]  # ("point", q, I) / ("dir", d, E)
    # (kind, radiance (B, H, W, 3) or split-sum tables, batch size, MC setup or None)
    envs: list[tuple[str, Any, int, MCSetup | None]]


def _light_inputs(sch: ShadingSchedule) -> _LightInputs:
    dev, cd = sch.req.gbuf.device, sch.cd
    table = uniform_table(sch.sel.camera, sch.points, sch.dirs, dev, cd) if sch.fused else None
    eager = []  # the fused kernel takes them all at once
    for pl in [] if sch.fused else sch.points:
        eager.append(("point", pl.position.to(device=dev, dtype=cd), pl.intensity.to(device=dev, dtype=cd)))
    for dl in [] if sch.fused else sch.dirs:
        eager.append(("dir", dl.direction.to(device=dev, dtype=cd), dl.irradiance.to(device=dev, dtype=cd)))
    envs: list[tuple[str, Any, int, MCSetup | None]] = []
    for i, env in enumerate(sch.envs):
        rad = env.radiance.to(device=dev, dtype=cd)
        env_b = rad.shape[0] if rad.dim() == 4 else 1
        if sch.req.env_strategy == "mc":
            envs.append(("mc", as_bhwc(rad).contiguous(), env_b, sch.mc_setups[i]))
        else:
            envs.append(("split_sum", _split_sum_env(env, rad, cd), env_b, None))
    return _LightInputs(table, eager, envs)


def _add_mc_passes(acc: Tensor, brdf, px: _PixelInputs, env_data: Tensor, eb, setup: MCSetup) -> None:
    """Add one environment's Monte Carlo estimate to ``acc`` ``(P, 3)``, in bounded passes."""
    per_pass = max(1, ENV_ELEMENTS_PER_PASS // max(px.size, 1))
    slobes = sampling_lobes_for(brdf, px.mat)
    for technique, total, shift in setup.techniques():
        k = min(per_pass, max(total, 1))
        for start in range(0, total, k):
            count = min(k, total - start)
            term = passes.checkpointed_pass(
                px.size * count, mc_pass, brdf, slobes, px.n, px.v, px.x, px.y, px.mat, env_data, eb, setup,
                technique, start, count, px.take(shift),
            )
            acc.add_(term)


def _shade_chunk(sch: ShadingSchedule, px: _PixelInputs, lights: _LightInputs) -> Tensor:
    """Outgoing radiance ``(P, 3)`` at the pixels of ``px``: every light's passes added up."""
    brdf = sch.req.brdf
    # One accumulator per chunk, updated in place: a fresh sum per light would land on
    # top of the heap each time and fragment it (freed pages stay resident).
    if lights.table is not None:  # fused (the kernel's output is a fresh buffer: accumulate into it)
        acc = fused_lights_term(
            lights.table, px.pos, px.n, px.x, px.y, px.mat, px.bidx, sch.mat.lobes, sch.mat.need_frame,
            sch.normal_in_kernel, len(sch.points), len(sch.dirs), sch.loop_brdf or ("principled", {}),
        )
    else:
        acc = px.pos.new_zeros(px.size, 3)
    for kind, p1, p2 in lights.eager:
        fn = passes.point_term if kind == "point" else passes.directional_term
        term = passes.checkpointed_pass(
            px.size, fn, brdf, px.pos, px.n, px.v, px.x, px.y, px.mat, p1, p2, px.bidx
        )
        acc.add_(term)
    for kind, env_data, env_b, setup in lights.envs:
        eb = px.bidx if env_b > 1 else None
        if kind == "mc":
            assert setup is not None  # every "mc" entry carries its setup
            _add_mc_passes(acc, brdf, px, env_data, eb, setup)
        else:
            term = passes.checkpointed_pass(
                px.size, integrate_environment_split_sum, brdf, px.n, px.v, env_data, px.mat, x=px.x, y=px.y,
                batch_index=eb,
            )
            acc.add_(term)
    if not acc.requires_grad and px.pos.requires_grad:
        acc = acc + 0.0 * px.pos  # no lights: keep the graph connected (zero gradients)
    return acc


def _run(sch: ShadingSchedule) -> Tensor:
    """Shade the prepared call: ``(B, 3, H, W)`` in the g-buffer's dtype."""
    gbuf, sel = sch.req.gbuf, sch.sel
    b, h, w = gbuf.shape
    p_count = sel.pixels.count
    if p_count == 0:
        zero = sel.position.new_zeros(b, 3, h, w)
        # Keep the graph connected so backward() works and yields zero gradients.
        return cast_back(zero + 0.0 * sel.position.sum(), gbuf.dtype)
    px = _gather_inputs(sch)
    lights = _light_inputs(sch)
    # Without `chunk`, no comparison with the pixel count: under torch.compile each would be a
    # guard on the image size (a recompile per size).
    if sch.req.chunk is None or sch.chunk_px >= p_count:
        out = _shade_chunk(sch, px, lights)
    else:
        step = sch.chunk_px
        chunks = [px.chunk(s, min(s + step, p_count)) for s in range(0, p_count, step)]
        out = torch.cat([_shade_chunk(sch, part, lights) for part in chunks], dim=0)
    img = sel.pixels.scatter(out)
    if not sel.data_prune:
        img = torch.where(sel.active.unsqueeze(1), img, torch.zeros_like(img))
    if gbuf.mask is not None and gbuf.mask.is_floating_point():
        img = img * gbuf.mask.to(sch.cd)
    return cast_back(img.contiguous(), gbuf.dtype)


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
            (masked-out pixels may hold anything) or in a light, and a negative light
            intensity, irradiance or radiance; without validation such a pixel's value
            follows ``docs/numerics.md`` ("Non-finite inputs").

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
    return _run(_prepare(gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling))


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
    return describe(_prepare(gbuf, lights, brdf, env_strategy, env_samples, seed, chunk, prune, env_sampling))


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
        name = "principled" if self.brdf is None else brdf_name(self.brdf)
        return (
            f"brdf={name}, env_strategy={self.env_strategy!r}, env_samples={self.env_samples}, "
            f"env_sampling={self.env_sampling!r}, chunk={self.chunk}"
        )
