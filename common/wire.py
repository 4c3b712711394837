"""The JSON bodies of the HTTP API (docs/api.md), defined once: the server answers with them (its routes' response
models, so also the OpenAPI document) and the client parses the answers with them.

The classes that appear in the OpenAPI document carry no docstring (it would become the schema's description);
their comments say what they are."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

SceneState = Literal["queued", "running", "ready", "failed"]
STATES: tuple[SceneState, ...] = ("queued", "running", "ready", "failed")


# every error answer: {"error": {"code", "message", "field"}}; field names the request field at fault, or is null
class ErrorDetail(BaseModel):
    code: str
    message: str
    field: str | None = None


class ErrorBody(BaseModel):
    error: ErrorDetail


def error_body(code: str, message: str, field: str | None = None) -> dict[str, Any]:
    """The JSON of an error answer."""
    return ErrorBody(error=ErrorDetail(code=code, message=message, field=field)).model_dump()


def failure_answer(code: str) -> tuple[int, str | None]:
    """(status, field) of the error that POST /v1/scenes?wait= answers for a scene failed with ``code`` (and that
    the client raises for it after polling): invalid_input 422 naming the rig, storage_full 507, else 500."""
    status = {"invalid_input": 422, "storage_full": 507}.get(code, 500)
    return status, "rig" if status == 422 else None


# an input camera of a scene's rig
class CameraInfo(BaseModel):
    name: str
    width: int
    height: int
    model: str


# the detail layer a scene was posted with (POST /v1/scenes ?detail=, ?detail_stride=)
class DetailInfo(BaseModel):
    enabled: bool = Field(description="whether the detail layer was asked for (POST ?detail=)")
    stride: int | None = Field(None, description="input pixels per detail Gaussian along each axis (null when off)")


# a scene as POST /v1/scenes, GET /v1/scenes/{id} and the list answer it
class SceneInfo(BaseModel):
    id: str = Field(examples=["q3R1x9Z2bC7dE5fG8hJ0kA"])
    name: str | None = Field(None, examples=["clipgt-026d6a39-bd8f-4175-bc61-fe50ed0403a3"])
    state: SceneState
    created: str
    updated: str
    error: ErrorDetail | None = None
    cameras: list[CameraInfo]
    detail: DetailInfo | None = None
    model: dict[str, Any] | None = None
    counts: dict[str, int] | None = None
    gaussians: int | None = None
    background: bool | None = None
    bbox: dict[str, list[float]] | None = None
    timings: dict[str, float] | None = None
    bytes: int | None = None
    links: dict[str, str]


# a page of GET /v1/scenes, newest first; next: the next page's path, null on the last page
class SceneList(BaseModel):
    scenes: list[SceneInfo]
    total: int
    offset: int
    limit: int
    next: str | None = None


# GET /v2/health/ready
class Readiness(BaseModel):
    ready: bool
    reason: str | None = None


# GET /v2/models/{name}/ready
class ModelReadiness(BaseModel):
    name: str
    ready: bool


class FrameInfo(BaseModel):
    """One frame of a batch render: its file in the zip, its size, and its camera (K: 3x3 pixels, null for a
    camera without one, e.g. an equirectangular one; cam_to_ego: 4x4, OpenCV camera axes)."""

    file: str
    width: int
    height: int
    K: list[list[float]] | None
    cam_to_ego: list[list[float]]


class BatchIndex(BaseModel):
    """index.json, the last file of a batch render's zip (POST /v1/scenes/{id}/render)."""

    scene: str
    output: Literal["rgb", "depth", "alpha"]
    format: Literal["png", "jpeg", "exr"]
    frames: list[FrameInfo]


__all__ = ["STATES", "BatchIndex", "CameraInfo", "DetailInfo", "ErrorBody", "ErrorDetail", "FrameInfo",
           "ModelReadiness", "Readiness", "SceneInfo", "SceneList", "SceneState", "error_body", "failure_answer"]
