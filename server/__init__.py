"""The HTTP service (FastAPI) over xyzcyl.runtime: ``create_app(Settings(...))``; ``xyzcyl serve`` runs it.
This package imports xyzcyl.runtime and xyzcyl.common only (tests/test_packaging.py checks it). docs/api.md describes
the API; docs/design.md the modules (app.py the shell, routes/ parse and answer, service.py does the work)."""

from __future__ import annotations

from xyzcyl.common.version import __version__


def __getattr__(name: str):
    if name == "create_app":
        from .app import create_app

        return create_app
    if name == "Settings":
        from .settings import Settings

        return Settings
    raise AttributeError(name)


__all__ = ["Settings", "__version__", "create_app"]
