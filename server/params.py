"""Unknown query parameters are refused, not ignored: ``known_query``, a dependency of the /v1 routers, compares the
request's query string with the parameters its route declares and answers 422 naming every unknown one (a typo
such as ``render?camera=CAM_FRONT&widht=1600`` used to answer 200 at the default width). The batch POST's JSON
items are checked the same way by runtime.views ("unknown field (... takes ...)"); routes that declare no query
parameter are left alone (a cache-busting ``?_=123`` on them changes nothing)."""

from __future__ import annotations

import contextlib
import difflib

from fastapi import Request

from .errors import Invalid


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


__all__ = ["declared_query", "known_query", "unknown_query"]
