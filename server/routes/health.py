"""Open Inference Protocol paths (health, server and model metadata) and Prometheus metrics. None of these need
an API key, and none wait for a queue: they answer while the service is busy."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from xyzcyl.common.wire import ModelReadiness, Readiness

from ..deps import service_of
from ..schemas import NO_MODEL

router = APIRouter(tags=["health and metadata"])


@router.get("/v2/health/live", summary="the process answers")
async def live() -> dict:
    return {"live": True}


@router.get("/v2/health/ready", summary="the model is loaded and scenes can be posted", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "still loading, draining, the workers failed to "
                                                                 "start, or the scene store cannot be reached"}})
async def ready(request: Request):
    reason = await service_of(request).not_ready()
    if reason is None:
        return {"ready": True}
    return JSONResponse({"ready": False, "reason": reason}, status_code=503, headers={"Retry-After": "1"})


@router.get("/v2", summary="server metadata (Open Inference Protocol)")
async def server_metadata(request: Request) -> dict:
    from .. import __version__

    return {"name": "xyzcyl", "version": __version__, "extensions": []}


@router.get("/v2/models/{name}", summary="model metadata (Open Inference Protocol)", responses=NO_MODEL)
async def model_metadata(request: Request, name: str) -> dict:
    return service_of(request).model_metadata(name)


@router.get("/v2/models/{name}/ready", summary="model readiness (Open Inference Protocol)",
            response_model=ModelReadiness, responses={**NO_MODEL, 503: {"model": ModelReadiness}})
async def model_ready(request: Request, name: str):
    s = service_of(request)
    s.model_metadata(name)
    ok = await s.not_ready() is None
    return JSONResponse({"name": name, "ready": ok}, status_code=200 if ok else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    from prometheus_client import CONTENT_TYPE_LATEST

    return Response(service_of(request).metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
