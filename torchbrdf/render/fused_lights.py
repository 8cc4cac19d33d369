"""The fused route of the shader: every point and directional light in one kernel pass per chunk.

With the principled BRDF or the SVBRDF GGX (:func:`light_loop_brdf`), :func:`fused_lights_term`
evaluates all point and directional lights through ONE fused kernel (the ``torchbrdf::shade_lights_fwd`` operator),
forward and recompute-backward, generated from the same per-light formula the eager passes
run (:func:`torchbrdf.brdf.formula.point_light`, ``directional_light``), including the gradients
w.r.t. the light parameters and the camera (the uniform table's gradient).
:func:`fused_lights_wanted` is the rule that picks it.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchbrdf._checks import active_transforms
from torchbrdf.brdf.principled import PRINCIPLED_DEFAULTS
from torchbrdf.render.gbuffer import GBuffer
from torchbrdf.render.lights import DirectionalLight, PointLight

__all__ = ["light_loop_brdf", "fused_lights_wanted", "uniform_table", "fused_lights_term"]

#: Each light-loop BRDF's material inputs and the channel counts the kernel reads for each.
_MATERIAL_CHANNELS: dict[str, dict[str, tuple[int, ...]]] = {
    "principled": {"base_color": (1, 3), **{k: (1,) for k in PRINCIPLED_DEFAULTS if k != "base_color"}},
    # (svbrdf_ggx refuses a grey albedo map; a number is grey)
    "svbrdf_ggx": {"diffuse_albedo": (3,), "specular_albedo": (3,), "roughness": (1,)},
}


def light_loop_brdf(brdf: Any, kind: str) -> tuple[str, dict[str, float]] | None:
    """The light-loop kernel's BRDF family for ``brdf`` and its fixed floats, or None.

    ``("principled", {})`` for :func:`torchbrdf.principled` and a ``PrincipledBRDF``;
    ``("svbrdf_ggx", {floor: value})`` for :func:`torchbrdf.brdf.svbrdf_ggx.svbrdf_ggx` and an
    ``SVBRDFGGX``, with the floor it applies. A module counts only as itself: not a subclass,
    nor one with hooks or its own ``forward`` (the kernel would skip what they do). Any other
    callable: None (per-light passes).

    Raises:
        ValueError: an ``SVBRDFGGX`` whose floors were set to values it refuses.
    """
    from torchbrdf.brdf.principled import PrincipledBRDF, principled
    from torchbrdf.brdf.svbrdf_ggx import ALPHA_MIN, SVBRDFGGX, check_floors, svbrdf_ggx

    if brdf is principled:
        return "principled", {}
    if brdf is svbrdf_ggx:
        return "svbrdf_ggx", {"alpha_floor": ALPHA_MIN}
    if kind == "principled" and _plain(brdf, PrincipledBRDF):
        return "principled", {}
    if _plain(brdf, SVBRDFGGX):
        check_floors(brdf.alpha_floor, brdf.roughness_floor)
        if brdf.roughness_floor is not None:
            return "svbrdf_ggx", {"roughness_floor": float(brdf.roughness_floor)}
        return "svbrdf_ggx", {"alpha_floor": ALPHA_MIN if brdf.alpha_floor is None else float(brdf.alpha_floor)}
    return None


def _plain(module: Any, cls: type) -> bool:
    """``module`` is a ``cls`` exactly, calling its own ``forward`` with no hook on the way."""
    from torch.nn.modules import module as nn_module

    if type(module) is not cls or "forward" in vars(module):
        return False
    hooks = [getattr(module, name, None) for name in ("_forward_hooks", "_forward_pre_hooks")]
    hooks += [getattr(nn_module, name, None) for name in ("_global_forward_hooks", "_global_forward_pre_hooks")]
    return not any(hooks)


def fused_lights_wanted(
    gbuf: GBuffer,
    family: str | None,
    values: dict[str, Any],
    points: list[PointLight],
    dirs: list[DirectionalLight],
    cam: Tensor,
    dev: torch.device,
    cd: torch.dtype,
    elements: int,
) -> bool:
    """Whether the point and directional lights go through the fused shading kernel.

    A light-loop BRDF (``family``, :func:`light_loop_brdf`; None: none), its material and
    nothing else as inputs the kernel reads (4-D maps or constants), and the fused
    kernels' dispatch rule (``principled.fused_backend``, on ``elements`` pixel-lights) picking
    the C or the Triton kernels (the shading kernel is printed in both). The lights and ``cam``
    may require grad: the kernel's backward differentiates them too.
    """
    if family is None or not (points or dirs):
        return False
    channels = _MATERIAL_CHANNELS[family]
    required = {"base_color"} if family == "principled" else set(channels)
    if not required <= set(values) or set(values) - set(channels):
        return False  # the eager call raises the error naming the argument
    from torchbrdf.brdf import principled as _pr

    # The shade ops have a reverse rule for torch.func (grad, vjp) but no vmap or jvp rule.
    transforms = [] if torch.compiler.is_compiling() else active_transforms()
    if any(kind != "Grad" for kind, _ in transforms):
        return False
    tensors = []
    for k, t in [("position", gbuf.position), ("normal", gbuf.normal), *values.items()]:
        if not isinstance(t, Tensor):
            continue
        allowed = (3,) if k in ("position", "normal") else channels[k]
        if not (t.dim() == 0 or (t.dim() == 4 and t.shape[1] in allowed)):
            return False
        tensors.append(t)
    return _pr.fused_backend(dev, cd, tensors, lambda: elements) in ("c", "triton")


def uniform_table(
    cam: Tensor, points: list[PointLight], dirs: list[DirectionalLight], dev: torch.device, cd: torch.dtype
) -> Tensor:
    """``(R, 3 + 6 L)``: camera, then ``(q, I)`` per point and ``(d, E)`` per directional light,
    one row per batch element (``R = 1`` when nothing is batched); differentiable w.r.t. the
    camera and the lights' tensors."""
    parts = [cam.reshape(-1, 3)]
    for light in points:
        parts += [
            light.position.to(device=dev, dtype=cd).reshape(-1, 3),
            light.intensity.to(device=dev, dtype=cd).reshape(-1, 3),
        ]
    for sun in dirs:
        parts += [
            sun.direction.to(device=dev, dtype=cd).reshape(-1, 3),
            sun.irradiance.to(device=dev, dtype=cd).reshape(-1, 3),
        ]
    rows = max(p.shape[0] for p in parts)
    return torch.cat([p.expand(rows, 3) for p in parts], dim=1).contiguous()


