"""The server layer's command (gathered by xyzcyl.cli): ``xyzcyl serve``, imported only when it runs."""

from __future__ import annotations

from xyzcyl.common.command import Command


def _serve():
    from . import serve

    return serve


COMMANDS: tuple[Command, ...] = (Command("serve", "run the HTTP service (FastAPI + uvicorn)", _serve, "server"),)

__all__ = ["COMMANDS"]
