"""The JSON bodies of the HTTP API (docs/api.md), defined once: the server answers with them (its routes' response
models, so also the OpenAPI document) and the client parses the answers with them.

The classes that appear in the OpenAPI document carry no docstring (it would become the schema's description);
their comments say what they are."""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Mapping
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    ValidationError,
    WithJsonSchema,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .errors import FieldError
from .poses import (
    CARLA_POSE,
    MOVE_FIELDS,
    MOVE_NAMES,
    STRUCT_TOL,
    CameraMove,
    MoveError,
    PoseError,
    is_real,
    pose_matrix,
)

SceneState = Literal["queued", "running", "ready", "failed"]
Output = Literal["rgb", "depth", "alpha"]          # what a rendered view holds (docs/api.md, GET /v1/scenes/{id}/render)
Format = Literal["png", "jpeg", "exr"]             # its encoding
OUTPUTS: tuple[str, ...] = get_args(Output)
FORMATS: tuple[str, ...] = get_args(Format)
LOCAL_OUTPUTS = (*OUTPUTS, "all")   # all: R G B A Z in one EXR (`xyzcyl render`'s .exr default; not on the wire)
MEDIA_TYPES = {"png": "image/png", "jpeg": "image/jpeg", "exr": "image/x-exr"}

# the detail layer's stride (POST /v1/scenes ?detail_stride=, `xyzcyl reconstruct --detail-stride`, the client):
# input pixels per detail Gaussian along each axis
DETAIL_STRIDE_MIN, DETAIL_STRIDE_MAX = 1, 16


def detail_stride_error(stride: Any, detail: bool = True, off: str = "detail=false") -> str | None:
    """Why a detail-layer request cannot be honoured (the message, without the field), or None: the stride, when
    given, an integer in DETAIL_STRIDE_MIN..DETAIL_STRIDE_MAX and only with the detail layer on (``off``: how the
    caller spells the layer off: the query's detail=false, the client's detail=False). The one statement of the
    rules: the route, the client, the CLI and runtime.detail.DetailOptions ask it."""
    if stride is None:
        return None
    if not detail:
        return f"cannot be combined with {off} (the detail layer is off)"
    if isinstance(stride, bool) or not isinstance(stride, numbers.Integral) \
            or not DETAIL_STRIDE_MIN <= stride <= DETAIL_STRIDE_MAX:
        return f"must be an integer in {DETAIL_STRIDE_MIN}..{DETAIL_STRIDE_MAX} (got {stride!r:.60})"
    return None

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


# ------------------------------------------------------------------------------------------- drives

# A recorded drive posted to POST /v1/scenes (docs/api.md "Drives"): a 'drive' part (the drive document, each
# frame's rig inline, the tracks inline) and each frame's files as parts named frames/<frame>/<name>
DRIVE_PART = "drive"
FRAME_PARTS = "frames/"
KEYFRAME_PARAMS = ("keyframe_spacing", "keyframe_gap")     # POST /v1/scenes' keyframe knobs (metres, seconds)


def frame_part(frame: int, name: str) -> str:
    """The multipart name of a drive frame's part: ``frames/<frame>/<name>``, ``name`` a camera, ``depth:<camera>``,
    ``ego_mask:<camera>`` or ``lidar`` (what a one-rig upload names the part)."""
    return f"{FRAME_PARTS}{int(frame)}/{name}"


def is_drive_document(doc: Any) -> bool:
    """Whether a JSON document is a drive ({"frames": [...]}), not a rig.json ({"cameras": [...]})."""
    return isinstance(doc, Mapping) and "frames" in doc and "cameras" not in doc


def is_drive_file(path: Any) -> bool:
    """Whether the file ``path`` is a drive file (is_drive_document; docs/inference.md "Drives"), not a rig.json;
    False when it cannot be read as JSON. `xyzcyl reconstruct` and the client tell a drive from a rig so."""
    try:
        with open(path, "rb") as f:
            return is_drive_document(json.loads(f.read()))
    except (OSError, ValueError):
        return False


