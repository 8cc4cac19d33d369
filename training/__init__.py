"""Runnable recovery, evaluation and fitting scripts of the repository.

Thin command-line wrappers around :mod:`torchbrdf.recovery`; this folder is not installed
(pip users have the ``torchbrdf-recover`` and ``torchbrdf-fit-merl`` commands).
"""

import os

# These scripts are commands that own their process, so they may choose how OpenMP threads
# wait: a short poll, then sleep. libgomp's default (300 000 polls) made the recovery several
# times slower next to one busy process; sleeping at once (PASSIVE) costs ~35 % on a quiet
# machine, where the many short parallel regions pay a wake-up each; 2000 polls keep most of
# both (docs/fast_path.md, "Threads"). libgomp (torch's runtime on Linux) takes GOMP_SPINCOUNT
# over the policy; other runtimes take PASSIVE. They are read once, when torch loads the
# runtime, and ``python -m training.<script>`` runs this file before the script imports torch.
# A value the user set (OMP_WAIT_POLICY or GOMP_SPINCOUNT) is kept. The library itself never
# sets them (the console script torchbrdf-recover does the same, in torchbrdf/__init__.py).
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    os.environ["GOMP_SPINCOUNT"] = "2000"
