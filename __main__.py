"""``python -m xyzcyl``: the `xyzcyl` console script (xyzcyl.cli)."""

import sys

from xyzcyl.cli import main

if __name__ == "__main__":         # not when a spawned worker process imports it (runtime.drive's keyframe workers)
    sys.exit(main())
