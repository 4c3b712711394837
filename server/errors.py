"""One error hierarchy that carries its HTTP status, and the one error body every answer uses:

    {"error": {"code": "invalid", "message": "camera 'CAM_FRONT': K: fx must be > 0", "field": "rig"}}

Endpoints raise ApiError subclasses; app.py turns them (and FastAPI's own validation errors, unknown routes and
wrong methods) into that body (xyzcyl.common.wire.ErrorBody, which the client parses). docs/api.md has the table
of codes."""

from __future__ import annotations

from typing import Any

from xyzcyl.common.wire import error_body, failure_answer


class ApiError(Exception):
    status = 500
    code = "internal"

    def __init__(self, message: str, field: str | None = None, headers: dict[str, str] | None = None,
                 code: str | None = None, status: int | None = None):
        super().__init__(message)
        self.message = message
        self.field = field
        self.headers = dict(headers or {})
        if code is not None:
            self.code = code
        if status is not None:
            self.status = status

    def body(self) -> dict[str, Any]:
        return error_body(self.code, self.message, self.field)


class Unauthorized(ApiError):
    status, code = 401, "unauthorized"

    def __init__(self, message: str = "a valid API key is required (Authorization: Bearer KEY or X-API-Key: KEY)"):
        super().__init__(message, None, {"WWW-Authenticate": "Bearer"})


class NotFound(ApiError):
    status, code = 404, "not_found"


class Conflict(ApiError):
    status, code = 409, "not_ready"


class TooLarge(ApiError):
    status, code = 413, "too_large"


class UnsupportedMedia(ApiError):
    status, code = 415, "unsupported_media_type"


class Invalid(ApiError):
    status, code = 422, "invalid"


class Busy(ApiError):
    status, code = 503, "busy"

    def __init__(self, message: str, retry_after: int):
        super().__init__(message, None, {"Retry-After": str(int(retry_after))})


class StorageFull(ApiError):
    status, code = 507, "storage_full"


def scene_failure(sid: str, code: str, message: str, headers: dict[str, str] | None = None) -> ApiError:
    """What POST /v1/scenes?wait= answers for a scene that failed with ``code`` (wire.failure_answer: the status
    and field the client maps back)."""
    status, field = failure_answer(code)
    return ApiError(f"scene {sid}: {message}", field, headers, code=code, status=status)


__all__ = ["ApiError", "Busy", "Conflict", "Invalid", "NotFound", "StorageFull", "TooLarge",
           "Unauthorized", "UnsupportedMedia", "error_body", "scene_failure"]
