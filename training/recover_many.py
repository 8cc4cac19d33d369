"""``python -m training.recover_many``: batch SVBRDF recovery on Ray (the same as ``torchbrdf-recover-many``).

See :mod:`torchbrdf.recovery.batch` and ``docs/cluster.md``.
"""

import sys

from torchbrdf.recovery.batch import main

if __name__ == "__main__":
    sys.exit(main())
