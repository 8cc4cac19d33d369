"""The g-buffer: what :func:`torchbrdf.shade` needs to know about each pixel.

A :class:`GBuffer` bundles world-space positions and normals, the camera position, the
principled material (maps or constants), an optional tangent map and an optional mask.
Everything image-like is channel-first ``(B, C, H, W)``; :func:`torchbrdf.shade` converts to
channel-last once, at its boundary.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchbrdf.brdf.principled import SCALAR_PARAMS

__all__ = ["GBuffer", "PRINCIPLED_SCALAR_PARAMS", "COLOR_PARAMS"]

#: Material names that must be single-channel maps (C = 1): the principled scalars.
PRINCIPLED_SCALAR_PARAMS = SCALAR_PARAMS
#: Material names that must be RGB maps (C = 3).
COLOR_PARAMS = ("base_color",)


def _shape(t: Tensor) -> list[int]:
    return list(t.shape)


@dataclass(frozen=True)
class GBuffer:
    """World-space geometry, camera and material of a batch of images.

    Args:
        position: ``(B, 3, H, W)`` world-space surface points ``P``.
        normal: ``(B, 3, H, W)`` world-space shading normals (normalised by the shader).
        camera_position: ``(3,)`` or ``(B, 3)`` camera centre ``C``; a sequence of 3 numbers
            is converted to a tensor. Each pixel's view vector is ``normalize(C - P)``.
        material: principled parameter name -> ``(B, C, H, W)`` map (C = 3 for
            ``base_color``, 1 for the scalar parameters; a batch of 1 and ``H = W = 1``
            broadcast), a 0-d tensor or a Python float. Missing names take the BRDF's
            defaults. Names other than the principled ones are passed to the BRDF unchanged
            (C = 1 or 3).
        tangent: optional ``(B, 3, H, W)`` world-space tangent guesses; the shading frame
            follows by Gram–Schmidt against the normal. Without it, an anisotropic material
            gets a frame built from the normal (Duff et al. 2017).
        mask: optional ``(B, 1, H, W)`` coverage, bool or floating; pixels where it is 0 (or
            False) are not shaded and come out 0. A floating mask also multiplies the result
            (soft coverage), so it receives gradients.

    Raises:
        TypeError / ValueError: naming the argument, when a shape, dtype or device does not fit.

    Example:
        >>> P = torch.zeros(1, 3, 4, 4)
        >>> N = torch.zeros(1, 3, 4, 4); N[:, 2] = 1
        >>> g = GBuffer(P, N, torch.tensor([0.0, 0.0, 3.0]), {"base_color": torch.ones(1, 3, 4, 4)})
        >>> g.shape
        (1, 4, 4)
    """

    position: Tensor
    normal: Tensor
    camera_position: Tensor
    material: Mapping = field(default_factory=dict)
    tangent: Tensor | None = None
    mask: Tensor | None = None

    def __post_init__(self):
        pos = self.position
        if not isinstance(pos, Tensor):
            raise TypeError(
                f"GBuffer: `position` must be a torch.Tensor of shape [B, 3, H, W], got {type(pos).__name__}"
            )
        if not pos.is_floating_point():
            raise TypeError(f"GBuffer: `position` must be floating point, got dtype {pos.dtype}")
        if pos.dim() != 4 or pos.shape[1] != 3:
            raise ValueError(f"GBuffer: `position` must have shape [B, 3, H, W], got {_shape(pos)}")
        b, _, h, w = pos.shape
        self._check_image("normal", self.normal, 3, exact_batch=True)
        if self.tangent is not None:
            self._check_image("tangent", self.tangent, 3, exact_batch=True)
        if self.mask is not None:
            m = self.mask
            if not isinstance(m, Tensor):
                raise TypeError(
                    f"GBuffer: `mask` must be a tensor of shape [B, 1, H, W], got {type(m).__name__}"
                )
            if m.dim() != 4 or m.shape[1] != 1 or m.shape[0] not in (1, b) or tuple(m.shape[2:]) != (h, w):
                raise ValueError(
                    f"GBuffer: `mask` must have shape [{b}, 1, {h}, {w}] (batch 1 broadcasts), "
                    f"got {_shape(m)}"
                )
            if m.device != pos.device:
                raise ValueError(f"GBuffer: `mask` is on {m.device} but `position` is on {pos.device}")
        cam = self.camera_position
        if not isinstance(cam, Tensor):
            if isinstance(cam, Sequence) and not isinstance(cam, str):
                cam = torch.as_tensor(cam, dtype=pos.dtype, device=pos.device)
                object.__setattr__(self, "camera_position", cam)
            else:
                raise TypeError(
                    "GBuffer: `camera_position` must be a tensor of shape [3] or [B, 3], "
                    f"got {type(cam).__name__}"
                )
        if not cam.is_floating_point():
            raise TypeError(f"GBuffer: `camera_position` must be floating point, got dtype {cam.dtype}")
        if not (cam.shape == (3,) or (cam.dim() == 2 and cam.shape[1] == 3 and cam.shape[0] in (1, b))):
            raise ValueError(f"GBuffer: `camera_position` must have shape [3] or [{b}, 3], got {_shape(cam)}")
        if cam.device != pos.device:
            raise ValueError(
                f"GBuffer: `camera_position` is on {cam.device} but `position` is on {pos.device}"
            )
        if not isinstance(self.material, Mapping):
            raise TypeError(
                "GBuffer: `material` must be a dict of name -> map or float, "
                f"got {type(self.material).__name__}"
            )
        mat = {}
        for name, value in self.material.items():
            mat[name] = self._check_material(name, value)
        object.__setattr__(self, "material", mat)

    # ------------------------------------------------------------------ validation
    def _check_image(self, name: str, t, channels: int, exact_batch: bool) -> None:
        pos = self.position
        b, _, h, w = pos.shape
        if not isinstance(t, Tensor):
            raise TypeError(
                f"GBuffer: `{name}` must be a torch.Tensor of shape [B, {channels}, H, W], "
                f"got {type(t).__name__}"
            )
        if not t.is_floating_point():
            raise TypeError(f"GBuffer: `{name}` must be floating point, got dtype {t.dtype}")
        if (
            t.dim() != 4
            or t.shape[1] != channels
            or tuple(t.shape[2:]) != (h, w)
            or (t.shape[0] != b if exact_batch else t.shape[0] not in (1, b))
        ):
            raise ValueError(
                f"GBuffer: `{name}` must have shape [{b}, {channels}, {h}, {w}] to match `position` "
                f"{_shape(pos)}, got {_shape(t)}"
            )
        if t.device != pos.device:
            raise ValueError(f"GBuffer: `{name}` is on {t.device} but `position` is on {pos.device}")

    def _check_material(self, name: str, value):
        where = f"GBuffer: material[{name!r}]"
        if isinstance(value, bool) or not isinstance(value, (numbers.Real, Tensor)):
            raise TypeError(
                f"{where} must be a [B, C, H, W] tensor, a 0-d tensor or a float, got {type(value).__name__}"
            )
        if isinstance(value, numbers.Real):
            return float(value)
        if not value.is_floating_point():
            raise TypeError(f"{where} must be floating point, got dtype {value.dtype}")
        if value.device != self.position.device:
            raise ValueError(f"{where} is on {value.device} but `position` is on {self.position.device}")
        if value.dim() == 0:
            return value
        b, _, h, w = self.position.shape
        allowed: tuple[int, ...]
        if name in COLOR_PARAMS:
            allowed = (3,)
        elif name in PRINCIPLED_SCALAR_PARAMS:
            allowed = (1,)
        else:
            allowed = (1, 3)
        ok = (
            value.dim() == 4
            and value.shape[0] in (1, b)
            and value.shape[1] in allowed
            and value.shape[2] in (1, h)
            and value.shape[3] in (1, w)
        )
        if not ok:
            c = "/".join(str(a) for a in allowed)
            raise ValueError(
                f"{where} must have shape [{b}, {c}, {h}, {w}] (batch and H, W of 1 broadcast), "
                f"got {_shape(value)}"
            )
        return value

    # ------------------------------------------------------------------ properties
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(B, H, W)``."""
        b, _, h, w = self.position.shape
        return (b, h, w)

    @property
    def batch_size(self) -> int:
        """``B``."""
        return self.position.shape[0]

    @property
    def height(self) -> int:
        """``H``."""
        return self.position.shape[2]

    @property
    def width(self) -> int:
        """``W``."""
        return self.position.shape[3]

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of ``position`` (the shader's output dtype)."""
        return self.position.dtype

    @property
    def device(self) -> torch.device:
        """Device of ``position``."""
        return self.position.device

    # ------------------------------------------------------------------ conversions
    def _map(self, fn) -> "GBuffer":
        def conv(t):
            return fn(t) if isinstance(t, Tensor) else t

        return GBuffer(
            position=conv(self.position),
            normal=conv(self.normal),
            camera_position=conv(self.camera_position),
            material={k: conv(v) for k, v in self.material.items()},
            tangent=conv(self.tangent),
            mask=conv(self.mask),
        )

    def detach(self) -> "GBuffer":
        """A copy with every tensor detached from autograd."""
        return self._map(lambda t: t.detach())

    def to(self, *args: Any, **kwargs: Any) -> "GBuffer":  # Any: whatever Tensor.to accepts
        """``Tensor.to`` applied to every tensor (a boolean mask keeps its dtype)."""

        def conv(t):
            if t.dtype == torch.bool:
                dev = next((a for a in args if isinstance(a, (str, torch.device))), kwargs.get("device"))
                return t if dev is None else t.to(dev)
            return t.to(*args, **kwargs)

        return self._map(conv)

    def replace(self, **changes: Any) -> "GBuffer":  # Any: each field has its own type
        """A copy with some fields replaced (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)
