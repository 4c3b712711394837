"""Fixtures of the client tests: ``sent``, the query parameters of each render request the client makes, answered
by a mock transport with a few PNG bytes (client_helpers.PNG), so no server runs."""

from __future__ import annotations

import pytest
from client_helpers import PNG


@pytest.fixture
def sent(monkeypatch):
    """The query parameters of each render request, answered with ``PNG``."""
    httpx = pytest.importorskip("httpx")
    calls: list[dict[str, str]] = []
    real = httpx.Client

    def handler(request):
        calls.append(dict(request.url.params))
        return httpx.Response(200, content=PNG, headers={"content-type": "image/png"})

    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(handler), **kw))
    monkeypatch.delenv("XYZCYL_API_KEY", raising=False)
    return calls
