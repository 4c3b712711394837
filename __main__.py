"""``python -m xyzcyl``: the `xyzcyl` console script (xyzcyl.cli.entry)."""

from xyzcyl.cli import entry

if __name__ == "__main__":         # not when a spawned worker process imports it (runtime.drive's keyframe workers)
    entry()
