"""The recovery's options: :class:`RecoveryConfig` (the CLI flags of ``torchbrdf-recover``).
"""

from __future__ import annotations

from dataclasses import dataclass, field


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