def keyframe_error(value: Any) -> str | None:
    """Why a keyframe knob (keyframe_spacing metres, keyframe_gap seconds) cannot be used (the message, without
    the field), or None: a finite number > 0, as `xyzcyl reconstruct --keyframe-spacing/--keyframe-gap` take it."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < float("inf"):
        return f"must be a finite number > 0 (got {value!r:.60})"
    return None


# a scene posted as a recorded drive: its frames and the keyframes reconstructed (docs/api.md "Drives")
class DriveInfo(BaseModel):
    frames: int = Field(description="the drive's frames (rigs) as posted")
    keyframes: list[int] = Field(description="the frames reconstructed (indices into the frames)")
    keyframe_spacing: float = Field(description="metres: a keyframe each time the ego moved this far (the "
                                                "query's keyframe_spacing or the default)")
    keyframe_gap: float = Field(description="seconds: a keyframe at least this often (the query's keyframe_gap "
                                            "or the default)")
    timestamp_s: float = Field(description="the first frame's time, seconds on the rigs' clock (a render's "
                                           "default time)")
    duration_s: float = Field(description="seconds from the first frame to the last")
    tracks: int = Field(0, description="annotated objects posted with the drive")
    stationary_actors: bool = Field(False, description="its stationary tracks are actors too (POST "
                                                       "?stationary_actors=true)")


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
    counts: dict[str, int | float] | None = None    # integers, but for areas (ground_filled_m2: square metres)
    gaussians: int | None = None
    background: bool | None = None
    bbox: dict[str, list[float]] | None = None
    timings: dict[str, float] | None = None
    bytes: int | None = None
    drive: DriveInfo | None = None         # a recorded drive's frames and keyframes; null for one rig
    links: dict[str, str]

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> SceneInfo:
        """The scene of the server's JSON (a pydantic ValidationError when it is not one)."""
        return cls.model_validate(doc)

    @property
    def raw(self) -> dict[str, Any]:
        """The JSON it was read from (the keys that were there)."""
        return self.model_dump(mode="json", exclude_unset=True)

    @property
    def ready(self) -> bool:
        return self.state == "ready"

    @property
    def failed(self) -> bool:
        return self.state == "failed"

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]


# a page of GET /v1/scenes, newest first; next: the next page's path, null on the last page
# one actor of a drive's scene (GET /v1/scenes/{id}/actors; runtime.actors.Actors.listing)
class ActorInfo(BaseModel):
    id: str = Field(description="the id a view's actors edits name (a track's id; moved@<frame> for cells that "
                                "moved away without a track)")
    label: str = Field(description="the track's class (Car, Pedestrian, ...); \"moved\" for cells that moved "
                                   "away without a track")
    tracked: bool = Field(description="from the drive's tracks (false: found moving without one)")
    size: tuple[float, float, float] = Field(description="its box: length, width, height, metres")
    span_s: tuple[float, float] = Field(description="its first and last recorded time, seconds on the rigs' clock "
                                                    "(drawn half a frame interval beyond either end, unless edited)")
    copies: int = Field(description="keyframes whose Gaussians of it are kept (a view draws the one nearest its "
                                    "time)")
    gaussians: int = Field(description="its Gaussians over all copies")
    filled_m2: float = Field(0.0, description="the ground under it that no frame saw (it stood there), filled "
                                              "with the neighbouring road's colour, square metres")
    pose: tuple[float, ...] | None = Field(None, description=(
        "with ?time=: its box -> scene frame then (16 numbers, row-major 4x4, metres; null when it is not drawn "
        "then)"))


# GET /v1/scenes/{id}/actors: a drive scene's actors (an empty list for any other scene)
class ActorList(BaseModel):
    time: float | None = Field(None, description="the ?time= the poses are at (seconds on the rigs' clock)")
    actors: list[ActorInfo]


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
    output: Output
    format: Format
    frames: list[FrameInfo]



# ------------------------------------------------------------------------------------------- the render view

MAX_SIZE = 16384  # pixels: the largest width or height of any camera, input or render
# pixels of one rendered view (4096 x 4096, the service's limit since it began): a render holds ~40 bytes a pixel
# (colour, alpha, depth, the background and the raster's per-pixel state), ~0.7 GB at this cap; 16384 x 16384 (what
# the side limit alone allowed the CLI) died in numpy's allocator. check_render_size applies both, before anything
# is allocated.
MAX_RENDER_PIXELS = 4096 * 4096


def render_limit(max_side: int = MAX_SIZE, max_pixels: int = MAX_RENDER_PIXELS) -> str:
    """The render limit in words (every refusal of a too large view says it)."""
    return f"the render limit ({max_side} pixels a side, {max_pixels} pixels in all)"


