"""The dependencies of the endpoints, the one module the routes take them from (never from app.py):

- ``service_of(request)``: the app's Service (service.py);
- ``require_key``: when ``settings.api_keys`` is set, every /v1 route needs ``Authorization: Bearer KEY`` or
  ``X-API-Key: KEY`` (compared in constant time against every configured key); health, metadata and metrics stay
  open;
- ``known_query``: unknown query parameters are refused, not ignored. It compares the request's query string with
  the parameters its route declares and answers 422 naming every unknown one (a typo such as
  ``render?camera=CAM_FRONT&widht=1600`` used to answer 200 at the default width). The batch POST's JSON items
  are checked the same way by runtime.views ("unknown field (... takes ...)"); routes that declare no query
  parameter are left alone (a cache-busting ``?_=123`` on them changes nothing).

The /v1 routers run require_key first (401 before anything else), then known_query."""

from __future__ import annotations

import contextlib
import difflib
import hmac

from fastapi import Request
from fastapi.security import APIKeyHeader, HTTPBearer
from pydantic import BaseModel

from .errors import Invalid, Unauthorized, UnsupportedMedia
from .service import Service


def service_of(request: Request) -> Service:
    return request.app.state.service


# ----------------------------------------------------------------------------------------------- API keys

# declared for the OpenAPI document (auto_error=False: the check below gives our own 401 body)
bearer_scheme = HTTPBearer(auto_error=False, description="Authorization: Bearer KEY")
key_scheme = APIKeyHeader(name="X-API-Key", auto_error=False, description="X-API-Key: KEY")


def key_matches(given: str, keys: tuple[str, ...]) -> bool:
    """Whether ``given`` is one of ``keys`` (the HTTP routes' and the gRPC calls' one check)."""
    g = given.encode("utf-8", "surrogateescape")
    ok = False
    for k in keys:   # every key compared (no early exit), each in constant time
        ok |= hmac.compare_digest(g, k.encode("utf-8"))
    return ok


async def require_key(request: Request) -> None:
    keys = service_of(request).settings.api_keys
    if not keys:
        return
    given = request.headers.get("x-api-key")
    if given is None:
        auth = request.headers.get("authorization", "")
        scheme, _, token = auth.partition(" ")
        if scheme.lower() == "bearer" and token:
            given = token.strip()
    if not given or not key_matches(given, keys):
        raise Unauthorized()


# ----------------------------------------------------------------------------------------------- the body's type

def require_content_type(request: Request, media: str, what: str) -> None:
    """UnsupportedMedia (415) unless the request's body is ``media`` (routes that read their body themselves call
    it where that check belongs among theirs)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith(media):
        raise UnsupportedMedia(f"{what} takes {media}, not {ctype or 'no content type'!r}", "content-type")


# ----------------------------------------------------------------------------------------------- query parameters

def declared_query(route) -> tuple[str, ...]:
    """The query parameter names (aliases) a route declares, its dependencies' included, in declaration order
    (computed once per route, kept on it)."""
    names = getattr(route, "_xyzcyl_query", None)
    if names is None:
        names = _declared(route)
        with contextlib.suppress(AttributeError, TypeError):
            route._xyzcyl_query = names
    return names


def _declared(route) -> tuple[str, ...]:
    def walk(dependant):
        for p in dependant.query_params:
            model = getattr(p.field_info, "annotation", None)
            if isinstance(model, type) and issubclass(model, BaseModel):    # a query model: its fields
                yield from (f.alias or name for name, f in model.model_fields.items())
            else:
                yield getattr(p, "alias", None) or p.name
        for sub in dependant.dependencies:
            yield from walk(sub)

    dependant = getattr(route, "dependant", None)
    return () if dependant is None else tuple(dict.fromkeys(walk(dependant)))


def unknown_query(given, allowed: tuple[str, ...], where: str) -> Invalid | None:
    """The 422 for the names in ``given`` (an iterable of query keys) that ``allowed`` lacks, or None."""
    unknown = [k for k in dict.fromkeys(given) if k not in allowed]
    if not unknown:
        return None
    hints = {k: close[0] for k in unknown if (close := difflib.get_close_matches(k, allowed, n=1, cutoff=0.6))}
    if len(unknown) == 1 and hints:
        hint = f"; did you mean {hints[unknown[0]]}?"
    else:
        hint = f"; did you mean {', '.join(f'{v} for {k}' for k, v in hints.items())}?" if hints else ""
    plural = "s" if len(unknown) > 1 else ""
    return Invalid(f"{', '.join(unknown)}: unknown query parameter{plural} ({where} takes {', '.join(allowed)}"
                   f"{hint})", unknown[0])


async def known_query(request: Request) -> None:
    """422 when the query string names a parameter that the matched route does not declare."""
    route = request.scope.get("route")
    allowed = declared_query(route) if route is not None else ()
    if not allowed or not request.query_params:
        return
    methods = "|".join(sorted(getattr(route, "methods", None) or ()))
    err = unknown_query(request.query_params.keys(), allowed, f"{methods} {route.path}".strip())
    if err is not None:
        raise err


__all__ = ["declared_query", "key_matches", "known_query", "require_content_type", "require_key", "service_of",
           "unknown_query"]
