"""xyzcyl.clients: the Python client of the HTTP service (``from xyzcyl.clients import Client``; docs/client.md)
and the `xyzcyl client` command (clients/commands). The client is imported lazily, so ``xyzcyl --help`` does not
import httpx or numpy."""

from __future__ import annotations

_CLIENT_NAMES = ("AuthError", "BusyError", "Client", "ConnectionFailed", "DriveUpload", "FrameBatch",
                 "InvalidArgumentError", "InvalidRequestError", "NotFoundError", "NotReadyError", "SceneInfo",
                 "ServerError", "StorageFullError", "WaitTimeout", "XyzcylError", "decode_image", "encode_png",
                 "error_for", "is_drive_file", "read_drive", "view_params")


def __getattr__(name: str):
    if name in _CLIENT_NAMES:
        from . import client

        return getattr(client, name)
    raise AttributeError(f"module 'xyzcyl.clients' has no attribute {name!r}")


__all__ = list(_CLIENT_NAMES)