POSE_TEXT_MAX = 1024      # characters of a pose given as text (the GET query's cam_to_ego)
LENS_TEXT_MAX = 4096      # characters of a lens given as JSON text (the GET query's distortion)
CAMERA_NAME_MAX = 256
_SIZE = f"pixels; at most {render_limit()}, or the server's lower max_render_side / max_render_pixels settings"


class ViewError(FieldError):
    """A render view that cannot be honoured. ``field``: the request field at fault as the user named it (a query
    parameter "fov", a JSON path "cameras[3].fov", a CLI flag "--fov", a protocol field "items[0].request.
    image_quality"); str(e) = "<field>: <message>"."""


def _query_text(v: Any) -> Any:
    """A query parameter's value as FastAPI hands it to a field typed as a list (every value of the name): one
    value is that value's text; several stay a list (a pose given as 16 repeated parameters)."""
    if isinstance(v, list) and len(v) == 1 and isinstance(v[0], str):
        return v[0]
    return v


def _pose16(v: Any) -> Any:
    """cam_to_ego's 16 numbers, row-major (common.poses.pose_matrix reads every form)."""
    v = _query_text(v)
    if v is None:
        return None
    if isinstance(v, str) and len(v) > POSE_TEXT_MAX:
        raise PydanticCustomError("pose", f"at most {POSE_TEXT_MAX} characters")
    try:
        return tuple(float(x) for x in pose_matrix(v, "cam_to_ego").ravel())
    except PoseError as e:
        raise PydanticCustomError("pose", e.message) from None


def _json_text(v: Any, kind: str, limit: int) -> Any:
    """A query parameter's JSON text (at most ``limit`` characters) parsed; anything else as given."""
    v = _query_text(v)
    if isinstance(v, str):
        if len(v) > limit:
            raise PydanticCustomError(kind, f"at most {limit} characters")
        try:
            return json.loads(v)
        except ValueError as e:
            raise PydanticCustomError(kind, f"not valid JSON ({e})") from None
    return v


def _lens(v: Any) -> Any:
    """A lens as rig.json writes one: OpenCV's coefficient list, or an object with a "model" (JSON text in a
    query). Its parameters are checked where the camera is made (runtime.lenses)."""
    v = _json_text(v, "lens", LENS_TEXT_MAX)
    if v is None:
        return None
    if not isinstance(v, (list, dict)):
        raise PydanticCustomError("lens", "a JSON list or object expected")
    if isinstance(v, list) and not all(is_real(x) for x in v):
        raise PydanticCustomError("lens", "OpenCV's coefficients must be numbers")
    if isinstance(v, dict) and not all(isinstance(x, str) or is_real(x) or (isinstance(x, list)
                                                                          and all(map(is_real, x)))
                                       for x in v.values()):
        raise PydanticCustomError("lens", "a lens's parameters are numbers, lists of numbers or names")
    return v


def _not_bool(v: Any) -> Any:
    if isinstance(v, bool):         # pydantic's lax int takes True for 1
        raise PydanticCustomError("pixels", f"must be an integer in 1..{MAX_SIZE} (got {v!r})")
    return v


Pose16 = Annotated[tuple[float, ...], Field(min_length=16, max_length=16), BeforeValidator(_pose16)]
Pixels = Annotated[int, Field(ge=1), BeforeValidator(_not_bool)]
# in a query, JSON text (the schema says so); in a JSON body, the list or object itself
LensJSON = Annotated[list[float] | dict[str, str | float | list[float]], BeforeValidator(_lens),
                     WithJsonSchema({"type": "string", "contentMediaType": "application/json",
                                     "maxLength": LENS_TEXT_MAX})]
ACTOR_ID_MAX = 256          # characters of an actor's id
ACTOR_EDITS_MAX = 256       # actor edits in one view
ACTORS_TEXT_MAX = 65536     # characters of a view's actor edits given as JSON text (the GET query's actors)


def _actors_json(v: Any) -> Any:
    """A view's actor edits: a JSON list of objects (JSON text in a query)."""
    v = _json_text(v, "actors", ACTORS_TEXT_MAX)
    if v is not None and not isinstance(v, (list, tuple)):
        raise PydanticCustomError("actors", 'a JSON list of edits expected ([{"id": ..., "pose" | "offset" | '
                                            '"hide": ...}, ...])')
    return v


