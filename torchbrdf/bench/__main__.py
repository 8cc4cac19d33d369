"""``python -m torchbrdf.bench``: see :mod:`torchbrdf.bench.brdf`."""

import sys

from torchbrdf.bench.brdf import main

sys.exit(main())
