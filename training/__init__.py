"""Runnable recovery, evaluation and fitting scripts of the repository.

Thin command-line wrappers around :mod:`torchbrdf.recovery`; this folder is not installed
(pip users have the ``torchbrdf-recover`` and ``torchbrdf-fit-merl`` commands).
"""

import os

# These scripts are commands that own their process, so they may choose how OpenMP threads
# wait: sleeping, not spinning. Spinning threads made the recovery several times slower next to
# one busy process (docs/fast_path.md, "Threads"). libgomp reads this once, when torch loads it,
# and ``python -m training.<script>`` runs this file before the script imports torch. A value the
# user set (OMP_WAIT_POLICY or GOMP_SPINCOUNT) is kept. The library itself never sets it.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
