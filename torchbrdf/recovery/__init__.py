"""SVBRDF recovery from multi-light captures, and fitting principled parameters to measured BRDFs.

``svbrdf`` is the recovery (:func:`recover` -> :class:`RecoveryResult`, :class:`RecoveryConfig`;
:func:`load_outputs` reads an output folder back; the
``torchbrdf-recover`` command), ``smoothness_prior`` its coupled spatial prior and the
conjugate-gradient solve, ``batch`` many captures on Ray
(``torchbrdf-recover-many``; Ray imported only when used), ``fit_measured`` the MERL fit (``torchbrdf-fit-merl``).

May import everything below it: ``torchbrdf.capture``, ``torchbrdf.render``,
``torchbrdf.brdf``, ``torchbrdf.io`` and the plumbing.
"""

from torchbrdf.recovery.svbrdf import (
    RecoveryConfig,
    RecoveryError,
    RecoveryResult,
    load_outputs,
    map_errors,
    psnr,
    recover,
)

__all__ = ["RecoveryConfig", "RecoveryError", "RecoveryResult", "recover", "load_outputs", "map_errors",
           "psnr"]
