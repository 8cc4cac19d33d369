"""``python -m training.fit_measured``: fit principled parameters to a MERL file (``torchbrdf-fit-merl``).

See :mod:`torchbrdf.recovery.fit_measured`.
"""

import sys

from torchbrdf.recovery.fit_measured import main

if __name__ == "__main__":
    sys.exit(main())
