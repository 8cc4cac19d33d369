"""SVBRDF recovery from multi-light captures, and fitting principled parameters to measured BRDFs.

``svbrdf`` is the recovery (:func:`recover` -> :class:`RecoveryResult`, :class:`RecoveryConfig`;
:func:`load_outputs` reads an output folder back; the
``torchbrdf-recover`` command). Its algorithm, one concept per module, imports run downward:
``engine`` (the resumable :class:`~torchbrdf.recovery.engine.Recovery`) over ``soft_metal``
(the final stage's continuous metallic), ``classes`` (metal / dielectric), ``search``
(propagation, normal search), ``calibration`` (the lights), ``priors`` (non-local), ``lm``
(Levenberg–Marquardt), ``levels`` (the capture at one resolution), ``map_ops``, ``params``
(the unknowns) and ``config`` (:class:`RecoveryConfig`); ``solver`` re-exports the former
single module's names. ``smoothness_prior`` is its coupled spatial prior and the
conjugate-gradient solve, ``batch`` many captures on Ray
(``torchbrdf-recover-many``; Ray imported only when used), ``fit_measured`` the MERL fit (``torchbrdf-fit-merl``).

May import everything below it: ``torchbrdf.capture``, ``torchbrdf.render``,
``torchbrdf.brdf``, ``torchbrdf.io`` and the plumbing.
"""

from torchbrdf.recovery.config import CalibrationConfig, ClassConfig, PriorConfig, ScheduleConfig
from torchbrdf.recovery.svbrdf import (
    RecoveryConfig,
    RecoveryError,
    RecoveryResult,
    load_outputs,
    map_errors,
    psnr,
    recover,
)

__all__ = ["RecoveryConfig", "ScheduleConfig", "PriorConfig", "CalibrationConfig", "ClassConfig", "RecoveryError",
           "RecoveryResult", "recover", "load_outputs", "map_errors", "psnr"]
