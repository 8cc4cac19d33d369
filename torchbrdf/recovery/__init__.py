"""SVBRDF recovery from multi-light captures, and fitting principled parameters to measured BRDFs.

``api`` is the recovery (:func:`recover` -> :class:`RecoveryResult`, :class:`RecoveryConfig`),
``outputs`` its output folder (:func:`load_outputs` reads one back), ``checkpoint`` the
fingerprints and checkpoint checks, ``previews`` its figures, ``progress`` its messages,
``options``/``cli`` the ``torchbrdf-recover`` command (``svbrdf`` re-exports them),
and its algorithm, one concept per module, imports running downward: ``engine`` (the
resumable :class:`~torchbrdf.recovery.engine.Recovery`) over ``soft_metal`` (the final stage's
continuous metallic), ``classes`` (metal / dielectric), ``search`` (propagation, normal search),
``calibration`` (the lights), ``priors`` (non-local), ``lm`` (Levenberg–Marquardt), ``levels``
(the capture at one resolution), ``map_ops``, ``params`` (the unknowns) and ``config``
(:class:`RecoveryConfig`); ``solver`` re-exports the former single module's names.
``prior`` is the learned prior; ``smoothness_prior`` the coupled spatial prior and the
conjugate-gradient solve, ``pixel_systems`` the per-pixel linear algebra under both, ``batch`` many captures on Ray
(``torchbrdf-recover-many``; Ray imported only when used), ``fit_measured`` the MERL fit (``torchbrdf-fit-merl``).

May import everything below it: ``torchbrdf.capture``, ``torchbrdf.render``,
``torchbrdf.brdf``, ``torchbrdf.io``, ``torchbrdf.parallel`` (the thread count), ``torchbrdf.kernels``
(the lane-wise C linear algebra, lazily at dispatch) and the plumbing.
"""

from torchbrdf.recovery.api import map_errors, recover
from torchbrdf.recovery.checks import RecoveryError
from torchbrdf.recovery.config import CalibrationConfig, ClassConfig, PriorConfig, RecoveryConfig, ScheduleConfig
from torchbrdf.recovery.engine import psnr
from torchbrdf.recovery.outputs import RecoveryResult, load_outputs
from torchbrdf.recovery.prior import Prior, prior_penalty, prior_weight

__all__ = ["RecoveryConfig", "ScheduleConfig", "PriorConfig", "CalibrationConfig", "ClassConfig", "RecoveryError",
           "RecoveryResult", "recover", "load_outputs", "map_errors", "psnr", "Prior", "prior_penalty",
           "prior_weight"]
