"""The recovery's options and the method's constants.

:class:`RecoveryConfig` is what a user sets (the flags of ``torchbrdf-recover``): a few run
settings and four groups — :class:`ScheduleConfig`, :class:`PriorConfig`,
:class:`CalibrationConfig`, :class:`ClassConfig` — 20 fields in all. Everything else the
algorithm reads is a constant of the method, documented with its reason in :class:`Settings`,
the flat parameter set the solver runs on (:meth:`RecoveryConfig.settings`). Experiments and
tests replace a constant there (``RecoveryConfig().settings(fuse_rounds=1)``); the test hooks
(``fault_at``, ``signal_at``) live only there.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar, overload

__all__ = ["RecoveryConfig", "ScheduleConfig", "PriorConfig", "CalibrationConfig", "ClassConfig", "Settings",
           "settings_of", "SCHEDULES"]

#: The schedules a user chooses by name (``RecoveryConfig(schedule="fast")``, ``--schedule``): the
#: :class:`ScheduleConfig` fields each sets, the rest at their defaults. ``fast`` plans 18 LM
#: iterations (the default plan's proportions) and stops a full-resolution stage at a 3 % change;
#: ``thorough`` plans twice the default's 39 and stops only below 0.2 %, after at least 4.
#: Time against held-out accuracy: docs/recovery_measurements.md, "Schedules: time against accuracy".
SCHEDULES: dict[str, dict[str, Any]] = {
    "fast": {"iters": 18, "converge_tol": 0.03},
    "default": {},
    "thorough": {"iters": 78, "converge_tol": 0.002, "converge_min_iters": 4},
}


@dataclass
class ScheduleConfig:
    """How long the fit runs: levels, iterations, step and the early stop.

    Attributes:
        levels: coarse-to-fine levels (S/4, S/2, S with 3); the coarse levels settle the class
            choice and the low frequencies cheaply (docs/recovery.md, "Coarse to fine").
        iters: total LM iterations, spread over the stages in the default plan's proportions
            (0: the default plan, 39 at most).
        lr: the LM step multiplier (halved after a non-finite loss); 1 is the Gauss–Newton step.
        converge_tol: a full-resolution stage ends once an iteration changes its fit loss by
            less than this fraction (0: every planned iteration); 1 % keeps every map within
            measurement noise of the full plan at about half its full-resolution iterations.
        converge_min_iters: ... after at least this many of its iterations (the first has no
            earlier fit of its stage to compare with).
    """

    levels: int = 3
    iters: int = 0
    lr: float = 1.0
    converge_tol: float = 0.01
    converge_min_iters: int = 2

    @classmethod
    def preset(cls, name: str) -> ScheduleConfig:
        """The schedule called ``name``, one of :data:`SCHEDULES` (``"fast"``, ``"default"``,
        ``"thorough"``).

        Raises:
            ValueError: ``name`` is not one of them (the message lists them).
        """
        if name not in SCHEDULES:
            raise ValueError(f"schedule: expected one of {', '.join(SCHEDULES)}, got {name!r}")
        return cls(**SCHEDULES[name])


@dataclass
class PriorConfig:
    """Precisions of the spatial priors, in units of one residual's squared log error.

    Attributes:
        roughness: tie between 4-neighbours' roughness logits of one class, × the base-colour
            similarity guide: fills in glossy pixels whose highlight no light reaches.
        specular: the same for a dielectric's specular.
        metal_base: tie between neighbouring metals' F0 (base colour), × the same guide.
        nonlocal_base: precision of the non-local average of a metal's F0 (0: off); the average
            holds a metal far from every highlight at the F0 of the well-observed metal around it.
    """

    roughness: float = 0.002
    specular: float = 0.002
    metal_base: float = 0.02
    nonlocal_base: float = 0.003


@dataclass
class CalibrationConfig:
    """Which light errors are estimated with the maps.

    Attributes:
        light_scale: each light's intensity scale (False: no light estimate at all); the
            training lights' mean log scale stays at the stated one.
        light_position: also each light's position offset (prior 1 cm), the rig's placement
            held as stated.
    """

    light_scale: bool = True
    light_position: bool = True


@dataclass
class ClassConfig:
    """The metal / dielectric decision.

    Attributes:
        soft_metal: the final stage's continuous metallic at class boundaries and on poorly
            fitting pixels (False: every pixel exactly 0 or 1).
        false_metal_rate: the rate, per pixel, at which noise alone may buy a metal for a
            dielectric. Every metal/dielectric choice is a likelihood-ratio test at the
            capture's measured noise level whose threshold, the χ²(7) quantile at
            ``1 − false_metal_rate``, follows from this rate
            (``torchbrdf.recovery.classes.evidence_threshold``). 1e-4: a fifth of the 0.05 %
            of a dielectric's pixels that may be called metal, leaving room for the misfit of
            a forward model the fit does not share; measured by
            ``python -m torchbrdf.bench.false_metal`` (docs/recovery_measurements.md). The same
            rate marks the pixels whose misfit the noise does not explain: the ones the
            propagation within a stage tries (``torchbrdf.recovery.search.unexplained``).
    """

    soft_metal: bool = True
    false_metal_rate: float = 1e-4


_T = TypeVar("_T")

# Options that no longer exist, and what took their place.
_REMOVED = {"metal_margin": " (removed: the class choice is a likelihood-ratio test at the measured noise; "
                            "classes.false_metal_rate sets its false-positive rate)"}

# Former flat RecoveryConfig fields that map onto a group's field: old name -> (group, field).
_FLAT = {
    "levels": ("schedule", "levels"), "iters": ("schedule", "iters"), "lr": ("schedule", "lr"),
    "converge_tol": ("schedule", "converge_tol"), "converge_min_iters": ("schedule", "converge_min_iters"),
    "prior_roughness": ("priors", "roughness"), "prior_specular": ("priors", "specular"),
    "prior_metal_base": ("priors", "metal_base"), "prior_nonlocal_base": ("priors", "nonlocal_base"),
    "light_scale": ("calibration", "light_scale"), "light_position": ("calibration", "light_position"),
    "soft_metal": ("classes", "soft_metal"), "false_metal_rate": ("classes", "false_metal_rate"),
}
_GROUPS = {"schedule": ScheduleConfig, "priors": PriorConfig, "calibration": CalibrationConfig,
           "classes": ClassConfig}


class _Flat(Generic[_T]):
    """A former flat field, read and written through its group (``cfg.iters`` is ``cfg.schedule.iters``)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.group, self.field = _FLAT[name]

    @overload
    def __get__(self, obj: None, owner: type) -> _Flat[_T]: ...
    @overload
    def __get__(self, obj: object, owner: type) -> _T: ...

    def __get__(self, obj: object | None, owner: type) -> Any:
        return self if obj is None else getattr(getattr(obj, self.group), self.field)

    def __set__(self, obj: object, value: _T) -> None:
        setattr(getattr(obj, self.group), self.field, value)


