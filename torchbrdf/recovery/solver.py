"""SVBRDF recovery: the algorithm (capture in, per-pixel principled maps out).

``python -m training.recover_svbrdf --capture DIR --out DIR`` (or ``--demo``) fits per-pixel
principled maps — base colour, roughness, metallic, specular, normal — so that the capture format's
image formation reproduces every captured image.

Method (each choice measured, see ``docs/recovery.md``):

* **Parameters in unconstrained spaces**: logits for base colour, specular and roughness, a
  2-D slope ``(p, q)`` for the normal (``n ∝ (p, q, 1)``, always z > 0). Metallic is not a
  continuous unknown: each pixel is either dielectric or metal (two *starts*, below), so
  a metallic that should be 0 is exactly 0 — no sigmoid started at 0.1.
* **Photometric-stereo initialisation** of normals and albedo (Lambertian least squares,
  the brightest observations of each pixel dropped as likely highlights).
* **Loss in log space**: ``log(pred + ε) − log(obs + ε)``, which matches 1 % relative noise
  and keeps highlights (radiance > 50) from dominating the dark pixels.
* **Per-pixel Levenberg–Marquardt** (Gauss–Newton with per-pixel damping; the Jacobian by
  forward-mode AD, ``torch.func.jvp``): pixels are independent except through the priors, so
  the normal equations are one 7×7 block per pixel plus the prior's sparse Laplacian, solved
  by conjugate gradients on the prior-joined channels (the others eliminated per pixel).
  At most 39 iterations in the default schedule: a full-resolution stage ends once an
  iteration changes its fit loss by less than 1 % (``converge_tol``).
  A step that raises a pixel's
  cost — or makes it non-finite — is rejected for that pixel and its damping raised (step
  back, smaller step); a non-finite total loss also halves the global step (``--lr``).
* **Coarse to fine** (S/4, S/2, S): cheap levels settle the metal/dielectric choice and the
  low frequencies; the full level only refines.
* **Metal/dielectric: two starts**, a dielectric (metallic 0) and a metal (metallic 1)
  hypothesis fitted side by side; a pixel is metal when its cost on the training lights
  *plus a held-out captured light* (a light the fit never saw) is below half the
  dielectric's, dielectric when above twice it; the pixels in between, which the data
  cannot decide, take their neighbours' class (a few ICM sweeps), then isolated choices are
  removed.
* **Propagation and search** (PatchMatch-style, between LM iterations): each pixel tries
  its 8 neighbours' parameters — same class, or the other class under the same margin
  rule — and keeps them when they lower its data cost plus prior; pixels still fitting
  far worse than the noise level try a grid of normals (tilts up to 40°) combined with
  their own and their neighbours' parameters. Gauss–Newton only walks downhill: this is
  what finds the highlight of a steep inlay rim whose normal starts 30° off.
* **Spatial priors**: roughness and specular are tied to their 4-neighbours of the same
  class, weighted by albedo similarity (``exp(-|Δbase|²/σ²)``), which fills in the glossy
  pixels whose highlight no light hits. The prior couples pixels, so each LM step solves
  the whole sparse system (per-pixel 7×7 blocks + the prior's weighted Laplacian) by
  block-preconditioned conjugate gradients: a weakly observed region moves as a whole
  instead of being held at its start value by frozen neighbours (a Jacobi prior kept tiles'
  grout at roughness 0.74 instead of 0.85).
* **Non-local fusion of a metal's F0** (after the last iteration): each metal pixel's base
  colour is fused with the average of the metal pixels within a large Gaussian window
  (weighted by their shrinkage ``info / (info + κ)`` and by their fit, ``min(1, w · median
  cost / cost)`` with ``w = nonlocal_fit_weight`` and the median over the metal pixels: a
  pixel the model fits k× worse is 1/k the evidence),
  by precisions — its own marginal information ``info = 1/diag((JᵀJ)⁻¹)`` against a fixed
  ``κ = prior_nonlocal_base``;
  pixels far from every highlight (low information) take the average, the well-observed
  ones keep their own value.
* **Refit before the class choice**: where the metal hypothesis wins but the dielectric never
  converged (a narrow structure the coarse levels blended, such as tiles' half-width grout at
  the image edge), the dielectric is refitted per pixel from the metal's geometry first — a
  metal's win is evidence only against a converged dielectric. Class votes count only the
  neighbours a pixel has (5 on an edge, 3 in a corner), not padded copies of itself.
* **Per-light intensity scales** (calibration error) are estimated jointly with the maps, the
  training lights' geometric mean held at the stated intensities.
* **Non-local fill** (before the last stage): under-determined roughness / specular get a
  unary prior toward the reliability-weighted value of same-material pixels found anywhere
  in the image (base colour and normal-spread similarity).
* **Confidence** (``Recovery.confidence_map``): the posterior variance of roughness and
  specular from the marginal information, mapped to [0, 1].
* **Validation**: the held-out light's PSNR is reported (``report.json``:
  ``validation_psnr``); the last iterations then use every light.

Checkpoints (``OUT/checkpoint.pt``, written atomically) every ``--checkpoint-every``
iterations and on SIGINT/SIGTERM; ``--resume`` continues bit-for-bit where the run stopped.
Maps are never written with non-finite values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from torchbrdf.capture.format import Capture, pixel_points
from torchbrdf.capture.synthetic import (light_geometry, log_residual_points, log_residual_points_jvp,
                                         render_capture)
from torchbrdf.io import atomic_path
from torchbrdf.recovery.smoothness_prior import edge_weights, laplacian, laplacian_diag, local_prior, pcg, prior_energy

__all__ = ["RecoveryConfig", "Recovery", "psnr", "CHECKPOINT"]

CHECKPOINT = "checkpoint.pt"
_N_PARAMS = 7  # logit base (3), logit specular, logit roughness, slope p, slope q
_R_MIN, _R_MAX = 0.03, 1.0  # roughness range the logit maps onto (alpha floor is 1e-3)


@dataclass
class RecoveryConfig:
    """Options of :func:`recover` (the CLI flags)."""

    iters: int = 0  # 0: default schedule; otherwise total LM iterations, spread over levels
    lr: float = 1.0  # LM step multiplier
    size: int | None = None  # working resolution (default: the capture's)
    seed: int = 0
    device: str = "cpu"
    levels: int = 3
    prior_roughness: float = 0.002
    prior_specular: float = 0.002
    prior_sigma: float = 0.1
    prior_metal_base: float = 0.02
    metal_base_guided: bool = True  # ... × the base-colour guide (prior_sigma) of the other ties
    propagate: bool = True  # PatchMatch-style neighbour propagation (see propagate)
    propagate_passes: int = 6  # passes at the start of each stage (one pixel further per pass)
    propagate_every: bool = True  # and one pass before every LM iteration of the single-hypothesis stages
    cg_iters: int = 30  # conjugate-gradient iterations per LM step (the coupled prior)
    # A full-resolution stage ends early once an iteration changes its fit loss (a dual stage's: of
    # each pixel's better hypothesis) by less than this fraction (0: run every planned iteration),
    # after at least converge_min_iters of its iterations (Recovery._converged).
    converge_tol: float = 0.01
    converge_min_iters: int = 2
    fill: bool = False  # non-local fill of roughness / specular (nonlocal_fill; measured, not kept: docs)
    fill_sigma: float = 0.05  # its width in map units (and the reliability tolerance)
    fill_weight: float = 1.0  # its precision, × sigma² / fill_sigma²
    fill_range: float = 0.04  # base-colour similarity scale
    fill_texture: float = 0.05  # normal-spread similarity scale (slope units)
    fill_candidates: int = 256  # random same-class candidates per pixel
    fill_min_similar: float = 2.0  # fewer similar candidates (summed similarity): no fill
    refit_before_choice: bool = True  # refit unconverged dielectric pixels before calling them metal
    # Full resolution, after the class choice: a dielectric at the glossy end (roughness below
    # rough_tie_glossy) is moved to the rough basin (refitted with its roughness held at
    # rough_tie_start) where that fits its data within rough_tie noise variances of the glossy fit
    # (rough_basin_tie; 0: off). The images cannot tell a glossy dielectric whose highlights fall
    # between the lights from a rough one (dust specks: two basins at the same cost); the rough
    # basin is the wider one (dusty_metal 3 roughness RMSE 0.0762 -> 0.0443; docs/recovery.md,
    # issue 18)
    rough_tie: float = 2.0
    rough_tie_glossy: float = 0.1
    rough_tie_start: float = 0.85
    # The same in the final stage (soft_rough_tie), with metallic free: a glossy (roughness below
    # soft_rough_tie_glossy) dielectric or fractional pixel among its candidates and grown pixels
    # takes a rough fit (started at rough_tie_start) within soft_rough_tie noise variances (0: off).
    # A rough rim, partly metal, fits as well as a glossy dielectric whose lobe falls between the
    # lights, and shows as a firefly under another light (dusty_metal 162: worst held-out light 24.6
    # -> 45.4 dB; docs, issue 18)
    soft_rough_tie: float = 2.0
    soft_rough_tie_glossy: float = 0.2
    light_position: bool = True  # with light_scale: also a per-light position offset (prior 1 cm)
    light_scale: bool = True  # estimate each light's intensity scale (False: no light estimate at all)
    # Start the estimates in the two-hypothesis stages (positions: the full-resolution one; False:
    # both from the single-class stages on)
    dual_calibration: bool = True
    # ... the intensity scales from the coarsest two-hypothesis level on (False: from the
    # full-resolution one). Coarse levels fitted under the stated intensities put a light's error
    # into the maps, and a rough region taken into the low-specular, glossy valley there stays in
    # it (photo gravel 1 with calibration error: roughness RMSE 0.062 -> 0.023; docs, issue 13)
    dual_calibration_coarse: bool = True
    # ... in the full-resolution two-hypothesis stage also the position of a light beside the camera
    # (a flash, camera_lights; False: from the single-class stages on). The least determined
    # position (10x the ring lights' posterior deviation), it took up what the two-hypothesis maps
    # had not yet fitted on a capture without calibration error (rusted_metal 4: 2.1 cm off, base
    # RMSE 0.0215; 0.0176 held there) but held, a real error of it stays (held-out photo coffee
    # 101: roughness 0.049 -> 0.065): measured, not kept (docs/recovery.md, issue 18, "The flash's
    # position")
    dual_calibration_at_camera: bool = True
    # The non-local F0 average (nonlocal_prior) as a unary prior of the fit itself from the polish
    # stage on (renewed at each single-class stage's start), not only fused at the end: the joint
    # light step then sees a weakly observed metal's F0 held by the well-measured metal instead of
    # free along the F0-roughness valley (rusted_metal 4 base RMSE 0.0215 -> 0.0113; docs, issue 18)
    fit_nonlocal_tie: bool = True
    light_joint: bool = True  # step the lights with the maps eliminated (False: alternating steps)
    metal_margin: float = 0.5  # a pixel is metal when its metal cost < margin x dielectric cost
    prior_nonlocal: float = 0.0  # precision of the non-local roughness prior (0: off; measured worse)
    prior_nonlocal_base: float = 0.003  # precision of the non-local prior on a metal's base colour
    nonlocal_range: float = 0.02  # base-colour range sigma of the non-local roughness prior
    nonlocal_sigma: float = 0.25  # its spatial radius, as a fraction of the map size
    nonlocal_clusters: int = 12  # base-colour clusters per class guiding it
    # A metal pixel's weight in the non-local F0 average, × min(1, this × the median metal pixel's
    # cost / its cost): a pixel the model fits k× worse than that says 1/k as much (0: off)
    nonlocal_fit_weight: float = 1.0
    fuse_refit_iters: int = 3  # LM iterations taking a fused metal's other unknowns to the fused F0 (0: off)
    # Rounds of the fusion, each round's average from the last one's result (each combined with
    # the same own value): a pixel's one-step estimate of its own F0 optimum is better from a
    # point nearer it (rusted_metal 1 / 6 / 7 base colour 0.0206 / 0.0204 / 0.0179 with 1 round,
    # 0.0170 / 0.0156 / 0.0148 with 3; docs). With the tie in the fit (fit_nonlocal_tie) a third
    # round moves no unknown by more than 3e-5 and changes no tuning capture's maps by more than
    # 0.0003 RMSE: two.
    fuse_rounds: int = 2
    # Final step: continuous metallic where the binary choice fits poorly (Recovery._soft_metal)
    soft_metal: bool = True
    soft_metal_factor: float = 8.0  # ... for pixels whose cost is above this × the median (and boundaries)
    soft_metal_well: float = 32.0  # double-well prior w m²(1−m)², w in per-residual noise variances σ²
    soft_metal_gain: float = 8.0  # keep a fractional value only if it lowers the cost by this × σ²
    soft_metal_smooth: float = 64.0  # second pass: pull toward the neighbours' metallic (× σ²)
    soft_metal_band: int = 2  # ... and pixels within this many pixels of a class boundary (or colour step)
    soft_metal_iters: int = 5  # per-pixel LM iterations
    soft_metal_max: float = 0.35  # at most this fraction of the pixels (the worst fitting) are candidates
    # ... and metal pixels within the band of a base-colour step this large, or this far from
    # the mean colour of the metal around them (σ = the far blend width, BLEND_SIGMAS)
    soft_metal_edge: float = 0.15
    soft_metal_context: float = 0.25  # the gain, × this, beside a fractional pixel (second pass, growth)
    soft_metal_passes: int = 2  # second-pass rounds, each from the neighbours' metallic of the round before
    soft_metal_grow: int = 3  # rounds of refitting the untried pixels beside a run of fractional ones
    # Pull (× σ²) toward the metallic that explains a candidate or grown pixel as a blend of the
    # nearest clear metal and clear dielectric (unmix_metallic), which also starts a candidate's
    # fit; 0: off, start at ½
    soft_metal_unmix: float = 128.0
    # A candidate whose blend is its own class and whose data cost is at most this × the median
    # pixel's (the noise level; 1.5: the 98.5th percentile of 51 residuals' noise) is left out of
    # the stage's metallic fits and growth: nothing in its data asks for a mixture (may_be_mixed;
    # with unmixing only; 0: off). The glossy/rough tie still tests it.
    soft_metal_quiet: float = 1.5
    # Last, the fractional pixels' base colour is tied (× σ² per unit²) to the blend of the clear
    # ends beside them at their own metallic (soft_metal_fit's ``line``); 0: off. 2500 = 1/0.02²:
    # the ends are local means of clear pixels, known to about 0.02.
    soft_metal_line: float = 2500.0
    holdout: int | None = None  # index of the validation light (default: light 0 with 5+ lights; -1: none)
    checkpoint_every: int = 5
    model: str = "principled"
    threads: int | None = None
    fault_at: int | None = None  # testing: inject a NaN into the parameters at this iteration
    signal_at: int | None = None  # testing: send ourselves SIGTERM after this iteration
    schedule: list = field(default_factory=list)


# --------------------------------------------------------------------------------------
# Parametrisation
# --------------------------------------------------------------------------------------


def _logit(x: Tensor, lo=0.0, hi=1.0, eps=1e-4) -> Tensor:
    t = ((x - lo) / (hi - lo)).clamp(eps, 1 - eps)
    return torch.log(t) - torch.log1p(-t)


def decode(theta: Tensor, metal: Tensor) -> dict:
    """Principled parameters ``(P, C)`` from unconstrained ``theta (P, 7)`` and ``metal (P, 1)``."""
    s = torch.sigmoid(theta[:, 0:5])  # one op for the five logits (decode runs ~700 times a fit)
    # (no arithmetic with Python numbers: under vmap of jvp, as the fit's Jacobian runs it, each
    # such op takes a decomposition's slow path; this form halves that call's fixed cost)
    lo, hi = (torch.full((1,), v, dtype=theta.dtype, device=theta.device) for v in (_R_MIN, _R_MAX))
    rough = torch.lerp(lo, hi, s[:, 4:5])  # (filled on the device: no copy from the host, no sync)
    n = F.pad(theta[:, 5:7], (0, 1), value=1.0)
    n = n * torch.rsqrt((n * n).sum(-1, keepdim=True))
    return {"base_color": s[:, 0:3], "specular": s[:, 3:4], "roughness": rough, "metallic": metal,
            "normal": n}


def encode(params: dict) -> Tensor:
    """Inverse of :func:`decode` for ``(P, C)`` parameter tensors."""
    n = params["normal"]
    nz = n[:, 2:3].clamp(min=0.05)
    return torch.cat(
        (
            _logit(params["base_color"]),
            _logit(params["specular"]),
            _logit(params["roughness"], _R_MIN, _R_MAX),
            n[:, 0:1] / nz,
            n[:, 1:2] / nz,
        ),
        -1,
    )


# --------------------------------------------------------------------------------------
# Data at one level
# --------------------------------------------------------------------------------------


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
        self._light: dict[tuple, dict] = {}  # light-set tuple -> light_geometry (not the principled's)

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
        sub._log_targets, sub._light = {}, {}
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
            self._light = {}  # the cached light geometry depends on the positions

    def residual(self, theta: Tensor, metal: Tensor, idx: list[int], model: str = "principled",
                 rows: Tensor | slice | None = None) -> Tensor:
        """Log residuals ``(N, len(idx) * 3)`` on lights ``idx``.

        ``theta (N, 7)`` and ``metal (N, 1)`` are every pixel's (``N = P``), or, with
        ``rows`` (pixel indices ``(N,)``, repeats allowed, or a slice), those of the listed pixels.
        """
        points, log_obs, light = self._targets(idx, model, rows)
        r = log_residual(decode(theta, metal), points, self.camera, self.pos[idx], self.inten[idx], log_obs,
                         self.eps, model, light)
        return r.reshape(theta.shape[0], -1)

    def residual_jvp(self, x: Tensor, metal: Tensor, idx: list[int], model: str, tangents: Tensor,
                     rows: Tensor | slice | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`residual` and its derivatives along ``K`` directions of the unknowns at once.

        ``x (N, 7)``: theta; or ``(N, 8)``: theta and a continuous metallic (``metal`` is then
        unused); ``tangents (K, N, x's columns)``; ``metal``, ``idx``, ``model``, ``rows`` as for
        :meth:`residual`. Returns ``(r (N, M), dr (K, N, M))``, ``M = 3 len(idx)``, ``dr[k]``
        = ``torch.func.jvp`` of :meth:`residual` along ``tangents[k]``, in ``x``'s dtype, on its
        device. The principled model evaluates them in one call of the fused operators
        (:func:`log_residual_points_jvp`, :func:`decode`'s own tangents by ``torch.func``); the
        others through ``torch.func``.
        """
        def unknowns(v: Tensor) -> tuple[Tensor, Tensor]:
            return (v[:, :7], v[:, 7:8]) if v.shape[1] == 8 else (v, metal)

        if model != "principled":
            return _vmapped_jvp(lambda v: self.residual(*unknowns(v), idx, model, rows))(x, tangents)
        points, log_obs, _ = self._targets(idx, model, rows)
        # (a parameter the directions do not move has a zero tangent: the kernel drops it)
        p, dp = _vmapped_jvp(lambda v: decode(*unknowns(v)))(x, tangents)
        r, dr = log_residual_points_jvp(p["normal"], points, self.camera, self.pos[idx], self.inten[idx], p,
                                        log_obs, self.eps, dp, any_size=True)
        return r.reshape(x.shape[0], -1), dr.reshape(tangents.shape[0], x.shape[0], -1)

    def _targets(self, idx: list[int], model: str, rows: Tensor | slice | None
                 ) -> tuple[Tensor, Tensor, dict | None]:
        """The pixels' points ``(N, 3)``, log targets ``(N, L, 3)`` and light geometry.

        On lights ``idx``; the geometry only for models other than the principled (else None);
        ``rows`` as for :meth:`residual`.
        """
        key = tuple(idx)
        log_obs = self._log_targets.get(key)
        if log_obs is None:  # per light set, once
            if self._log_obs is None and self._level is not None and self._rows is not None:
                # a subset: its level's, gathered (asked for as the principled model's: no geometry)
                log_obs = self._level._targets(idx, "principled", None)[1][self._rows]
            else:
                log_obs = self.log_obs[idx].permute(1, 0, 2).contiguous()  # (P, L, 3)
            self._log_targets[key] = log_obs
        light = None
        if model != "principled":  # the geometry the other models render with, per light set once
            if key not in self._light:
                self._light[key] = light_geometry(self.points, self.camera, self.pos[idx])
            light = self._light[key]
        points = self.points
        if rows is not None:
            points, log_obs = points[rows], log_obs[rows]
        if rows is not None and light is not None:
            light = {"v": light["v"][rows], "l": light["l"][:, rows], "inv_d2": light["inv_d2"][:, rows]}
        return points, log_obs, light


