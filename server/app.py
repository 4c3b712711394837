"""``create_app(settings)``: the FastAPI application of the service (docs/api.md).

    from xyzcyl.server import Settings, create_app
    app = create_app(Settings(store="/tmp/store"))        # uvicorn.run(app) or `xyzcyl serve`

The application is the HTTP shell around one service.Service (``app.state.service``), which owns what the
endpoints do. The lifespan starts it: it opens the store (recovering from a crash) and then, in the background,
warms up (``warm_up``: a tiny render in the render pool, runtime.warmup) and starts the reconstruction workers
(each loads the model and, with ``warm_up``, runs a tiny reconstruction); ``/v2/health/ready`` answers 503 until
all of that has finished, so the first real request compiles no numba kernel. Middleware: the body limit (413
from Content-Length before anything is read, or as soon as a streamed body passes it), metrics per route
template, CORS when origins are configured. Errors become the one error body (errors.py). Endpoints live in
routes/ and take their dependencies (the service, API keys, known query parameters) from deps.py, never from
this module. With ``grpc_port`` set the lifespan also runs the gRPC SensorsimService (sensorsim/servicer.py) over
the same service, on that port (``app.state.grpc_port``: the one it listens on).
"""

from __future__ import annotations

import contextlib
import json
import logging
import time

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from xyzcyl.common.wire import field_path

from .deps import service_of
from .errors import ApiError, TooLarge, error_body
from .metrics import Metrics
from .routes import health, render, scenes, viewer
from .service import Service
from .settings import Settings
from .store import StoreUnavailable

log = logging.getLogger("xyzcyl.server")
API_VERSION = "1"


def _status_code_name(status: int) -> str:
    return {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
            405: "method_not_allowed", 406: "not_acceptable", 409: "not_ready", 413: "too_large",
            415: "unsupported_media_type", 422: "invalid", 429: "busy", 503: "busy"}.get(status, "error")


def _json_error(status: int, code: str, message: str, field: str | None = None,
                headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(error_body(code, message, field), status_code=status, headers=headers)


class _Guard:
    """Pure ASGI middleware (outermost): the body limit and the per-route metrics."""

    def __init__(self, app, settings: Settings, metrics: Metrics):
        self.app = app
        self.limit = settings.max_body_bytes
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = {"code": 500, "t": None}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                status["t"] = time.perf_counter()
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"server"]
                message = {**message, "headers": headers}
            await send(message)

        try:
            length = None
            for k, v in scope.get("headers", []):
                if k == b"content-length":
                    try:
                        length = int(v)
                    except ValueError:
                        length = -1
            if length is not None and (length < 0 or length > self.limit):
                resp = _json_error(413 if length > self.limit else 400,
                                   "too_large" if length > self.limit else "bad_request",
                                   f"the request body of {length} bytes is over the limit of {self.limit} bytes"
                                   if length > self.limit else "Content-Length is not a number",
                                   "body", {"Connection": "close"})
                await resp(scope, receive, send_wrapper)
                return
            seen = {"n": 0}
            limit = self.limit

            async def receive_wrapper():
                message = await receive()
                if message["type"] == "http.request":
                    seen["n"] += len(message.get("body", b""))
                    if seen["n"] > limit:
                        raise TooLarge(f"the request body is over the limit of {limit} bytes", "body")
                return message

            await self.app(scope, receive_wrapper, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            method = scope.get("method", "")
            self.metrics.requests.labels(path, method, str(status["code"])).inc()
            self.metrics.latency.labels(path, method).observe((status["t"] or time.perf_counter()) - t0)


def _install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        return JSONResponse(exc.body(), status_code=exc.status, headers=exc.headers)

    @app.exception_handler(StoreUnavailable)
    async def _store_down(request: Request, exc: StoreUnavailable):
        # the s3:// store stopped answering after start-up (logged by the store): not this request's fault, and
        # over once the bucket answers again
        retry = str(service_of(request).settings.retry_after_s)
        return _json_error(503, "store_unavailable", str(exc), None, {"Retry-After": retry})

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errs = exc.errors()
        first = errs[0] if errs else {}
        loc = [x for x in first.get("loc", ()) if x not in ("query", "path", "body", "header")]
        field_name = field_path(loc) or None
        msg = first.get("msg", "invalid request")
        return _json_error(422, "invalid", f"{field_name}: {msg}" if field_name else msg, field_name)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no route {request.url.path}"
        return _json_error(exc.status_code, _status_code_name(exc.status_code), detail, None,
                           dict(exc.headers or {}))

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect):
        # the client closed the connection while sending its body: nothing can be answered, and it is not a server
        # error (it was a 500 with a traceback, twice). 499 as nginx counts it ("client closed request").
        log.info("%s %s: the client disconnected before its request body ended", request.method, request.url.path)
        return Response(status_code=499)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return _json_error(500, "internal", "an unexpected error occurred; it was logged")


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application. Raises runtime.inference.ModelError at once when the model folder is missing or
    altered."""
    from . import __version__

    settings = settings or Settings()
    service = Service.create(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        await service.start()
        grpc_server = None
        try:
            if settings.grpc_port is not None:      # the SensorsimService beside the routes (docs/simulators.md)
                from .sensorsim import servicer

                grpc_server, app.state.grpc_port = await servicer.start(service)
            yield
        finally:
            if grpc_server is not None:
                await servicer.stop(grpc_server)
            await service.stop()

    # /openapi.json, /docs and /redoc are not behind the API keys (a browser sends no key): with keys set they are
    # off unless api_docs says otherwise
    docs = settings.docs_open()
    app = FastAPI(title="xyzcyl", version=__version__, lifespan=lifespan,
                  openapi_url="/openapi.json" if docs else None, docs_url="/docs" if docs else None,
                  redoc_url="/redoc" if docs else None,
                  summary="Feed-forward 3D Gaussian splatting of a surround-camera rig: post a rig, get Gaussians, "
                          "render views at any pose.",
                  description="docs/api.md in the repository: every endpoint with a curl example and the error "
                              "table. Every error answers `{\"error\": {\"code\", \"message\", \"field\"}}`.")
    app.state.service = service
    _install_handlers(app)
    app.include_router(health.router)
    app.include_router(scenes.router)
    app.include_router(render.router)
    app.include_router(viewer.router)
    viewer.mount_files(app, settings)          # the viewer page's files and its npm modules (server/viewer)
    if settings.cors_origins:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins), allow_methods=["*"],
                           allow_headers=["*"], expose_headers=["Location", "ETag", "Retry-After"])
    app.add_middleware(_Guard, settings=settings, metrics=service.metrics)
    return app


__all__ = ["API_VERSION", "create_app"]
