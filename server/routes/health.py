"""Open Inference Protocol paths (health, server and model metadata) and Prometheus metrics. None of these need
an API key, and none wait for a queue: they answer while the service is busy."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel

from ..app import service_of
from ..errors import NotFound
from .scenes import ErrorBody

router = APIRouter(tags=["health and metadata"])



class Readiness(BaseModel):
    ready: bool
    reason: str | None = None


class ModelReadiness(BaseModel):
    name: str
    ready: bool


_NOT_FOUND = {404: {"model": ErrorBody, "description": "no such model"}}

_DTYPES = {"float32": "FP32", "float16": "FP16", "int64": "INT64", "int32": "INT32", "uint8": "UINT8",
           "bool": "BOOL"}


@router.get("/v2/health/live", summary="the process answers")
async def live() -> dict:
    return {"live": True}


async def not_ready(s) -> str | None:
    """Why the service cannot take work now (None: it can): draining, loading (or its start-up error), or a store
    that cannot be reached (an s3:// store probes its bucket, at most every 2 s)."""
    if s.draining:
        return "draining"
    if not s.ready:
        return s.startup_error or "loading the model"
    return await asyncio.to_thread(s.store.health)


@router.get("/v2/health/ready", summary="the model is loaded and scenes can be posted", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "still loading, draining, the workers failed to "
                                                                 "start, or the scene store cannot be reached"}})
async def ready(request: Request):
    reason = await not_ready(service_of(request))
    if reason is None:
        return {"ready": True}
    return JSONResponse({"ready": False, "reason": reason}, status_code=503, headers={"Retry-After": "1"})


@router.get("/v2", summary="server metadata (Open Inference Protocol)")
async def server_metadata(request: Request) -> dict:
    from .. import __version__

    return {"name": "xyzcyl", "version": __version__, "extensions": []}


def _tensors(entries) -> list[dict]:
    out = []
    for e in entries:
        shape = [d if isinstance(d, int) else -1 for d in e.get("shape", [])]
        out.append({"name": e["name"], "datatype": _DTYPES.get(str(e.get("dtype")), str(e.get("dtype")).upper()),
                    "shape": shape})
    return out


def _model_metadata(request: Request, name: str) -> dict:
    s = service_of(request)
    info = s.info
    if name != info.name:
        raise NotFound(f"no model {name!r}; this server serves {info.name!r}", "name")
    graphs = info.meta.get("graphs", {})
    enc = graphs.get("encode", {})
    return {"name": info.name, "versions": [info.version], "platform": "onnxruntime_onnx",
            "inputs": _tensors(enc.get("inputs", [])), "outputs": _tensors(enc.get("outputs", [])),
            "parameters": {"graphs": sorted(graphs), "input": info.meta.get("input"),
                           "counts": info.meta.get("counts")}}


@router.get("/v2/models/{name}", summary="model metadata (Open Inference Protocol)", responses=_NOT_FOUND)
async def model_metadata(request: Request, name: str) -> dict:
    return _model_metadata(request, name)


@router.get("/v2/models/{name}/ready", summary="model readiness (Open Inference Protocol)",
            response_model=ModelReadiness, responses={**_NOT_FOUND, 503: {"model": ModelReadiness}})
async def model_ready(request: Request, name: str):
    _model_metadata(request, name)
    ok = await not_ready(service_of(request)) is None
    return JSONResponse({"name": name, "ready": ok}, status_code=200 if ok else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    from prometheus_client import CONTENT_TYPE_LATEST

    return Response(service_of(request).metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