@dataclass(init=False)
class RecoveryConfig:
    """Options of :func:`recover` (the CLI flags): run settings and four groups of the method.

    Attributes:
        size: working resolution (None: the capture's).
        seed: the seed of every random choice (the results are deterministic for a seed).
        device: torch device to run on (``"cpu"``, ``"cuda"``).
        model: the BRDF fitted: ``"principled"`` or ``"svbrdf_ggx"``.
        holdout: index of the validation light, left out of the fit until the last stage
            (None: light 0 with 5+ lights; -1: none).
        checkpoint_every: iterations between checkpoints in ``--out``.
        threads: CPU threads for torch (None: torch's choice).
        schedule, priors, calibration, classes: the groups (:class:`ScheduleConfig`,
            :class:`PriorConfig`, :class:`CalibrationConfig`, :class:`ClassConfig`); ``schedule``
            may also name one of :data:`SCHEDULES` (``"fast"``, ``"default"``, ``"thorough"``),
            which flat keywords such as ``iters`` then adjust.

    The former flat names of the groups' fields (``iters``, ``lr``, ``levels``,
    ``converge_tol``, ``converge_min_iters``, ``prior_roughness``, ``prior_specular``,
    ``prior_metal_base``, ``prior_nonlocal_base``, ``light_scale``, ``light_position``,
    ``soft_metal``, ``false_metal_rate``) are accepted as keywords and attributes.
    """

    size: int | None
    seed: int
    device: str
    model: str
    holdout: int | None
    checkpoint_every: int
    threads: int | None
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    priors: PriorConfig = field(default_factory=PriorConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    classes: ClassConfig = field(default_factory=ClassConfig)

    levels = _Flat[int]()
    iters = _Flat[int]()
    lr = _Flat[float]()
    converge_tol = _Flat[float]()
    converge_min_iters = _Flat[int]()
    prior_roughness = _Flat[float]()
    prior_specular = _Flat[float]()
    prior_metal_base = _Flat[float]()
    prior_nonlocal_base = _Flat[float]()
    light_scale = _Flat[bool]()
    light_position = _Flat[bool]()
    soft_metal = _Flat[bool]()
    false_metal_rate = _Flat[float]()

    def __init__(self, *, size: int | None = None, seed: int = 0, device: str = "cpu", model: str = "principled",
                 holdout: int | None = None, checkpoint_every: int = 5, threads: int | None = None,
                 schedule: ScheduleConfig | str | None = None, priors: PriorConfig | None = None,
                 calibration: CalibrationConfig | None = None, classes: ClassConfig | None = None,
                 **flat: Any) -> None:
        self.size, self.seed, self.device, self.model = size, seed, device, model
        self.holdout, self.checkpoint_every, self.threads = holdout, checkpoint_every, threads
        if isinstance(schedule, str):
            schedule = ScheduleConfig.preset(schedule)
        for name, value in (("schedule", schedule), ("priors", priors), ("calibration", calibration),
                            ("classes", classes)):
            kind = _GROUPS[name]
            if value is not None and not isinstance(value, kind):
                raise TypeError(f"RecoveryConfig: {name} must be a {kind.__name__}, got {type(value).__name__}")
            setattr(self, name, dataclasses.replace(value) if value is not None else kind())
        for name, value in flat.items():
            if name not in _FLAT:
                hint = (" (a constant of the method: RecoveryConfig().settings(...) replaces it)"
                        if name in _SETTING_NAMES else _REMOVED.get(name, ""))
                raise TypeError(f"RecoveryConfig: unexpected keyword {name!r}{hint}")
            setattr(self, name, value)

    def settings(self, **constants: Any) -> Settings:
        """The flat parameter set the solver runs on: these options, the method's constants as
        documented in :class:`Settings`, and ``constants`` replacing some of those (experiments
        and tests; a name :class:`Settings` lacks raises ``TypeError``)."""
        user = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in _GROUPS}
        user |= {name: getattr(self, name) for name in _FLAT}
        return Settings(**(user | constants))


