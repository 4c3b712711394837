"""``python -m xyzcyl``: the `xyzcyl` console script (xyzcyl.cli)."""

import sys

from xyzcyl.cli import main

sys.exit(main())
