"""``python -m training.recover_svbrdf``: SVBRDF recovery (the same as ``torchbrdf-recover``).

See :mod:`torchbrdf.recovery.svbrdf` and ``docs/recovery.md``.
"""

import os
import sys

# A command owns its process, so it may choose how OpenMP threads wait: sleeping, not spinning.
# Spinning threads made the recovery 5x slower next to one busy process (docs/fast_path.md).
# libgomp reads this once, when torch loads it: so before the first torch import. A value the
# user set (OMP_WAIT_POLICY or GOMP_SPINCOUNT) is kept.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from torchbrdf.recovery.svbrdf import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
