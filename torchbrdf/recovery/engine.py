"""SVBRDF recovery: the algorithm (capture in, per-pixel principled maps out).

``python -m training.recover_svbrdf --capture DIR --out DIR`` (or ``--demo``) fits per-pixel
principled maps — base colour, roughness, metallic, specular, normal — so that the capture format's
image formation reproduces every captured image.

Method (``docs/recovery.md``; its measurements in ``docs/recovery_measurements.md``):

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
  hypothesis fitted side by side; evidence decides: a likelihood-ratio test of their costs
  on the training lights *plus a held-out captured light* (a light the fit never saw) at the
  measured noise level, inside an MRF whose Potts term is in the same noise units, so a
  pixel against a coherent neighbourhood needs the full evidence and the pixels the data
  cannot decide take their neighbours' class (``classes.choose_class``).
* **Propagation and search** (PatchMatch-style, between LM iterations): each pixel tries
  its 8 neighbours' parameters — same class, or the other class under the same evidence
  test — and keeps them when they lower its data cost plus prior; pixels still fitting
  far worse than the noise level try a grid of normals (tilts up to 40°) combined with
  their own and their neighbours' parameters. Gauss–Newton only walks downhill: this is
  what finds the highlight of a steep inlay rim whose normal starts 30° off.
* **Spatial priors**: roughness and specular are tied to their 4-neighbours of the same
  class, weighted by albedo similarity (``exp(-|Δbase|²/σ²)``), which fills in the glossy
  pixels whose highlight no light hits. The prior couples pixels, so each LM step solves
  the whole sparse system (per-pixel 7×7 blocks + the prior's weighted Laplacian) by
  block-preconditioned conjugate gradients: a weakly observed region moves as a whole
  instead of being held at its start value by frozen neighbours (a Jacobi prior kept a
  grout line at roughness 0.74 instead of 0.85).
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
  converged (a narrow structure the coarse levels blended, such as a half-width grout line at
  the image edge), the dielectric is refitted per pixel from the metal's geometry first — a
  metal's win is evidence only against a converged dielectric. Class votes count only the
  neighbours a pixel has (5 on an edge, 3 in a corner), not padded copies of itself.
* **Per-light intensity scales** (calibration error) are estimated jointly with the maps, the
  training lights' geometric mean held at the stated intensities.
* **Non-local fill** (before the last stage): each pixel's roughness / specular get a
  Gaussian prior, the predictive distribution of the same material's pixels found anywhere in
  the image (base colour and normal-spread similarity), their values weighed by their own
  information (data and smoothness ties), members stuck in another basin set aside; each
  pixel is moved to the mode of its data and that prior, which then stays in the last stage's
  fit: silent pixels take the material's measured value, measured ones keep their own.
* **Confidence** (``Recovery.confidence_map``): the posterior variance of roughness and
  specular from the marginal information, mapped to [0, 1].
* **Learned prior** (optional, ``recover(..., prior=...)``): its metallic as evidence in the
  class choice; once each pixel's class is chosen, a Gaussian unary toward the network's maps
  with its errors measured on the capture, each precision weighed by its share against the
  data's information (:class:`~torchbrdf.recovery.prior.LearnedPrior`); the start stays the
  data's own.
* **Validation**: the held-out light's PSNR is reported (``report.json``:
  ``validation_psnr``); the last iterations then use every light.

Checkpoints (``OUT/checkpoint.pt``, written atomically) every ``--checkpoint-every``
iterations and on SIGINT/SIGTERM; ``--resume`` continues bit-for-bit where the run stopped.
Maps are never written with non-finite values.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchbrdf.capture.format import Capture
from torchbrdf.io import atomic_path
from torchbrdf.recovery.calibration import light_joint_step, light_position_step, light_scale_step, rest_iterations
from torchbrdf.recovery.classes import (choose_class, residual_variance, rough_basin_tie,
                                        unconverged_dielectric_rows)
from torchbrdf.recovery.config import RecoveryConfig, Settings, settings_of
from torchbrdf.recovery.levels import LevelData, photometric_stereo, render_fit
from torchbrdf.recovery.lm import (conditional_shift, gauss_newton, lm_step, map_prior_terms,
                                   marginal_information, pixel_cost, refit_pixels, sum_unary)
from torchbrdf.recovery.map_ops import neighbour_mean, upsample
from torchbrdf.recovery.params import R_MAX, R_MIN, decode, encode
from torchbrdf.recovery.prior import (LearnedPrior, class_costs_with_prior, class_prior_cost, measured_map_errors,
                                      measured_metallic_error)
from torchbrdf.recovery.priors import fit_information, fuse_fill, nonlocal_fill, nonlocal_prior
from torchbrdf.recovery.search import normal_search, propagate_passes, unexplained
from torchbrdf.recovery.soft_metal import soft_metal_stage


__all__ = ["Recovery", "psnr", "CHECKPOINT"]

CHECKPOINT = "checkpoint.pt"


def _schedule(size: int, cfg: Settings) -> list[tuple[int, str, int]]:
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


class Recovery:
    """The resumable optimisation state machine (see the module docstring)."""

    def __init__(self, cap: Capture, cfg: RecoveryConfig | Settings, out: Path | None = None,
                 log: Callable[[str], Any] = print, prior: LearnedPrior | None = None):
        self.cap, self.cfg, self.out, self.log = cap, settings_of(cfg), out, log
        self.prior = prior  # the learned prior's maps: the start, and a unary term of every stage
        cfg = self.cfg
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
        # pixels that moved since. Not state: a resumed run
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
        ones = torch.ones(d.points.shape[0], 1, dtype=alb.dtype, device=alb.device)
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
        if self.prior is not None:  # the prior is a Gaussian term of the fit, not its start (_prior_stage)
            self._prior_stage(s0, self.plan[0][1])

    def _prior_stage(self, size: int, kind: str) -> None:
        """At a stage's start (level ``size``, ``kind``): what the learned prior's weight rests on, in the state.

        ``prior_noise``, the fit's per-residual noise variance ``σ²``: the median pixel's mean
        squared residual on the training lights (each pixel's better hypothesis in a dual stage),
        within [1e-6, ``prior_noise_cap``]; in a single-class stage ``prior_information``, the
        data's marginal information ``(P, 7)`` on the unknowns, against which the prior's
        precisions are weighed (:func:`~torchbrdf.recovery.prior.prior_unary`); None in a dual
        stage, where the maps' term is off (:meth:`_prior_unary`).
        """
        st = self.state
        d = self.data(size)
        if st["metal"] is not None and len(st["theta"]) == 1:
            pairs = [(st["theta"][0], st["metal"])]
        else:
            pairs = [(t, torch.full_like(t[:, :1], float(h))) for h, t in enumerate(st["theta"])]
        costs = [pixel_cost(d.residual(t, m, d.train_idx, self.cfg.model)) for t, m in pairs]
        sigma2 = residual_variance(torch.stack(costs).amin(0), 3 * len(d.train_idx))
        st["prior_noise"] = min(max(sigma2, 1e-6), self.cfg.prior_noise_cap)
        # what the images say about each unknown of each hypothesis fitted, for the prior's share
        st["prior_information"] = None if kind == "dual" else \
            [marginal_information(d, t, m, self.cfg.model) for t, m in pairs]
        if st["prior_information"] is not None and self.prior is not None:  # its errors on the measured pixels
            st["prior_map_errors"] = measured_map_errors(pairs[0][0], self.prior.at(size), st["prior_noise"],
                                                         self.prior.errors, st["prior_information"][0])

    def _prior_unary(self, size: int, kind: str, theta: Tensor, metal: Tensor, hypothesis: int = 0,
                     capture_unary: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor] | None:
        """The learned prior's unary term at ``theta (P, 7)`` for the classes ``metal (P, 1)`` of
        ``hypothesis`` (its index in ``state["theta"]``) at the level ``size`` of a stage of
        ``kind`` (None: no prior, or a dual stage).

        Each precision is weighted by its share against what the capture says: the data's
        information at the stage's start plus the precision of ``capture_unary``, the unary
        priors made from the same material's measured pixels (the F0 tie, the non-local fill).

        Off in the dual stages, where the network enters through its metallic in the class choice
        only: a pull on both hypotheses' fits makes their data costs unequal, so the class test
        would favour the one pulled less, and before they converge the residual variance that
        weights the prior is the fit's misfit, not the noise (docs/recovery.md, Learned prior)."""
        if self.prior is None or kind == "dual":
            return None
        if self.state.get("prior_information") is None:  # a run resumed with a prior it did not have
            self._prior_stage(size, kind)
        info = self.state["prior_information"][hypothesis]
        if capture_unary is not None:
            info = info + capture_unary[1]
        return self.prior.unary(theta, metal, self.state["prior_noise"], info, self.state.get("prior_map_errors"))

    def save_checkpoint(self) -> None:
        """Write ``OUT/checkpoint.pt`` atomically (nothing when there is no ``out``).

        It holds the state, the plan, the RNG state and ``self.fingerprint`` (set by the
        driver, :mod:`torchbrdf.recovery.svbrdf`: what the checkpoint belongs to). The blob is
        serialised in memory first so that a full disk surfaces as ``OSError(ENOSPC)`` from
        the file write (torch's own writer reports it as an opaque ``RuntimeError``).
        """
        if self.out is None:
            return
        blob = {"state": self.state, "plan": self.plan, "config": vars(self.cfg),
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
            why = (str(e).strip().splitlines() or [""])[0].split(". ")[0][:160]  # torch's first sentence
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

    def step(self) -> None:
        """Run one iteration of the current stage (and end the stage when its iterations are done)."""
        st = self.state
        size, kind, n_it = self.plan[st["stage"]]
        data = self.data(size, all_lights=(kind == "all"))
        self._sync_light_scale()
        if self.cfg.fault_at is not None and st["global_it"] == self.cfg.fault_at:
            st["theta"][0][: max(1, st["theta"][0].shape[0] // 10)] = float("nan")  # injected fault
        hyps = [0, 1] if kind == "dual" else [0]
        # Unary priors: the non-local fill (last stage, off by default), the metals' F0 tie.
        shared_unary = sum_unary(st.get("fill") if kind == "all" else None,
                                  st.get("tie") if kind != "dual" else None)
        self.fit_cost = {}
        residuals: dict[int, Tensor | None] = {}
        total = 0.0
        for h in hyps:
            metal = torch.full_like(st["lam"][h], float(h)) if kind == "dual" else st["metal"]
            theta = st["theta"][h]
            # (linearised at this iteration's start, as the data are)
            learned = self._prior_unary(size, kind, torch.nan_to_num(theta), metal, h, shared_unary)
            unary = sum_unary(shared_unary, learned)
            bad = ~torch.isfinite(theta).all(-1, keepdim=True)
            if bad.any():  # a non-finite parameter: step back to its last finite neighbour value
                st["events"].append({"iteration": st["global_it"], "event": "non-finite parameters",
                                     "pixels": int(bad.sum()), "action": "reset to neighbours, lr halved"})
                self.log(f"warning: {int(bad.sum())} non-finite parameters at iteration {st['global_it']}; "
                         "stepping back and halving the step")
                fill = neighbour_mean(torch.nan_to_num(theta, nan=0.0), size)
                theta = torch.where(bad, torch.nan_to_num(fill, nan=0.0), theta)
                st["lam"][h] = torch.where(bad, st["lam"][h] * 100, st["lam"][h])
                st["lr"] = max(st["lr"] * 0.5, 0.05)
            if self.cfg.propagate and (st["it"] == 0 or (self.cfg.propagate_every and kind != "dual")):
                # Single-class stages: a neighbour of the other class is a candidate, judged at
                # the noise level measured at the class choice.
                cross = None if kind == "dual" else st.get("class_sigma2")
                # A stage's start (a new level, or the class choice) moves pixels far; "all"
                # continues the converged polish at its size, like one more of its iterations.
                passes = self.cfg.propagate_passes if st["it"] == 0 and kind != "all" else 1
                # Within a stage only the pixels the last LM step left fitting worse than the
                # noise explains try their neighbours: elsewhere a neighbour rarely wins.
                last = st.get("data_cost") if st["it"] > 0 else None
                active = None if last is None or cross is None else unexplained(last, cross, 3 * len(data.train_idx),
                                                               self.cfg.false_metal_rate)
                if active is None or bool(active.any()):
                    theta, metal = propagate_passes(data, theta, metal, self.cfg, passes, class_sigma2=cross,
                                                    unary=unary, active=active)
                if kind != "dual":
                    st["metal"] = metal
            if st["it"] == 0 and self.cfg.propagate and kind != "all":
                theta, _ = normal_search(data, theta, metal, self.cfg.model)
            calibrate = self.cfg.light_scale and kind != "dual"
            extra: dict[str, Any] = {}
            # (the residuals themselves feed the alternating light-scale steps and the fit loss of
            # a stage with more than the training lights; the summed squares serve the rest)
            keep_r = self.cfg.light_scale and not self.cfg.light_joint or list(data.train_idx) != self.train_idx
            theta, lam, cost, n_bad = lm_step(data, theta, metal, st["lam"][h], self.cfg, st["lr"],
                                              extra, unary, self._take_stage_gn(data, theta, metal), residual=keep_r)
            self.fit_cost[h] = self._training_fit(extra, data)
            # (each pixel's, for the next iteration's propagation gate: at the lights before this
            # iteration's light step, which moves them by little once the fit has settled)
            if kind != "dual":
                st["data_cost"] = extra["data_cost"]
            if calibrate and self.cfg.light_joint:
                self._light_joint_step(data, theta, metal, self.cfg.light_position, size, unary)
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
            residuals[h] = extra.get("residual")
            if h == 0 or kind != "dual":
                total = float(cost.mean()) / max(1, len(data.train_idx) * 3)
        full = size == self.plan[-1][0]
        if kind == "dual" and self.cfg.light_scale and self.cfg.dual_calibration \
                and (full or self.cfg.dual_calibration_coarse):
            # The lights are estimated already in the dual stages, from each pixel's better
            # hypothesis: the maps would otherwise absorb part of a light's error (normals tilt,
            # a rough region slides into the glossy low-specular valley) before the
            # single-hypothesis stages can see it. Below full resolution only the intensity
            # scales: the coarse maps' blended pixels moved the positions.
            better = (self.fit_cost[1] < self.fit_cost[0])[:, None]
            if self.cfg.light_joint:
                theta = torch.where(better, st["theta"][1], st["theta"][0])
                metal = better.to(theta.dtype)
                self._light_joint_step(data, theta, metal, self.cfg.light_position and full, size, None,
                                       at_camera=self.cfg.dual_calibration_at_camera)
            else:
                r0, r1 = residuals[0], residuals[1]
                assert r0 is not None and r1 is not None  # (kept: light_scale without light_joint)
                better_res = torch.where(better, r1, r0)
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

    #: Deprecated name of :meth:`step`.
    tick = step

    def _light_joint_step(self, data: LevelData, theta: Tensor, metal: Tensor, position: bool, size: int,
                          unary: tuple[Tensor, Tensor] | None, at_camera: bool = True) -> None:
        """The joint light step (:func:`light_joint_step`) at ``theta (P, 7)``, ``metal (P, 1)``
        of level ``size``, the maps' prior with the ``unary`` terms (or none).

        With ``Settings.light_rest`` a step is followed by as many iterations without one as
        could not move the lights beyond noise: consecutive steps point the same way while the
        maps still move, so resting ``s`` iterations leaves at most about ``s δg`` unapplied,
        whose cost ``s² δgᵀHδg / σ²`` (the χ² of :func:`light_joint_step`) stays below its K
        degrees of freedom, what noise alone puts between the data's optimum and the true
        lights. The next step re-measures; a rest that reaches past the ``m`` planned iterations
        the stage has left (``m² χ² < K``) ends the stage's light steps.
        """
        st = self.state
        rest = st.get("lights_rest")  # (stage, the first iteration that steps again)
        if rest is not None and rest[0] == st["stage"] and st["it"] < rest[1]:
            return
        evidence: dict[str, float] = {}
        st["light_log_scale"], st["light_offset"] = light_joint_step(
            data, theta, metal, self.light_log_scale(), self.light_offset(), self.train_idx, self.cfg.model,
            position, map_prior_terms(theta, metal, size, self.cfg, unary), at_camera=at_camera,
            evidence=evidence)
        if self.cfg.light_rest and evidence:
            st["lights_rest"] = (st["stage"], st["it"] + 1 + rest_iterations(evidence["chi2"], evidence["dof"]))
        self._sync_light_scale()

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
        summed squares ``extra["data_cost"] (P, 1)``, or, in the "all" stage, which also fits
        the held-out light the fit loss leaves out, from its residuals ``extra["residual"]
        (P, 3 · len(data.train_idx))``."""
        if list(data.train_idx) == list(self.train_idx):
            cost = extra["data_cost"][:, 0]
        else:
            r = extra["residual"]
            cols = [3 * data.train_idx.index(k) + c for k in self.train_idx for c in range(3)]
            r = r.index_select(1, torch.tensor(cols, device=r.device))
            cost = (r * r).sum(-1)
        return torch.nan_to_num(cost, nan=float("inf")) / max(1, len(self.train_idx) * 3)

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
            self._choose_classes(size)
        nxt = st["stage"] + 1
        if nxt < len(self.plan):
            s1, kind1, _ = self.plan[nxt]
            if kind1 != "dual" and kind == "dual":
                m = st["metal"]
                st["theta"] = [torch.where(m > 0.5, st["theta"][1], st["theta"][0])]
                st["lam"] = [torch.where(m > 0.5, st["lam"][1], st["lam"][0])]
            if s1 != size:
                st["theta"] = [upsample(t, size, s1) for t in st["theta"]]
                st["lam"] = [torch.full((s1 * s1, 1), 1e-2, dtype=t.dtype, device=t.device) for t in st["lam"]]
                if st["metal"] is not None:
                    st["metal"] = (upsample(st["metal"], size, s1) > 0.5).to(st["theta"][0].dtype)
            if self.prior is not None:  # the prior's weight follows the fit's noise level, stage by stage
                self._prior_stage(s1, kind1)
            if kind1 != "dual" and st["metal"] is not None and self.cfg.fit_nonlocal_tie \
                    and self.cfg.prior_nonlocal_base > 0:
                self._renew_tie(s1, kind1)
            if kind1 == "all":
                st["validation"] = self.validation()
                if self.cfg.fill and kind == "polish":
                    self._fill(size)
        elif self.cfg.prior_nonlocal > 0 or self.cfg.prior_nonlocal_base > 0:
            self._fuse_nonlocal(size, kind)
        if nxt >= len(self.plan) and self.cfg.soft_metal and st.get("metal") is not None:
            self._soft_metal(size, kind)
        st["stage"] = nxt
        st["it"] = 0

    def _fill(self, size: int) -> None:
        """End of the polish stage: what no captured highlight constrains, from the same material
        where one does — the non-local fill (:func:`nonlocal_fill`) as the last stage's unary
        prior (``state["fill"]``), each pixel first moved to the mode of its data and that prior
        (:func:`fuse_fill`, with the metals' F0 tie)."""
        st = self.state
        d = self.data(size, all_lights=True)  # the last stage's lights
        self._sync_light_scale()
        th, mt, model = st["theta"][0], st["metal"], self.cfg.model
        gn = gauss_newton(d, th, mt, d.train_idx, model)
        info = fit_information(d, th, mt, self.cfg, gn[1])
        fill = nonlocal_fill(d, th, mt, self.cfg, info=info, residual=gn[0])
        st["fill"] = fill
        st["theta"][0] = fuse_fill(d, th, mt, sum_unary(fill, st.get("tie")) or fill, model, gn=gn)

    def _choose_classes(self, size: int) -> None:
        """End of a two-hypothesis stage: each pixel's class (``state["metal"]``) from the two fits."""
        st = self.state
        # Choose per pixel by the data cost (no prior terms) on the training lights plus
        # the held-out light the fit never saw.
        scores = []
        lights = self.train_idx + ([self.holdout] if self.holdout is not None else [])
        for h in (0, 1):
            metal = torch.full_like(st["lam"][h], float(h))
            r = self.data(size).residual(st["theta"][h], metal, lights, self.cfg.model)
            c = (r * r).sum(-1, keepdim=True)
            scores.append(torch.nan_to_num(c, nan=float("inf")))
        n_res = int(r.shape[-1])
        # The capture's noise level: the median pixel's better fit, per residual.
        sigma2 = residual_variance(torch.minimum(scores[0], scores[1]), n_res)
        if self.cfg.refit_before_choice:
            scores[0] = self._refit_unconverged_dielectric(size, scores, lights, sigma2, n_res)
        if self.prior is not None:  # the network's metallic as its (bounded) odds; its error here is reported
            net = self.prior.metallic(size).to(scores[0])
            st["prior_metallic_error"] = measured_metallic_error(scores[0], scores[1], sigma2, net,
                                                                 self.prior.errors["metallic"])
            prior_cost = class_prior_cost(net, st["prior_noise"])
            scores = list(class_costs_with_prior(scores[0], scores[1], prior_cost, sigma2, n_res,
                                                 self.cfg.false_metal_rate))
        # Evidence decides (a likelihood-ratio test at the measured noise), with the neighbours'
        # classes as an MRF prior: see choose_class.
        st["metal"] = choose_class(scores[0], scores[1], size, sigma2, n_res, self.cfg.false_metal_rate)
        st["class_sigma2"] = sigma2
        st.pop("costs", None)
        if self.cfg.rough_tie > 0 and size == self.plan[-1][0]:
            # On the dielectric hypothesis (the next stage takes it where the pixel is
            # dielectric). A moved pixel keeps its LM damping: restarting it there changed no map
            # error by more than 0.0005.
            cfg = self.cfg
            st["theta"][0], _ = rough_basin_tie(self.data(size), st["theta"][0], st["metal"],
                                                self.train_idx, cfg.model, cfg.rough_tie,
                                                cfg.rough_tie_glossy, cfg.rough_tie_start)

    def _renew_tie(self, s1: int, kind1: str) -> None:
        """At a single-class stage's start (level ``s1``, kind ``kind1``): the metals' F0 tie
        (``state["tie"]``), the non-local average as a unary prior of the fit."""
        st = self.state
        # The fusion's non-local average, renewed at the stage's start, as a prior of the fit.
        # (A level's data made here has the stated lights until the next step syncs the
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
        w, m, _ = nonlocal_prior(d, th, mt, self.cfg, jtj, pixel_cost(r0), jtr, rows=rows)
        st["tie"] = (m, w)

    def _fuse_nonlocal(self, size: int, kind: str) -> None:
        """After the last iteration: each metal's F0 fused with its non-local estimate (see
        :func:`nonlocal_prior`), its other unknowns following; ``state["info"]`` the information."""
        st = self.state
        # Done: fuse each pixel's roughness / metal base colour with its non-local
        # estimate by their precisions (see nonlocal_prior), and let its other unknowns
        # follow: a metal's F0 moved alone leaves the F0–roughness valley of the GGX tail
        # (thousands of pixels then fitted at 10–100× the noise).
        d = self.data(size, all_lights=(kind == "all"))
        metal, model = st["metal"], self.cfg.model
        r0, jtj, jtr = gauss_newton(d, st["theta"][0], metal, d.train_idx, model)
        # Each round's fused value combines the *same* own value (before the fusion) with
        # that round's average, so rounds refine the average without compounding the pull;
        # fit weights and the refit test use the costs before the fusion too.
        th0, c0 = st["theta"][0].clone(), pixel_cost(r0)
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
            cost = [pixel_cost(d.residual(x, metal[rows], d.train_idx, model, rows=rows))
                    for x in (fused, shifted)]
            th[rows] = torch.where(cost[1] <= cost[0], shifted, fused)
            # Where even the better of the two fits more than 1.5× worse than before, the
            # valley bent away from the linear response (corners far from every highlight
            # at 10³–10⁴ noise variances): a few data-only LM
            # iterations with the fused unknowns held take the others to their
            # conditional optimum.
            bent = torch.minimum(cost[0], cost[1])[:, 0] > 1.5 * c0[rows, 0]
            b_rows = rows[bent]
            if b_rows.numel() and self.cfg.fuse_refit_iters > 0:
                th[b_rows] = refit_pixels(d, th, metal, b_rows, [th[b_rows]], d.train_idx, model,
                                          self.cfg.fuse_refit_iters, held=wr[bent] > 0)[0]
        st["info"] = info

    def _refit_unconverged_dielectric(self, size: int, scores: list[Tensor], lights: list[int], sigma2: float,
                                      n_residuals: int, max_pixels: int = 4096, iters: int = 8) -> Tensor:
        """Before the metal/dielectric choice: refit the dielectric hypothesis where the metal wins
        but neither fit is at the noise level ``sigma2`` (:func:`unconverged_dielectric_rows`).

        A metal's win is evidence only against a converged dielectric. Where the coarse levels
        blended a narrow structure (a grout line at the image edge is half as wide as inside:
        one coarse pixel at S/4), the dielectric's start at this level is a glossy, flat local
        optimum that Gauss–Newton does not leave, while the metal start (rough, flat) reached the
        rim's normal — and without a refit those pixels would be called metal, a frame along the image border.
        They get a per-pixel LM (:func:`refit_pixels`, data only) from their own parameters
        and from the metal hypothesis's normal and roughness (geometry does not depend on the
        material) with specular 0.5; the better result replaces the dielectric where it fits
        better. Returns the dielectric's updated scores ``(P, 1)`` on ``lights``.
        """
        st = self.state
        rows = unconverged_dielectric_rows(scores[0], scores[1], sigma2, n_residuals, self.cfg.false_metal_rate)
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
        c = pixel_cost(r)
        better = c < scores[0][rows]
        st["theta"][0] = th0.clone()
        st["theta"][0][rows] = torch.where(better, new, th0[rows])
        out = scores[0].clone()
        out[rows] = torch.where(better, c, scores[0][rows])
        return out

    def _soft_metal(self, size: int, kind: str) -> None:
        """Final stage (:func:`soft_metal_stage`) on the chosen maps; records ``state["soft_metal"]``
        (pixels refitted, growth included; fractional; moved glossy to rough; seconds)."""
        t_start = time.perf_counter()
        st = self.state
        data = self.data(size, all_lights=(kind == "all"))
        st["theta"][0], st["metal"], counts = soft_metal_stage(data, st["theta"][0], st["metal"], self.cfg)
        st["soft_metal"] = counts | {"seconds": time.perf_counter() - t_start}

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
        var_r = sigma2 / info[:, 4:5] * ((R_MAX - R_MIN) * sr * (1 - sr)) ** 2
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
            pred = render_fit(maps, (d.pos[[self.holdout]], d.inten[[self.holdout]]), d.camera, self.cfg.model)
        assert d.images is not None  # a full level, not a pixel subset
        return {"light": self.holdout, "file": self.cap.files[self.holdout],
                "psnr": psnr(pred[0], d.images[self.holdout])}


def psnr(pred: Tensor, ref: Tensor) -> float:
    """PSNR in dB of linear images ``pred`` and ``ref`` (any one shape, e.g. ``(L, 3, H, W)``),
    peak = the reference's maximum; +inf where they are equal."""
    mse = float(((pred - ref) ** 2).mean())
    peak = float(ref.max())
    return float("inf") if mse == 0 else 10 * math.log10(peak * peak / mse)
