"""`xyzcyl client ...`: subcommands that talk to a running server over HTTP (clients/client.py): ``COMMANDS``,
gathered by the `xyzcyl` console script (xyzcyl.cli). The module is imported only when the command runs."""

from __future__ import annotations

from xyzcyl.common.command import Command


def _client():
    from . import client
    return client


COMMANDS: tuple[Command, ...] = (
    Command("client", "talk to a running server: reconstruct, render, path, gaussians, scenes, delete", _client,
            "client"),
)

__all__ = ["COMMANDS"]
