"""What :func:`torchbrdf.shade` will compute for a scene, and roughly what it costs.

:func:`describe` turns a prepared :class:`~torchbrdf.render.prepare.ShadingSchedule` into a
:class:`ShadingPlan` of plain Python values (``print(plan)`` shows it). Only
:func:`torchbrdf.plan` builds one: the descriptions stay out of the shading itself (and out of
any graph ``torch.compile`` traces).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import torch
from torch import Tensor

from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS
from torchbrdf.render.env import PREFILTER_ROUGHNESS, sampling_lobes_for
from torchbrdf.render.lights import DirectionalLight, EnvironmentLight, PointLight
from torchbrdf.render.prepare import ShadingSchedule, brdf_name

__all__ = ["ShadingPlan", "describe", "ENV_ELEMENTS_PER_PASS"]

# Environment samples are evaluated in passes of about this many (pixel, sample) pairs, so an
# environment pass costs about as much memory as one point light over 2^18 pixels.
ENV_ELEMENTS_PER_PASS = 1 << 18
# Rough relative cost of one BRDF evaluation per lobe (diffuse = 1), for the plan's estimate.
_LOBE_COST = {"diffuse": 1.0, "subsurface": 0.6, "specular": 2.0, "sheen": 0.4, "clearcoat": 1.2}
# Bytes of live intermediates per (pixel, sample) element and per unit of lobe cost during
# the backward of one pass, float32 (measured on the principled BRDF; see docs/shading.md).
_BYTES_PER_ELEMENT_COST = 40
_PROPOSAL_NAMES = {"diffuse": "cosine", "specular": "GGX visible normals", "clearcoat": "GTR1"}


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


def _describe_value(v) -> str:
    if isinstance(v, Tensor):
        grad = ", requires grad" if v.requires_grad else ""
        return f"map {list(v.shape)}{grad}" if v.dim() else f"0-d tensor{grad}"
    return f"constant {v:g}"


def _describe_material(sch: ShadingSchedule) -> dict[str, str]:
    """How each material entry reaches the BRDF, then the principled defaults it falls back on."""
    desc = {}
    for name, v in sch.req.gbuf.material.items():
        how, val = sch.mat.reduction[name], sch.mat.values[name]
        if how == "constant":
            desc[name] = _describe_value(val)
        elif how == "zeros":
            desc[name] = f"all zeros, no grad -> Python 0.0 ({'0-d' if v.dim() == 0 else list(v.shape)})"
        elif how == "scalar":
            desc[name] = f"0-d tensor, no grad -> constant {val:g}"
        elif how == "uniform":
            desc[name] = f"uniform map {list(v.shape)}, no grad -> constant {val:g}"
        else:
            desc[name] = _describe_value(v)
    if sch.req.kind == "principled":
        for k, d in PRINCIPLED_DEFAULTS.items():
            desc.setdefault(k, f"default {d:g}")
    return desc


def _describe_frames(sch: ShadingSchedule) -> str:
    if not sch.mat.need_frame:
        return "none (isotropic: anisotropic is a Python 0)"
    if sch.req.gbuf.tangent is not None:
        return "Gram–Schmidt from the tangent map"
    return "built from the normal (Duff et al. 2017)"


def _describe_lights(sch: ShadingSchedule) -> list[str]:
    out = []
    for i, light in enumerate(sch.req.lights):
        batched = "per-batch" if light.batch_size not in (None, 1) else "shared"
        if isinstance(light, PointLight):
            out.append(
                f"[{i}] point light ({batched}): f·I·max(n·l,0)/|q-P|², 1 BRDF evaluation per pixel"
            )
        elif isinstance(light, DirectionalLight):
            out.append(f"[{i}] directional light ({batched}): f·E·max(n·l,0), 1 BRDF evaluation per pixel")
        else:
            shape = list(cast(EnvironmentLight, light).radiance.shape)
            out.append(f"[{i}] environment {shape} ({batched}): {sch.req.env_strategy}")
    return out


def _mc_proposal(setup, sampling: str, proposal: str) -> str:
    if sampling == "mis":
        if setup.n_map:
            return (
                f"{setup.n_brdf} BRDF-sampled ({proposal}) + {setup.n_map} map-sampled, power-heuristic MIS"
            )
        return f"{setup.n_brdf} BRDF-sampled ({proposal}) (constant map: no map sampling)"
    if sampling == "brdf":
        return f"{setup.n_brdf} BRDF-sampled ({proposal}; no map sampling)"
    if sampling == "map":
        return f"{setup.n_map} map-sampled (luminance × solid angle; no BRDF sampling)"
    return f"{setup.n_uniform} uniform-hemisphere (no importance sampling)"


def _describe_environment(sch: ShadingSchedule, n_slices: int) -> tuple[str | None, int, int]:
    """The environment lights' description, BRDF evaluations and passes."""
    req = sch.req
    if not sch.envs:
        return None, 0, 0
    if req.env_strategy != "mc":
        desc = (
            f"split sum: irradiance map + {len(PREFILTER_ROUGHNESS)} GGX-prefiltered levels"
            " + (n·v, roughness) table;"
            " no BRDF evaluations"
        )
        return desc, 0, n_slices * len(sch.envs)
    slobes = sampling_lobes_for(req.brdf, sch.mat.values)
    proposal = " + ".join(_PROPOSAL_NAMES[k] for k in ("diffuse", "specular", "clearcoat") if k in slobes)
    per_pass = max(1, ENV_ELEMENTS_PER_PASS // max(sch.chunk_px, 1))
    parts, evals, passes = [], 0, 0
    for setup in sch.mc_setups:
        for _, total, _ in setup.techniques():
            passes += n_slices * math.ceil(total / min(per_pass, total))
        evals += sch.sel.pixels.count * int(req.env_samples)
        parts.append(_mc_proposal(setup, req.env_sampling, proposal))
    desc = "Monte Carlo, env_sampling=%r, stratified (rotated Hammersley), seed %s: %s per pixel" % (
        req.env_sampling,
        req.seed,
        "; ".join(parts),
    )
    return desc, evals, passes


def describe(sch: ShadingSchedule) -> ShadingPlan:
    """The :class:`ShadingPlan` of a prepared shading call (counts, lobes, lights, estimated cost)."""
    req, sel, mat = sch.req, sch.sel, sch.mat
    b, h, w = req.gbuf.shape
    p_count = sel.pixels.count
    n_lights = len(sch.points) + len(sch.dirs)
    n_slices = 0 if p_count == 0 else math.ceil(p_count / max(sch.chunk_px, 1))
    env_desc, env_evals, env_passes = _describe_environment(sch, n_slices)
    brdf_evals = p_count * n_lights + env_evals
    lobe_cost = sum(_LOBE_COST[x] for x in mat.lobes) if mat.lobes is not None else 4.0
    # Fused: all point and directional lights in one kernel pass per chunk.
    passes = n_slices * (min(1, n_lights) if sch.fused else n_lights) + env_passes
    mc = sch.envs and req.env_strategy == "mc"
    elements_per_pass = sch.chunk_px
    if mc:
        elements_per_pass = max(sch.chunk_px, min(ENV_ELEMENTS_PER_PASS, sch.chunk_px * int(req.env_samples)))
    itemsize = torch.finfo(sch.cd).bits // 8
    est = int(elements_per_pass * lobe_cost * _BYTES_PER_ELEMENT_COST * itemsize / 4)
    est += int(p_count * itemsize * 3 * (4 + len([v for v in mat.values.values() if isinstance(v, Tensor)])))
    notes = []
    if sch.fused:
        notes.append(
            f"point/directional lights: fused kernel, the {n_lights} light(s) looped inside"
            " one pass (forward and recompute-backward)"
        )
    if not req.prune:
        notes.append("pruning disabled (prune=False): every pixel and every material map is evaluated")
    return ShadingPlan(
        brdf=brdf_name(req.brdf),
        brdf_kind=req.kind,
        image=(b, h, w),
        dtype=str(req.gbuf.dtype).replace("torch.", ""),
        pixels_total=b * h * w,
        pixels_shaded=p_count,
        pixels_masked=sel.n_masked,
        pixels_backfacing=sel.n_back,
        lobes=mat.lobes,
        pruned_lobes=mat.pruned_lobes,
        material=_describe_material(sch),
        frames=_describe_frames(sch),
        lights=_describe_lights(sch),
        environment=env_desc,
        passes=passes,
        brdf_evaluations=brdf_evals,
        relative_cost=brdf_evals * lobe_cost,
        estimated_peak_bytes=est,
        pruning=req.prune,
        notes=notes,
    )
