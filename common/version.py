"""The version of xyzcyl, from one source: pyproject.toml's ``[project] version``, as the installed distribution's
metadata records it (``importlib.metadata``). The console script's ``--version``, the HTTP service (OpenAPI, the
/v2 server metadata) and the gRPC service's get_version all report this one; the model's own version is in its
model.json (runtime.model_folder) and is reported beside it."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _distribution_version

UNKNOWN = "0+unknown"     # a tree imported without being installed: no metadata to read


def package_version() -> str:
    """The installed distribution's version, UNKNOWN when xyzcyl is not installed."""
    try:
        return _distribution_version("xyzcyl")
    except PackageNotFoundError:
        return UNKNOWN


__version__ = package_version()

__all__ = ["UNKNOWN", "__version__", "package_version"]
