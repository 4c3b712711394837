"""View flags shared by `xyzcyl render` and `xyzcyl client render`: one definition of the flags and of their
arithmetic, so both commands read a pose, move a camera and pick a file's encoding the same way.

- a 4x4 matrix flag (``--cam-to-world``) takes 16 numbers in any float notation (``-1e-05`` too; the dispatcher's
  parser accepts negative numbers in scientific notation, common/command.py), or one value: a JSON list (flat 16 or
  4x4; numpy's printed form, brackets without commas, too), or a file: ``.npy`` (16 or 4x4 numbers) or
  ``.json`` / text (a list as above, or an object with ``cam_to_ego`` or ``cam_to_world``) -- parse_matrix;
- the camera moves ``--forward M``, ``--left M``, ``--up M`` (metres along ego x, y, z: x forward, y left, z up)
  and ``--yaw DEG`` (turn left, counter-clockwise seen from above, about the vertical through the camera's
  centre; applied before the shift) -- add_move_arguments, move_from_args, CameraMove.apply (a 4x4 pose) and
  CameraMove.apply_carla (a CARLA transform; the same move in CARLA's left-handed axes). CameraMove is the one
  definition of the move fields (names, units, bounds: MOVE_FIELDS) for every front end: the two commands' flags,
  the HTTP query and batch items, the Python client; runtime.views.move_camera applies it;
- the output file's encoding: ``--out FILE`` and ``--format png|jpeg|exr`` -- add_format_argument, out_format.

- CARLA_POSE: the names of a CARLA transform's six numbers, as the render endpoint's query and the client take
  them.

Light on purpose: argparse, json, math and pathlib at import, numpy inside the functions, nothing of xyzcyl but
common.errors, so the HTTP client (clients/commands/client.py) uses it without the runtime (the renderer, numba,
OpenCV).
"""

from __future__ import annotations

import argparse
import json
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from .errors import FieldError

CARLA_POSE = ("x", "y", "z", "pitch", "yaw", "roll")   # location (metres) and rotation (degrees), in this order
MATRIX_KEYS = ("cam_to_ego", "cam_to_world")     # the pose's key in a .json object
# K's structural zeros and ones and a pose's bottom row are compared with this absolute tolerance: JSON written by
# float code can carry 1e-16-level round-off, anything larger is a real (refused) parameter.
STRUCT_TOL = 1e-9


class PoseArgError(FieldError):
    """A pose flag's value that cannot be used. ``field``: the flag (e.g. "--cam-to-world");
    str(e) = "<flag>: <message>"."""


def add_matrix_argument(parser, *flags: str, help: str) -> None:
    """A 4x4 matrix flag (``flags``: its name, then aliases): 16 numbers, or one JSON list / .npy / .json file (see
    parse_matrix)."""
    action = parser.add_argument(*flags, nargs="+", default=None, metavar="M",
                                 help=f"{help}; 16 numbers row-major, or one JSON list (16 or 4x4) or a .npy/.json "
                                      "file")
    action.numbers = 16     # xyzcyl's parser (common/command.py) takes 16 numbers in a row as one value, no more


def _numbers_in(text: str) -> list[str]:
    """The number tokens of a list written as JSON, numpy prints it or plain: brackets and commas are separators."""
    return text.replace("[", " ").replace("]", " ").replace(",", " ").split()


def _in(what: str) -> str:
    return f"{what}: " if what else ""


class PoseError(FieldError):
    """A 4x4 pose that cannot be read (pose_matrix). ``field``: the caller's name of the pose ("cam_to_ego",
    "cameras[2].cam_to_ego", "--cam-to-world")."""