@dataclass
class Settings:
    """Every parameter the solver reads, flat: :class:`RecoveryConfig`'s, and the method's constants.

    The constants are fixed by the method, each for the reason given beside it; they are not
    options (:meth:`RecoveryConfig.settings` replaces them for an experiment or a test). Noise
    variances ``σ²`` are measured on the capture (the median pixel's cost per residual).
    """

    # The user's options (RecoveryConfig), flat
    iters: int = 0
    lr: float = 1.0
    size: int | None = None
    seed: int = 0
    device: str = "cpu"
    levels: int = 3
    prior_roughness: float = 0.002
    prior_specular: float = 0.002
    prior_metal_base: float = 0.02
    prior_nonlocal_base: float = 0.003
    converge_tol: float = 0.01
    converge_min_iters: int = 2
    light_position: bool = True
    light_scale: bool = True
    false_metal_rate: float = 1e-4
    soft_metal: bool = True
    holdout: int | None = None
    checkpoint_every: int = 5
    model: str = "principled"
    threads: int | None = None

    # Spatial prior
    prior_sigma: float = 0.1  # base-colour similarity scale of the ties: a step of 0.1 cuts them
    metal_base_guided: bool = True  # the metal F0 tie × that guide: a rust island must not darken the metal
    # Propagation and search
    propagate: bool = True  # PatchMatch-style neighbour propagation: Gauss–Newton only walks downhill
    propagate_passes: int = 6  # passes at a stage's start, one pixel further per pass
    # ... and one pass before every later LM iteration of the single-class stages, on the pixels
    # whose cost the noise does not explain (search.unexplained, at false_metal_rate; on every
    # pixel where those are over search.FULL_PASS_SHARE of the map)
    propagate_every: bool = True
    cg_iters: int = 30  # conjugate-gradient iterations per LM step (the coupled prior)
    # The learned prior's noise variance σ² (its precision is σ² / σ_map²): the fit's median
    # per-residual cost, at most this (a 3 % log error); a fit far from the data early on
    # would otherwise make the prior's pull as strong as its own misfit.
    prior_noise_cap: float = 1e-3
    # Non-local fill of roughness / specular (nonlocal_fill): each dielectric pixel's Gaussian prior
    # is the same material's measured value, its width the material's measured spread; a metal's
    # valley is held by the F0 tie alone (docs/recovery.md)
    fill: bool = True
    fill_range: float = 0.04  # base-colour similarity scale
    fill_texture: float = 0.05  # normal-spread similarity scale (slope units)
    fill_candidates: int = 256  # random same-class candidates per pixel
    # Metal / dielectric
    refit_before_choice: bool = True  # a metal's win is evidence only against a converged dielectric
    # Full resolution, after the class choice: a dielectric at the glossy end (roughness below
    # rough_tie_glossy) moves to the rough basin (refitted with roughness held at rough_tie_start)
    # where that fits within rough_tie noise variances of the glossy fit (rough_basin_tie; 0: off):
    # between two basins that fit alike, the wider one holds more posterior mass.
    rough_tie: float = 2.0
    rough_tie_glossy: float = 0.1
    rough_tie_start: float = 0.85
    # The same in the final stage (soft_rough_tie), metallic free, below soft_rough_tie_glossy: a
    # rough, partly metal rim fits as well as a glossy dielectric whose lobe falls between the lights.
    soft_rough_tie: float = 2.0
    soft_rough_tie_glossy: float = 0.2
    # Light calibration
    # Start the estimates in the two-hypothesis stages: the maps otherwise absorb part of a
    # light's error before the single-class stages can see it.
    dual_calibration: bool = True
    dual_calibration_coarse: bool = True  # ... the scales from the coarsest level on (same reason)
    # ... and, at full resolution, the position of a light beside the camera, the least determined
    # one (held, a real error of it stays in the maps).
    dual_calibration_at_camera: bool = True
    light_joint: bool = True  # step the lights with the maps eliminated (alternating steps creep)
    # ... resting after a step as many iterations as could not move them beyond noise (s of
    # them, the step's χ² × s² below its degrees of freedom; off: a step at every iteration)
    light_rest: bool = True
    # Non-local F0
    # The non-local F0 average as a unary prior of the fit from the polish stage on, not only
    # fused at the end: the light step then sees a weak metal's F0 held, not free along the
    # F0-roughness valley.
    fit_nonlocal_tie: bool = True
    prior_nonlocal: float = 0.0  # precision of a non-local roughness prior (0: off; the fill does its job)
    nonlocal_range: float = 0.02  # base-colour range of that roughness prior
    nonlocal_sigma: float = 0.25  # the non-local window's radius, a fraction of the map size
    nonlocal_clusters: int = 12  # base-colour clusters per class guiding the roughness prior
    # A metal pixel's weight in the F0 average, × min(1, this × the median metal cost / its cost):
    # a pixel the model fits k× worse says 1/k as much (0: off)
    nonlocal_fit_weight: float = 1.0
    fuse_refit_iters: int = 3  # LM iterations taking a fused metal's other unknowns to the fused F0
    # Rounds of the fusion, each from the last one's average: a pixel's one-step estimate of its
    # F0 optimum is better from nearer it; a third round barely moves any unknown.
    fuse_rounds: int = 2
    # Continuous metallic (the final stage, soft_metal_stage); σ² units throughout
    soft_metal_factor: float = 8.0  # candidates: a cost above this × the median (and boundaries)
    soft_metal_well: float = 32.0  # double-well prior w m²(1−m)²: metallic 0 and 1 are the likely values
    # Keep a fractional value only if it lowers the cost by this × σ²: a likelihood-ratio test for
    # one extra unknown at a rate P(χ²(1) > 8) = 0.5 %. The class test's stricter threshold
    # (false_metal_rate, 15.1 σ²) rejects the small gains along soft ramps.
    soft_metal_gain: float = 8.0
    soft_metal_smooth: float = 64.0  # second pass: pull toward the neighbours' metallic
    soft_metal_band: int = 2  # ... and pixels within this many pixels of a class boundary (a ramp's width)
    soft_metal_iters: int = 5  # per-pixel LM iterations
    soft_metal_max: float = 0.35  # at most this fraction of the pixels (the worst fitting) are candidates
    # ... and metals within the band of a base-colour step this large, or this far from the mean
    # colour of the metal around them: a rust island called metal has no class boundary
    soft_metal_edge: float = 0.15
    soft_metal_context: float = 0.25  # the gain, × this, beside a fractional pixel: a ramp goes on
    soft_metal_passes: int = 2  # second-pass rounds: a ramp settles from both of its ends
    soft_metal_grow: int = 3  # rounds of refitting the untried pixels beside a run of fractional ones
    # Pull toward the metallic that explains a candidate as a blend of the nearest clear metal and
    # dielectric (unmix_metallic; also its start): along that line the base colour tells the coverage
    soft_metal_unmix: float = 128.0
    # A candidate whose blend is its own class and whose cost is at most this × the median (1.5:
    # the 98.5th percentile of 51 residuals' noise) stays out of the metallic fits: nothing in its
    # data asks for a mixture (may_be_mixed; 0: off).
    soft_metal_quiet: float = 1.5
    # Last, a fractional pixel's base colour tied (× σ² per unit²) to the blend of the clear ends
    # beside it; 2500 = 1/0.02²: the ends are local means of clear pixels, known to about 0.02.
    soft_metal_line: float = 2500.0
    # Test hooks
    fault_at: int | None = None  # inject a NaN into the parameters at this iteration
    signal_at: int | None = None  # send ourselves SIGTERM after this iteration

    def settings(self, **constants: Any) -> Settings:
        """A copy with ``constants`` replaced (as :meth:`RecoveryConfig.settings`)."""
        return dataclasses.replace(self, **constants)


_SETTING_NAMES = frozenset(f.name for f in dataclasses.fields(Settings))


def settings_of(cfg: RecoveryConfig | Settings) -> Settings:
    """The flat :class:`Settings` of a :class:`RecoveryConfig` (a :class:`Settings` as it is).

    Raises:
        TypeError: ``cfg`` is neither.
    """
    if isinstance(cfg, Settings):
        return cfg
    if isinstance(cfg, RecoveryConfig):
        return cfg.settings()
    raise TypeError(f"expected a RecoveryConfig, got {type(cfg).__name__}")
