"""The recovery's algorithm, by its former single-module name.

The algorithm now lives one concept per module (``params``, ``levels``, ``map_ops``, ``lm``,
``priors``, ``calibration``, ``search``, ``classes``, ``soft_metal``, ``engine``; the options in
``config``): this module re-exports the names outside code imported from it.
"""

from torchbrdf.recovery.config import RecoveryConfig
from torchbrdf.recovery.engine import CHECKPOINT, Recovery, psnr

__all__ = ["RecoveryConfig", "Recovery", "psnr", "CHECKPOINT"]
