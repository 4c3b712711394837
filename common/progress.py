"""Progress bars: the one helper that creates every tqdm bar of the project (the client's uploads and downloads, the
synthetic generator, training, evaluation). A bar is drawn only when its stream (stderr by default) is a terminal:
redirected to a file, a pipe or a CI log, tqdm wrote a line per refresh (``upload: 0.00B [00:00, ?B/s]``), so there
the bar is off (the returned tqdm object still counts; its updates print nothing). Only tqdm and the standard
library: the HTTP client imports it too."""

from __future__ import annotations

import sys
from typing import IO, Any


def is_terminal(stream: IO[str] | None) -> bool:
    """Whether ``stream`` is an open terminal (False for files, pipes, closed or missing streams)."""
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def progress_bar(*, enabled: bool = True, file: IO[str] | None = None, **kwargs: Any):
    """A tqdm bar on ``file`` (default sys.stderr), disabled unless ``enabled`` and that stream is a terminal.
    ``kwargs`` go to tqdm (total, desc, unit, unit_scale, leave, dynamic_ncols, ...)."""
    from tqdm import tqdm

    stream = sys.stderr if file is None else file
    return tqdm(file=stream, disable=not (enabled and is_terminal(stream)), **kwargs)


__all__ = ["is_terminal", "progress_bar"]