def _short(v: Any) -> str:
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def pose_matrix(value: Any, field: str = "cam_to_ego"):
    """[4, 4] float64 of a 4x4 pose matrix (row-major) as any front end states one -- the project's one reader of a
    pose's numbers (the GET render query, batch items, camera paths, rig.json cameras, the CLI's flags, the gRPC
    front end's poses once composed):

    - 16 numbers, or a nested [4][4] list / tuple / numpy array of numbers (JSON; booleans are not numbers);
    - text: 16 numbers separated by commas and/or white space, brackets ignored (the GET query's
      ``cam_to_ego=0,0,1,...``; a JSON list or numpy's printed form as text);
    - a one-element list of such text (a query parameter read as a list).

    Every entry must be finite. PoseError naming ``field`` otherwise (the message names the first non-finite
    entry, [row][column]). Only the numbers are read here: the pose's structure (bottom row, an orthonormal rotation with det +1)
    is checked where a camera is made (runtime.camera.check_pose)."""
    import numpy as np

    if isinstance(value, (list, tuple)) and len(value) == 1 and isinstance(value[0], str):
        value = value[0]
    if isinstance(value, str):
        try:
            m = np.array([float(t) for t in _numbers_in(value)], dtype=np.float64)
        except ValueError:
            raise PoseError(field, "16 comma-separated numbers expected") from None
        if m.size != 16:
            raise PoseError(field, f"16 comma-separated numbers expected, got {m.size}")
    else:
        a = value
        ok = isinstance(a, np.ndarray) and a.dtype.kind in "iuf" and a.size == 16 and a.shape in ((16,), (4, 4))
        if not ok and isinstance(a, (list, tuple)):
            flat = len(a) == 16 and all(is_real(x) for x in a)
            nested = len(a) == 4 and all(isinstance(r, (list, tuple)) and len(r) == 4 and all(is_real(x) for x in r)
                                         for r in a)
            ok = flat or nested
        if not ok:
            got = f"shape {list(a.shape)}" if isinstance(a, np.ndarray) else _short(a)
            raise PoseError(field, f"must be 16 numbers (row-major) or a [4, 4] array (got {got})")
        m = np.array(a, dtype=np.float64)
    m = m.reshape(4, 4)
    bad = np.argwhere(~np.isfinite(m))
    if len(bad):
        r, c = (int(i) for i in bad[0])
        raise PoseError(field, f"entry [{r}][{c}] is not finite")
    return m


def is_real(x: Any) -> bool:
    """Whether ``x`` is a real number (int, float, numpy scalar; a bool is not: JSON's true is no coordinate)."""
    import numpy as np

    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def _to_matrix(v: Any, flag: str, what: str):
    """pose_matrix for a CLI flag's value (``what``: where in the flag's value, e.g. a file's name)."""
    try:
        return pose_matrix(v, flag)
    except PoseError as e:
        raise PoseArgError(e.field, f"{_in(what)}{e.message}") from None


def _from_text(text: str, flag: str, what: str):
    try:
        doc = json.loads(text)
    except ValueError:
        doc = None
    if isinstance(doc, dict):
        keys = [k for k in MATRIX_KEYS if k in doc]
        if len(keys) != 1:
            raise PoseArgError(flag, f"{_in(what)}a JSON object must hold one of {', '.join(MATRIX_KEYS)}")
        return _to_matrix(doc[keys[0]], flag, f"{_in(what)}{keys[0]}")
    if isinstance(doc, list):
        return _to_matrix(doc, flag, what)
    tokens = _numbers_in(text)
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not is_number(t))
        raise PoseArgError(flag, f"{_in(what)}{bad!r} is not a number") from None
    if len(values) != 16:
        raise PoseArgError(flag, f"{_in(what)}expected 16 numbers, got {len(values)}")
    return _to_matrix(values, flag, what)


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except (OSError, ValueError):      # e.g. a long list of numbers is no file name
        return False