def log_residual(p: dict, points: Tensor, camera: Tensor, pos: Tensor, inten: Tensor, log_obs: Tensor,
                 eps: float, model: str = "principled", light: dict | None = None) -> Tensor:
    """The fit's log residuals ``(N, L, 3)``: ``log(max(pred + ε, ε/2)) − log_obs``.

    ``p`` the decoded maps of ``N`` pixels at ``points (N, 3)``, lights at ``pos (L, 3)`` with
    ``inten (L, 3)``, ``log_obs (N, L, 3)``, all of one dtype and device (the result's). For
    ``"principled"`` one fused evaluation (:func:`log_residual_points`); the other models
    render through :func:`_render_points` with ``light`` (:func:`light_geometry`, computed
    when None). Differentiable w.r.t. every tensor input, in reverse and forward mode. The
    principled residual runs on the fused kernels at every size (``any_size``): one engine for
    the whole fit, whose first full-size call compiles them anyway.
    """
    if model == "principled":
        return log_residual_points(p["normal"], points, camera, pos, inten, p, log_obs, eps, any_size=True)
    light = light_geometry(points, camera, pos) if light is None else light
    pred = _render_points(p, inten, model, light)
    return torch.log(torch.clamp(pred + eps, min=0.5 * eps)).permute(1, 0, 2) - log_obs


def _render_points(p, inten, model, light):
    """Radiance ``(L, P, 3)`` of the fit's other models (``"principled"`` goes through the fused
    :func:`log_residual_points`); ``light`` is :func:`light_geometry` of the pixels and lights."""
    if model == "svbrdf_ggx":  # the GGX model of torchbrdf.capture_model (not tuned)
        from torchbrdf.brdf.capture_model import svbrdf_ggx

        l = light["l"]
        n = p["normal"][None].expand_as(l)
        spec_alb = 0.08 * p["specular"] * (1 - p["metallic"]) + p["base_color"] * p["metallic"]
        f = svbrdf_ggx(l, light["v"][None].expand_as(l), n, diffuse_albedo=p["base_color"] * (1 - p["metallic"]),
                       specular_albedo=spec_alb, roughness=p["roughness"])
        return f * inten[:, None] * torch.clamp((n * l).sum(-1, keepdim=True), min=0) * light["inv_d2"]
    raise ValueError(f"unknown model {model!r}")


# --------------------------------------------------------------------------------------
# Photometric stereo
# --------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------
# Levenberg–Marquardt with spatial priors
# --------------------------------------------------------------------------------------


def _neighbour_mean(x: Tensor, size: int) -> Tensor:
    """Mean ``(P, C)`` of each pixel's 4-neighbours that exist (2 in a corner, 3 on an edge)."""
    img = x.T.reshape(1, -1, size, size)
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=x.dtype, device=x.device)
    s = F.conv2d(img, k.view(1, 1, 3, 3).expand(img.shape[1], 1, 3, 3), padding=1, groups=img.shape[1])
    n = F.conv2d(torch.ones_like(img[:, :1]), k.view(1, 1, 3, 3), padding=1)
    return (s / n)[0].reshape(x.shape[1], -1).T


def _blur(x: Tensor, size: int, sigma: float) -> Tensor:
    """Gaussian blur of a ``(P, C)`` map (zero padding: callers divide by a blurred weight).

    The normalised kernel is truncated at ``3 sigma`` (and at the map's size). Each separable
    pass is one product with the ``(size, size)`` banded matrix of the kernel (zero padding is
    its missing rows): the non-local windows are a quarter of the map wide, where a grouped
    convolution is 20x (float32) to 100x (float64) slower than the matrix product.
    """
    r = int(min(3 * sigma, size - 1))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype, device=x.device) / sigma) ** 2)
    i = torch.arange(size, device=x.device)
    off = i[None, :] - i[:, None]  # (size, size), symmetric band
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    band = torch.where(off.abs() <= r, (k / k.sum())[(off + r).clamp(0, 2 * r)], zero)
    c = x.shape[1]
    img = band @ (x.T.reshape(c, size, size) @ band)  # along x, then along y (band is symmetric)
    return img.reshape(c, -1).T


def _kmeans(x: Tensor, k: int, iters: int = 8, return_centres: bool = False) -> Tensor:
    """Deterministic k-means labels of ``x (N, 3)`` (farthest-point start)."""
    k = min(k, x.shape[0])
    cent = [x.mean(0)]
    d = ((x - cent[0]) ** 2).sum(-1)
    for _ in range(k - 1):
        cent.append(x[int(torch.argmax(d))])
        d = torch.minimum(d, ((x - cent[-1]) ** 2).sum(-1))
    c = torch.stack(cent)
    for _ in range(iters):
        lab = torch.cdist(x, c).argmin(-1)
        cnt = torch.zeros(k, dtype=x.dtype, device=x.device).index_add_(0, lab, torch.ones_like(x[:, 0]))
        s = torch.zeros_like(c).index_add_(0, lab, x)
        c = torch.where(cnt[:, None] > 0, s / cnt.clamp(min=1)[:, None], c)
    return c if return_centres else torch.cdist(x, c).argmin(-1)


def _vmapped_jvp(fn: Callable[[Tensor], Any]) -> Callable[[Tensor, Tensor], tuple[Any, Any]]:
    """``torch.func.jvp`` of ``fn`` vmapped over the directions (the primal computed once).

    Returns ``jvp(x, tangents (K, *x.shape)) -> (fn(x), derivatives (K, *fn(x).shape))`` (for
    an ``fn`` returning a dict of tensors, dicts of them).
    """
    out_dims: Any = (None, 0)  # the primal is not batched over the directions

    def jvp(x: Tensor, tangents: Tensor) -> tuple[Any, Any]:
        pair: Any = torch.func.vmap(lambda tg: torch.func.jvp(fn, (x,), (tg,)), out_dims=out_dims)(tangents)
        return pair

    return jvp


def fit_jacobian(jvp: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]], x: Tensor, n_t: int
                 ) -> tuple[Tensor, Tensor]:
    """Residuals and their per-pixel Jacobian by forward mode, the base colour in one direction.

    ``jvp(x, tangents (K, N, K')) -> (r (N, M), derivatives (K, N, M))``: the residuals at
    ``x (N, K')`` and their derivatives along ``K`` directions of ``x`` at once
    (:meth:`LevelData.residual_jvp`, or :func:`_vmapped_jvp` of a residual function). Returns
    ``r`` and its Jacobian ``(N, n_t, M)`` w.r.t. the first ``n_t`` (≥ 3) columns of ``x`` —
    the unknowns of :func:`decode`, base-colour logits first.

    The fit's models act on each colour channel with that channel's base colour alone (no tint:
    :func:`decode` sets none), and ``M`` interleaves the channels (light-major, ``3 l + c``), so
    one direction along all three base-colour logits gives their three columns at once, each on
    its own channel's residuals: ``n_t − 2`` directions instead of ``n_t``. Non-finite Jacobian
    entries are 0; the residuals are as they come. Both on ``x``'s device, in its dtype.
    """
    k = n_t - 2
    tan = torch.zeros(k, x.shape[1], dtype=x.dtype, device=x.device)
    tan[0, 0:3] = 1.0
    tan[1:, 3:n_t] = torch.eye(n_t - 3, dtype=x.dtype, device=x.device)
    r, cols = jvp(x, tan[:, None, :].expand(k, *x.shape))
    cols = cols.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)  # (k, N, M), a fresh tensor: in place
    channel = torch.arange(cols.shape[-1], device=x.device) % 3
    own = (channel == torch.arange(3, device=x.device)[:, None]).to(cols.dtype)  # (3, M)
    # (one buffer: torch.cat of the transposed directions copied element by element)
    jac = cols.new_empty(x.shape[0], n_t, cols.shape[-1])
    jac[:, :3] = cols[0][:, None, :] * own  # (an assignment, not out=: autograd may run through it)
    jac[:, 3:] = cols[1:].transpose(0, 1)
    return r, jac


def gauss_newton(data: "LevelData", theta: Tensor, metal: Tensor, idx: list[int], model: str,
                 chunk: int = 16384) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals and the per-pixel normal equations of the log residuals on lights ``idx``.

    Returns ``r (P, M)`` (the residuals at ``theta``, non-finite entries as they come),
    ``JᵀJ (P, 7, 7)`` and ``Jᵀr (P, 7)`` w.r.t. each pixel's 7 unknowns (non-finite Jacobian
    entries and residuals count as 0 there). Pixels are independent, so forward mode
    (:func:`fit_jacobian`: five directions for the seven unknowns, in one call of the fused
    operators, the residual as their primal output) gives every pixel's Jacobian. It runs over blocks of
    ``chunk`` pixels and reduces each block to its 7×7 products at once, so the
    ``7 × lights × pixels`` Jacobian never exists whole: its blocks stay in cache and below
    the allocator's mmap threshold (a whole 256² Jacobian is 88 MB, and every fresh
    allocation that size is page-faulted in anew: 0.5 s of a 1.4 s Jacobian, measured).
    """
    P = theta.shape[0]
    r_out = theta.new_empty(P, 3 * len(idx))
    jtj = theta.new_empty(P, _N_PARAMS, _N_PARAMS)
    jtr = theta.new_empty(P, _N_PARAMS)
    for s0 in range(0, P, chunk):
        rows = slice(s0, min(s0 + chunk, P))
        t, m = theta[rows], metal[rows]
        r, jt = fit_jacobian(lambda x, tg: data.residual_jvp(x, m, idx, model, tg, rows=rows),  # noqa: B023
                             t, _N_PARAMS)
        r_out[rows] = r
        torch.bmm(jt, jt.transpose(1, 2), out=jtj[rows])
        torch.bmm(jt, torch.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0)[..., None], out=jtr[rows, :, None])
    return r_out, jtj, jtr


def marginal_information(data: "LevelData", theta: Tensor, metal: Tensor, model: str,
                         jtj: Tensor | None = None) -> Tensor:
    """Per-parameter marginal information ``1 / diag((JᵀJ)⁻¹)`` ``(P, 7)`` of the data term.

    It is what the captured images say about each parameter once the others are free to
    trade off against it (Gauss–Newton posterior precision): small for a glossy pixel's
    roughness when no highlight reaches it, and for a metal's F0 far from every highlight.
    """
    if jtj is None:  # the normal matrices ``(P, 7, 7)`` at theta, when the caller has none
        jtj = gauss_newton(data, theta, metal, data.train_idx, model)[1]
    jtj = jtj + 1e-6 * torch.eye(_N_PARAMS, dtype=jtj.dtype, device=jtj.device)
    cov = torch.linalg.inv(jtj.double())
    return (1.0 / torch.diagonal(cov, dim1=-2, dim2=-1).clamp(min=1e-12)).to(theta.dtype)


def nonlocal_prior(data: "LevelData", theta: Tensor, metal: Tensor, cfg: RecoveryConfig,
                   jtj: Tensor | None = None, cost: Tensor | None = None, jtr: Tensor | None = None,
                   rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Confidence-weighted non-local estimate of a metal's base colour (and, optionally, roughness).

    A metal's base colour (F0, logit) gets the average of the metal pixels within a large
    Gaussian window (``cfg.nonlocal_sigma`` × size), weighted by their marginal information;
    with ``cfg.prior_nonlocal > 0`` each pixel's roughness also gets the information-weighted
    average of same-class pixels of similar base colour (bilateral grid over k-means colour
    clusters) — off by default: rough pixels always carry little roughness information, so
    the average is pulled toward nearby glossy pixels (tiles' grout came out too smooth).
    ``jtj (P, 7, 7)``: the normal matrices at ``theta`` when the caller has them (else computed);
    ``cost (P, 1)``: each pixel's data cost there (its squared residuals' sum; None: not used),
    which scales a metal's weight by ``min(1, cfg.nonlocal_fit_weight × median / cost)`` (the
    median over the metal pixels with a finite cost; a non-finite cost weighs 0);
    ``jtr (P, 7)``: the data gradients there — with ``jtj``, each metal pixel enters the average
    at its own data optimum as one Gauss–Newton step predicts it (:func:`newton_step`), not
    where its fit stopped: in the GGX tail a metal's data pin F0·α², not F0, and the fit
    slides along that valley slowly from its dark start (None: where the fit stopped).
    ``rows (N,)`` (int64): the pixels that ``jtj``, ``cost`` and ``jtr`` (all three given) are
    of, ``(N, 7, 7)``, ``(N, 1)``, ``(N, 7)``; it must hold every metal pixel, and the
    information is then 0 elsewhere. Only without the roughness average, which needs every
    pixel's (None: all P pixels).
    Returns ``(precisions (P, 7), targets (P, 7), information (P, 7))``; the caller fuses
    ``(info θ + w m) / (info + w)``: pixels the data pins down (information ≫ precision)
    keep their value, the under-determined ones take the average.
    """
    size = data.size
    if rows is None:
        info = marginal_information(data, theta, metal, cfg.model, jtj)
    else:
        if cfg.prior_nonlocal > 0 or jtj is None or cost is None or jtr is None:
            raise ValueError("nonlocal_prior: `rows` needs jtj, cost and jtr, and prior_nonlocal = 0")

        def spread(x: Tensor, fill: float) -> Tensor:  # (N, ...) at rows -> (P, ...), fill elsewhere
            out = x.new_full((theta.shape[0], *x.shape[1:]), fill)
            out[rows] = x
            return out

        covered = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
        covered[rows] = True
        if bool(((metal[:, 0] > 0.5) & ~covered).any()):
            raise ValueError("nonlocal_prior: `rows` must hold every metal pixel")
        info = spread(marginal_information(data, theta[rows], metal[rows], cfg.model, jtj), 0.0)
        jtj, cost, jtr = spread(jtj, 0.0), spread(cost, float("inf")), spread(jtr, 0.0)
    sig = cfg.nonlocal_sigma * size
    base = torch.sigmoid(theta[:, 0:3])
    w = torch.zeros_like(theta)
    m = theta.clone()
    ism = metal[:, 0] > 0.5
    ci = info[:, 4:5]
    for cls in (ism, ~ism) if cfg.prior_nonlocal > 0 else ():
        if int(cls.sum()) == 0:
            continue
        # A bilateral grid in base colour: splat into k-means clusters, slice with a
        # Gaussian range weight around each pixel's own colour.
        cent = _kmeans(base[cls], cfg.nonlocal_clusters, return_centres=True)
        num = torch.zeros(theta.shape[0], dtype=theta.dtype, device=theta.device)
        den = torch.zeros_like(num)
        lab = torch.cdist(base, cent).argmin(-1)
        g = torch.exp(-((base[:, None, :] - cent[None]) ** 2).sum(-1) / cfg.nonlocal_range**2)  # (P, K)
        for k in range(cent.shape[0]):
            mk = ((lab == k) & cls).to(theta.dtype)[:, None]
            if mk.sum() == 0:
                continue
            b = _blur(torch.cat((mk * ci * theta[:, 4:5], mk * ci), -1), size, sig)
            num += g[:, k] * b[:, 0]
            den += g[:, k] * b[:, 1]
        m[cls, 4] = torch.where(den[cls] > 1e-9, num[cls] / den[cls].clamp(min=1e-12), theta[cls, 4])
        w[cls, 4] = cfg.prior_nonlocal
    if bool(ism.any()):
        mm = ism.to(theta.dtype)[:, None]
        # Weights saturate at 1 (the pixel's shrinkage factor info / (info + precision)):
        # a pixel wrongly called metal fits a dielectric's strong diffuse with very high
        # "information" and must not dominate the average (circuit seed 1: 180 such pixels).
        cb = info[:, 0:3] / (info[:, 0:3] + max(cfg.prior_nonlocal_base, 1e-12))
        finite = torch.isfinite(cost[:, 0]) & ism if cost is not None else ism[:0]
        if cost is not None and cfg.nonlocal_fit_weight > 0 and bool(finite.any()):
            # ... and by how well the model fits the pixel: one fitted far above the median
            # metal pixel (a rust front called metal, a blend of two materials) is no evidence
            # of its neighbours' F0 (rusted_metal 1: the average came out dark; base RMSE
            # 0.052 -> 0.046 on the tuning captures, see docs/recovery.md). A non-finite
            # cost weighs 0.
            ref = cfg.nonlocal_fit_weight * cost[finite].median()
            fit = torch.where(cost <= ref, torch.ones_like(cost), ref / cost)
            cb = cb * torch.nan_to_num(fit, nan=0.0, posinf=0.0)
        own = theta[:, 0:3]
        if jtr is not None and jtj is not None:
            # Weights ∝ information, so a pixel the data hardly see moves the average little
            # however far its step goes (rusted_metal 6 / 7: F0 bias −1.5 / −1.1 % → −1.1 / −0.8 %).
            own = own.clone()
            own[ism] += newton_step(jtj[ism], jtr[ism])[:, 0:3]
        num = _blur(torch.cat((mm * cb * own, mm * cb), -1), size, sig)
        mb = torch.where(num[:, 3:6] > 1e-9, num[:, 0:3] / num[:, 3:6].clamp(min=1e-12), theta[:, 0:3])
        m[:, 0:3] = torch.where(ism[:, None], mb, theta[:, 0:3])
        w[:, 0:3] = cfg.prior_nonlocal_base * mm
    m = torch.nan_to_num(m)
    return w, m, info


def _normal_texture(theta: Tensor, size: int, radius: int = 2) -> Tensor:
    """Local standard deviation ``(P, 1)`` of the normal slope ``(p, q)`` in a ``(2r+1)²`` window
    (reflect-padded: an edge pixel's window lies inside the image): the geometry statistic
    that tells a smooth glaze from a bumpy stone of the same colour."""
    img = theta[:, 5:7].T.reshape(1, 2, size, size)
    k = 2 * radius + 1
    mode = "reflect" if size > radius else "replicate"
    pad = F.pad(torch.cat((img, img * img), 1), (radius,) * 4, mode=mode)
    mom = F.avg_pool2d(pad, k, 1)
    var = (mom[:, 2:] - mom[:, :2] ** 2).clamp(min=0).sum(1)
    return var.sqrt().reshape(-1, 1)


