"""The server layer's commands (gathered by xyzcyl.cli): ``xyzcyl serve``, ``xyzcyl view`` and ``xyzcyl batch``, imported only when
they run."""

from __future__ import annotations

from xyzcyl.common.command import Command


def _serve():
    from . import serve

    return serve


def _batch():
    from . import batch

    return batch


def _view():
    from . import view

    return view


COMMANDS: tuple[Command, ...] = (
    Command("serve", "run the HTTP service (FastAPI + uvicorn)", _serve, "server"),
    Command("view", "open a scene folder in the web viewer (a local server on 127.0.0.1)", _view, "server"),
    Command("batch", "reconstruct every drive a manifest lists on Ray into a scene store", _batch, "batch"),
)

__all__ = ["COMMANDS"]
