"""GET /v1/scenes/{id}/viewer: the web viewer's page of a ready scene (server/viewer/, docs/viewer.md). Same API-key
rule as every /v1 route. A browser that opened it sees an error as a page (the API's error body, as HTML, with the
API's status), never a blank canvas; a client that asks for JSON gets the usual error body."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse
from xyzcyl.common.wire import CAMERA_NAME_MAX, Pixels

from ..deps import known_query, require_key, service_of
from ..errors import ApiError
from ..schemas import ERRORS

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["viewer"], dependencies=[Depends(require_key), Depends(known_query)])


def _answer_error(request: Request, err: ApiError):
    if "text/html" in request.headers.get("accept", ""):
        from ..viewer import error_page

        return HTMLResponse(error_page(err.status, err.body()), status_code=err.status, headers=err.headers)
    return JSONResponse(err.body(), status_code=err.status, headers=err.headers)


# the errors: the error body (application/json: response_class would declare the model as text/html), or the same as
# a page for a request that accepts text/html (a browser)
_ERRORS = {status: {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}},
                                "text/html": {"schema": {"type": "string"}}}} for status in ERRORS}


@router.get("/scenes/{scene_id}/viewer", response_class=HTMLResponse, summary="the web viewer of a scene (an HTML "
            "page: Spark + three.js, served by this server)",
            responses={200: {"content": {"text/html": {}}, "description": "the viewer page"}, **_ERRORS})
async def viewer(request: Request, scene_id: str,
                 camera: str | None = Query(None, max_length=CAMERA_NAME_MAX, description=(
                     "the input camera the page opens at (default: the rig's first)")),
                 width: Pixels | None = Query(None, description=(
                     "draw the view at exactly this many pixels wide (default: fit the window); with height, or the "
                     "camera's aspect ratio")),
                 height: Pixels | None = Query(None, description="pixels high (see width)")):
    try:
        return HTMLResponse(await service_of(request).viewer_page(
            scene_id, camera, width, height, base=request.scope.get("root_path", "")),
            headers={"Cache-Control": "no-store"})
    except ApiError as err:
        return _answer_error(request, err)


def mount_files(app, settings) -> None:
    """The page's own files (/viewer/web/) and the npm modules it imports (/viewer/modules/): server/viewer.install."""
    from ..viewer import install

    install(app, settings)


__all__ = ["mount_files", "router"]