def nonlocal_fill(data: "LevelData", theta: Tensor, metal: Tensor, cfg: "RecoveryConfig",
                  info: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Targets and precisions ``(P, 7)`` of a unary prior that fills under-determined roughness and
    specular from same-material pixels the captured highlights do constrain.

    Each pixel draws ``cfg.fill_candidates`` pixels of its class from the whole image
    (non-local: a glossy region no highlight reaches borrows from the same material where one
    does) and averages their roughness / specular logits with weights
    ``similarity × reliability``: similarity ``exp(−|Δbase|²/σ_b² − Δtex²/σ_t²)`` in base
    colour and in the local spread of the normal (``_normal_texture``), reliability the
    candidate's own confidence ``1 / (1 + var / tol²)`` from its marginal information
    ``1 / diag((JᵀJ)⁻¹)`` (its posterior variance in map units; ``tol`` = ``cfg.fill_sigma``).
    The prior's precision (logit units) is ``σ² / fill_sigma² · (dvalue/dlogit)²`` × the
    mean reliability of the similar candidates — a value ``fill_sigma`` wide around the
    material's measured one, as strong as the data at a pixel of confidence ½, and nothing
    where no similar pixel was measured. The LM then fuses it with each pixel's data: the
    well-measured pixels keep their own values, the under-determined ones take the material's.
    """
    size = data.size
    if info is None:
        info = marginal_information(data, theta, metal, cfg.model)
    r = data.residual(theta, metal, data.train_idx, cfg.model)
    sigma2 = float(torch.nan_to_num((r * r).mean(-1), nan=0.0).median())
    sr, ss = torch.sigmoid(theta[:, 4:5]), torch.sigmoid(theta[:, 3:4])
    d_r = (_R_MAX - _R_MIN) * sr * (1 - sr)  # d roughness / d logit
    d_s = ss * (1 - ss)
    tol = cfg.fill_sigma
    rel_r = 1.0 / (1.0 + sigma2 * d_r**2 / (info[:, 4:5].clamp(min=1e-12) * tol**2))
    rel_s = 1.0 / (1.0 + sigma2 * d_s**2 / (info[:, 3:4].clamp(min=1e-12) * tol**2))
    feat = torch.cat((torch.sigmoid(theta[:, 0:3]) / cfg.fill_range,
                      _normal_texture(theta, size) / cfg.fill_texture), -1)  # (P, 4)
    gen = torch.Generator().manual_seed(int(cfg.seed) + 7919)
    tgt = theta.clone()
    prec = torch.zeros_like(theta)
    ism = metal[:, 0] > 0.5
    for cls in (~ism, ism):
        pool = torch.nonzero(cls).flatten()
        if pool.numel() < 2:
            continue
        k = min(cfg.fill_candidates, pool.numel())
        rows = pool
        num = torch.zeros(rows.numel(), 2, dtype=theta.dtype, device=theta.device)
        den = torch.zeros_like(num)
        sim_sum = torch.zeros(rows.numel(), 1, dtype=theta.dtype, device=theta.device)
        chunk = max(1, 2**21 // k)
        for s0 in range(0, rows.numel(), chunk):
            rr = rows[s0:s0 + chunk]
            cand = pool[torch.randint(0, pool.numel(), (rr.numel(), k), generator=gen)]  # (n, K)
            sim = torch.exp(-((feat[cand] - feat[rr][:, None]) ** 2).sum(-1))  # (n, K)
            w = sim[..., None] * torch.stack((rel_s[cand, 0], rel_r[cand, 0]), -1)  # (n, K, 2)
            num[s0:s0 + rr.numel()] = (w * theta[cand][..., 3:5]).sum(1)
            den[s0:s0 + rr.numel()] = w.sum(1)
            sim_sum[s0:s0 + rr.numel()] = sim.sum(1, keepdim=True)
        ok = den > 1e-9
        tgt[rows, 3:5] = torch.where(ok, num / den.clamp(min=1e-12), theta[rows, 3:5])
        support = (den / sim_sum.clamp(min=1e-12)) * (sim_sum >= cfg.fill_min_similar)  # mean reliability
        base_prec = sigma2 / tol**2 * torch.cat((d_s[rows], d_r[rows]), -1) ** 2
        prec[rows, 3:5] = cfg.fill_weight * base_prec * support * ok
    if bool(ism.any()):
        prec[ism, 3] = 0.0  # a metal's specular is invisible and already tied to its neighbours
    return torch.nan_to_num(tgt), torch.nan_to_num(prec)


def prior_gradient(theta: Tensor, wx: Tensor, wy: Tensor, size: int,
                   unary: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Gradient ``(P, 7)`` of the maps' prior energy at ``theta``.

    The smoothness prior's weighted Laplacian (:func:`edge_weights` ``wx``, ``wy``) plus the
    unary fill's pull.
    """
    g = laplacian(theta, wx, wy, size)
    if unary is not None:
        g = g + unary[1] * (theta - unary[0])
    return g


def map_prior_terms(theta: Tensor, metal: Tensor, size: int, cfg: RecoveryConfig,
                    unary: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Gradient and Hessian diagonal ``(P, 7)`` each of the maps' prior energy at ``theta``.

    ``theta (P, 7)``, ``metal (P, 1)`` of a ``size × size`` map; ``unary`` as in :func:`lm_step`.
    The results have ``theta``'s dtype and device.
    """
    wx, wy = edge_weights(theta, metal, size, cfg)
    hdiag = laplacian_diag(wx, wy, size)
    return prior_gradient(theta, wx, wy, size, unary), hdiag if unary is None else hdiag + unary[1]


def lm_step(data: LevelData, theta: Tensor, metal: Tensor, lam: Tensor, cfg: RecoveryConfig, lr: float,
            extra: dict | None = None, unary: tuple[Tensor, Tensor] | None = None,
            gn: tuple[Tensor, Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor, int]:
    """One Levenberg–Marquardt iteration with the coupled smoothness prior.

    ``theta (P, 7)`` unknowns, ``metal (P, 1)`` classes, ``lam (P, 1)`` per-pixel damping;
    ``lr`` scales the step. Returns ``(theta, lam, cost (P, 1), n_nonfinite)``; when ``extra``
    (a dict) is given, ``extra["residual"]`` receives the residuals ``(P, M)`` at the returned
    ``theta`` (for the light-scale update and the fit loss, without another render). ``unary = (target, precision)``
    ``(P, 7)`` each adds ``½ Σ precision (θ − target)²`` (the non-local fill, :func:`nonlocal_fill`,
    and the metals' F0 tie, :func:`nonlocal_prior`). ``gn``: :func:`gauss_newton`'s result at
    ``theta`` on these lights when the caller has it (else computed).
    """
    idx, size = data.train_idx, data.size
    wx, wy = edge_weights(theta, metal, size, cfg)
    fn = lambda t: data.residual(t, metal, idx, cfg.model)  # noqa: E731
    r0, jtj, jtr = gn if gn is not None else gauss_newton(data, theta, metal, idx, cfg.model)
    g = jtr + prior_gradient(theta, wx, wy, size, unary)
    if unary is not None:
        jtj = jtj + torch.diag_embed(unary[1])
    hd = torch.diagonal(jtj, dim1=-2, dim2=-1) + laplacian_diag(wx, wy, size)
    hess = jtj + torch.diag_embed(lam * (hd + 1e-6))  # per-pixel Marquardt damping
    step = pcg(hess, wx, wy, -g, size, cfg.cg_iters)
    step = torch.where(torch.isfinite(step), step, torch.zeros_like(step)).clamp(-3, 3)
    c0 = (r0 * r0).sum(-1, keepdim=True) + prior_energy(theta, wx, wy, size) + _unary_cost(theta, unary)
    c0 = torch.where(torch.isfinite(c0), c0, torch.full_like(c0, float("inf")))
    cand = theta + lr * step
    r1 = fn(cand)
    c1 = (r1 * r1).sum(-1, keepdim=True) + prior_energy(cand, wx, wy, size) + _unary_cost(cand, unary)
    c1 = torch.where(torch.isfinite(c1), c1, torch.full_like(c1, float("inf")))
    better = c1 < c0
    theta = torch.where(better, cand, theta)
    lam = torch.where(better, (lam * 0.3).clamp(min=1e-5), (lam * 10).clamp(max=1e6))
    cost = torch.where(better, c1, c0)
    if extra is not None:
        extra["residual"] = torch.where(better, r1, r0)
    return theta, lam, cost, int((~torch.isfinite(c1)).sum())


def light_position_step(data: LevelData, theta: Tensor, metal: Tensor, offset: Tensor, model: str,
                        prior_sigma: float = 0.01, stride: int = 4, at_camera: bool = True) -> Tensor:
    """One Gauss–Newton update of the per-light position offsets ``(L, 3)`` (world units).

    Each light's residuals depend only on its own position, so three forward-mode passes (one
    per axis, every light at once) give every light's ``(pixels, 3)`` Jacobian; the step solves
    each light's 3×3 normal equations with a Gaussian prior of ``prior_sigma`` (1 cm) on the
    offset, over every ``stride``-th pixel (cheap; the offset is 3 numbers per light against
    thousands of pixels). Lights not in ``data.train_idx`` keep their offsets, and so, with
    ``at_camera=False``, does a light beside the camera (:func:`camera_lights`).
    """
    idx = data.train_idx
    rows = torch.arange(0, theta.shape[0], stride, device=theta.device)
    p = decode(theta[rows], metal[rows])
    pts, cam = data.points[rows], data.camera
    log_obs = data.log_obs[idx][:, rows]
    inten = data.inten[idx]
    base = data.pos_stated[idx] + offset[idx]

    def res(pos):  # (L, N, 3)
        r = log_residual(p, pts, cam, pos, inten, log_obs.permute(1, 0, 2), data.eps, model)
        return r.permute(1, 0, 2)

    r = torch.nan_to_num(res(base))
    cols = []
    for k in range(3):
        tg = torch.zeros_like(base)
        tg[:, k] = 1.0
        cols.append(torch.nan_to_num(torch.func.jvp(res, (base,), (tg,))[1]))
    jac = torch.stack(cols, -1).reshape(len(idx), -1, 3)  # (L, N*3, 3)
    r = r.reshape(len(idx), -1)
    sigma2 = float(r.pow(2).median()) + 1e-12  # robust per-residual noise variance
    # Huber weights: a residual beyond 3 noise deviations counts linearly, not quadratically, so
    # the few pixels the maps do not fit yet (a material front, an unconverged rim) cannot move
    # a light to explain them.
    w = (3.0 * math.sqrt(sigma2) / r.abs().clamp(min=1e-30)).clamp(max=1.0)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    jtj = torch.einsum("lni,lnj->lij", jac * w[..., None], jac) + (sigma2 / prior_sigma**2) * eye
    g = torch.einsum("lni,ln->li", jac, w * r) + (sigma2 / prior_sigma**2) * offset[idx]
    step = torch.linalg.solve(jtj, -g[..., None])[..., 0]
    if not at_camera:
        step[camera_lights(data.pos_stated[idx], cam, data.points.mean(0))] = 0.0
    out = offset.clone()
    out[idx] = (offset[idx] + torch.nan_to_num(step)).clamp(-5 * prior_sigma, 5 * prior_sigma)
    return out


def camera_lights(pos: Tensor, camera: Tensor, centre: Tensor, frac: float = 0.1) -> Tensor:
    """``(L,)`` bool: the lights beside the camera (a flash).

    Within ``frac`` × the camera's distance to the surface ``centre (3,)`` of ``camera (3,)``;
    ``pos (L, 3)``; the mask is on ``pos``'s device (any float dtype).

    Such a light lights every pixel from near the viewing direction, so a small move of it
    changes the images much as its intensity scale and a slow variation of the maps do: the
    least determined of the lights' positions (rusted_metal 4 at its true maps: 0.19 cm
    posterior deviation along the axis against 0.01–0.02 cm for the ring lights), and the one
    that soaked up what the two-hypothesis maps had not yet fitted
    (``RecoveryConfig.dual_calibration_at_camera``).
    """
    reach = frac * float((camera - centre).norm())
    return (pos - camera).norm(dim=-1) < reach


def rig_free_directions(pos: Tensor, centre: Tensor, held: Tensor | None = None) -> Tensor:
    """``(3L, 3L - 7 - 3H)`` orthonormal light-position changes that keep the rig's placement.

    Moving every light together (a translation, a turn or a dilation about the surface's
    ``centre``) changes the images almost as moving, tilting or scaling the surface would,
    which the per-pixel maps absorb (normals take a tilt; a near-uniform material is unchanged
    by a shift); with the maps eliminated these seven directions are barely constrained by the
    data, and a little model mismatch ran them to the clamp (dusty_metal 2 without calibration
    error: every light 8 cm inward). Like the overall intensity scale, the rig's placement is
    the stated one. ``pos (L, 3)`` light positions, ``centre (3,)``; ``held (L,)`` bool: lights
    whose position is kept as stated (``H`` of them; no component on their coordinates; None:
    none); rows are light-major (light ``i``'s x, y, z at ``3i .. 3i+2``); ``pos``'s dtype and
    device.
    """
    n = pos.shape[0]
    rel = pos - centre
    eye = torch.eye(3, dtype=pos.dtype, device=pos.device)
    turns = [torch.linalg.cross(e.expand_as(rel), rel).reshape(-1, 1) for e in eye]
    modes = torch.cat((eye.repeat(n, 1), rel.reshape(-1, 1), *turns), 1)  # (3L, 7)
    if held is not None and bool(held.any()):  # ... and each held light's x, y and z alone
        coords = torch.eye(3 * n, dtype=pos.dtype, device=pos.device)
        modes = torch.cat((modes, coords[:, held.repeat_interleave(3)]), 1)
    q, _ = torch.linalg.qr(modes, mode="complete")
    return q[:, modes.shape[1]:]


def light_joint_step(data: LevelData, theta: Tensor, metal: Tensor, log_scale: Tensor, offset: Tensor,
                     ref_idx: list[int], model: str, position: bool = True,
                     map_prior: tuple[Tensor, Tensor] | None = None, scale_sigma: float = 0.1,
                     position_sigma: float = 0.01, max_pixels: int = 8192,
                     damping: float = 1e-3, at_camera: bool = True) -> tuple[Tensor, Tensor]:
    """One Gauss–Newton step on the lights' log scales and offsets, the pixels' unknowns eliminated.

    ``theta (P, 7)``, ``metal (P, 1)`` the maps; ``log_scale (L,)`` and ``offset (L, 3)`` the
    current estimates; returns the updated pair (lights not in ``data.train_idx`` keep theirs).

    Stepping the lights with the maps held fixed (:func:`light_scale_step`,
    :func:`light_position_step`) sees only the part of a light's error the maps cannot absorb
    (a tilted normal, a wider lobe), so alternating with the map steps creeps toward the joint
    optimum. Here each pixel's 7 unknowns are eliminated (a Schur complement, as in bundle
    adjustment): with ``A = JpᵀWJp + H``, ``B = JpᵀWJg`` and ``gp = JpᵀWr + g`` per pixel,
    the reduced normal equations ``(Σ JgᵀWJg − Σ BᵀA⁻¹B) δg = −(Σ JgᵀWr − Σ BᵀA⁻¹ gp)`` give
    the step the maps would follow. ``map_prior = (g, H)``, both ``(P, 7)``, are the gradient
    and the Hessian's diagonal of the maps' prior energy at ``theta`` (:func:`map_prior_terms`;
    block-Jacobi: the prior's coupling between pixels is left out): after an LM step the data
    gradient balances the prior's rather than vanishing.

    One forward-mode pass with 7 + 4 tangents over at most ``max_pixels`` evenly strided
    pixels gives both Jacobians (a light's residuals depend only on its own 4 numbers); the
    reduction runs in float64 (``Σ BᵀA⁻¹B`` nearly cancels ``Σ JgᵀWJg`` in the weak
    directions). Huber weights ``W`` (3 noise deviations) as in :func:`light_position_step`;
    pixels with a non-finite residual or derivative are left out. Gaussian priors of
    ``scale_sigma`` (log) and ``position_sigma`` (world units). The step keeps the training
    lights' (``ref_idx``) mean log scale and, with ``position``, moves no light rig as a whole
    (:func:`rig_free_directions`): the maps absorb both, so the capture's stated values fix
    them; nor, with ``at_camera=False``, a light beside the camera (:func:`camera_lights`). With
    ``position=False``, or fewer than 3 lights, only the scales are stepped. The
    result has ``log_scale``'s and ``offset``'s dtype and device (CPU or CUDA alike).
    """
    idx = data.train_idx
    n_l = len(idx)
    stride = max(1, math.ceil(theta.shape[0] / max_pixels))
    rows = torch.arange(0, theta.shape[0], stride, device=theta.device)
    t0, m = theta[rows], metal[rows]
    pts, cam = data.points[rows], data.camera
    log_obs = data.log_obs[idx][:, rows].permute(1, 0, 2)  # (n, L, 3)
    inten0 = data.inten_stated[idx]
    pos0 = data.pos_stated[idx] + offset[idx]
    s0 = log_scale[idx]

    def res(t, pos, s):  # (n, L * 3)
        inten = inten0 * torch.exp(s)[:, None]
        r = log_residual(decode(t, m), pts, cam, pos, inten, log_obs, data.eps, model)
        return r.reshape(t.shape[0], -1)

    n = t0.shape[0]
    eye7 = torch.eye(_N_PARAMS, dtype=theta.dtype, device=theta.device)
    tt = torch.cat((eye7[:, None, :].expand(_N_PARAMS, n, _N_PARAMS), t0.new_zeros(4, n, _N_PARAMS)))
    tp = pos0.new_zeros(_N_PARAMS + 4, *pos0.shape)
    ts = s0.new_zeros(_N_PARAMS + 4, n_l)
    for k in range(3):
        tp[_N_PARAMS + k, :, k] = 1.0
    ts[_N_PARAMS + 3] = 1.0
    out_dims: Any = (None, 0)
    pair: Any = torch.func.vmap(lambda a, b, c: torch.func.jvp(res, (t0, pos0, s0), (a, b, c)),
                                out_dims=out_dims)(tt, tp, ts)
    r, cols = pair  # (n, M), (11, n, M): M = L * 3, light-major
    ok = torch.isfinite(r).all(1) & torch.isfinite(cols).all(2).all(0)  # (n,)
    if not bool(ok.any()):
        return log_scale, offset
    f64 = torch.float64
    r = torch.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0).to(f64)
    cols = torch.nan_to_num(cols, nan=0.0, posinf=0.0, neginf=0.0).to(f64)
    jp = cols[:_N_PARAMS].permute(1, 0, 2)  # (n, 7, M)
    position = position and n_l >= 3  # two lights have no position freedom beyond the rig's
    keep = slice(0, 4) if position else slice(3, 4)  # the light unknowns: offset xyz, log scale
    jg = cols[_N_PARAMS:].permute(1, 2, 0).reshape(n, n_l, 3, 4)[..., keep]  # (n, L, 3, G)
    n_g = jg.shape[-1]
    sigma2 = float(r[ok].pow(2).median()) + 1e-12
    w = (3.0 * math.sqrt(sigma2) / r.abs().clamp(min=1e-30)).clamp(max=1.0) * ok[:, None]  # Huber, (n, M)
    jpw = jp * w[:, None, :]
    a = torch.bmm(jpw, jp.transpose(1, 2))
    a = a + torch.diag_embed(damping * torch.diagonal(a, dim1=-2, dim2=-1) + 1e-9)
    b = torch.einsum("nplc,nlcg->nplg", jpw.reshape(n, _N_PARAMS, n_l, 3), jg)
    b = b.reshape(n, _N_PARAMS, n_l * n_g)  # light-major, G inner
    gp = (jpw @ r[..., None])[..., 0]  # (n, 7)
    if map_prior is not None:
        gp = gp + torch.nan_to_num(map_prior[0][rows].to(f64)) * ok[:, None]
        a = a + torch.diag_embed(torch.nan_to_num(map_prior[1][rows].to(f64)) * ok[:, None])
    wr = (w * r).reshape(n, n_l, 3)
    gg = torch.einsum("nlcg,nlc->lg", jg, wr).reshape(-1)  # (L G,)
    c = torch.einsum("nlcg,nlc,nlch->lgh", jg, w.reshape(n, n_l, 3), jg)  # (L, G, G)
    x = torch.linalg.solve(a, torch.cat((b, gp[..., None]), -1))  # A⁻¹ [B | gp]
    schur = torch.block_diag(*c) - torch.einsum("npg,nph->gh", b, x[..., :-1])
    rhs = gg - torch.einsum("npg,np->g", b, x[..., -1])
    prior = torch.tensor([1 / position_sigma**2] * 3 + [1 / scale_sigma**2], dtype=f64,
                         device=r.device)[keep].repeat(n_l) * sigma2
    cur = torch.cat((offset[idx], s0[:, None]), -1)[:, keep].reshape(-1).to(f64)
    held = None if at_camera or not position else camera_lights(data.pos_stated[idx], data.camera,
                                                                 data.points.mean(0))
    basis, n_pos = _light_step_basis(data, ref_idx, position, held)  # (L G, K): the directions a step takes
    h = basis.T @ (schur + torch.diag(prior)) @ basis
    step = (basis @ torch.linalg.solve(h, -(basis.T @ (rhs + prior * cur)))).reshape(n_l, n_g)
    if not bool(torch.isfinite(step).all()):
        return log_scale, offset
    step = step.to(theta.dtype)
    new_off, new_s = offset.clone(), log_scale.clone()
    if position:
        moved = (offset[idx] + step[:, :3]).clamp(-5 * position_sigma, 5 * position_sigma)
        free = basis[:, :n_pos].reshape(n_l, n_g, -1)[:, :3].reshape(3 * n_l, -1).to(theta.dtype)
        # the clamp may leave the subspace: project back
        new_off[idx] = (free @ (free.T @ moved.reshape(-1))).reshape(n_l, 3)
        if held is not None:  # exactly as before (the projection leaves rounding dust)
            fixed = torch.as_tensor(idx, device=offset.device)[held]
            new_off[fixed] = offset[fixed]
    new_s[idx] = log_scale[idx] + step[:, -1]
    new_s[ref_idx] = new_s[ref_idx] - new_s[ref_idx].mean()
    return new_s.clamp(-0.3, 0.3), new_off


def _light_step_basis(data: LevelData, ref_idx: list[int], position: bool, held: Tensor | None = None
                      ) -> tuple[Tensor, int]:
    """Orthonormal directions ``(L G, K)`` a light step may take, and how many of them move positions.

    ``G`` = 4 with ``position`` (offset xyz, log scale per light, light-major), else 1: positions
    that move no rig as a whole and none of the ``held (L,)`` lights (:func:`rig_free_directions`,
    ``3L − 7 − 3H``; the first columns) and log scales that keep the mean over ``ref_idx``
    (``L − 1``, or ``L`` when none of ``data.train_idx`` is one).
    """
    idx = data.train_idx
    n_l, n_g = len(idx), 4 if position else 1
    dev, f64 = data.points.device, torch.float64
    ref = torch.tensor([float(i in ref_idx) for i in idx], dtype=f64, device=dev)
    if bool(ref.any()):
        scales = torch.linalg.qr(ref[:, None], mode="complete")[0][:, 1:]  # ⟂ the reference mean
    else:
        scales = torch.eye(n_l, dtype=f64, device=dev)
    parts = []
    n_pos = 0
    if position:
        free = rig_free_directions(data.pos_stated[idx].to(f64), data.points.mean(0).to(f64), held)
        n_pos = free.shape[1]
        pos_part = torch.zeros(n_l, n_g, n_pos, dtype=f64, device=dev)
        pos_part[:, :3] = free.view(n_l, 3, -1)
        parts.append(pos_part.reshape(n_l * n_g, -1))
    scale_part = torch.zeros(n_l, n_g, scales.shape[1], dtype=f64, device=dev)
    scale_part[:, -1] = scales
    parts.append(scale_part.reshape(n_l * n_g, -1))
    return torch.cat(parts, 1), n_pos


def newton_step(jtj: Tensor, g: Tensor, held: Tensor | None = None, chunk: int = 65536) -> Tensor:
    """Each pixel's Gauss–Newton step ``−H_ff⁻¹ g_f`` ``(P, 7)`` on its free unknowns (0 on the held).

    ``jtj (P, 7, 7)`` the normal matrices ``H``, ``g (P, 7)`` the gradients, ``held (P, 7)`` the
    unknowns kept fixed (None: none). ``H_ff`` gets a relative 1e-6 (plus 1e-9) on its diagonal,
    so a direction the data do not see takes a bounded step; steps are clamped to ±3 (logit /
    slope units). The float64 algebra runs over blocks of ``chunk`` pixels (a 1024² map's 7×7
    blocks are 0.4 GB each); the result has ``g``'s dtype and device.
    """
    out = torch.empty_like(g)
    for s0 in range(0, g.shape[0], chunk):
        rows = slice(s0, s0 + chunk)
        # float64 copies, damped in place (copy=True: a float64 caller's own blocks stay as they are)
        h, rhs = jtj[rows].to(torch.float64, copy=True), -g[rows].double()
        if held is not None:  # (a held row becomes the identity's, its rhs 0: its step is 0)
            _hold(h, rhs, held[rows])
        diag = torch.diagonal(h, dim1=-2, dim2=-1)
        diag.add_(1e-6 * diag + 1e-9)
        x = torch.linalg.solve(h, rhs[..., None])[..., 0]
        out[rows] = torch.nan_to_num(x).clamp(-3, 3).to(g.dtype)
    return out


def conditional_shift(jtj: Tensor, delta: Tensor, moved: Tensor, chunk: int = 65536) -> Tensor:
    """The other unknowns' first-order response ``(P, 7)`` to moving some of a pixel's unknowns.

    ``jtj (P, 7, 7)`` each pixel's normal matrix, ``delta (P, 7)`` the change imposed on the
    unknowns where ``moved (P, 7)`` is true (per pixel). Returns ``−H_oo⁻¹ H_om δ_m`` on the
    others (zero on the moved ones): how the data optimum of the free unknowns moves with the
    moved ones under the Gauss–Newton model — exactly the least-squares response where the
    data gradient on the free unknowns is zero, as at a converged fit: the Newton step from
    the gradient ``H δ_m`` that the move creates (:func:`newton_step`). After a prior moves a
    metal's F0 along the F0–roughness valley, its roughness and normal follow. Callers keep a
    shift only where it helps (a curved valley bends away from the linear response). ``chunk``:
    as in :func:`newton_step`.
    """
    g = torch.empty_like(delta)
    for s0 in range(0, delta.shape[0], chunk):  # H δ_m in float64, block by block (as the solve)
        rows = slice(s0, s0 + chunk)
        dm = (delta[rows] * moved[rows]).double()
        g[rows] = (jtj[rows].double() @ dm[..., None])[..., 0].to(delta.dtype)
    return newton_step(jtj, g, moved, chunk)


def _sum_unary(a: tuple[Tensor, Tensor] | None, b: tuple[Tensor, Tensor] | None
               ) -> tuple[Tensor, Tensor] | None:
    """The sum of two unary priors ``(target, precision)`` ``(P, 7)`` each (None: absent), as one."""
    if a is None or b is None:
        return a if b is None else b
    prec = a[1] + b[1]
    target = torch.where(prec > 0, (a[1] * a[0] + b[1] * b[0]) / prec.clamp(min=1e-30), a[0])
    return target, prec


def _unary_cost(theta: Tensor, unary: tuple[Tensor, Tensor] | None):
    """Per-pixel share ``(P, 1)`` (on the ``|r|²`` scale) of the unary prior, or 0."""
    if unary is None:
        return 0.0
    return (unary[1] * (theta - unary[0]) ** 2).sum(-1, keepdim=True)


def light_scale_step(residual: Tensor, idx: list[int], log_scale: Tensor, ref_idx: list[int],
                     prior_sigma: float = 0.1) -> Tensor:
    """One Gauss–Newton update of the per-light log intensity scales ``(L,)``.

    ``residual (P, len(idx) * 3)`` are the log residuals on lights ``idx``. A light whose
    stated intensity is off by a factor ``c`` shifts every bright pixel's log residual by
    ``log c``; the update is minus the per-light *median* residual over pixels (robust to
    the few badly fitted ones; the log residual's derivative w.r.t. the log scale is
    ``pred / (pred + ε) ≈ 1``), shrunk by a Gaussian prior of width ``prior_sigma`` on the
    log scale. One number per light against every pixel (65k at 256²): 1 % noise moves it
    by ~5e-5, so it cannot fit noise. The absolute scale is fixed by the capture's stated
    intensities: the mean log scale over ``ref_idx`` (the training lights) is kept at 0.
    """
    p = residual.shape[0]
    r = residual.reshape(p, len(idx), -1).mean(-1)  # (P, n) per pixel and light
    r = torch.where(torch.isfinite(r), r, torch.zeros_like(r))
    med = r.median(0).values  # (n,)
    noise = float((r - med).abs().median()) * 1.4826 + 1e-12  # robust std of one pixel's residual
    shrink = p / (p + (noise / prior_sigma) ** 2)
    out = log_scale.clone()
    out[idx] = shrink * (out[idx] - med)  # posterior mean: data optimum shrunk toward 0
    out[ref_idx] = out[ref_idx] - out[ref_idx].mean()
    return out.clamp(-0.3, 0.3)


def propagate(data: LevelData, theta: Tensor, metal: Tensor, cfg: RecoveryConfig,
              margin: float | None = None,
              unary: tuple[Tensor, Tensor] | None = None,
              active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """PatchMatch-style propagation: each pixel tries its 8 neighbours' parameters.

    A pixel stuck in a bad local optimum (typically on a material edge, where upsampling a
    coarse level blends two materials) adopts the parameters of a neighbour when they
    explain its own observations better — data cost on the training lights plus the
    smoothness prior, so where the data cannot tell two solutions apart (a dielectric whose
    specular went to 0 leaves roughness free) the one agreeing with its neighbours wins.
    Cheap: 8 renders of the level, no Jacobian. With ``margin`` (the metal/dielectric decision
    margin), a neighbour of the other class is a candidate too, judged by the same rule as
    the dual-hypothesis choice: becoming metal needs a cost below ``margin`` × the pixel's
    own, becoming dielectric one below ``1 / margin`` × it.

    ``active (P,)`` (bool, optional): only these pixels try their neighbours (the renders
    shrink to them); the others keep their parameters. A pass after a pass can give a new
    answer only where something in the pixel's 3×3 neighbourhood changed (its candidates,
    the prior's neighbours and edge weights are all there), so ``active =``
    :func:`_dilate` ``(changed)`` gives the same result as a full pass.

    Returns ``(theta (P, 7), metal (P, 1), changed (P,) bool)``.
    """
    size, c = data.size, theta.shape[1]
    rows = None if active is None else active.nonzero()[:, 0]
    if rows is not None and rows.numel() == 0:
        return theta, metal, torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)

    def sel(x: Tensor) -> Tensor:
        return x if rows is None else x[rows]

    def cost(t: Tensor, m: Tensor) -> Tensor:
        r = data.residual(t, m, data.train_idx, cfg.model, rows=rows)
        return torch.nan_to_num((r ** 2).sum(-1, keepdim=True), nan=float("inf"))

    un = None if unary is None else (sel(unary[0]), sel(unary[1]))
    wx, wy = edge_weights(theta, metal, size, cfg)
    own, own_metal = sel(theta), sel(metal)
    best, best_metal = own, own_metal
    best_score = cost(own, own_metal) + sel(local_prior(theta, theta, wx, wy, size)) + _unary_cost(own, un)
    pad = F.pad(theta.T.reshape(1, c, size, size), (1, 1, 1, 1), mode="replicate")[0]
    padm = F.pad(metal.T.reshape(1, 1, size, size), (1, 1, 1, 1), mode="replicate")[0]
    for dy, dx in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        cand_all = pad[:, 1 + dy: 1 + dy + size, 1 + dx: 1 + dx + size].reshape(c, -1).T
        cand = sel(cand_all)
        cm = sel(padm[:, 1 + dy: 1 + dy + size, 1 + dx: 1 + dx + size].reshape(1, -1).T)
        same = cm == own_metal
        prior = sel(local_prior(cand_all, theta, wx, wy, size)) + _unary_cost(cand, un)
        if margin is None:
            score = torch.where(same, cost(cand, own_metal) + prior, float("inf"))
        else:  # the prior's weights join pixels of one class: a class change is judged on data
            data_cost = cost(cand, cm)
            score = torch.where(same, data_cost + prior,
                                data_cost * torch.where(cm > 0.5, 1.0 / margin, margin))
        better = score < best_score
        best = torch.where(better, cand, best)
        best_metal = torch.where(better, cm, best_metal)
        best_score = torch.where(better, score, best_score)
    if rows is not None:
        best = theta.index_copy(0, rows, best)
        best_metal = metal.index_copy(0, rows, best_metal)
    return best, best_metal, (best != theta).any(-1)


def _dilate(mask: Tensor, size: int) -> Tensor:
    """``mask (P,)`` bool grown by one pixel in every direction (3×3)."""
    m = mask.reshape(1, 1, size, size).to(torch.float32)
    return (F.max_pool2d(m, 3, stride=1, padding=1) > 0).reshape(-1)


def _keep_better(best: Tensor | None, best_c: Tensor | None, x: Tensor, c: Tensor
                 ) -> tuple[Tensor, Tensor]:
    """Per pixel, the better of ``(best, best_c)`` and ``(x, c)`` (lower cost ``(N, 1)``; the
    first start when ``best`` is None)."""
    if best is None or best_c is None:
        return x, c
    better = c < best_c
    return torch.where(better, x, best), torch.where(better, c, best_c)


def _pixel_cost(r: Tensor) -> Tensor:
    """Each pixel's data cost ``(N, 1)``: the sum of its squared residuals ``r (N, M)``.

    A non-finite sum is +inf, so it never wins a comparison and drops out of finite medians;
    ``r``'s dtype and device.
    """
    inf = float("inf")
    return torch.nan_to_num((r * r).sum(-1, keepdim=True), nan=inf, posinf=inf)


def _hold(jtj: Tensor, g: Tensor, held: Tensor) -> tuple[Tensor, Tensor]:
    """Per-pixel normal equations ``jtj (N, K, K)``, ``g (N, K)`` with ``held (N, K)`` unknowns decoupled.

    A held unknown's row and column are the identity's and its gradient is 0, so an LM step leaves
    it at its value. In place: ``jtj`` and ``g`` must be the caller's own (fresh) tensors.
    Returns them, in their dtype, on their device.
    """
    free = (~held).to(jtj.dtype)
    jtj.mul_(free[:, :, None] * free[:, None, :])
    torch.diagonal(jtj, dim1=-2, dim2=-1).add_(1 - free)
    return jtj, g.mul_(free)


def refit_pixels(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, starts: list[Tensor],
                 idx: list[int], model: str, iters: int = 10, held: Tensor | None = None
                 ) -> tuple[Tensor, Tensor]:
    """Per-pixel Levenberg–Marquardt (data term only) on the listed pixels from several starts.

    ``theta (P, 7)``, ``metal (P, 1)``, ``rows (N,)`` pixel indices, ``starts``: ``(N, 7)``
    starting points; ``idx`` the lights; ``held (N, 7)``: unknowns kept at their start (None:
    all free). Cheap — a few thousand pixels, no prior coupling.
    Returns the best ``(theta rows (N, 7), data cost (N, 1))`` over the starts.
    """
    m = metal[rows]
    sub = data.subset(rows)

    def cost(t):
        return _pixel_cost(sub.residual(t, m, idx, model))

    best: Tensor | None = None
    best_c: Tensor | None = None
    for t in starts:
        t = t.clone()
        lam = torch.full((t.shape[0], 1), 1e-2, dtype=t.dtype, device=t.device)
        c = cost(t)
        for _ in range(iters):
            _, jtj, g = gauss_newton(sub, t, m, idx, model)
            if held is not None:
                jtj, g = _hold(jtj, g, held)
            h = jtj + torch.diag_embed(lam * (torch.diagonal(jtj, dim1=-2, dim2=-1) + 1e-6))
            step = torch.nan_to_num(torch.linalg.solve(h, -g[..., None])[..., 0]).clamp(-3, 3)
            cand = t + step
            c1 = cost(cand)
            better = c1 < c
            t = torch.where(better, cand, t)
            c = torch.where(better, c1, c)
            lam = torch.where(better, (lam * 0.3).clamp(min=1e-5), (lam * 10).clamp(max=1e6))
        best, best_c = _keep_better(best, best_c, t, c)
    assert best is not None and best_c is not None, "refit_pixels: `starts` must not be empty"
    return best, best_c


def rough_basin_tie(data: LevelData, theta: Tensor, metal: Tensor, idx: list[int], model: str, margin: float,
                    glossy: float = 0.1, rough: float = 0.85, iters: int = 8, max_pixels: int = 4096
                    ) -> tuple[Tensor, Tensor]:
    """Move glossy dielectrics to the rough basin where that fits their data as well.

    A dielectric whose highlights all fall between the lights fits its images as a glossy
    surface (the lobe unseen) and as a rough one (the lobe broad and dim) at the same cost: the
    dust specks of dusty_metal, roughness 0.9, come out 0.05 where the coarse levels blended them
    with a glossier metal, and with specular held the cost profile over roughness has two
    basins at the same height with a barrier of hundreds of noise variances between them
    (docs/recovery.md, issue 18). The fit's path decides, and the confidence, linearised in the
    glossy basin, calls the answer measured. Between basins that fit equally well the wider
    one is the likelier (its posterior mass): the rough one, where a small change of roughness
    changes nothing. A glossy surface whose highlight is seen fits far worse rough and stays.
    The price: a truly glossy dielectric whose highlight no light shows anywhere comes out
    rough (the images do not tell it; docs/recovery.md, Known limits).

    The pixels tested: ``metal (P, 1)`` < ½ with roughness below ``glossy``, at most
    ``max_pixels`` of them (the glossiest first: each costs two small refits). Each is refitted
    (:func:`refit_pixels`, data only, lights ``idx``, ``iters`` iterations) with its roughness
    held twice — at its own value and at ``rough`` — and takes the rough fit where its cost is
    at most the glossy fit's plus ``margin`` noise variances (the median dielectric pixel's cost
    per residual). ``theta (P, 7)``.
    Returns ``(theta (P, 7), moved (P,) bool)``, on ``theta``'s device and in its dtype.
    """
    moved = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    diel = metal[:, 0] < 0.5
    zero = torch.zeros_like(metal)
    rough_now = decode(theta, zero)["roughness"][:, 0]
    rows = torch.nonzero(diel & (rough_now < glossy)).flatten()
    if rows.numel() == 0:
        return theta, moved
    if rows.numel() > max_pixels:
        rows = rows[torch.topk(rough_now[rows], max_pixels, largest=False).indices]
    cost = _pixel_cost(data.residual(theta, zero, idx, model))[diel]
    finite = torch.isfinite(cost)
    sigma2 = float(cost[finite].median()) / (3 * len(idx)) if bool(finite.any()) else 0.0
    held = torch.zeros(rows.numel(), _N_PARAMS, dtype=torch.bool, device=theta.device)
    held[:, 4] = True  # the roughness logit
    _, c_glossy = refit_pixels(data, theta, zero, rows, [theta[rows]], idx, model, iters, held=held)
    start = theta[rows].clone()
    start[:, 4] = _logit(torch.full_like(start[:, 4], rough), _R_MIN, _R_MAX)
    t_rough, c_rough = refit_pixels(data, theta, zero, rows, [start], idx, model, iters, held=held)
    take = c_rough <= c_glossy + margin * sigma2  # (a non-finite rough cost only where the glossy's is too)
    theta = theta.clone()
    theta[rows] = torch.where(take, t_rough, theta[rows])
    moved[rows] = take[:, 0]
    return theta, moved


# --------------------------------------------------------------------------------------
# Continuous metallic (final stage)
# --------------------------------------------------------------------------------------


def soft_metal_candidates(cost: Tensor, metal: Tensor, size: int, factor: float, max_frac: float,
                          band: int = 1, base: Tensor | None = None, edge: float = 0.0,
                          context: float = 0.0) -> Tensor:
    """Pixels ``(N,)`` (indices) where metallic may become continuous: the binary choice fits
    poorly (data ``cost (P, 1)`` above ``factor`` × its median, the noise level) or the pixel
    lies within ``band`` pixels of a metal/dielectric boundary (band 1: one of its 8 neighbours
    is of the other class; a soft ramp is several pixels wide, and the binary choice puts its
    boundary anywhere on it), or, with ``base (P, 3)`` and ``edge > 0``, it is a metal within
    ``band`` pixels of a base-colour step larger than ``edge`` between 4-neighbours (a rust
    island called metal has no class boundary, and it fits as a rough dark metal), or, with
    ``context > 0`` as well, a metal whose base colour differs by more than ``edge`` from the
    Gaussian-weighted mean (σ = ``context`` pixels, truncated at 3σ) of the metal around it:
    the inside of a partly rusted plateau called metal has no step, and as a clear metal it
    would be its own rim's metal end (:func:`blend_ends`; rusted_metal 122).

    ``metal (P, 1)`` in {0, 1}. At most ``max_frac`` × P pixels, the worst fitting first;
    int64 indices on ``cost``'s device.
    """
    img = (metal > 0.5).to(cost.dtype).T.reshape(1, 1, size, size)
    k = 2 * band + 1
    hi = F.max_pool2d(img, k, 1, band)  # a metal within the band
    lo = -F.max_pool2d(-img, k, 1, band)  # a dielectric within the band
    boundary = (hi != lo).reshape(-1, 1)
    if base is not None and edge > 0:
        b = base.T.reshape(1, 3, size, size)
        dx = ((b[..., :, 1:] - b[..., :, :-1]) ** 2).sum(1, keepdim=True) > edge**2
        dy = ((b[..., 1:, :] - b[..., :-1, :]) ** 2).sum(1, keepdim=True) > edge**2
        e = torch.zeros_like(img)
        e[..., :, 1:] += dx
        e[..., :, :-1] += dx
        e[..., 1:, :] += dy
        e[..., :-1, :] += dy
        e = F.max_pool2d((e > 0).to(cost.dtype), k, 1, band) * img  # within the band of a metal's colour edge
        boundary = boundary | (e > 0).reshape(-1, 1)
        if context > 0:  # a metal unlike the metal around it
            w = (metal > 0.5).to(base.dtype)
            around = _blur(torch.cat((w, base * w), -1), size, context)
            mean = around[:, 1:] / around[:, :1].clamp(min=1e-12)
            unlike = ((base - mean) ** 2).sum(-1, keepdim=True) > edge**2
            boundary = boundary | (unlike & (w > 0))
    finite = torch.isfinite(cost)
    med = float(cost[finite].median()) if bool(finite.any()) else 0.0
    sel = ((cost > factor * med) | boundary)[:, 0]
    rows = torch.nonzero(sel).flatten()
    cap = max(1, int(max_frac * cost.shape[0]))
    if rows.numel() > cap:
        rows = rows[torch.topk(torch.nan_to_num(cost[rows, 0], nan=float("inf")), cap).indices]
    return rows


#: :func:`blend_ends`' Gaussian widths in pixels, nearest first: the clear pixels beside a texel,
#: else the same class further off. A small dust speck on a metal, or a partly rusted plateau, is
#: mixed throughout, with no clear dielectric within the narrow widths' reach; the pixel's own
#: values (a metal) made its blend a guess, and such specks came out 80-93 % metal for 10-40 %
#: (dusty_metal 162 / 188, rusted_metal 122; docs/recovery.md, issue 18, "Far ends"). The widest
#: is also the context in which soft_metal_candidates finds a metal unlike the metal around it.
BLEND_SIGMAS = (2.0, 6.0, 24.0)


def blend_ends(theta: Tensor, metal: Tensor, rows: Tensor, size: int, sigmas: tuple = BLEND_SIGMAS
               ) -> tuple[tuple[Tensor, Tensor], Tensor]:
    """The clear dielectric and the clear metal nearest to each pixel of ``rows (N,)``.

    Each end: base colour, specular and roughness ``(N, 5)`` (the quantities a blend mixes
    linearly), the Gaussian-weighted mean (the first width of ``sigmas``, in pixels, that
    reaches one) of the ``metal (P, 1)`` == 0, resp. == 1, pixels not in ``rows``; where no
    width reaches one, the pixel's own values. ``theta (P, 7)``.
    Returns ``((dielectric end, metal end), found (N, 2) bool)``, on ``theta``'s device (the
    ends in its dtype).
    """
    p = decode(theta, metal)
    lin = torch.cat((p["base_color"], p["specular"], p["roughness"]), -1)  # (P, 5)
    clear = torch.ones(theta.shape[0], dtype=torch.bool, device=theta.device)
    clear[rows] = False
    ends, founds = [], []
    for cls in (0.0, 1.0):
        w = (clear & (metal[:, 0] == cls)).to(theta.dtype)[:, None]
        end, found = lin[rows], torch.zeros(rows.shape[0], 1, dtype=torch.bool, device=theta.device)
        for sigma in sigmas:  # the nearest scale that has any; a wider one only where none has yet
            if bool(found.all()) or not bool(w.any()):
                break
            b = _blur(torch.cat((w, lin * w), -1), size, sigma)[rows]  # the weight and the weighted sum
            ok = (b[:, :1] > 1e-3) & ~found
            end = torch.where(ok, b[:, 1:] / b[:, :1].clamp(min=1e-12), end)
            found = found | ok
        ends.append(end)
        founds.append(found)
    return (ends[0], ends[1]), torch.cat(founds, -1)


#: :func:`unmix_metallic`'s batch: pixel-values of its coverage grid evaluated per call.
UNMIX_PIXELS = 1 << 17


def unmix_metallic(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   size: int, steps: int = 11, sigmas: tuple = BLEND_SIGMAS) -> tuple[Tensor, Tensor]:
    """Pixels ``rows (N,)`` explained as blends of the clear metal and dielectric beside them.

    Each pixel's coverage ``t``: the best fit to its data (lights ``idx``) of ``steps`` even
    values of [0, 1], moved to the vertex of the parabola through it and its two neighbours.

    A texel that straddles two materials (an anti-aliased edge, a rust front, a dust rim) has
    base colour, roughness and metallic all blended with one weight, its coverage. Free, the
    fit cannot tell a 15 %-metal rough pixel from a rough dielectric (its base colour and
    roughness take up the difference); along the line between its neighbours' two materials
    its base colour tells the coverage. The two ends are :func:`blend_ends` of the
    ``metal (P, 1)`` == 0 and == 1 pixels not in ``rows`` (the candidates are the mixed ones):
    the nearest ones, or the same class further off where none is near (the core of a small
    dust speck is all candidates; a rust island inside a metal has no clear rust beside it;
    ``sigmas``, :data:`BLEND_SIGMAS`), else the pixel's own parameters (the blend is then a
    guess, measured better than none: docs/recovery.md, issue 18); the metal end takes the
    dielectric end's specular (a metal's is not observed). The normal is the pixel's own.
    Where no blend has a finite cost, ``t`` and its theta are NaN (no blend). ``theta (P, 7)``.
    Returns ``(theta of the blend (N, 7), t (N, 1))``, on ``theta``'s device and in its dtype.
    """
    n = rows.shape[0]
    if n == 0:
        return theta.new_empty(0, theta.shape[1]), theta.new_empty(0, 1)
    (diel, met), _ = blend_ends(theta, metal, rows, size, sigmas)
    met = torch.cat((met[:, 0:3], diel[:, 3:4], met[:, 4:5]), -1)
    normal, sub = decode(theta[rows], metal[rows])["normal"], data.subset(rows)

    def blend(t: Tensor) -> Tensor:  # theta of the blend at coverages t (k N, 1): k per pixel, value-major
        k = t.shape[0] // n
        v = diel.repeat(k, 1) * (1 - t) + met.repeat(k, 1) * t
        return encode({"base_color": v[:, 0:3], "specular": v[:, 3:4], "roughness": v[:, 4:5],
                       "normal": normal.repeat(k, 1)})

    # Several grid values of every pixel per evaluation: fewer calls' fixed cost, at most
    # UNMIX_PIXELS pixel-values per call (a bounded batch at any size).
    parts = []
    grid = torch.linspace(0, 1, steps, dtype=theta.dtype, device=theta.device)
    for values in grid.split(max(1, UNMIX_PIXELS // n)):
        t_k = values.repeat_interleave(n)[:, None]
        each = torch.arange(n, device=theta.device).repeat(values.shape[0])
        parts.append(_pixel_cost(sub.residual(blend(t_k), t_k, idx, model, rows=each)).view(-1, n))
    costs = torch.cat(parts).T  # (N, steps)
    k = costs.argmin(-1, keepdim=True)  # _pixel_cost: a NaN cost is already +inf
    t = k.to(theta.dtype) / (steps - 1)
    # Between grid values: the vertex of the parabola through the best and its two neighbours
    # (an end of [0, 1] stays exact: a clear pixel's blend is its own class).
    inner = (k > 0) & (k < steps - 1)
    km, kp = (k - 1).clamp(min=0), (k + 1).clamp(max=steps - 1)
    cm, c0, cp = costs.gather(-1, km), costs.gather(-1, k), costs.gather(-1, kp)
    curv = cm - 2 * c0 + cp
    fit = inner & torch.isfinite(cm) & torch.isfinite(cp) & (curv > 0)
    shift = torch.where(fit, 0.5 * (cm - cp) / torch.where(fit, curv, 1.0), 0.0)  # |shift| ≤ ½: c0 least
    t = t + shift / (steps - 1)
    t = torch.where(torch.isfinite(c0), t, float("nan"))
    return torch.where(torch.isnan(t), float("nan"), blend(t)), t


def may_be_mixed(coverage: Tensor, metal: Tensor, cost: Tensor, quiet: float) -> Tensor:
    """The soft-metal candidates ``(N,)`` bool that stay in the final stage's metallic fits.

    Left out: a candidate whose best blend of its clear neighbours (``coverage (N, 1)``,
    :func:`unmix_metallic`) is its own class ``metal (N, 1)`` and whose data ``cost (N, 1)``
    is at most ``quiet`` (the caller's noise level: 1.5 × the median pixel's, the 98.5th
    percentile of 51 residuals' noise). Nothing in its data asks for a mixture, and one more
    unknown would only fit noise: at the median, 1 of 2813 such pixels (rusted_metal 4) and 1 of
    7088 (dusty_metal 3) left their class in the free fit; up to 1.5 × it, 2-3 % of them end
    fractional, their mean metallic error after the stage 0.0018 against 0.0015 as they were
    (dusty_metal 102) and 0.0020 against 0.0027 (rusted_metal 101), and leaving them out takes
    a third (dusty_metal 102) to an eighth (rusted_metal 101) of the stage's time
    (docs/recovery.md, issue 18). A candidate with no blend (NaN coverage) stays.
    """
    return ~((coverage == metal) & (cost <= quiet))[:, 0]


def growth_front(metal: Tensor, tried: Tensor, size: int) -> Tensor:
    """Pixels ``(N,)`` (indices) beside a run of fractional metallic that were not refitted yet.

    ``metal (P, 1)``, ``tried (P,)`` bool. A run: a fractional pixel with a fractional
    4-neighbour (an isolated one, on a binary material, is not a ramp and does not grow);
    beside: its 8-neighbourhood (the run's own untried pixels included). int64 indices on
    ``metal``'s device.
    """
    fr = ((metal > 0) & (metal < 1)).to(metal.dtype)
    run = (fr[:, 0] > 0) & (_neighbour_mean(fr, size)[:, 0] > 0)
    return torch.nonzero(_dilate(run, size) & ~tried).flatten()


def _soft_prior(x: Tensor, well: float, target: Tensor | None = None, smooth: float | Tensor = 0.0,
                line: tuple[Tensor, Tensor] | None = None, line_weight: float | Tensor = 0.0
                ) -> tuple[Tensor, Tensor]:
    """The prior residuals of the soft-metal unknowns ``x (N, 8)`` and their Jacobian.

    The double-well term ``√well · m (1 − m)`` (its square is ``well m² (1 − m)²``) on metallic
    ``m = x[:, 7]``; with ``target (N, 1)``, the pull ``√smooth · (m − target)`` toward the
    metallic the neighbours suggest; with ``line = (dielectric, metal)`` base colours ``(N, 3)``
    each, ``√line_weight · (base − ((1 − m) dielectric + m metal))`` per channel (base =
    sigmoid of ``x[:, 0:3]``): the base colour a blend of the two at the pixel's own metallic
    would have. ``smooth``, ``line_weight``: a float or ``(N, 1)``.
    Returns ``(residuals (N, k), Jacobian (N, k, 8))``, k = 1 [+ 1] [+ 3], on ``x``'s device
    and in its dtype.
    """
    m = x[:, 7:8]
    cols = torch.arange(x.shape[1], device=x.device)
    metal_col = (cols == 7).to(x.dtype)  # (8,)
    sw = math.sqrt(well)
    res, jac = [sw * m * (1 - m)], [(sw * (1 - 2 * m))[..., None] * metal_col]
    if target is not None:
        ss = smooth.sqrt() if isinstance(smooth, Tensor) else torch.full_like(m, math.sqrt(smooth))
        res.append(ss * (m - target))
        jac.append(ss[..., None] * metal_col)
    if line is not None:
        sl = (line_weight.sqrt() if isinstance(line_weight, Tensor)
              else torch.full_like(m, math.sqrt(line_weight)))  # (N, 1)
        diel, met = line
        base = torch.sigmoid(x[:, 0:3])
        res.append(sl * (base - (diel + m * (met - diel))))
        jac.append(torch.cat((torch.diag_embed(sl * base * (1 - base)), base.new_zeros(*base.shape, 4),
                              (-sl * (met - diel))[..., None]), -1))  # (N, 3, 8)
    return torch.cat(res, -1), torch.cat(jac, 1)


_Rows = Tensor | None  # pixel indices into an LM call's N pixels; None: all of them


def _at(v: Any, r: _Rows) -> Any:
    """A per-pixel tensor (or a tuple or dict of them) at rows ``r``; None rows or a float: as is."""
    if isinstance(v, tuple):
        return tuple(_at(x, r) for x in v)
    if isinstance(v, dict):
        return {k: _at(x, r) for k, x in v.items()}
    return v[r] if isinstance(v, Tensor) and r is not None else v


def _soft_lm(jvp: Callable[[Tensor, Tensor, _Rows], tuple[Tensor, Tensor]],
             cost: Callable[[Tensor, _Rows], Tensor], x: Tensor, iters: int, fix_metal: bool = False,
             prior: Callable[[Tensor, _Rows], tuple[Tensor, Tensor]] | None = None, tol: float = 1e-3,
             held: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``iters`` per-pixel LM iterations on ``x (N, 8)`` (the data residuals and their
    derivatives along K directions from ``jvp``, as :meth:`LevelData.residual_jvp`; metallic —
    the last column — clamped to [0, 1] after each step; held fixed with ``fix_metal``, which
    then has no tangent: 5 instead of 6 per Jacobian, :func:`fit_jacobian`). ``prior``: the
    prior residuals and their Jacobian (``x`` → ``(N, k)``, ``(N, k, 8)``, as
    :func:`_soft_prior`), added to the normal equations by hand (they are not part of the data
    residuals' forward-mode Jacobian, which would copy them once per tangent); ``cost`` must
    be the summed squares of both (a linearised candidate's cost is taken from them: only the
    last iteration's candidates are costed by ``cost``). ``jvp``, ``cost`` and ``prior`` take
    the unknowns of some of the pixels and their indices (``None``: all N, in order); the
    base-colour unknowns act each on its own channel's residuals (:func:`fit_jacobian`).
    ``held (N, 8)`` bool: unknowns kept at their start (None: none held but metallic with
    ``fix_metal``, which ignores its column 7; a held metallic is still clamped to [0, 1]).

    A pixel whose accepted step (at no more than the starting damping) lowered its finite cost by
    less than ``tol`` of it has converged and leaves the iterations (0: every pixel runs every
    iteration): most of a warm-started refit's pixels settle in two or three (soft-metal stage:
    40–60 % of its LM work saved, maps within measurement noise, docs/recovery.md).
    Returns ``(x, cost (N, 1))``, on ``x``'s device and in its dtype."""
    n_t = x.shape[1] - 1 if fix_metal else x.shape[1]  # the unknowns that move
    lam0 = 1e-2  # the starting damping
    lam = torch.full((x.shape[0], 1), lam0, dtype=x.dtype, device=x.device)

    def linearise(v: Tensor, rows: _Rows) -> tuple[Tensor, Tensor, Tensor]:
        # The cost (n, 1) at v and its normal equations (n, n_t, n_t), (n, n_t): the residuals
        # come with the Jacobian (the same values `cost` gives).
        r, jac = fit_jacobian(lambda u, tg: jvp(u, tg, rows), v, n_t)  # (n, M), (n, n_t, M)
        pr, pj = prior(v, rows) if prior is not None else (r[:, :0], None)
        c = _pixel_cost(torch.cat((r, pr), -1))
        r = r.nan_to_num_()  # (a fresh tensor of the jvp: cleaned in place)
        # (the gradients, and the priors' few rows, as products and sums: a batch of small
        # matrix-vector products is slower, 4.4 against 3.3 ms at 8500 pixels)
        jtj = torch.bmm(jac, jac.transpose(1, 2))
        g = (jac * r[:, None, :]).sum(-1)
        if pj is not None:
            pj = pj[..., :n_t]  # (n, k, n_t)
            jtj = jtj + (pj[..., :, None] * pj[..., None, :]).sum(1)
            g = g + (pj * pr[..., None]).sum(1)
        if held is not None:
            jtj, g = _hold(jtj, g, _at(held, rows)[:, :n_t])
        return c, jtj, g

    # Each candidate step is judged by its cost, which its linearisation gives too: an accepted
    # step's normal equations are the next iteration's, a rejected one keeps the pixel's own,
    # and only the last iteration's candidates are evaluated without their Jacobian (one
    # residual evaluation per iteration less than linearising each accepted point anew).
    # (the first iteration runs on every pixel and replaces x, c, lam, jtj, g with new tensors:
    # the caller's x is never written to)
    c, jtj, g = linearise(x, None)
    active = torch.arange(x.shape[0], device=x.device)
    for it in range(iters):
        if active.numel() == 0:
            break
        rows: _Rows = None if active.numel() == x.shape[0] else active
        if rows is None:
            xa, ca, la, ja, ga = x, c, lam, jtj, g
        else:
            xa, ca, la, ja, ga = x[rows], c[rows], lam[rows], jtj[rows], g[rows]
        h = ja + torch.diag_embed(la * (torch.diagonal(ja, dim1=-2, dim2=-1) + 1e-6))
        step = torch.nan_to_num(torch.linalg.solve(h, -ga[..., None])[..., 0]).clamp(-3, 3)
        cand = xa + torch.nn.functional.pad(step, (0, x.shape[1] - n_t))
        cand = torch.cat((cand[:, :-1], cand[:, -1:].clamp(0.0, 1.0)), -1)
        last = it == iters - 1
        if last:
            c1 = cost(cand, rows)
        else:
            c1, j1, g1 = linearise(cand, rows)
        better = c1 < ca
        new_x, new_c = torch.where(better, cand, xa), torch.where(better, c1, ca)
        new_l = torch.where(better, (la * 0.3).clamp(min=1e-5), (la * 10).clamp(max=1e6))
        if rows is None:
            x, c, lam = new_x, new_c, new_l
        else:
            x[rows], c[rows], lam[rows] = new_x, new_c, new_l
        if not last:
            new_j, new_g = torch.where(better[..., None], j1, ja), torch.where(better, g1, ga)
            if rows is None:
                jtj, g = new_j, new_g
            else:
                jtj[rows], g[rows] = new_j, new_g
        # Converged: an accepted step that gained less than tol of a finite cost, taken at no more
        # than the starting damping (after rejected steps a step is short because of the
        # damping, not because the pixel is done; a rejected step is not convergence either).
        done = (better & (la <= lam0) & torch.isfinite(ca) & (ca - c1 <= tol * ca))[:, 0]
        active = active[~done]
    return x, c


def _snap_metallic(m: Tensor, snap: float) -> Tensor:
    """Metallic ``m (N, 1)`` with values within ``snap`` of 0 or 1 set to them.

    A 1 % lobe is below what the noise can tell apart: a clear pixel. ``m``'s dtype and device.
    """
    return torch.where(m < snap, torch.zeros_like(m), torch.where(m > 1 - snap, torch.ones_like(m), m))


def _soft_energy(sub: LevelData, idx: list[int], model: str, well: float, target: Tensor | None = None,
                 smooth: float | Tensor = 0.0, line: tuple[Tensor, Tensor] | None = None,
                 line_weight: float | Tensor = 0.0) -> tuple[Callable, Callable, Callable]:
    """The final stage's energy of ``sub``'s pixels, as :func:`_soft_lm` takes it.

    Returns ``(jvp, prior, cost)`` of some of the pixels' unknowns ``x (n, 8)`` by their
    indices: the data residuals on lights ``idx`` and their derivatives, the prior residuals
    (:func:`_soft_prior`; ``target``, ``smooth``, ``line``, ``line_weight`` per pixel of ``sub``
    or floats) and their Jacobian, and the summed cost ``(n, 1)`` of both, on ``sub``'s device
    and in its dtype.
    """
    def residual(v: Tensor, r: _Rows) -> Tensor:
        return sub.residual(v[:, :7], v[:, 7:8], idx, model, rows=r)

    def jvp(v: Tensor, tg: Tensor, r: _Rows) -> tuple[Tensor, Tensor]:
        return sub.residual_jvp(v, v[:, 7:8], idx, model, tg, rows=r)

    def prior(v: Tensor, r: _Rows) -> tuple[Tensor, Tensor]:
        return _soft_prior(v, well, _at(target, r), _at(smooth, r), _at(line, r), _at(line_weight, r))

    return jvp, prior, lambda v, r: _pixel_cost(torch.cat((residual(v, r), prior(v, r)[0]), -1))


def soft_metal_fit(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   well: float, gain: float | Tensor, iters: int = 8, starts: tuple = (None, 0.5),
                   target: Tensor | None = None, smooth: float | Tensor = 0.0, refit_reference: bool = True,
                   snap: float = 0.02, line: tuple[Tensor, Tensor] | None = None,
                   line_weight: float | Tensor = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel LM on 8 unknowns — theta (7) and a continuous metallic in [0, 1] — for ``rows (N,)``.

    Energy: data (lights ``idx``) + the double-well prior ``well · m²(1 − m)²`` (minima at exactly
    0 and 1) [+ ``smooth · (m − target)²``, ``target (N, 1)``, ``smooth`` a float or ``(N, 1)``:
    the metallic the neighbours suggest, which decides where the data cannot — a rough metal's
    broad lobe mimics a rough dielectric's diffuse] [+ ``line_weight · |base − ((1 − m) d + m e)|²``,
    ``line = (d, e)`` base colours ``(N, 3)``: the blend of a dielectric and a metal at the
    pixel's own metallic, which holds a fractional pixel's base colour where the data trade it
    against metallic]. Metallic is a bounded value, clamped to
    [0, 1] after each step (projected LM), so
    a pixel can land on exactly 0 or 1. The Jacobian is forward-mode (:func:`fit_jacobian`,
    6 tangents for the 8 unknowns, 5 with metallic held). ``starts``: metallic start values,
    ``None`` = the pixel's own, ``"target"`` = ``target``, a float, or ``(theta start (N, 7),
    one of those)``; the lowest
    energy wins. A fractional result replaces a binary ``metal`` only where it lowers the
    energy — the pulls included: where the data cannot tell, the metallic they suggest is the
    evidence — by more than ``gain`` (a float, or ``(N, 1)`` per pixel; the caller scales it by the
    noise variance) below the same fit with metallic held at its own value (with
    ``refit_reference``; else below ``theta``, ``metal`` as given): one more unknown always
    fits noise a little, and a clear pixel must stay exactly 0 or 1 (it then keeps the better
    of its old and its refitted 7 unknowns — its old ones where the free fit does not beat even
    the unrefitted reference, which is then not refitted — or of its old and the free fit's
    where the free fit ended on its class); a metallic within ``snap`` of 0 or 1 is set to it
    (and judged there).
    ``theta (P, 7)``, ``metal (P, 1)``.
    Returns ``(theta rows (N, 7), metal rows (N, 1), changed (N,))``.
    """
    if rows.numel() == 0:
        return theta[rows], metal[rows], torch.zeros(0, dtype=torch.bool, device=theta.device)
    sub = data.subset(rows)
    t0, m0 = theta[rows], metal[rows]

    jvp, prior, cost = _soft_energy(sub, idx, model, well, target, smooth, line, line_weight)

    best, best_c = None, None
    for m_start in starts:
        # Several metallic starts: a pixel that is 30 % metal has another local optimum near
        # the class it was given.
        t_init = t0
        if isinstance(m_start, tuple):  # (theta start (N, 7), metallic start)
            t_init, m_start = m_start
        m_init = m0 if m_start is None else target if m_start == "target" else torch.full_like(m0, m_start)
        assert m_init is not None, "soft_metal_fit: a 'target' start needs `target`"
        x, c = _soft_lm(jvp, cost, torch.cat((t_init, m_init), -1), iters, prior=prior)
        best, best_c = _keep_better(best, best_c, x, c)
    assert best is not None and best_c is not None, "soft_metal_fit: `starts` must not be empty"
    # Within `snap` of 0 or 1 is a clear pixel: a 1 % lobe is below what the noise can tell
    # apart, so it is set exactly.
    m = best[:, 7:8]
    m_snap = _snap_metallic(m, snap)
    snapped = m_snap != m
    best = torch.cat((best[:, :7], m_snap), -1)
    if bool(snapped.any()):  # judged by the energy of what is returned
        best_c = torch.where(snapped, cost(best, None), best_c)
    ref = torch.cat((t0, m0), -1)  # the solution so far (a binary one: no double-well cost)
    c_ref = cost(ref, None)
    keep = torch.zeros_like(c_ref, dtype=torch.bool)
    # The reference a fractional (or other-class) result must beat: the same per-pixel fit
    # with metallic held at the pixel's own value, so it wins by what it explains, not by the
    # refit of the other unknowns (the main fit's priors leave some pixels off their data
    # optimum). Only where the free fit left the pixel's class (about 40 % of pass 1's pixels):
    # one it returned to its own class has nothing to judge, and keeps the better of its old
    # unknowns and the free fit's (snapped to its class).
    # A refit only lowers the reference, so a pixel whose result does not beat even the
    # unrefitted one (by the gain, where newly fractional) is refused either way and keeps its
    # old unknowns: only the others are refitted (dusty_metal 3: 6057 of 12519 pixels that left
    # their class).
    newly_fractional = (m_snap > 0) & (m_snap < 1) & ((m0 == 0) | (m0 == 1))
    margin = torch.where(newly_fractional, gain, 0.0)
    away = torch.nonzero(((m_snap != m0) & (best_c < c_ref - margin))[:, 0]).squeeze(1) if refit_reference \
        else rows[:0]
    if away.numel():
        jvp_a, prior_a, cost_a = _soft_energy(sub.subset(away), idx, model, well, _at(target, away),
                                              _at(smooth, away), _at(line, away), _at(line_weight, away))
        ref_a, c_fix = _soft_lm(jvp_a, cost_a, ref[away], iters, fix_metal=True, prior=prior_a)
        keep_a = c_fix < c_ref[away]
        ref[away] = torch.where(keep_a, ref_a, ref[away])
        c_ref[away] = torch.where(keep_a, c_fix, c_ref[away])
        keep[away] = keep_a
    accepted = (best_c < c_ref - margin)[:, 0]
    best = torch.where(accepted[:, None], best, ref)
    accepted = accepted | keep[:, 0]
    return best[:, :7], best[:, 7:8], accepted


def soft_rough_tie(data: LevelData, theta: Tensor, metal: Tensor, rows: Tensor, idx: list[int], model: str,
                   well: float, margin: float, glossy: float = 0.2, rough: float = 0.85, iters: int = 8,
                   coverage: Tensor | None = None, snap: float = 0.02) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`rough_basin_tie` in the final stage, where a blend of metal and dielectric is an answer.

    At a metal's edge a rough, partly metal rim (dusty_metal 162: 15-25 % metal, roughness 0.8) fits its
    images as well as a glossy dielectric with a strong specular whose lobe falls between the lights:
    the binary tie cannot tell them apart (a dielectric's F0 stops at 0.08) and the final stage's free
    fit stays in the glossy basin, which a held-out light then shows as a firefly. Here each of
    ``rows (N,)`` (int64 indices into the P pixels) with metallic below 1 and roughness below
    ``glossy`` is refitted twice on 8 unknowns (:func:`_soft_energy`: data on lights ``idx`` and the
    double-well ``well`` only, none of the stage's pulls; ``iters`` LM iterations, as the binary
    tie's) — with its roughness held at its own value, and free from ``rough`` with metallic from
    ``coverage (P, 1)`` (the blend of its clear neighbours, :func:`unmix_metallic`; ½ where NaN or
    None; clamped to ``[snap, 1 − snap]``) — and takes the second where that stayed rough (above
    ``2 × glossy``) at a finite energy at most ``margin`` (in the energy's units: the caller scales
    it by the noise variance) above the first. A metallic within ``snap`` of 0 or 1 is set to it
    before that comparison (the other unknowns refitted with it held) and judged there. Roughness is
    free on the rough side: held at one value, a rough metal's lobe misses (the rim's truth is
    0.76-0.82). ``theta (P, 7)``, ``metal (P, 1)``.
    Returns ``(theta (P, 7), metal (P, 1), moved (P,) bool)`` on ``theta``'s device, in its dtype.
    """
    moved = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    test = rows[(decode(theta[rows], metal[rows])["roughness"][:, 0] < glossy) & (metal[rows, 0] < 1)]
    if test.numel() == 0:
        return theta, metal, moved
    x0 = torch.cat((theta[test], metal[test]), -1)
    start = x0.clone()
    start[:, 4] = _logit(torch.full_like(start[:, 4], rough), _R_MIN, _R_MAX)
    u = torch.full_like(start[:, 7], 0.5) if coverage is None else coverage[test, 0]
    start[:, 7] = torch.nan_to_num(u, nan=0.5).clamp(snap, 1 - snap)
    # Both fits in one LM call (each pixel twice: glossy held, then rough free; the pixels'
    # iterations are independent, so this only saves the calls' fixed cost)
    n = test.numel()
    jvp, prior, cost = _soft_energy(data.subset(torch.cat((test, test))), idx, model, well)
    held = torch.zeros(2 * n, x0.shape[1], dtype=torch.bool, device=x0.device)
    held[:n, 4] = True  # the glossy fit's roughness logit
    x, c = _soft_lm(jvp, cost, torch.cat((x0, start)), iters, prior=prior, held=held)
    c_glossy, x, c_rough = c[:n], x[n:], c[n:]
    m = x[:, 7:8]
    m_snap = _snap_metallic(m, snap)
    snapped = (m_snap != m)[:, 0]
    x = torch.cat((x[:, :7], m_snap), -1)
    if bool(snapped.any()):
        # Judged at the value returned (a 0.985 would become a full metal), after a refit of the
        # others with it held: a rough dielectric left at metallic 0.01 fits a little worse at 0
        # until its base colour follows.
        s_rows = snapped.nonzero()[:, 0]
        jvp_s, prior_s, cost_s = _soft_energy(data.subset(test[s_rows]), idx, model, well)
        x_s, c_s = _soft_lm(jvp_s, cost_s, x[s_rows], iters, fix_metal=True, prior=prior_s)
        x[s_rows], c_rough[s_rows] = x_s, c_s
    stayed_rough = decode(x[:, :7], x[:, 7:8])["roughness"][:, 0] > 2 * glossy
    take = (torch.isfinite(c_rough) & (c_rough <= c_glossy + margin))[:, 0] & stayed_rough
    theta, metal = theta.clone(), metal.clone()
    theta[test[take]], metal[test[take]] = x[take, :7], x[take, 7:8]
    moved[test[take]] = True
    return theta, metal, moved


def _candidate_slopes(dtype, device, tilts=(8.0, 16.0, 24.0, 32.0, 40.0), azimuths: int = 8) -> Tensor:
    """Normal slopes ``(K, 2)``: the flat normal and a polar grid of tilts (degrees)."""
    out = [torch.zeros(1, 2, dtype=torch.float64)]
    for k, t in enumerate(tilts):
        az = (torch.arange(azimuths, dtype=torch.float64) + 0.5 * (k % 2)) * (2 * math.pi / azimuths)
        out.append(math.tan(math.radians(t)) * torch.stack((az.cos(), az.sin()), -1))
    return torch.cat(out).to(dtype=dtype, device=device)


def normal_search(data: LevelData, theta: Tensor, metal: Tensor, model: str, factor: float = 10.0,
                  max_pixels: int = 4096) -> tuple[Tensor, int]:
    """Re-seed badly fitted pixels by a discrete search over normals and neighbours' parameters.

    Gauss–Newton only walks downhill: a glossy pixel whose normal starts 30° off (the steep
    rim of an inlay, where the upsampled coarse level is flat) never finds its highlight.
    Pixels whose data cost exceeds ``factor`` × the median cost (the noise level) try every
    combination of {their own, their 8 same-class neighbours'} parameters × a grid of
    normals (flat, tilts 8–40°, 8 azimuths), and keep the best if it lowers their cost.
    At most ``max_pixels`` (the worst) are searched per call.

    Returns ``(theta (P, 7), number of pixels changed)``.
    """
    size, c = data.size, theta.shape[1]
    idx = data.train_idx
    cost = torch.nan_to_num((data.residual(theta, metal, idx, model) ** 2).sum(-1), nan=float("inf"))
    thr = factor * float(cost[torch.isfinite(cost)].median()) if bool(torch.isfinite(cost).any()) else float("inf")
    bad = torch.nonzero(cost > thr).flatten()
    if bad.numel() == 0:
        return theta, 0
    if bad.numel() > max_pixels:
        bad = bad[torch.topk(cost[bad], max_pixels).indices]
    # Own parameters and the 8 neighbours' (replicated border), same class only.
    r, col = bad // size, bad % size
    base_list, valid_list = [], []
    for dy, dx in ((0, 0), (-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        q = (r + dy).clamp(0, size - 1) * size + (col + dx).clamp(0, size - 1)
        base_list.append(theta[q])
        valid_list.append(metal[q, 0] == metal[bad, 0])
    bases = torch.stack(base_list, 1)  # (B, 9, 7)
    valid = torch.stack(valid_list, 1)  # (B, 9)
    slopes = _candidate_slopes(theta.dtype, theta.device)  # (K, 2)
    nb, nbase, k = bad.numel(), bases.shape[1], slopes.shape[0]
    cand = bases[:, :, None, :].expand(nb, nbase, k + 1, c).clone()
    cand[:, :, 1:, 5:7] = slopes[None, None]  # index 0 keeps the base's own normal
    cand = cand.reshape(nb, -1, c)
    ccost = torch.empty(cand.shape[:2], dtype=theta.dtype, device=theta.device)
    chunk = max(1, 65536 // cand.shape[1])
    for s0 in range(0, nb, chunk):
        sl = slice(s0, s0 + chunk)
        n = cand[sl].shape[0]
        rows = bad[sl].repeat_interleave(cand.shape[1])
        rr = data.residual(cand[sl].reshape(-1, c), metal[rows], idx, model, rows=rows)
        ccost[sl] = torch.nan_to_num((rr * rr).sum(-1), nan=float("inf")).reshape(n, -1)
    ccost = torch.where(valid[:, :, None].expand(nb, nbase, k + 1).reshape(nb, -1), ccost, float("inf"))
    best_cost, best = ccost.min(1)
    better = best_cost < cost[bad]
    theta = theta.clone()
    theta[bad[better]] = cand[better, best[better]]
    return theta, int(better.sum())


# --------------------------------------------------------------------------------------
# Driver with checkpoints
# --------------------------------------------------------------------------------------


def _schedule(size: int, cfg: RecoveryConfig) -> list[tuple[int, str, int]]:
    """Stages ``(level size, kind, iterations)``; kind in dual / polish / all."""
    sizes = []
    s = size
    for _ in range(max(1, cfg.levels)):
        sizes.append(s)
        if s // 2 < 16:
            break
        s //= 2
    sizes = sizes[::-1]
    default = {"dual_coarse": 14, "dual": 6, "polish": 10, "all": 3}
    plan = []
    for k, s in enumerate(sizes):
        plan.append((s, "dual", default["dual_coarse"] if k == 0 else default["dual"]))
    plan.append((sizes[-1], "polish", default["polish"]))
    plan.append((sizes[-1], "all", default["all"]))
    if cfg.iters:
        total = sum(p[2] for p in plan)
        scaled = [max(1, round(p[2] * cfg.iters / total)) for p in plan]
        plan = [(p[0], p[1], n) for p, n in zip(plan, scaled)]
    return plan


def _upsample(x: Tensor, s0: int, s1: int, mode="bilinear") -> Tensor:
    img = x.T.reshape(1, -1, s0, s0)
    kw = {"align_corners": False} if mode == "bilinear" else {}
    up = F.interpolate(img, size=(s1, s1), mode=mode, **kw)
    return up[0].reshape(x.shape[1], -1).T.contiguous()


def _neighbour_count(label: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Number of metal pixels among each pixel's 8 neighbours, and the number of neighbours it has.

    ``label (P, 1)`` in {0, 1} → two ``(P, 1)`` maps. Pixels on the image edge have 5
    neighbours, corners 3: the outside is *absent*, not a copy of the edge (replicate padding
    made an edge pixel its own neighbour, so a wrong pixel on the edge outvoted its real
    neighbours and an edge row of one class could never be flipped by the rows inside).
    """
    img = label.T.reshape(1, 1, size, size)
    ones = torch.ones_like(img)
    s = F.avg_pool2d(F.pad(img, (1, 1, 1, 1)), 3, 1) * 9 - img
    n = F.avg_pool2d(F.pad(ones, (1, 1, 1, 1)), 3, 1) * 9 - ones
    return s.reshape(-1, 1), n.reshape(-1, 1)


def unconverged_dielectric_rows(cost_diel: Tensor, cost_metal: Tensor, margin: float,
                                factor: float = 5.0) -> Tensor:
    """Pixels ``(N,)`` whose metal win is no evidence: the dielectric hypothesis never converged.

    The metal wins (``cost_metal < margin × cost_diel``, data costs ``(P, 1)``), the dielectric
    fits above ``factor`` × its median cost (the noise level) and the metal does not fit at the
    noise level either (> 2× that median; a metal that does is a metal, and skipping it keeps
    metal-heavy captures cheap — the border rims' metal fits were 2–10× it). ``factor`` 5: a
    run of the README example's bottom-edge grout (tiles 7, row 252) had its dielectric stuck
    at 7–11× the median and was called metal with 10. Returns int64 indices on the costs' device.
    """
    med = float(cost_diel.median())
    sus = (cost_metal < margin * cost_diel) & (cost_diel > factor * med) & (cost_metal > 2.0 * med)
    return torch.nonzero(sus[:, 0]).flatten()


def _choose_class(cost_diel: Tensor, cost_metal: Tensor, margin: float, size: int, sweeps: int = 8) -> Tensor:
    """Per-pixel metal (1) / dielectric (0) choice ``(P, 1)`` from the two hypotheses' data costs.

    Decisive pixels follow the data: metal when its cost is below ``margin`` × the
    dielectric's, dielectric when above ``1 / margin`` × it. The pixels in between are ones the
    data cannot decide — typically a metal far from every highlight, whose tail a black
    glossy dielectric reproduces as well — and take the majority class of their
    neighbours (8 inside the image, 5 on an edge, 3 in a corner; a few
    iterated-conditional-modes sweeps grow the decisive regions into them); with no
    decisive neighbourhood they stay dielectric, the common case.
    """
    ratio = cost_metal / cost_diel.clamp(min=1e-30)
    sure_metal = ratio < margin
    ambiguous = ~sure_metal & (ratio <= 1.0 / margin)
    label = sure_metal.to(cost_diel.dtype)
    for _ in range(sweeps if bool(ambiguous.any()) else 0):
        metal_nb, n_nb = _neighbour_count(label, size)
        label = torch.where(ambiguous, (metal_nb > 0.5 * n_nb).to(label.dtype), label)
    return label


def _majority(metal: Tensor, size: int) -> Tensor:
    """3×3 majority vote ``(P, 1)`` over the pixel and its neighbours that exist."""
    metal_nb, n_nb = _neighbour_count(metal, size)
    return ((metal_nb + metal) > 0.5 * (n_nb + 1)).to(metal.dtype)


def _despeckle(metal: Tensor, size: int) -> Tensor:
    """Flip isolated choices ``(P, 1)``: at most one in 8 of the pixel's neighbours agrees with it
    (on an edge: none of its 5; keeps one-pixel-wide lines, which have 2 agreeing neighbours)."""
    metal_nb, n_nb = _neighbour_count(metal, size)
    agree = torch.where(metal > 0.5, metal_nb, n_nb - metal_nb)
    return torch.where(agree * 8 <= n_nb, 1 - metal, metal)


class Recovery:
    """The resumable optimisation state machine (see the module docstring)."""

    def __init__(self, cap: Capture, cfg: RecoveryConfig, out: Path | None = None,
                 log: Callable[[str], Any] = print):
        self.cap, self.cfg, self.out, self.log = cap, cfg, out, log
        self.size = cfg.size or max(cap.width, cap.height)
        n_l = len(cap)
        if cfg.holdout is not None:
            self.holdout = cfg.holdout if cfg.holdout >= 0 else None  # -1: none (recover checks the range)
        else:
            self.holdout = 0 if n_l >= 5 else None
        self.train_idx = [k for k in range(n_l) if k != self.holdout]
        self.eps = float(0.01 * cap.images.clamp(min=0).mean())
        self.plan = _schedule(self.size, cfg)
        self.stop_requested = False
        self._data: dict[tuple[int, bool], LevelData] = {}
        # Each hypothesis' data cost per pixel (P,) on the training lights after the last LM step
        # (before that iteration's light-calibration update), per light and channel: the fit loss
        # the progress bar shows. Not state: every iteration sets it anew.
        self.fit_cost: dict[int, Tensor] = {}
        # The Gauss–Newton pass made at a single-class stage's start for its F0 tie, with the
        # theta and metal it was made at: the stage's first LM step re-linearises only the
        # pixels that moved since (its propagation moves 1–5 %). Not state: a resumed run
        # computes the step's own.
        self._stage_gn: tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor]] | None = None
        self.state: dict[str, Any] = {}  # filled by init_state / load_checkpoint

    def data(self, size: int, all_lights: bool = False) -> LevelData:
        key = (size, all_lights)
        if key not in self._data:
            idx = list(range(len(self.cap))) if all_lights else self.train_idx
            self._data[key] = LevelData(self.cap, size, idx, self.eps)
        return self._data[key]

    # -- state ---------------------------------------------------------------------------
    def init_state(self) -> None:
        s0 = self.plan[0][0]
        d = self.data(s0)
        n, alb = photometric_stereo(d, self.train_idx)
        p = d.points.shape[0]
        ones = torch.ones(p, 1, dtype=alb.dtype, device=alb.device)
        diel = encode({"base_color": alb, "specular": 0.5 * ones, "roughness": 0.5 * ones, "normal": n})
        flat = torch.zeros_like(n)
        flat[:, 2] = 1.0  # Lambertian normals mean nothing on a metal: start it flat
        met = encode({"base_color": torch.full_like(alb, 0.7), "specular": 0.5 * ones,
                      "roughness": 0.4 * ones, "normal": flat})
        self.state = {
            "stage": 0, "it": 0, "global_it": 0, "lr": float(self.cfg.lr),
            "theta": [diel, met], "lam": [torch.full_like(ones, 1e-2), torch.full_like(ones, 1e-2)],
            "metal": None, "history": [], "events": [], "seconds": 0.0,
        }

    def save_checkpoint(self) -> None:
        """Write ``OUT/checkpoint.pt`` atomically (nothing when there is no ``out``).

        It holds the state, the plan, the RNG state and ``self.fingerprint`` (set by the
        driver, :mod:`torchbrdf.recovery.svbrdf`: what the checkpoint belongs to). The blob is
        serialised in memory first so that a full disk surfaces as ``OSError(ENOSPC)`` from
        the file write (torch's own writer reports it as an opaque ``RuntimeError``).
        """
        if self.out is None:
            return
        import io

        blob = {"state": self.state, "plan": self.plan, "config": vars(self.cfg) | {"schedule": []},
                "torch_rng": torch.get_rng_state(), "fingerprint": getattr(self, "fingerprint", None)}
        buf = io.BytesIO()
        torch.save(blob, buf)
        with atomic_path(self.out / CHECKPOINT) as tmp, open(tmp, "wb") as f:
            f.write(buf.getbuffer())

    def load_checkpoint(self, path: Path, check: Callable[[dict], Any] | None = None) -> dict:
        """Restore the state saved by :meth:`save_checkpoint`; returns the checkpoint blob.

        ``check(blob)``, when given, runs before anything is restored and may raise (the
        driver compares fingerprints there).

        Raises:
            ValueError: the file is not a readable recovery checkpoint (the message names it),
                or it was made with a different schedule.
        """
        try:
            # weights_only: tensors and plain Python containers only, so a checkpoint placed
            # in OUT cannot run code when loaded.
            blob = torch.load(path, weights_only=True, map_location=self.cap.images.device)
            if not isinstance(blob, dict) or not {"state", "plan", "torch_rng"} <= blob.keys():
                raise ValueError("not a recovery checkpoint")
        except Exception as e:  # truncated, corrupt, or another kind of file
            why = (str(e).strip().splitlines() or [""])[0][:160]
            raise ValueError(f"{path}: corrupt or unreadable checkpoint ({type(e).__name__}"
                             f"{': ' + why if why else ''}); delete it to start over") from e
        if check is not None:
            check(blob)
        if blob["plan"] != self.plan:
            raise ValueError(f"{path}: checkpoint was made with a different schedule {blob['plan']}, now {self.plan}")
        self.state = blob["state"]
        torch.set_rng_state(blob["torch_rng"])
        return blob

    # -- one iteration ---------------------------------------------------------------------
    def light_log_scale(self) -> Tensor:
        """Estimated per-light log intensity scales ``(L,)`` (0: as stated in capture.json)."""
        s = self.state.get("light_log_scale") if self.state else None
        return s if s is not None else torch.zeros(len(self.cap), dtype=self.cap.light_intensities.dtype,
                                                    device=self.cap.light_intensities.device)

    def light_offset(self) -> Tensor:
        """Estimated per-light position offsets ``(L, 3)`` (0: as stated in capture.json)."""
        s = self.state.get("light_offset") if self.state else None
        return s if s is not None else torch.zeros_like(self.cap.light_positions)

    def _sync_light_scale(self):
        for d in self._data.values():
            d.set_light_scale(self.light_log_scale())
            d.set_light_offset(self.light_offset())

    def light_corrections(self) -> dict:
        """``{image file: estimated intensity / stated intensity}`` (report.json)."""
        s = torch.exp(self.light_log_scale())
        return {f: float(s[k]) for k, f in enumerate(self.cap.files)}

    def light_position_corrections(self) -> dict:
        """``{image file: estimated − stated position (3,)}`` (report.json)."""
        o = self.light_offset()
        return {f: [float(x) for x in o[k]] for k, f in enumerate(self.cap.files)}

    def tick(self) -> None:
        st = self.state
        size, kind, n_it = self.plan[st["stage"]]
        data = self.data(size, all_lights=(kind == "all"))
        self._sync_light_scale()
        if self.cfg.fault_at is not None and st["global_it"] == self.cfg.fault_at:
            st["theta"][0][: max(1, st["theta"][0].shape[0] // 10)] = float("nan")  # injected fault
        hyps = [0, 1] if kind == "dual" else [0]
        # Unary priors: the non-local fill (last stage, off by default), the metals' F0 tie.
        unary = _sum_unary(st.get("fill") if kind == "all" else None,
                           st.get("tie") if kind != "dual" else None)
        self.fit_cost = {}
        residuals: dict[int, Tensor] = {}
        total = 0.0
        for h in hyps:
            metal = torch.full_like(st["lam"][h], float(h)) if kind == "dual" else st["metal"]
            theta = st["theta"][h]
            bad = ~torch.isfinite(theta).all(-1, keepdim=True)
            if bad.any():  # a non-finite parameter: step back to its last finite neighbour value
                st["events"].append({"iteration": st["global_it"], "event": "non-finite parameters",
                                     "pixels": int(bad.sum()), "action": "reset to neighbours, lr halved"})
                self.log(f"warning: {int(bad.sum())} non-finite parameters at iteration {st['global_it']}; "
                         "stepping back and halving the step")
                fill = _neighbour_mean(torch.nan_to_num(theta, nan=0.0), size)
                theta = torch.where(bad, torch.nan_to_num(fill, nan=0.0), theta)
                st["lam"][h] = torch.where(bad, st["lam"][h] * 100, st["lam"][h])
                st["lr"] = max(st["lr"] * 0.5, 0.05)
            if self.cfg.propagate and (st["it"] == 0 or (self.cfg.propagate_every and kind != "dual")):
                cross = None if kind == "dual" else self.cfg.metal_margin
                active = None  # a later pass needs only the pixels near the last one's changes
                # A stage's start (a new level, or the class choice) moves pixels far; "all"
                # continues the converged polish at its size, like one more of its iterations.
                for _ in range(self.cfg.propagate_passes if st["it"] == 0 and kind != "all" else 1):
                    theta, metal, changed = propagate(data, theta, metal, self.cfg, margin=cross, unary=unary,
                                                      active=active)
                    if not bool(changed.any()):
                        break
                    active = _dilate(changed, size)
                if kind != "dual":
                    st["metal"] = metal
            if st["it"] == 0 and self.cfg.propagate and kind != "all":
                theta, _ = normal_search(data, theta, metal, self.cfg.model)
            calibrate = self.cfg.light_scale and kind != "dual"
            extra: dict[str, Any] = {}
            theta, lam, cost, n_bad = lm_step(data, theta, metal, st["lam"][h], self.cfg, st["lr"],
                                              extra, unary, self._take_stage_gn(data, theta, metal))
            self.fit_cost[h] = self._training_fit(extra, data)
            if calibrate and self.cfg.light_joint:
                st["light_log_scale"], st["light_offset"] = light_joint_step(
                    data, theta, metal, self.light_log_scale(), self.light_offset(), self.train_idx,
                    self.cfg.model, self.cfg.light_position,
                    map_prior_terms(theta, metal, size, self.cfg, unary))
                self._sync_light_scale()
            elif calibrate:  # alternate: maps (LM step above), then each light's intensity scale
                st["light_log_scale"] = light_scale_step(extra["residual"], data.train_idx,
                                                         self.light_log_scale(), self.train_idx)
                self._sync_light_scale()
                if self.cfg.light_position:
                    st["light_offset"] = light_position_step(data, theta, metal, self.light_offset(),
                                                             self.cfg.model)
                    self._sync_light_scale()
            if n_bad:
                st["events"].append({"iteration": st["global_it"], "event": "non-finite loss", "pixels": n_bad,
                                     "action": "step rejected, damping raised"})
            st["theta"][h], st["lam"][h] = theta, lam
            residuals[h] = extra["residual"]
            if h == 0 or kind != "dual":
                total = float(cost.mean()) / max(1, len(data.train_idx) * 3)
        full = size == self.plan[-1][0]
        if kind == "dual" and self.cfg.light_scale and self.cfg.dual_calibration \
                and (full or self.cfg.dual_calibration_coarse):
            # The lights are estimated already in the dual stages, from each pixel's better
            # hypothesis: the maps would otherwise absorb part of a light's error (normals tilt,
            # a rough region slides into the glossy low-specular valley) before the
            # single-hypothesis stages can see it. Below full resolution only the intensity
            # scales: the coarse maps' blended pixels moved the positions (docs, issue 13).
            better = (self.fit_cost[1] < self.fit_cost[0])[:, None]
            if self.cfg.light_joint:
                theta = torch.where(better, st["theta"][1], st["theta"][0])
                metal = better.to(theta.dtype)
                st["light_log_scale"], st["light_offset"] = light_joint_step(
                    data, theta, metal, self.light_log_scale(), self.light_offset(), self.train_idx,
                    self.cfg.model, self.cfg.light_position and full,
                    map_prior_terms(theta, metal, size, self.cfg),
                    at_camera=self.cfg.dual_calibration_at_camera)
                self._sync_light_scale()
            else:
                better_res = torch.where(better, residuals[1], residuals[0])
                st["light_log_scale"] = light_scale_step(better_res, data.train_idx, self.light_log_scale(),
                                                         self.train_idx)
                self._sync_light_scale()
                if self.cfg.light_position and full:
                    theta = torch.where(better, st["theta"][1], st["theta"][0])
                    st["light_offset"] = light_position_step(data, theta, better.to(theta.dtype),
                                                             self.light_offset(), self.cfg.model,
                                                             at_camera=self.cfg.dual_calibration_at_camera)
                    self._sync_light_scale()
        if not math.isfinite(total):
            st["lr"] = max(st["lr"] * 0.5, 0.05)
        st["history"].append({"iteration": st["global_it"], "size": size, "stage": kind, "loss": total})
        st["it"] += 1
        st["global_it"] += 1
        summary = self.fit_summary()
        if st["it"] < n_it and self._converged(size, summary.get("best", summary.get("chosen", math.nan))):
            st["history"][-1]["skipped"] = n_it - st["it"]  # planned iterations the stage no longer needs
            st["it"] = n_it
        if st["it"] >= n_it:
            self.end_stage()

    def _take_stage_gn(self, data: LevelData, theta: Tensor, metal: Tensor
                       ) -> tuple[Tensor, Tensor, Tensor] | None:
        """The stage-start Gauss–Newton pass (:attr:`_stage_gn`) at ``theta``, ``metal``, or None.

        Re-linearised on the pixels of ``theta (P, 7)``, ``metal (P, 1)`` that differ from where
        it was made; None when there is none. Used once: it is cleared.
        """
        if self._stage_gn is None:
            return None
        th0, mt0, (r0, jtj, jtr) = self._stage_gn
        self._stage_gn = None
        rows = ((theta != th0).any(-1) | (metal != mt0).any(-1)).nonzero()[:, 0]
        if rows.numel():
            r0[rows], jtj[rows], jtr[rows] = gauss_newton(data.subset(rows), theta[rows], metal[rows],
                                                          data.train_idx, self.cfg.model)
        return r0, jtj, jtr

    def fit_summary(self) -> dict[str, float]:
        """The fit loss of the last iteration, from :attr:`fit_cost` (empty before the first).

        ``dielectric``, ``metal`` and each pixel's better hypothesis, ``best``, in a dual stage;
        ``chosen`` otherwise.
        """
        fc = self.fit_cost
        if len(fc) == 2:
            return {"dielectric": float(fc[0].mean()), "metal": float(fc[1].mean()),
                    "best": float(torch.minimum(fc[0], fc[1]).mean())}
        return {"chosen": float(fc[0].mean())} if fc else {}

    def _training_fit(self, extra: dict, data: LevelData) -> Tensor:
        """Data cost ``(P,)`` per training light and channel (non-finite: inf) from an LM step's
        residuals ``extra["residual"] (P, 3 · len(data.train_idx))``; the "all" stage also fits
        the held-out light, which the fit loss leaves out."""
        r = extra["residual"]
        if list(data.train_idx) != list(self.train_idx):
            cols = [3 * data.train_idx.index(k) + c for k in self.train_idx for c in range(3)]
            r = r.index_select(1, torch.tensor(cols, device=r.device))
        return torch.nan_to_num((r * r).sum(-1), nan=float("inf")) / max(1, len(self.train_idx) * 3)

    def _converged(self, size: int, fit: float) -> bool:
        """Whether the stage at ``size`` is done: its fit loss ``fit`` (this iteration's; in a
        dual stage, of each pixel's better hypothesis) changed by less than ``converge_tol`` of
        its previous value.

        Each pixel's better hypothesis, not each hypothesis' mean: a hypothesis' mean is
        dominated by the pixels of the other class, where it fits badly and stays put. Only
        the full-resolution stages stop early (the coarse ones are cheap and set up the finer
        ones), and only after ``converge_min_iters`` iterations (at least 2: the first has no
        earlier fit of its stage to compare with, and it moves the state by propagation and
        normal search as well as by LM).
        """
        st, cfg = self.state, self.cfg
        last, st["last_fit"] = st.get("last_fit"), (st["stage"], fit)
        if cfg.converge_tol <= 0 or size != self.plan[-1][0] or st["it"] < cfg.converge_min_iters:
            return False
        if last is None or last[0] != st["stage"] or not math.isfinite(fit):
            return False
        return abs(last[1] - fit) < cfg.converge_tol * last[1]

    def end_stage(self) -> None:
        st = self.state
        size, kind, _ = self.plan[st["stage"]]
        if kind == "dual":
            # Choose per pixel by the data cost (no prior terms) on the training lights plus
            # the held-out light the fit never saw.
            scores = []
            lights = self.train_idx + ([self.holdout] if self.holdout is not None else [])
            for h in (0, 1):
                metal = torch.full_like(st["lam"][h], float(h))
                r = self.data(size).residual(st["theta"][h], metal, lights, self.cfg.model)
                c = (r * r).sum(-1, keepdim=True)
                scores.append(torch.nan_to_num(c, nan=float("inf")))
            if self.cfg.refit_before_choice:
                scores[0] = self._refit_unconverged_dielectric(size, scores, lights)
            # Metal only when clearly better: a rough metal's broad GGX lobe can mimic a
            # rough dielectric's diffuse, and dielectrics are the common case.
            metal = _choose_class(scores[0], scores[1], self.cfg.metal_margin, size)
            # 3x3 majority vote on the coarse levels only: at full resolution it erodes the
            # one-pixel-wide edges of inlays and scratches (see docs/recovery.md).
            # At full resolution only isolated choices are flipped (a pixel with at most one
            # of its 8 neighbours agreeing), which keeps one-pixel edges.
            st["metal"] = _majority(metal, size) if size < self.plan[-1][0] else _despeckle(metal, size)
            st.pop("costs", None)
            if self.cfg.rough_tie > 0 and size == self.plan[-1][0]:
                # On the dielectric hypothesis (the next stage takes it where the pixel is
                # dielectric). A moved pixel keeps its LM damping: restarting it there changed the
                # tuning maps by at most 0.0005 (dusty_metal 3's metallic 0.0155 -> 0.0160).
                cfg = self.cfg
                st["theta"][0], _ = rough_basin_tie(self.data(size), st["theta"][0], st["metal"],
                                                    self.train_idx, cfg.model, cfg.rough_tie,
                                                    cfg.rough_tie_glossy, cfg.rough_tie_start)
        nxt = st["stage"] + 1
        if nxt < len(self.plan):
            s1, kind1, _ = self.plan[nxt]
            if kind1 != "dual" and kind == "dual":
                m = st["metal"]
                st["theta"] = [torch.where(m > 0.5, st["theta"][1], st["theta"][0])]
                st["lam"] = [torch.where(m > 0.5, st["lam"][1], st["lam"][0])]
            if s1 != size:
                st["theta"] = [_upsample(t, size, s1) for t in st["theta"]]
                st["lam"] = [torch.full((s1 * s1, 1), 1e-2, dtype=t.dtype, device=t.device) for t in st["lam"]]
                if st["metal"] is not None:
                    st["metal"] = (_upsample(st["metal"], size, s1) > 0.5).to(st["theta"][0].dtype)
            if kind1 != "dual" and st["metal"] is not None and self.cfg.fit_nonlocal_tie \
                    and self.cfg.prior_nonlocal_base > 0:
                # The fusion's non-local average, renewed at the stage's start, as a prior of the fit.
                # (A level's data made here has the stated lights until the next tick syncs the
                # estimates: then its pass is not the first LM step's and is not handed on.)
                synced = (s1, kind1 == "all") in self._data
                d = self.data(s1, all_lights=(kind1 == "all"))
                th, mt, model = st["theta"][0], st["metal"], self.cfg.model
                # The F0 average needs the metal pixels' pass only (the roughness average every
                # pixel's): a pass nobody takes up runs on them alone.
                rows = None if self.cfg.prior_nonlocal > 0 else torch.nonzero(mt[:, 0] > 0.5)[:, 0]
                self._stage_gn = None
                if synced or rows is None:
                    r0, jtj, jtr = gauss_newton(d, th, mt, d.train_idx, model)
                    if synced:  # handed on to the stage's first LM step
                        self._stage_gn = (th.clone(), mt.clone(), (r0, jtj, jtr))
                    if rows is not None:
                        r0, jtj, jtr = r0[rows], jtj[rows], jtr[rows]
                else:
                    r0, jtj, jtr = gauss_newton(d.subset(rows), th[rows], mt[rows], d.train_idx, model)
                w, m, _ = nonlocal_prior(d, th, mt, self.cfg, jtj, _pixel_cost(r0), jtr, rows=rows)
                st["tie"] = (m, w)
            if kind1 == "all":
                st["validation"] = self.validation()
                if self.cfg.fill and kind == "polish":
                    # Fill what no captured highlight constrains from the same material where one does.
                    st["fill"] = nonlocal_fill(self.data(size), st["theta"][0], st["metal"], self.cfg)
        elif self.cfg.prior_nonlocal > 0 or self.cfg.prior_nonlocal_base > 0:
            # Done: fuse each pixel's roughness / metal base colour with its non-local
            # estimate by their precisions (see nonlocal_prior), and let its other unknowns
            # follow: a metal's F0 moved alone leaves the F0–roughness valley of the GGX tail
            # (dusty_metal 3: 8645 pixels then fitted at 10–100× the noise).
            d = self.data(size, all_lights=(kind == "all"))
            metal, model = st["metal"], self.cfg.model
            r0, jtj, jtr = gauss_newton(d, st["theta"][0], metal, d.train_idx, model)
            # Each round's fused value combines the *same* own value (before the fusion) with
            # that round's average, so rounds refine the average without compounding the pull;
            # fit weights and the refit test use the costs before the fusion too.
            th0, c0 = st["theta"][0].clone(), _pixel_cost(r0)
            info0: Tensor | None = None
            moved: Tensor | None = None  # the pixels the last round moved
            for _ in range(self.cfg.fuse_rounds):
                th = st["theta"][0]
                if moved is not None:  # linearised anew where the last round moved them
                    rows = moved.nonzero()[:, 0]
                    r0[rows], jtj[rows], jtr[rows] = gauss_newton(d.subset(rows), th[rows], metal[rows],
                                                                  d.train_idx, model)
                w, m, info = nonlocal_prior(d, th, metal, self.cfg, jtj, c0, jtr)
                info0 = info if info0 is None else info0
                moved = (w > 0).any(-1)
                rows = moved.nonzero()[:, 0]  # the rest keep their values: only these are evaluated
                if rows.numel() == 0:  # no metal pixel (and no roughness fusion): nothing to fuse
                    break
                t, wr, ir, t0 = th[rows], w[rows], info0[rows], th0[rows]
                fused = torch.where(wr > 0, (ir * t0 + wr * m[rows]) / (ir + wr).clamp(min=1e-12), t)
                shifted = fused + conditional_shift(jtj[rows], fused - t, wr > 0)
                # Kept per pixel only where it fits the data at least as well as the fused F0
                # alone (a weakly determined unknown can take a large linear response).
                cost = [_pixel_cost(d.residual(x, metal[rows], d.train_idx, model, rows=rows))
                        for x in (fused, shifted)]
                th[rows] = torch.where(cost[1] <= cost[0], shifted, fused)
                # Where even the better of the two fits more than 1.5× worse than before, the
                # valley bent away from the linear response (rusted_metal 68: the corners far
                # from every highlight at 10³–10⁴ noise variances): a few data-only LM
                # iterations with the fused unknowns held take the others to their
                # conditional optimum.
                bent = torch.minimum(cost[0], cost[1])[:, 0] > 1.5 * c0[rows, 0]
                b_rows = rows[bent]
                if b_rows.numel() and self.cfg.fuse_refit_iters > 0:
                    th[b_rows] = refit_pixels(d, th, metal, b_rows, [th[b_rows]], d.train_idx, model,
                                              self.cfg.fuse_refit_iters, held=wr[bent] > 0)[0]
            st["info"] = info
        if nxt >= len(self.plan) and self.cfg.soft_metal and st.get("metal") is not None:
            self._soft_metal(size, kind)
        st["stage"] = nxt
        st["it"] = 0

    def _refit_unconverged_dielectric(self, size: int, scores: list[Tensor], lights: list[int],
                                      factor: float = 5.0, max_pixels: int = 4096, iters: int = 8) -> Tensor:
        """Before the metal/dielectric choice: refit the dielectric hypothesis where the metal wins
        but the dielectric never converged (cost > ``factor`` × its median, the noise level) and
        the metal does not fit at the noise level either (> 2× the median).

        A metal's win is evidence only against a converged dielectric. Where the coarse levels
        blended a narrow structure (tiles' grout at the image edge is half as wide as inside:
        one coarse pixel at S/4), the dielectric's start at this level is a glossy, flat local
        optimum that Gauss–Newton does not leave, while the metal start (rough, flat) reached the
        rim's normal — and those pixels were called metal, a frame along the image border.
        They get a per-pixel LM (:func:`refit_pixels`, data only) from their own parameters
        and from the metal hypothesis's normal and roughness (geometry does not depend on the
        material) with specular 0.5; the better result replaces the dielectric where it fits
        better. Returns the dielectric's updated scores ``(P, 1)`` on ``lights``.
        """
        st = self.state
        rows = unconverged_dielectric_rows(scores[0], scores[1], self.cfg.metal_margin, factor)
        if rows.numel() == 0:
            return scores[0]
        if rows.numel() > max_pixels:
            rows = rows[torch.topk(scores[0][rows, 0], max_pixels).indices]
        d = self.data(size)
        th0, th1 = st["theta"][0], st["theta"][1]
        cross = th0[rows].clone()
        cross[:, 4:7] = th1[rows, 4:7]
        cross[:, 3] = 0.0  # specular 0.5
        zero = torch.zeros_like(st["lam"][0])
        new, _ = refit_pixels(d, th0, zero, rows, [th0[rows], cross], self.train_idx, self.cfg.model, iters)
        r = d.subset(rows).residual(new, zero[rows], lights, self.cfg.model)
        c = _pixel_cost(r)
        better = c < scores[0][rows]
        st["theta"][0] = th0.clone()
        st["theta"][0][rows] = torch.where(better, new, th0[rows])
        out = scores[0].clone()
        out[rows] = torch.where(better, c, scores[0][rows])
        return out

    def _soft_metal(self, size: int, kind: str) -> None:
        """Final stage: continuous metallic where the binary choice fits poorly, at a class
        boundary or at a metal's colour step (:func:`soft_metal_candidates`,
        :func:`soft_metal_fit`), then along runs of fractional pixels (:func:`growth_front`),
        and last the fractional pixels once more with their base colour tied to the blend of
        their clear neighbours (``cfg.soft_metal_line``); a candidate (a metal unlike the metal
        around it is one too) may also change class, and every other pixel keeps its 0 or 1 (a
        candidate whose blend is its own class and that fits at the noise level too,
        :func:`may_be_mixed`, ``cfg.soft_metal_quiet``; only the glossy/rough tie may move it).
        Records ``state["soft_metal"]`` (pixels refitted, growth included; fractional; seconds)."""
        import time

        t_start = time.perf_counter()
        st, cfg = self.state, self.cfg
        data = self.data(size, all_lights=(kind == "all"))
        theta, metal = st["theta"][0], st["metal"]
        with torch.no_grad():
            r = data.residual(theta, metal, data.train_idx, cfg.model)
        cost = _pixel_cost(r)
        # Noise variance of one residual: the median pixel's cost per residual.
        finite = torch.isfinite(cost)
        typical = float(cost[finite].median()) if bool(finite.any()) else 0.0
        sigma2 = typical / max(1, r.shape[1])
        rows = soft_metal_candidates(cost, metal, size, cfg.soft_metal_factor, cfg.soft_metal_max,
                                     cfg.soft_metal_band, torch.sigmoid(theta[:, 0:3]), cfg.soft_metal_edge,
                                     context=BLEND_SIGMAS[-1])
        n_frac = n_grown = n_rough = 0
        # The candidates' coverage as a blend of their clear neighbours (NaN elsewhere).
        unmix = torch.full_like(metal, float("nan"))
        w_nb, w_un = cfg.soft_metal_smooth * sigma2, cfg.soft_metal_unmix * sigma2

        def neighbour_fit(rows_: Tensor, gain: float | Tensor, warm: bool = False) -> tuple[Tensor, Tensor]:
            # Pass 2 and growth: started from the 4-neighbours' mean parameters (with ``warm``:
            # from the pixels' own), metallic pulled toward theirs (the current theta / metal)
            # and, where known, toward the blend's: two quadratic pulls, one of their summed
            # weight toward their weighted mean.
            target, u = _neighbour_mean(metal, size)[rows_], unmix[rows_]
            known = ~torch.isnan(u)
            weight = torch.where(known, w_nb + w_un, w_nb).to(u.dtype)
            target = torch.where(known, (w_nb * target + w_un * u) / (w_nb + w_un), target)
            t, m, _ = soft_metal_fit(data, theta, metal, rows_, data.train_idx, cfg.model,
                                     cfg.soft_metal_well * sigma2, gain, cfg.soft_metal_iters,
                                     (None,) if warm else ((_neighbour_mean(theta, size)[rows_], "target"),),
                                     target, weight,
                                     refit_reference=False)
            return t, m

        if rows.numel() and sigma2 > 0:
            theta0, metal0 = theta, metal
            # One start, metallic ½: the own-class optimum is the reference fit's (metallic held),
            # and a start at the own class as well changed no map by more than 0.0013 RMSE on the
            # tuning captures, at a third of this pass's time. With the blend of the clear
            # neighbours known, the other unknowns start from it, and its coverage pulls.
            start: tuple = (0.5,)
            pull: dict = {}
            quiet = rows[:0]  # the candidates left out of the metallic fits and growth
            if w_un > 0:
                t_blend, u = unmix_metallic(data, theta, metal, rows, data.train_idx, cfg.model, size)
                unmix[rows] = u
                # Not the clear pixels that fit at the noise level (dusty_metal 102: 10 113 of
                # 19 678 candidates, rusted_metal 101: 3 989 of 14 121).
                if cfg.soft_metal_quiet > 0:
                    keep = may_be_mixed(u, metal[rows], cost[rows], cfg.soft_metal_quiet * typical)
                    quiet, rows, t_blend, u = rows[~keep], rows[keep], t_blend[keep], u[keep]
                known = ~torch.isnan(u)  # else the pixel's own unknowns, metallic ½ and no pull
                start = ((torch.where(known, t_blend, theta[rows]), 0.5),)
                pull = {"target": torch.nan_to_num(u), "smooth": torch.where(known, w_un, 0.0).to(u.dtype)}
            t_new, m_new, _ = soft_metal_fit(
                data, theta, metal, rows, data.train_idx, cfg.model, cfg.soft_metal_well * sigma2,
                cfg.soft_metal_gain * sigma2, cfg.soft_metal_iters, starts=start, **pull)
            theta, metal = theta.clone(), metal.clone()
            theta[rows], metal[rows] = t_new, m_new
            if cfg.soft_metal_smooth > 0:
                # Second pass: where the data cannot tell (a rough metal's lobe mimics a rough
                # dielectric's diffuse), the neighbours' metallic decides.
                # Start: its 4-neighbours' mean parameters (a rust pixel that pass 1 left in the
                # metal mode starts from the rust beside it), metallic = target; kept only if better.
                target = _neighbour_mean(metal, size)[rows]
                m1 = metal[rows]
                # Only where the neighbours say something the pixel does not (another metallic
                # beside it, or itself fractional): inside a uniform binary region the pull and
                # the start equal the pixel's own, and the fit would only repeat pass 1.
                ctx = ((target - m1).abs() > 1e-6) | ((m1 > 0) & (m1 < 1))
                rows2 = rows[ctx[:, 0]]
                # Beside a pixel pass 1 made fractional, a ramp is likely to go on: a smaller gain.
                fr = ((metal > 0) & (metal < 1)).to(theta.dtype)
                near = _neighbour_mean(fr, size)[rows2] > 0
                ctx_scale = torch.where(near, cfg.soft_metal_context, 1.0).to(theta.dtype)
                gain2 = cfg.soft_metal_gain * sigma2 * ctx_scale
                # Repeated, each round pulled toward the neighbours' metallic of the round
                # before: a ramp's values settle from both of its ends (Jacobi smoothing). A
                # pixel an earlier round made fractional is no longer asked for the gain (it is
                # not newly fractional): only its energy decides between its values. Rounds
                # after the first go on from the round before's answers: most pixels are settled
                # and leave the LM early, and the others continue where they were instead of
                # starting over from their neighbours' (moved) mean; a pixel the round before
                # refused gets no new neighbour start (tuning maps better without it, docs).
                for k in range(cfg.soft_metal_passes if rows2.numel() else 0):
                    theta[rows2], metal[rows2] = neighbour_fit(rows2, gain2, warm=k > 0)
                t_new, m_new = theta[rows], metal[rows]
            # Only a fractional or other-class answer is taken: a pixel that stays its class
            # keeps the fit it had, with the priors' regularisation (a data-only refit of a
            # metal's weakly observed F0 doubled scratched_metal 103's base-colour RMSE, 0.015 ->
            # 0.027). One that changed class beat its own class in soft_metal_fit's judgement (in
            # pass 1 its own class's refit; in the second pass its answer before, the neighbours'
            # pull included): a thin dielectric scratch the binary choice called metal
            # (scratched_metal 5: metallic RMSE 0.0136 -> 0.0005 with the far ends).
            take = ((metal[rows] > 0) & (metal[rows] < 1)) | (metal[rows] != metal0[rows])
            theta, metal = theta0.clone(), metal0.clone()
            theta[rows] = torch.where(take, t_new, theta0[rows])
            metal[rows] = torch.where(take, m_new, metal0[rows])
            # Growth: a ramp runs on past the candidates (a dust speck's soft rim, wider than
            # the band on its dielectric side). The untried pixels beside a run of fractional
            # ones (a fractional pixel with a fractional 4-neighbour; an isolated one on a
            # binary material is not a ramp) get the second pass's fit, a few rounds.
            tried = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
            tried[rows] = True
            tried[quiet] = True  # not grown into (the glossy/rough tie below still tests them)
            for _ in range(cfg.soft_metal_grow):
                front = growth_front(metal, tried, size)
                if front.numel() == 0:
                    break
                tried[front] = True
                if w_un > 0:  # their coverage pulls too (a speck's core, grown into from its rim)
                    _, unmix[front] = unmix_metallic(data, theta, metal, front, data.train_idx, cfg.model,
                                                     size)
                t_f, m_f = neighbour_fit(front, cfg.soft_metal_gain * cfg.soft_metal_context * sigma2)
                ff = (m_f > 0) & (m_f < 1)
                theta[front] = torch.where(ff, t_f, theta[front])
                metal[front] = torch.where(ff, m_f, metal[front])
                n_grown += int(front.numel())
            if cfg.soft_rough_tie > 0:
                # Glossy or rough, now with a blend as an answer (a rim's glossy fit is a firefly
                # under an unseen light), before the blend line, which then holds the moved
                # pixels' base colour too.
                theta, metal, moved = soft_rough_tie(
                    data, theta, metal, torch.nonzero(tried).flatten(), data.train_idx, cfg.model,
                    cfg.soft_metal_well * sigma2, cfg.soft_rough_tie * sigma2, cfg.soft_rough_tie_glossy,
                    cfg.rough_tie_start, coverage=unmix)
                n_rough = int(moved.sum())
            frac_rows = torch.nonzero(((metal > 0) & (metal < 1))[:, 0]).flatten()
            if cfg.soft_metal_line > 0 and frac_rows.numel():
                # Last: the fractional pixels refitted with their base colour tied to the blend of
                # the clear dielectric and metal beside them at their own metallic. Alone, the
                # data trade a little metallic for a lot of base colour (a 90 %-metal rust-front
                # pixel fits as well 0.005 less metal and 0.05 darker: rusted_metal 1); the
                # blend line crosses that valley at a steep angle.
                # (Only where both ends are within reach: elsewhere there is no line.) Twice the
                # stage's iterations: the valley is long (rusted_metal 1, base RMSE 0.0272 before:
                # 5 iterations 0.0220, 10 0.0213, 20 0.0212).
                (diel, met), found = blend_ends(theta, metal, frac_rows, size)
                both = found.all(-1)
                frac_rows, diel, met = frac_rows[both], diel[both, 0:3], met[both, 0:3]
                t_p, m_p, _ = soft_metal_fit(data, theta, metal, frac_rows, data.train_idx, cfg.model,
                                             cfg.soft_metal_well * sigma2, 0.0, 2 * cfg.soft_metal_iters,
                                             starts=(None,), refit_reference=False, line=(diel, met),
                                             line_weight=cfg.soft_metal_line * sigma2)
                theta[frac_rows], metal[frac_rows] = t_p, m_p
            st["theta"][0], st["metal"] = theta, metal
            n_frac = int(((metal > 0) & (metal < 1)).sum())
        st["soft_metal"] = {"pixels_refitted": int(rows.numel()) + n_grown, "fractional_pixels": n_frac,
                            "glossy_to_rough": n_rough, "seconds": time.perf_counter() - t_start}

    def finished(self) -> bool:
        return self.state["stage"] >= len(self.plan)

    def current_params(self) -> dict:
        """Current maps ``(C, S, S)`` (finite)."""
        st = self.state
        size = self.plan[min(st["stage"], len(self.plan) - 1)][0]
        if st["stage"] < len(self.plan) and self.plan[st["stage"]][1] == "dual":
            if st["metal"] is not None and st["metal"].shape[0] == size * size:
                metal = st["metal"]
            else:
                metal = torch.zeros_like(st["lam"][0])
            theta = torch.where(metal > 0.5, st["theta"][1], st["theta"][0])
        else:
            metal, theta = st["metal"], st["theta"][0]
        size = int(round(math.sqrt(theta.shape[0])))
        theta = torch.nan_to_num(theta, nan=0.0, posinf=0.0, neginf=0.0)
        p = decode(theta, metal)
        # Specular is invisible on a metal pixel (F0 = base colour): write the default. A
        # fractional metal's dielectric lobe shows its specular: keep the fitted value there.
        p["specular"] = torch.where(metal >= 1.0, torch.full_like(p["specular"], 0.5), p["specular"])
        return {k: v.T.reshape(-1, size, size).contiguous() for k, v in p.items()}

    def confidence_map(self, tol_roughness: float = 0.05, tol_specular: float = 0.1) -> Tensor:
        """Per-pixel confidence ``(1, S, S)`` in [0, 1] that roughness (and a dielectric's specular)
        were *measured*, not inferred.

        From the Gauss–Newton posterior: the marginal information ``1 / diag((JᵀJ)⁻¹)`` of the
        roughness and specular logits (the other unknowns free to trade off) and the residual
        noise variance ``σ²`` (median per-residual data cost) give each pixel's posterior
        variance in map units, ``var = σ² / info · (d value / d logit)²``; the confidence is
        ``1 / (1 + var_r / tol_r² + var_s / tol_s²)`` — about 1 where a captured highlight pins
        the value far inside the tolerances, → 0 where no highlight reaches (the value then
        comes from the priors). A metal's specular is invisible and not counted.
        """
        st = self.state
        size = self.plan[min(st["stage"], len(self.plan) - 1)][0]
        theta = torch.nan_to_num(st["theta"][0], nan=0.0, posinf=0.0, neginf=0.0)
        metal = st["metal"] if st["metal"] is not None else torch.zeros_like(theta[:, :1])
        kind = self.plan[min(st["stage"], len(self.plan) - 1)][1]
        data = self.data(size, all_lights=(kind == "all"))
        info = st.get("info")
        if info is None or info.shape[0] != theta.shape[0]:
            with torch.no_grad():
                info = marginal_information(data, theta, metal, self.cfg.model)
        with torch.no_grad():
            r = data.residual(theta, metal, data.train_idx, self.cfg.model)
        sigma2 = float(torch.nan_to_num((r * r).mean(-1), nan=0.0).median())
        sr = torch.sigmoid(theta[:, 4:5])
        ss = torch.sigmoid(theta[:, 3:4])
        var_r = sigma2 / info[:, 4:5] * ((_R_MAX - _R_MIN) * sr * (1 - sr)) ** 2
        var_s = sigma2 / info[:, 3:4] * (ss * (1 - ss)) ** 2 * (metal < 0.5)
        conf = 1.0 / (1.0 + var_r / tol_roughness**2 + var_s / tol_specular**2)
        return torch.nan_to_num(conf, nan=0.0).clamp(0, 1).T.reshape(1, size, size).contiguous()

    def validation(self) -> dict | None:
        if self.holdout is None:
            return None
        maps = self.current_params()
        size = maps["base_color"].shape[-1]
        d = self.data(size)
        with torch.no_grad():
            pred = render_capture(maps, (d.pos[[self.holdout]], d.inten[[self.holdout]]), d.camera, backend="compact")
        assert d.images is not None  # a full level, not a pixel subset
        return {"light": self.holdout, "file": self.cap.files[self.holdout],
                "psnr": psnr(pred[0], d.images[self.holdout])}


def psnr(pred: Tensor, ref: Tensor) -> float:
    """PSNR in dB of linear images, peak = the reference's maximum."""
    mse = float(((pred - ref) ** 2).mean())
    peak = float(ref.max())
    return float("inf") if mse == 0 else 10 * math.log10(peak * peak / mse)