def is_number(text: str) -> bool:
    """Whether ``text`` is a number in any float notation (``-1e-05``, ``inf``); the dispatcher's parser
    (common/command.py) asks it too."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def parse_matrix(values: str | list[str] | tuple[str, ...], flag: str = "--cam-to-world"):
    """[4, 4] float64 from a matrix flag's values (strings as argparse gives them, or one string):

    - 16 numbers, row-major, any float notation (``-1e-05``);
    - one value that names a file: ``.npy`` (16 or 4x4 numbers) or anything else read as text (.json: a list of
      16 or 4x4 numbers, or an object with ``cam_to_ego`` or ``cam_to_world``);
    - one value holding the numbers: a JSON list, numpy's printed form (``[[ 0. 0. 1. 5.] [-1. ...]]``), or 16
      numbers separated by spaces or commas (``--cam-to-world="0 0 1 5 ..."``).

    Values must be finite; the rotation is validated where the camera is made (the renderer, the server).
    PoseArgError naming ``flag`` otherwise."""
    import numpy as np

    vals = [values] if isinstance(values, str) else [str(v) for v in values]
    if not vals:
        raise PoseArgError(flag, "expected 16 numbers, a JSON list or a .npy/.json file")
    if len(vals) == 1:
        v = vals[0].strip()
        path = Path(v)
        if _is_file(path):
            try:
                if path.suffix.lower() == ".npy":
                    return _to_matrix(np.load(path, allow_pickle=False), flag, repr(v))
                return _from_text(path.read_text(), flag, repr(v))
            except PoseArgError:
                raise
            except OSError as e:
                raise PoseArgError(flag, f"cannot read {v!r}: {e.strerror or e}") from None
            except ValueError as e:     # not a .npy file (or one of objects), or not text
                kind = "a .npy array of numbers" if path.suffix.lower() == ".npy" else "text"
                raise PoseArgError(flag, f"{v!r} is not {kind} ({e})") from None
        if path.suffix.lower() in (".npy", ".json"):
            raise PoseArgError(flag, f"no such file {v!r}")
        return _from_text(v, flag, "")
    if len(vals) != 16:
        raise PoseArgError(flag, f"expected 16 numbers, got {len(vals)} values")
    return _from_text(" ".join(vals), flag, "")


def parse_lens(value: str, flag: str = "--distortion") -> list | dict:
    """A lens flag's value as rig.json writes a camera's ``distortion`` (an OpenCV coefficient list, or
    {"model": "opencv" | "opencv_fisheye" | "ftheta", ...}; docs/conventions.md, Lens models): JSON text, or a
    .json file holding that value or a rig camera entry / object with a ``distortion`` key. Checked for shape only
    here (a list or an object); the lens itself is validated where the camera is made. PoseArgError naming
    ``flag``."""
    v = value.strip()
    path = Path(v)
    if _is_file(path):
        try:
            text = path.read_text()
        except OSError as e:
            raise PoseArgError(flag, f"cannot read {v!r}: {e.strerror or e}") from None
    elif path.suffix.lower() == ".json":
        raise PoseArgError(flag, f"no such file {v!r}")
    else:
        text = v
    try:
        lens = json.loads(text)
    except ValueError as e:
        raise PoseArgError(flag, f"not valid JSON ({e})") from None
    if isinstance(lens, dict) and "distortion" in lens:
        lens = lens["distortion"]
    if not isinstance(lens, (list, dict)):
        raise PoseArgError(flag, 'expected a JSON list of OpenCV coefficients or an object {"model": ..., ...}')
    return lens


MOVE_MAX_M = 1000.0      # the largest shift along one ego axis, metres (beyond any scene's extent)
MOVE_MAX_DEG = 360.0     # the largest turn, degrees (either way)


class MoveError(FieldError):
    """A camera move's field that cannot be used. ``field``: the CameraMove field ("forward", "yaw")."""


def _move_field(unit: str, limit: float, help: str):
    """A CameraMove field: 0 by default, with its unit ("metres" or "degrees"), its bound (|value| <= limit) and
    what it does (help)."""
    return field(default=0.0, metadata={"unit": unit, "limit": limit, "help": help})


