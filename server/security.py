"""API keys: when ``settings.api_keys`` is set, every /v1 route needs ``Authorization: Bearer KEY`` or
``X-API-Key: KEY`` (compared in constant time against every configured key); health, metadata and metrics stay
open."""

from __future__ import annotations

import hmac

from fastapi import Request
from fastapi.security import APIKeyHeader, HTTPBearer

from .errors import Unauthorized

# declared for the OpenAPI document (auto_error=False: the check below gives our own 401 body)
bearer_scheme = HTTPBearer(auto_error=False, description="Authorization: Bearer KEY")
key_scheme = APIKeyHeader(name="X-API-Key", auto_error=False, description="X-API-Key: KEY")


def _matches(given: str, keys: tuple[str, ...]) -> bool:
    g = given.encode("utf-8", "surrogateescape")
    ok = False
    for k in keys:   # every key compared (no early exit), each in constant time
        ok |= hmac.compare_digest(g, k.encode("utf-8"))
    return ok


async def require_key(request: Request) -> None:
    keys = request.app.state.service.settings.api_keys
    if not keys:
        return
    given = request.headers.get("x-api-key")
    if given is None:
        auth = request.headers.get("authorization", "")
        scheme, _, token = auth.partition(" ")
        if scheme.lower() == "bearer" and token:
            given = token.strip()
    if not given or not _matches(given, keys):
        raise Unauthorized()


__all__ = ["require_key"]
