"""SVBRDF recovery from multi-light captures, and fitting principled parameters to measured BRDFs.

``svbrdf`` is the recovery (:func:`recover`, :class:`RecoveryConfig`; the
``torchbrdf-recover`` command), ``smoothness_prior`` its coupled spatial prior and the
conjugate-gradient solve, ``batch`` many captures on Ray
(``torchbrdf-recover-many``; Ray imported only when used), ``fit_measured`` the MERL fit (``torchbrdf-fit-merl``).

May import everything below it: ``torchbrdf.capture``, ``torchbrdf.render``,
``torchbrdf.brdf``, ``torchbrdf.io`` and the plumbing.
"""

from torchbrdf.recovery.svbrdf import RecoveryConfig, map_errors, psnr, recover

__all__ = ["RecoveryConfig", "recover", "map_errors", "psnr"]