@dataclass(frozen=True)
class CameraMove:
    """A camera move in the ego frame (x forward, y left, z up): turn ``yaw`` degrees to the left (counter-clockwise
    seen from above) about the vertical through the camera's centre, then shift ``forward``, ``left``, ``up`` metres
    along ego x, y, z. The one definition of the move fields (names, units, bounds, help; MOVE_FIELDS) that every
    front end reads: the flags of `xyzcyl render` and `xyzcyl client render` (add_move_arguments), the GET render
    query and the batch items (common.wire.ViewQuery), the Python client
    (clients.client.view_params); runtime.views.move_camera applies it to a render camera.

    Construction checks every field (a real number, finite, |value| <= its bound; ints become floats) and raises
    MoveError naming the field ("forward"); callers rename it to their own name of that field (a flag, a query
    parameter, a JSON path)."""

    forward: float = _move_field("metres", MOVE_MAX_M, "along ego x (forward; negative: back)")
    left: float = _move_field("metres", MOVE_MAX_M, "along ego y (left; negative: right)")
    up: float = _move_field("metres", MOVE_MAX_M, "along ego z (up; negative: down)")
    yaw: float = _move_field("degrees", MOVE_MAX_DEG, "to the left (counter-clockwise seen from above; negative: "
                                                      "right) about the vertical through the camera's centre, "
                                                      "before the shift")

    def __post_init__(self) -> None:
        for f in fields(self):
            v, unit, limit = getattr(self, f.name), f.metadata["unit"], f.metadata["limit"]
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise MoveError(f.name, f"must be a number of {unit} (got {v!r:.60})")
            x = float(v)
            if not math.isfinite(x):
                raise MoveError(f.name, f"must be finite, got {x}")
            if abs(x) > limit:
                raise MoveError(f.name, f"must be within -{limit:g}..{limit:g} {unit}, got {x:g}")
            object.__setattr__(self, f.name, x)

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> CameraMove:
        """The move of a mapping {name: value} holding some of MOVE_NAMES (None or absent: 0); MoveError naming the
        field. Other keys are ignored (the caller refuses those it does not know)."""
        return cls(**{k: values[k] for k in MOVE_NAMES if values.get(k) is not None})

    def __bool__(self) -> bool:
        return any(getattr(self, k) for k in MOVE_NAMES)

    def values(self) -> dict[str, float]:
        """The fields that are set (non-zero), in MOVE_NAMES order: what a request needs to carry."""
        return {k: getattr(self, k) for k in MOVE_NAMES if getattr(self, k)}

    def flags(self) -> list[str]:
        """The move flags that are set (for messages)."""
        return [f"--{k}" for k in self.values()]

    def apply(self, pose):
        """The moved copy of a 4x4 camera-to-ego pose (OpenCV camera axes; [4, 4] float64)."""
        import numpy as np

        T = pose_matrix(pose, "cam_to_ego")
        if self.yaw:
            a = math.radians(self.yaw)
            c, s = math.cos(a), math.sin(a)
            T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
        T[:3, 3] += (self.forward, self.left, self.up)
        return T

    def apply_carla(self, x: float, y: float, z: float, pitch: float, yaw: float, roll: float
                    ) -> tuple[float, float, float, float, float, float]:
        """The same move for a CARLA transform relative to the vehicle (left-handed: x forward, y right, z up,
        metres; pitch, yaw (turning right), roll degrees): CARLA's yaw is the outermost rotation, about the
        sensor's vertical, so the turn is yaw - self.yaw and the shift is (forward, -left, up)."""
        return (x + self.forward, y - self.left, z + self.up, pitch, yaw - self.yaw, roll)


@dataclass(frozen=True)
class MoveField:
    """One field of CameraMove as the front ends declare it: ``name`` ("forward"), ``unit`` ("metres" or
    "degrees"), ``limit`` (|value| <= limit) and ``help`` (the direction)."""

    name: str
    unit: str
    limit: float
    help: str

    @property
    def metavar(self) -> str:
        return "M" if self.unit == "metres" else "DEG"

    def describe(self) -> str:
        """One line for a query parameter or a JSON key: what it does, its unit and range."""
        verb = "shift" if self.unit == "metres" else "turn"
        return f"camera move: {verb} the camera this many {self.unit} {self.help}; -{self.limit:g}..{self.limit:g}"


