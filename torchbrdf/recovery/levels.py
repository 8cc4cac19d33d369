"""The capture at one resolution (:class:`LevelData`) and the fit's log residuals.

Also the photometric-stereo start and the forward-mode helper the residual Jacobians use.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.brdf import capture_residual
from torchbrdf.capture.format import Capture, pixel_points
from torchbrdf.brdf.formula import ggx_albedos
from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx
from torchbrdf.capture.synthetic import log_residual_points, log_residual_points_jvp, render_capture
from torchbrdf.recovery.params import decode, decode_directions, decode_jvp, decode_pattern, decode_slots


class LevelData:
    """Images, geometry and log-targets of a capture at one resolution."""

    def __init__(self, cap: Capture, size: int, train_idx: list[int], eps: float):
        img = cap.images
        if img.shape[-1] != size or img.shape[-2] != size:
            img = F.interpolate(img, size=(size, size), mode="area")
        self.size: int = size  # (a pixel subset, see subset, has no image layout: size 0)
        self.images: Tensor | None = img  # (L, 3, S, S); None on a pixel subset
        self._obs: Tensor | None = img.permute(0, 2, 3, 1).reshape(img.shape[0], -1, 3)  # (L, P, 3)
        self.points = pixel_points(size, size, device=img.device, dtype=img.dtype).reshape(-1, 3)
        # A pixel subset's level and its pixels there (subset): its targets are gathered from
        # the level's, its observations only when asked for.
        self._level: LevelData | None = None
        self._rows: Tensor | None = None
        self.camera = cap.camera_position
        self.pos, self.inten = cap.light_positions, cap.light_intensities
        self.inten_stated = cap.light_intensities  # capture.json's; self.inten carries the estimated scales
        self.pos_stated = cap.light_positions  # capture.json's; self.pos carries the estimated offsets
        self.eps = eps
        self._log_obs: Tensor | None = torch.log(torch.clamp(self._obs + eps, min=0.5 * eps))
        self.train_idx = list(train_idx)
        self._log_targets: dict[tuple, Tensor] = {}  # light-set tuple -> log targets (P, L, 3)

    def _gathered(self, name: str) -> Tensor:
        """``obs`` or ``log_obs``: a subset's are its level's at its pixels, gathered when first asked for."""
        value = getattr(self, "_" + name)
        if value is None:
            assert self._level is not None and self._rows is not None
            value = getattr(self._level, name)[:, self._rows]
            setattr(self, "_" + name, value)
        return value

    @property
    def obs(self) -> Tensor:
        """Observed radiance ``(L, N, 3)`` under every light (N = P on a full level)."""
        return self._gathered("obs")

    @obs.setter
    def obs(self, value: Tensor) -> None:
        self._obs = value

    @property
    def log_obs(self) -> Tensor:
        """``log(max(obs + eps, eps / 2))``, ``(L, N, 3)``: the targets of the log residuals."""
        return self._gathered("log_obs")

    @log_obs.setter
    def log_obs(self, value: Tensor) -> None:  # (new targets: the cached ones go)
        self._log_obs = value
        self._log_targets = {}

    def subset(self, rows: Tensor) -> "LevelData":
        """The same capture restricted to pixels ``rows (N,)`` (its own light-geometry cache).

        ``rows``: int64 indices (repeats allowed) or a bool mask of this data's pixels.
        Nothing of the images is copied here: a light set's targets are gathered from the
        level's when first used (``(N, L, 3)`` rows of its cached ``(P, L, 3)``, a tenth of the
        time of gathering every light's observations and transposing them: 0.3 against 11 ms
        at 8600 pixels), the observations only when asked for. A subset is a view of its level
        as the level is when the subset first uses it: targets set on the level afterwards
        (``level.log_obs = ...``) reach the subsets made after, and writes into a level's
        ``obs`` or ``log_obs`` in place are not seen by its subsets (nothing here writes them).
        """
        rows = torch.as_tensor(rows, device=self.points.device)
        if rows.dtype == torch.bool:
            if rows.shape != self.points.shape[:1]:
                raise IndexError(f"LevelData.subset: a mask of shape {tuple(rows.shape)} for "
                                 f"{self.points.shape[0]} pixels")
            rows = rows.nonzero()[:, 0]
        sub = LevelData.__new__(LevelData)
        sub.__dict__.update(self.__dict__)
        sub.size, sub.images = 0, None  # no image layout: a pixel list
        # (a subset of a subset gathers from the level too, unless it has observations of its own)
        if self._level is None or self._rows is None or self._obs is not None or self._log_obs is not None:
            sub._level, sub._rows = self, rows
        else:
            sub._level, sub._rows = self._level, self._rows[rows]
        sub._obs = sub._log_obs = None
        sub.points = self.points[rows]
        sub._log_targets = {}
        return sub

    def set_light_scale(self, log_scale: Tensor | None) -> None:
        """Use intensities ``stated × exp(log_scale)`` (``log_scale (L,)``; None: as stated)."""
        scale = 1.0 if log_scale is None else torch.exp(log_scale)[:, None]
        self.inten = self.inten_stated * scale

    def set_light_offset(self, offset: Tensor | None) -> None:
        """Use positions ``stated + offset`` (``offset (L, 3)``; None: as stated)."""
        pos = self.pos_stated if offset is None else self.pos_stated + offset
        if not torch.equal(pos, self.pos):
            self.pos = pos

    def residual(self, theta: Tensor, metal: Tensor, idx: list[int], model: str = "principled",
                 rows: Tensor | slice | None = None) -> Tensor:
        """Log residuals ``(N, len(idx) * 3)`` on lights ``idx``.

        ``theta (N, 7)`` and ``metal (N, 1)`` are every pixel's (``N = P``), or, with
        ``rows`` (pixel indices ``(N,)``, repeats allowed, or a slice), those of the listed pixels.
        """
        points, log_obs = self._targets(idx, rows)
        r = log_residual(decode(theta, metal), points, self.camera, self.pos[idx], self.inten[idx], log_obs,
                         self.eps, model)
        return r.reshape(theta.shape[0], 3 * len(idx))  # (an explicit width: N may be 0)

    def data_cost(self, theta: Tensor, metal: Tensor, idx: list[int], model: str = "principled",
                  rows: Tensor | slice | None = None) -> Tensor | None:
        """Each pixel's summed squared :meth:`residual` ``(N, 1)`` from the fused cost kernel, or None.

        Arguments as for :meth:`residual`. The squares are summed in float64 per pixel (a float32
        sum rounds less than ``(r * r).sum(-1)``) and a non-finite sum is +inf (``pixel_cost``'s
        rule), in ``theta``'s dtype, on its device, without the ``(N, 3 len(idx))`` residuals in
        memory (:func:`torchbrdf.brdf.capture_residual.data_cost`), for either model. None where
        that kernel does not apply (no fused path for this dtype or device).
        """
        points, log_obs = self._targets(idx, rows)
        p = decode(theta, metal)
        return capture_residual.data_cost(p["normal"], points, self.camera, self.pos[idx], self.inten[idx], p,
                                          log_obs, self.eps, model)

    def residual_jvp(self, x: Tensor, metal: Tensor, idx: list[int], model: str, tangents: Tensor,
                     rows: Tensor | slice | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`residual` and its derivatives along ``K`` directions of the unknowns at once.

        ``x (N, 7)``: theta; or ``(N, 8)``: theta and a continuous metallic (``metal`` is then
        unused); ``tangents (K, N, x's columns)``; ``metal``, ``idx``, ``model``, ``rows`` as for
        :meth:`residual`. Returns ``(r (N, M), dr (K, N, M))``, ``M = 3 len(idx)``, ``dr[k]``
        = ``torch.func.jvp`` of :meth:`residual` along ``tangents[k]``, in ``x``'s dtype, on its
        device. Either model evaluates them in one call of the fused operators
        (:func:`log_residual_points_jvp`, :func:`decode`'s tangents in closed form by
        :func:`decode_jvp`).
        """
        points, log_obs = self._targets(idx, rows)
        # (a parameter the directions do not move has a zero tangent: the kernel drops it)
        p, dp = decode_jvp(x, metal, tangents)
        r, dr = log_residual_points_jvp(p["normal"], points, self.camera, self.pos[idx], self.inten[idx], p,
                                        log_obs, self.eps, dp, any_size=True, family=model)
        m = 3 * len(idx)
        return r.reshape(x.shape[0], m), dr.reshape(tangents.shape[0], x.shape[0], m)

    def normal_equations(self, x: Tensor, metal: Tensor, idx: list[int], model: str, n_t: int,
                         rows: Tensor | slice | None = None
                         ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """:meth:`residual` and its per-pixel Gauss–Newton terms in one fused pass, or None.

        ``x``, ``metal``, ``idx``, ``model``, ``rows`` as for :meth:`residual_jvp`; ``n_t``: the
        unknowns differentiated, the first 7 (theta) or 8 (and the continuous metallic) columns
        of ``x``. Returns ``(r (N, M), cost (N,), JᵀJ (N, n_t, n_t), Jᵀr (N, n_t))`` (the
        residuals and their summed squares as they come, non-finite Jacobian entries and
        residuals counted as 0 in ``JᵀJ`` and ``Jᵀr``), in ``x``'s dtype, on its device: the
        decode's tangents in closed form (:func:`decode_directions`, three directions:
        :func:`decode_slots`), then one
        light-loop kernel (:func:`torchbrdf.brdf.capture_residual.normal_equations`), for either
        model. None where that kernel does not apply (no fused path for this dtype or device).
        """
        points, log_obs = self._targets(idx, rows)
        p, dp = decode_directions(x, metal, decode_slots(n_t))
        pattern = decode_pattern(n_t)
        return capture_residual.normal_equations(p["normal"], points, self.camera, self.pos[idx], self.inten[idx],
                                                 p, log_obs, self.eps, {k: dp[k] for k in pattern}, pattern, n_t,
                                                 model)

    def log_targets(self, idx: list[int], rows: Tensor | None = None) -> Tensor:
        """The log targets ``(N, len(idx), 3)`` on lights ``idx`` of pixels ``rows (N,)`` (int64;
        None: every pixel), gathered from the light set's cached ``(P, L, 3)``."""
        return self._targets(idx, rows)[1]

    def _targets(self, idx: list[int], rows: Tensor | slice | None) -> tuple[Tensor, Tensor]:
        """The pixels' points ``(N, 3)`` and log targets ``(N, L, 3)`` on lights ``idx``;
        ``rows`` as for :meth:`residual`."""
        key = tuple(idx)
        log_obs = self._log_targets.get(key)
        if log_obs is None:  # per light set, once
            if self._log_obs is None and self._level is not None and self._rows is not None:
                log_obs = self._level._targets(idx, None)[1][self._rows]  # a subset: its level's, gathered
            else:
                log_obs = self.log_obs[idx].permute(1, 0, 2).contiguous()  # (P, L, 3)
            self._log_targets[key] = log_obs
        points = self.points
        if isinstance(rows, Tensor) and rows.dtype != torch.bool:
            # (index_select copies whole rows: a quarter of the time of indexing, 7 against 28 ms
            # for 147456 rows of 16 lights)
            points, log_obs = points.index_select(0, rows), log_obs.index_select(0, rows)
        elif rows is not None:
            points, log_obs = points[rows], log_obs[rows]
        return points, log_obs


def log_residual(p: dict, points: Tensor, camera: Tensor, pos: Tensor, inten: Tensor, log_obs: Tensor,
                 eps: float, model: str = "principled") -> Tensor:
    """The fit's log residuals ``(N, L, 3)``: ``log(max(pred + ε, ε/2)) − log_obs``.

    ``p`` the decoded maps of ``N`` pixels at ``points (N, 3)``, lights at ``pos (L, 3)`` with
    ``inten (L, 3)``, ``log_obs (N, L, 3)``, all of one dtype and device (the result's); ``model``
    ``"principled"`` or ``"svbrdf_ggx"`` (the same maps rendered by the GGX model,
    :func:`torchbrdf.brdf.formula.ggx_albedos`). One fused evaluation
    (:func:`log_residual_points`), at every size (``any_size``): one engine for the whole fit,
    whose first full-size call compiles the kernels anyway. Differentiable w.r.t. every tensor
    input, in reverse and forward mode.
    """
    return log_residual_points(p["normal"], points, camera, pos, inten, p, log_obs, eps, any_size=True, family=model)


def render_fit(maps: dict, lights: Any, camera: Tensor, model: str = "principled") -> Tensor:
    """The images ``(L, 3, H, W)`` a fit's maps ``(C, H, W)`` predict under ``lights`` (as
    :func:`render_capture` takes them), rendered by the fit's ``model``: what its held-out and
    per-image PSNRs compare with the capture."""
    if model == "principled":
        return render_capture(maps, lights, camera, backend="compact")
    return render_capture(maps, lights, camera, brdf=_ggx_on_maps)


def _ggx_on_maps(l: Tensor, v: Tensor, n: Tensor, x: Tensor | None = None, y: Tensor | None = None,
                 **maps: Tensor) -> Tensor:
    """The recovery's GGX model on principled maps (``render_capture``'s ``brdf``)."""
    return svbrdf_ggx(l, v, n, **ggx_albedos(maps), roughness=maps["roughness"])


def photometric_stereo(data: LevelData, idx: list[int], drop: int = 3) -> tuple[Tensor, Tensor]:
    """Lambertian normals ``(P, 3)`` and albedo ``(P, 3)``, the ``drop`` brightest lights ignored."""
    pts = data.points
    dl = data.pos[idx][:, None] - pts[None]  # (L, P, 3)
    d2 = (dl * dl).sum(-1, keepdim=True)
    l = dl / d2.sqrt()
    e = data.inten[idx].mean(-1)[:, None, None] / d2  # (L, P, 1) irradiance at normal incidence
    obs = data.obs[idx]  # (L, P, 3)
    lum = obs.mean(-1, keepdim=True)
    y = lum / e  # = l · b,  b = albedo n / π
    w = torch.ones_like(y)
    if len(idx) - drop >= 4:
        order = torch.argsort(y, dim=0, descending=True)
        w.scatter_(0, order[:drop], 0.0)
    lt = l.permute(1, 0, 2)  # (P, L, 3)
    wt, yt = w.permute(1, 0, 2), y.permute(1, 0, 2)
    a = torch.einsum("pli,plj->pij", lt * wt, lt) + 1e-6 * torch.eye(3, dtype=pts.dtype, device=pts.device)
    bvec = torch.einsum("pli,plk->pi", lt * wt, yt)
    b = torch.linalg.solve(a, bvec)
    n = b / b.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    n = torch.where(n[:, 2:3] > 0.2, n, torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype, device=n.device))
    n = n / n.norm(dim=-1, keepdim=True)
    shade = (e * torch.clamp((l * n[None]).sum(-1, keepdim=True), min=0) / math.pi)  # (L, P, 1)
    alb = (w * shade * obs).sum(0) / (w * shade * shade).sum(0).clamp(min=1e-8)
    return n, alb.clamp(0.02, 0.98)


def vmapped_jvp(fn: Callable[[Tensor], Any]) -> Callable[[Tensor, Tensor], tuple[Any, Any]]:
    """``torch.func.jvp`` of ``fn`` vmapped over the directions (the primal computed once).

    Returns ``jvp(x, tangents (K, *x.shape)) -> (fn(x), derivatives (K, *fn(x).shape))`` (for
    an ``fn`` returning a dict of tensors, dicts of them).
    """
    out_dims: Any = (None, 0)  # the primal is not batched over the directions

    def jvp(x: Tensor, tangents: Tensor) -> tuple[Any, Any]:
        pair: Any = torch.func.vmap(lambda tg: torch.func.jvp(fn, (x,), (tg,)), out_dims=out_dims)(tangents)
        return pair

    return jvp