def fused_lights_term(
    table: Tensor,
    pos: Tensor,
    n: Tensor,
    x: Tensor | None,
    y: Tensor | None,
    mat: dict[str, Any],
    bidx: Tensor,
    active: tuple[str, ...] | None,
    frame: bool,
    normalize_n: bool,
    n_point: int,
    n_dir: int,
    family: tuple[str, dict[str, float]] = ("principled", {}),
) -> Tensor:
    """All point and directional lights at ``(P, 3)`` points in one fused kernel pass
    (``normalize_n``: ``n`` is the raw normal, normalised in the kernel; ``family``: the BRDF
    and its fixed floats, :func:`light_loop_brdf`)."""
    from torchbrdf.brdf.principled import needs_tint
    from torchbrdf.kernels.shade_ops import shade_lights

    name, fixed = family
    if name == "principled":
        assert active is not None  # the principled BRDF's lobes are known on this route
        c = {**PRINCIPLED_DEFAULTS, **mat, "pos": pos, "n": n, "x": x, "y": y}
        tint = needs_tint(c, active)
    else:
        active, frame, tint = (), False, False
        c = {**mat, **fixed, "pos": pos, "n": n}
    if table.shape[0] == 1:
        seg = [0, pos.shape[0]]
    else:  # points are batch-major: one segment (uniform row) per image
        counts = torch.bincount(bidx, minlength=table.shape[0])
        seg = [0] + torch.cumsum(counts, 0).tolist()
    backend = "c" if pos.device.type == "cpu" and not _triton_interpreted() else "triton"
    return shade_lights(c, table, seg, active, tint, frame, normalize_n, n_point, n_dir, backend, name)


def _triton_interpreted() -> bool:
    """CPU tensors go to the Triton shading kernels when the backend resolves to Triton (its
    interpreter, ``TRITON_INTERPRET=1``: how the tests run them without a GPU)."""
    from torchbrdf.kernels import backend

    return backend.resolve(torch.device("cpu")) == "triton"