MOVE_FIELDS: tuple[MoveField, ...] = tuple(MoveField(f.name, f.metadata["unit"], f.metadata["limit"],
                                                     f.metadata["help"]) for f in fields(CameraMove))
MOVE_NAMES: tuple[str, ...] = tuple(f.name for f in MOVE_FIELDS)          # forward, left, up, yaw
MOVE_FLAGS: tuple[str, ...] = tuple(f"--{n}" for n in MOVE_NAMES)


def add_move_arguments(parser) -> None:
    """--forward, --left, --up (metres along ego x, y, z) and --yaw (degrees, turning left): MOVE_FIELDS as flags."""
    g = parser.add_argument_group("camera moves (ego frame: x forward, y left, z up; applied to the pose, or to "
                                  "the input camera's pose)")
    for f in MOVE_FIELDS:
        verb = "move" if f.unit == "metres" else "turn"
        g.add_argument(f"--{f.name}", type=float, default=0.0, metavar=f.metavar,
                       help=f"{verb} the camera {f.metavar} {f.unit} {f.help}; -{f.limit:g}..{f.limit:g}")


OUT_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".exr": "exr"}   # --out's extension -> format
EXTENSIONS = {"png": ".png", "jpeg": ".jpg", "exr": ".exr"}                      # format -> the extension to use


def add_format_argument(parser) -> None:
    """--format png|jpeg|exr: the encoding of --out (default: its extension's)."""
    from .wire import FORMATS
    parser.add_argument("--format", choices=FORMATS, default=None,
                        help="the encoding: png, jpeg or exr (default: --out's extension; when both are given they "
                             "must agree, and --out may then have no extension)")


def out_format(out: str | Path, fmt: str | None = None) -> str:
    """The encoding of a view written to ``out``: its extension's (.png, .jpg / .jpeg, .exr), or ``fmt`` (the
    --format flag) when given, which must agree with the extension (a file without an extension takes it as it
    is). PoseArgError naming --out (an unknown extension) or --format (a disagreement)."""
    from .wire import FORMATS

    suffix = Path(out).suffix.lower()
    by_name = OUT_FORMATS.get(suffix)
    if fmt is not None and fmt not in FORMATS:
        raise PoseArgError("--format", f"must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if by_name is None and not (fmt is not None and not suffix):
        raise PoseArgError("--out", f"extension must be .png, .jpg, .jpeg or .exr (got {suffix or 'none'!r})"
                                    + ("" if fmt is None else f"; with --format {fmt}, use {EXTENSIONS[fmt]} or no "
                                                              "extension"))
    if fmt is not None and by_name is not None and fmt != by_name:
        raise PoseArgError("--format", f"{fmt} does not match --out's extension {suffix!r} ({by_name}); use "
                                       f"{EXTENSIONS[fmt]} or leave --format out")
    return fmt or by_name


def move_from_args(args: argparse.Namespace) -> CameraMove:
    """The CameraMove of the flags; PoseArgError naming the flag whose value cannot be used."""
    try:
        return CameraMove.from_values({n: getattr(args, n) for n in MOVE_NAMES})
    except MoveError as e:
        raise PoseArgError(f"--{e.field}", e.message) from None


__all__ = ["is_real", "CARLA_POSE", "STRUCT_TOL", "PoseError", "pose_matrix", "MOVE_FIELDS", "MOVE_FLAGS", "MOVE_MAX_DEG", "MOVE_MAX_M", "MOVE_NAMES",
           "OUT_FORMATS", "CameraMove", "MoveError", "MoveField", "PoseArgError", "add_format_argument",
           "add_matrix_argument", "add_move_arguments", "is_number", "move_from_args", "out_format", "parse_lens",
           "parse_matrix"]
