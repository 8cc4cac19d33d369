"""SVBRDF recovery from multi-light captures, and fitting principled parameters to measured BRDFs.

``api`` is the recovery (:func:`recover` -> :class:`RecoveryResult`, :class:`RecoveryConfig`),
``outputs`` its output folder (:func:`load_outputs` reads one back), ``checkpoint`` the
fingerprints and checkpoint checks, ``previews`` its figures, ``progress`` its messages,
``options``/``cli`` the ``torchbrdf-recover`` command (``svbrdf`` re-exports them),
``smoothness_prior`` its coupled spatial prior and the
conjugate-gradient solve, ``batch`` many captures on Ray
(``torchbrdf-recover-many``; Ray imported only when used), ``fit_measured`` the MERL fit (``torchbrdf-fit-merl``).

May import everything below it: ``torchbrdf.capture``, ``torchbrdf.render``,
``torchbrdf.brdf``, ``torchbrdf.io`` and the plumbing.
"""

from torchbrdf.recovery.api import map_errors, recover
from torchbrdf.recovery.checks import RecoveryError
from torchbrdf.recovery.outputs import RecoveryResult, load_outputs
from torchbrdf.recovery.solver import RecoveryConfig, psnr

__all__ = ["RecoveryConfig", "RecoveryError", "RecoveryResult", "recover", "load_outputs", "map_errors",
           "psnr"]
from torchbrdf.recovery.prior import Prior, prior_penalty, prior_weight  # noqa: E402  (the learned prior)
__all__ += ["Prior", "prior_penalty", "prior_weight"]
