"""``python -m training.recover_svbrdf``: SVBRDF recovery (the same as ``torchbrdf-recover``).

See :mod:`torchbrdf.recovery.svbrdf` and ``docs/recovery.md``.
"""

import sys

from torchbrdf.recovery.svbrdf import main

if __name__ == "__main__":
    sys.exit(main())
