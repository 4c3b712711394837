"""The service's settings: one frozen pydantic-settings object, read from the environment (``XYZCYL_<FIELD>``, e.g.
``XYZCYL_STORE``, ``XYZCYL_API_KEYS``) and overridden by ``xyzcyl serve`` flags (``--store``, ``--api-keys``; every
field has its flag). docs/api.md has the table with defaults; this module is the source of truth."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict
from xyzcyl.runtime.camera import MAX_RENDER_PIXELS, MAX_SIZE

MiB = 1 << 20


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


CommaList = Annotated[tuple[str, ...], NoDecode]


class Settings(BaseSettings):
    """Every knob of ``create_app``; sizes in bytes or pixels, times in seconds."""

    model_config = SettingsConfigDict(env_prefix="XYZCYL_", frozen=True, extra="forbid")

    # what is served and where scenes live
    model: Path | None = Field(None, description="model folder (default: the shipped models/xyzcyl-cpu-v1)")
    store: str = Field("./xyzcyl-store", description="scene store: a folder (created if absent) or s3://bucket/prefix")
    host: str = Field("127.0.0.1", description="`xyzcyl serve`: address to listen on")
    port: int = Field(8000, ge=0, le=65535, description="`xyzcyl serve`: TCP port (0: a free one)")
    grpc_port: int | None = Field(None, ge=0, le=65535,
                                  description="`xyzcyl serve`: also answer AlpaSim's and CARLA NuRec's SensorsimService "
                                              "(gRPC, docs/simulators.md) on this TCP port of the same host, over the "
                                              "same scenes, renders, limits and API keys (0: a free one; default: "
                                              "off)")
    header_timeout_s: float = Field(10.0, gt=0, description="`xyzcyl serve`: close a connection that has not sent a "
                                                            "whole request head (line + headers) this long after "
                                                            "connecting or after its previous answer (slow clients)")

    # request limits (422/413 beyond them)
    max_body_bytes: int = Field(256 * MiB, ge=1024, description="largest request body; 413 beyond, before it is read")
    max_cameras: int = Field(16, ge=1, le=64, description="most cameras in one rig")
    max_drive_frames: int = Field(200, ge=1, le=10000, description="most frames (rigs) in one posted drive "
                                                                  "(docs/api.md \"Drives\")")
    max_image_pixels: int = Field(4096 * 4096, ge=1, description="most pixels of one uploaded image (from its header)")
    max_render_pixels: int = Field(MAX_RENDER_PIXELS, ge=1, le=MAX_RENDER_PIXELS,
                                   description="most pixels of one rendered view (at most the runtime's limit)")
    max_render_side: int = Field(MAX_SIZE, ge=1, le=MAX_SIZE,
                                 description="longest side of one rendered view (at most the runtime's limit)")
    max_batch_frames: int = Field(2000, ge=1, description="most frames in one POST .../render batch")
    wait_max_s: float = Field(120.0, ge=0, description="longest ?wait= a POST /v1/scenes may hold")

    # work and backpressure (503 + Retry-After when full)
    reconstruct_workers: int = Field(1, ge=1, le=16, description="reconstruction worker processes")
    reconstruct_queue: int = Field(4, ge=0, description="reconstructions waiting beyond the running ones")
    reconstruct_timeout_s: float = Field(300.0, gt=0, description="a reconstruction running longer fails (a "
                                                                   "drive's too: raise it for long drives)")
    render_threads: int = Field(default_factory=_cores, ge=1, le=256, description="renders at once (default: cores)")
    render_queue: int = Field(8, ge=0, description="renders waiting beyond the running ones")
    ort_threads: int | None = Field(None, ge=1, description="onnxruntime threads per worker (default: all cores)")
    compute_nice: int = Field(5, ge=0, le=19, description="renders and reconstructions run this much nicer (lower CPU "
                                                         "priority) than the request loop, so health checks and "
                                                         "503s answer at once under load (0: the same priority)")
    retry_after_s: int = Field(1, ge=1, description="Retry-After of a 503 when busy")
    warm_up: bool = Field(True, description="before /v2/health/ready answers 200, render a tiny scene in the server "
                                            "and reconstruct a tiny rig (LiDAR, detail layer) in each worker, so "
                                            "every numba kernel is compiled or loaded from its cache (false: the "
                                            "first requests pay for that)")
    scene_cache: int = Field(4, ge=1, description="loaded scenes kept in memory for rendering")
    render_cache_bytes: int = Field(64 * MiB, ge=0, description="encoded views kept in memory (repeat poses)")

    # store quota
    max_scenes: int = Field(100, ge=1, description="most scenes in the store (ready, queued and running)")
    max_store_bytes: int = Field(10 * 1024 * MiB, ge=1, description="most bytes of ready scenes in the store")
    when_full: Literal["evict", "reject"] = Field(
        "evict", description="store full: evict the least recently used ready scenes, or answer 507")
    scene_ttl_s: float | None = Field(None, gt=0, description="delete scenes not used for this long (off: None)")

    # security
    api_keys: CommaList = Field((), description="accepted API keys (comma-separated); empty: no authentication")
    cors_origins: CommaList = Field((), description="CORS allowed origins (comma-separated); empty: CORS off")
    api_docs: bool | None = Field(None, description="serve /openapi.json, /docs and /redoc (the API's description, "
                                                    "without a key) to anyone; default: only when no API keys are set "
                                                    "(with keys they answer 404)")
    viewer_modules: Path | None = Field(None, description="the web viewer's browser modules (three, @sparkjsdev/spark): "
                                                          "a node_modules folder (default: ./node_modules, else the "
                                                          "source checkout's; `npm ci` installs it; docs/viewer.md)")

    # scale-out: the s3:// store (server/store/s3.py, docs/deploy.md)
    s3_cache: Path | None = Field(None, description="s3:// store: local folder for downloaded scenes and work in "
                                                    "progress (default: a temporary folder, removed at exit)")
    s3_cache_bytes: int = Field(2 * 1024 * MiB, ge=0, description="s3:// store: most bytes of downloaded scenes "
                                                                  "kept in s3_cache (least recently used dropped)")
    replica_id: str | None = Field(None, min_length=1, description="s3:// store: this replica's name in the "
                                                                   "records it owns (default: hostname:pid)")

    @field_validator("api_keys", "cors_origins", mode="before")
    @classmethod
    def _split(cls, v):
        if isinstance(v, str):
            return tuple(s.strip() for s in v.split(",") if s.strip())
        return v

    @field_validator("api_keys")
    @classmethod
    def _keys(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        for k in v:
            if len(k) < 8:
                raise ValueError("each API key must have at least 8 characters")
        return v

    @model_validator(mode="after")
    def _ports(self) -> Settings:
        if self.grpc_port and self.grpc_port == self.port:
            raise ValueError(f"grpc_port: {self.grpc_port} is the HTTP port too; give the gRPC API a port of its own")
        return self

    def model_dir(self) -> Path:
        """The model folder: ``model`` or the shipped default (runtime.inference.default_model_dir)."""
        if self.model is not None:
            return Path(self.model)
        from xyzcyl.runtime.inference import default_model_dir

        return default_model_dir()

    def docs_open(self) -> bool:
        """Whether /openapi.json, /docs and /redoc are served: ``api_docs``, else only without API keys."""
        return (not self.api_keys) if self.api_docs is None else bool(self.api_docs)


__all__ = ["Settings"]