def _finite3(v: Any) -> Any:
    if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(is_real(x) and math.isfinite(x) for x in v)):
        raise PydanticCustomError("offset", f"3 finite numbers expected (forward, left, up metres; got {v!r:.60})")
    return v


# one edit of a drive scene's actors for one view (ViewQuery.actors; docs/api.md "Actors"): the actor ``id`` (GET
# /v1/scenes/{id}/actors) drawn at ``pose`` (its box -> the scene's frame) or ``offset`` from where it is at the
# view's time, or hidden; with ``insert``, a copy of it is drawn under that new id and the actor itself stays.
# runtime.actors checks the ids, the poses and how far they are against the scene.
class ActorEdit(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(min_length=1, max_length=ACTOR_ID_MAX, description="an actor of the scene")
    pose: Pose16 | None = Field(None, description=(
        "the actor's box -> the scene's frame (x along its length, y to its left, z up, origin at the box's "
        "centre; the scene's frame is its first frame's ego frame, as cam_to_ego's): 16 numbers, row-major 4x4, "
        "metres; drawn there at any time"))
    offset: Annotated[tuple[float, float, float], BeforeValidator(_finite3)] | None = Field(None, description=(
        "metres along the actor's own axes (forward, left, up) from where it is at the view's time (its recorded "
        "pose then)"))
    hide: StrictBool = Field(False, description="true: the actor is not drawn")
    insert: str | None = Field(None, min_length=1, max_length=ACTOR_ID_MAX, description=(
        "draw a copy of the actor (its Gaussians) under this new id, at pose or offset; the actor itself stays"))

    @model_validator(mode="after")
    def _one_edit(self) -> ActorEdit:
        given = [k for k, on in (("pose", self.pose is not None), ("offset", self.offset is not None),
                                 ("hide", self.hide)) if on]
        if len(given) != 1:
            raise PydanticCustomError("actor", "give exactly one of pose, offset and hide (true); got "
                                               f"{' and '.join(given) or 'none'}")
        if self.insert is not None and self.hide:
            raise PydanticCustomError("actor", "insert places a copy: give it a pose or an offset, not hide")
        return self

    def wire(self) -> dict[str, Any]:
        """The edit as JSON (the fields that are set; the pose as 16 numbers)."""
        return self.model_dump(exclude_none=True, exclude_defaults=True) | {"id": self.id}


ActorEdits = Annotated[tuple[ActorEdit, ...], Field(max_length=ACTOR_EDITS_MAX), BeforeValidator(_actors_json),
                       WithJsonSchema({"type": "string", "contentMediaType": "application/json",
                                       "maxLength": ACTORS_TEXT_MAX})]


def field_path(loc: Any) -> str:
    """A pydantic error's location as a field path: ("actors", 2, "pose") -> "actors[2].pose" (every front end's
    errors name nested fields so)."""
    out = ""
    for x in loc:
        out += f"[{x}]" if isinstance(x, int) else (f".{x}" if out else str(x))
    return out


def actor_edits(value: Any, field: str = "actors") -> tuple[ActorEdit, ...]:
    """A view's actor edits from JSON text, a list of objects, or a path to a .json file holding the list (the
    CLI's --actors): ViewError naming ``field`` (and the edit's path: "--actors[1].pose") otherwise."""
    from pathlib import Path

    from pydantic import TypeAdapter

    if isinstance(value, str) and not value.lstrip().startswith("[") and value.endswith(".json"):
        try:
            value = Path(value).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise ViewError(field, f"cannot read {value!r} ({e})") from None
    try:
        return TypeAdapter(ActorEdits).validate_python(value)
    except ValidationError as e:
        first = e.errors()[0]
        raise ViewError(field_path((field, *first["loc"])), first["msg"]) from None


_MOVE = {f.name: f for f in MOVE_FIELDS}
_WITH_POSE = "with camera or cam_to_ego"


# one rendered view as a user states it (GET /v1/scenes/{id}/render's query, an item of POST .../render, the client,
# `xyzcyl render` and `xyzcyl client render`): exactly one pose -- an input camera (camera), an OpenCV pose
# (cam_to_ego with fx/fy/cx/cy or fov), a CARLA transform (x, y, z, pitch, yaw, roll with fov) -- an optional
# camera move (forward, left, up, yaw) of the first two, the size, the output and its encoding. runtime.views.resolve
# makes the render camera of it. yaw is two fields in one name: with camera or cam_to_ego the move's turn (degrees
# to the left), otherwise the CARLA rotation's yaw (degrees, CARLA's: turning right); carla() and move() split it.
class ViewQuery(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    camera: str | None = Field(None, max_length=CAMERA_NAME_MAX, description=(
        "an input camera of the scene's rig (its pose, K and lens; with distortion: that lens instead; moved by "
        "forward, left, up, yaw)"))
    cam_to_ego: Pose16 | None = Field(None, description=(
        "the camera's pose: 16 numbers, row-major 4x4, OpenCV camera -> ego, metres; in a query one "
        "comma-separated value (or 16 repeated values)"))
    fx: float | None = Field(None, gt=0, allow_inf_nan=False, description="focal length, pixels")
    fy: float | None = Field(None, gt=0, allow_inf_nan=False, description="focal length, pixels (default fx)")
    cx: float | None = Field(None, allow_inf_nan=False, description="principal point, pixels (default the centre)")
    cy: float | None = Field(None, allow_inf_nan=False, description="principal point, pixels (default the centre)")
    fov: float | None = Field(None, gt=0, lt=180, description="horizontal field of view, degrees")
    distortion: LensJSON | None = Field(None, description=(
        "the camera's lens as rig.json writes it: an OpenCV coefficient list, or {\"model\": \"opencv\" | "
        "\"opencv_fisheye\" | \"ftheta\", ...} (docs/conventions.md, Lens models); JSON text in a query; with "
        "cam_to_ego, or with camera: that camera's pose and K through this lens"))
    x: float | None = Field(None, allow_inf_nan=False, description="CARLA location, metres (vehicle frame)")
    y: float | None = Field(None, allow_inf_nan=False, description="CARLA location, metres")
    z: float | None = Field(None, allow_inf_nan=False, description="CARLA location, metres")
    pitch: float | None = Field(None, allow_inf_nan=False, description="CARLA rotation, degrees")
    yaw: float | None = Field(None, allow_inf_nan=False, description=(
        f"{_WITH_POSE}: the {_MOVE['yaw'].describe()}; otherwise the CARLA rotation's yaw, degrees (CARLA's "
        "axes: turning right)"))
    roll: float | None = Field(None, allow_inf_nan=False, description="CARLA rotation, degrees")
    forward: float | None = Field(None, description=f"{_MOVE['forward'].describe()}; {_WITH_POSE}")
    left: float | None = Field(None, description=f"{_MOVE['left'].describe()}; {_WITH_POSE}")
    up: float | None = Field(None, description=f"{_MOVE['up'].describe()}; {_WITH_POSE}")
    width: Pixels | None = Field(None, description=_SIZE)
    height: Pixels | None = Field(None, description=_SIZE)
    output: Output = "rgb"
    format: Format = "png"
    quality: int = Field(90, ge=1, le=100, description="JPEG quality")
    time: float | None = Field(None, allow_inf_nan=False, description=(
        "seconds on the rigs' clock: a drive's scene draws its moving objects where they were then (default: its "
        "first frame); a one-rig scene is the same at every time"))
    actors: ActorEdits | None = Field(None, description=(
        "a drive scene's actors edited for this view: a JSON list of {\"id\", and one of \"pose\" (16 numbers, "
        "box -> scene), \"offset\" ([forward, left, up] metres from its recorded pose), \"hide\": true; "
        "\"insert\": a new id draws a copy} (JSON text in a query; docs/api.md \"Actors\")"))

    def _yaw_is_the_moves(self) -> bool:
        return self.camera is not None or self.cam_to_ego is not None

    def carla(self) -> dict[str, float]:
        """The CARLA transform's values that were given, in CARLA_POSE's order (yaw only without camera and
        cam_to_ego)."""
        skip = ("yaw",) if self._yaw_is_the_moves() else ()
        return {k: getattr(self, k) for k in CARLA_POSE if k not in skip and getattr(self, k) is not None}

    def move_values(self) -> dict[str, float]:
        """The camera move's values that were given, by MOVE_NAMES (yaw only with camera or cam_to_ego)."""
        skip = () if self._yaw_is_the_moves() else ("yaw",)
        return {k: getattr(self, k) for k in MOVE_NAMES if k not in skip and getattr(self, k) is not None}

    def params(self) -> dict[str, str]:
        """The GET query parameters of this view (the fields that are set; numbers written exactly, the pose as one
        comma-separated value, the lens as compact JSON); output, format and quality only when not the defaults."""
        out: dict[str, str] = {}
        for name, v in self:
            if v is None or (name in _DEFAULTS and v == _DEFAULTS[name]):
                continue
            if name == "cam_to_ego":
                out[name] = ",".join(repr(float(x)) for x in v)
            elif name == "distortion":
                out[name] = json.dumps(v, separators=(",", ":"))
            elif name == "actors":
                out[name] = json.dumps([e.wire() for e in v], separators=(",", ":"))
            elif isinstance(v, float):
                out[name] = repr(v)
            else:
                out[name] = str(v)
        return out

    @classmethod
    def from_item(cls, item: Any, where: str) -> tuple[ViewQuery, dict[str, str]]:
        """The query of one item of a batch (POST /v1/scenes/{id}/render's "cameras") and the JSON path of each
        field it came from (for errors: {"fov": "cameras[2].fov", "x": "cameras[0].transform.location.x"}).
        ``where``: the item's path ("cameras[2]"). ViewError naming the path."""
        if not isinstance(item, Mapping):
            raise ViewError(where, f"must be an object: {ITEM_KINDS}")
        move = {k: item[k] for k in MOVE_NAMES if k in item}
        names = {k: f"{where}.{k}" for k in ("camera", "cam_to_ego", "width", "height", "fov", "distortion",
                                            *MOVE_NAMES)}
        if "camera" in item:
            _only(item, _RIG_KEYS, where, "an input camera")
            flat = {k: item[k] for k in ("camera", "width", "height", "distortion") if k in item}
        elif "transform" in item:   # a CARLA sensor; its other blueprint attributes (sensor_tick, ...) are ignored
            tf = item["transform"]
            if not isinstance(tf, Mapping):
                raise ViewError(f"{where}.transform", 'must be {"location": {x, y, z}, "rotation": {pitch, yaw, '
                                                      'roll}}')
            parts = {"location": ("x", "y", "z"), "rotation": ("pitch", "yaw", "roll")}
            flat = {}
            for key, keys in parts.items():
                sub = _get(tf, key, f"{where}.transform")
                if not isinstance(sub, Mapping):
                    raise ViewError(f"{where}.transform.{key}", f"must be an object {{{', '.join(keys)}}}")
                for k in keys:
                    flat[k] = _get(sub, k, f"{where}.transform.{key}")
                    names[k] = f"{where}.transform.{key}.{k}"
            flat.update(fov=_get(item, "fov", where), width=_get(item, "image_size_x", where),
                        height=_get(item, "image_size_y", where))
            names.update(width=f"{where}.image_size_x", height=f"{where}.image_size_y")
            if move:
                raise ViewError(f"{where}.{next(iter(move))}", "a CARLA pose takes no camera move: change its x, "
                                                              "y, z and yaw (moves go with camera or cam_to_ego)")
        elif "K" in item:
            _only(item, _OPENCV_K_KEYS, where, "an OpenCV camera with K")
            flat = {"cam_to_ego": _get(item, "cam_to_ego", where), **_intrinsics(item["K"], f"{where}.K"),
                    "width": _get(item, "width", where), "height": _get(item, "height", where)}
            names.update(dict.fromkeys(("fx", "fy", "cx", "cy"), f"{where}.K"))
        elif "fov" in item:
            _only(item, _OPENCV_FOV_KEYS, where, "an OpenCV camera with fov")
            flat = {"cam_to_ego": _get(item, "cam_to_ego", where), "fov": item["fov"],
                    "width": _get(item, "width", where), "height": _get(item, "height", where)}
        else:
            raise ViewError(where, f"expected one of {ITEM_KINDS}")
        if "distortion" in item and "transform" not in item:
            flat["distortion"] = item["distortion"]
        flat.update(move)
        for k in ("time", "actors"):    # any kind of item (a CARLA sensor's too)
            if k in item:
                flat[k] = item[k]
                names[k] = f"{where}.{k}"
        for k, v in flat.items():      # JSON's true and "70" are not numbers (pydantic's lax mode would take them)
            if k not in ("camera", "cam_to_ego", "distortion", "actors") and (isinstance(v, (bool, str))):
                what = f"an integer in 1..{MAX_SIZE}" if k in ("width", "height") else "a finite number"
                raise ViewError(names[k], f"must be {what} (got {v!r:.60})")
        return validated(flat, names), names


_DEFAULTS = {"output": "rgb", "format": "png", "quality": 90}
ITEM_KINDS = ('{"K", "cam_to_ego", "width", "height"[, "distortion"]} (OpenCV), {"fov", "cam_to_ego", "width", '
              '"height"} (OpenCV, horizontal degrees), {"transform", "fov", "image_size_x", "image_size_y"} (CARLA '
              'sensor) or {"camera"[, "width", "height", "distortion"]} (an input camera of the scene); the OpenCV '
              'and input-camera items also take a move: "forward", "left", "up" (metres), "yaw" (degrees to the '
              'left)')
_OPENCV_K_KEYS = ("K", "cam_to_ego", "width", "height", "distortion", "name", *MOVE_NAMES, "time", "actors")
_OPENCV_FOV_KEYS = ("fov", "cam_to_ego", "width", "height", "distortion", "name", *MOVE_NAMES, "time", "actors")
_RIG_KEYS = ("camera", "width", "height", "distortion", "name", *MOVE_NAMES, "time", "actors")


def validated(values: Mapping[str, Any], names: Mapping[str, str] | None = None) -> ViewQuery:
    """ViewQuery(**values), its first refusal as a ViewError naming the field by ``names`` (a JSON path, a flag;
    default: the field's own name)."""
    try:
        return ViewQuery(**values)
    except ValidationError as e:
        first = e.errors()[0]
        loc = first["loc"]
        key = str(loc[0]) if loc else "query"
        # a nested field's path: ("actors", 2, "pose") -> "actors[2].pose" (its root named by ``names``)
        raise ViewError(field_path(((names or {}).get(key, key), *loc[1:])), first["msg"]) from None


def _get(item: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in item:
        raise ViewError(f"{where}.{key}" if where else key, "is missing")
    return item[key]


def _only(item: Mapping[str, Any], allowed: tuple[str, ...], where: str, kind: str) -> None:
    for key in item:
        if key not in allowed:
            raise ViewError(f"{where}.{key}", f"unknown field ({kind} takes {', '.join(allowed)})")


def _intrinsics(K: Any, field: str) -> dict[str, float]:
    """fx, fy, cx, cy of a pinhole K: 9 numbers row-major or [3, 3], no skew."""
    flat = K if isinstance(K, (list, tuple)) and len(K) == 9 else None
    if isinstance(K, (list, tuple)) and len(K) == 3 and all(isinstance(r, (list, tuple)) and len(r) == 3 for r in K):
        flat = [x for r in K for x in r]
    if flat is None or not all(is_real(x) for x in flat):
        raise ViewError(field, f"must be 9 numbers (row-major) or a [3, 3] array (got {K!r:.60})")
    k = [float(x) for x in flat]
    if any(abs(k[i] - want) > STRUCT_TOL for i, want in ((1, 0.0), (3, 0.0), (6, 0.0), (7, 0.0), (8, 1.0))):
        raise ViewError(field, "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    return {"fx": k[0], "fy": k[4], "cx": k[2], "cy": k[5]}


def move_of(query: ViewQuery, names: Mapping[str, str] | None = None) -> CameraMove:
    """The query's camera move (checked by CameraMove: bounds, finite); ViewError naming the field by ``names``."""
    try:
        return CameraMove.from_values(query.move_values())
    except MoveError as e:
        raise ViewError((names or {}).get(e.field, e.field), e.message) from None

__all__ = ["ACTOR_EDITS_MAX", "ActorEdit", "ActorEdits", "ActorInfo", "ActorList", "actor_edits", "field_path", "LOCAL_OUTPUTS", "MAX_RENDER_PIXELS", "MAX_SIZE", "render_limit", "DETAIL_STRIDE_MAX", "DETAIL_STRIDE_MIN", "FORMATS", "ITEM_KINDS", "MEDIA_TYPES",
           "OUTPUTS", "Format", "LensJSON", "Output", "Pose16", "ViewError", "ViewQuery", "detail_stride_error",
           "move_of", "validated", "STATES", "BatchIndex", "CameraInfo", "DetailInfo", "DRIVE_PART", "DriveInfo",
           "ErrorBody", "FRAME_PARTS", "KEYFRAME_PARAMS", "frame_part", "is_drive_document", "is_drive_file", "keyframe_error",
           "ErrorDetail", "FrameInfo",
           "ModelReadiness", "Readiness", "SceneInfo", "SceneList", "SceneState", "error_body", "failure_answer"]
