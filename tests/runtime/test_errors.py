"""runtime.errors.FieldError (issue 27, house 2): every runtime error class that reports bad input derives from
it, carries ``field`` / ``message`` / ``where`` as attributes (str(e) = "where: field: message"), survives
pickling with all three (the server's worker processes pickle them), and no caller parses a message for a field."""

from __future__ import annotations

import importlib
import inspect
import json
import pickle
import pkgutil
import re
from pathlib import Path

import numpy as np
import pytest
import xyzcyl.common as common_pkg
import xyzcyl.runtime as runtime_pkg
from xyzcyl.runtime.errors import FieldError

REPO = Path(__file__).resolve().parents[2]

# Exception classes of runtime/ that do not report bad input (none today): name -> why.
NOT_INPUT: dict[str, str] = {}


def _runtime_exception_classes() -> list[type[BaseException]]:
    """Every exception class defined in a module of xyzcyl.runtime or xyzcyl.common (the base and the flag
    parser's error live there; imported here: the walk is complete)."""
    found = []
    infos = [info for pkg in (runtime_pkg, common_pkg) for info in pkgutil.walk_packages(pkg.__path__,
                                                                                         pkg.__name__ + ".")]
    for info in infos:
        mod = importlib.import_module(info.name)
        for _, cls in inspect.getmembers(mod, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == mod.__name__:
                found.append(cls)
    return sorted(set(found), key=lambda c: f"{c.__module__}.{c.__qualname__}")


CLASSES = _runtime_exception_classes()


def test_the_walk_finds_the_runtime_errors():
    names = {c.__name__ for c in CLASSES}
    assert {"FieldError", "RigError", "CameraError", "ViewError", "ConversionError", "SceneError", "LidarError",
            "DetailError", "InferenceError", "ModelError", "GaussianError", "CylinderError",
            "PoseArgError"} <= names, names


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: f"{c.__module__.removeprefix('xyzcyl.')}.{c.__name__}")
def test_every_runtime_error_is_a_field_error_and_pickles(cls):
    name = f"{cls.__module__}.{cls.__qualname__}"
    if name in NOT_INPUT:
        pytest.skip(NOT_INPUT[name])
    assert issubclass(cls, FieldError), f"{name} reports bad input but is not a runtime.errors.FieldError"
    for args in (("K[0][0]", "fx must be > 0 (got -1.0)", "camera 'CAM_FRONT'"), ("lidar", "file 'x' is missing")):
        e = cls(*args)
        where = args[2] if len(args) > 2 else None
        assert (e.field, e.message, e.where) == (args[0], args[1], where)
        assert str(e) == (f"{where}: {args[0]}: {args[1]}" if where else f"{args[0]}: {args[1]}")
        again = pickle.loads(pickle.dumps(e))
        assert type(again) is cls and (again.field, again.message, again.where, str(again)) == (
            e.field, e.message, e.where, str(e))


def _raised(fn, *args, **kwargs) -> FieldError:
    with pytest.raises(FieldError) as info:
        fn(*args, **kwargs)
    return info.value


def _rig(extra: dict | None = None):
    from xyzcyl.runtime.camera import Camera
    from xyzcyl.runtime.rig import Rig

    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    return Rig(cameras=(Camera(name="CAM_A", width=64, height=48, K=K, cam_to_ego=np.eye(4)),),
               extra=extra or {})


def _cases(tmp: Path):
    """(error, its class name, field, where) of one real raise site per module."""
    from xyzcyl.common.poses import parse_matrix
    from xyzcyl.runtime import convert
    from xyzcyl.runtime.commands.eval_real import parse_pairs
    from xyzcyl.runtime.cylinder import CylinderSpec
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.inference import MODEL_FORMAT, read_model_info
    from xyzcyl.runtime.lidar import load_lidar, read_points
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.scene import Scene

    (tmp / "g.ply").write_bytes(b"not a ply at all")
    (tmp / "model").mkdir()
    (tmp / "model" / "model.json").write_text(json.dumps({"format": MODEL_FORMAT}))
    yield _raised(read_points, tmp / "none.npy"), "LidarError", "lidar", None
    yield (_raised(load_lidar, _rig({"lidar": {"file": "s.npy", "lidar_to_ego": [[1, 0], [0, 1]]}})), "LidarError",
           "lidar.lidar_to_ego", "rig")
    yield _raised(load_lidar, _rig({"lidar": {}})), "LidarError", "lidar.file", None
    yield _raised(Gaussians.load_ply, tmp / "g.ply"), "GaussianError", "header", "PLY 'g.ply'"
    yield _raised(Gaussians.from_splat_bytes, b"x" * 33), "GaussianError", "splat", None
    yield _raised(Scene.load, tmp), "SceneError", "scene", None
    yield _raised(read_model_info, tmp / "none"), "ModelError", "model", None
    yield _raised(read_model_info, tmp / "model"), "ModelError", "name", "model"
    yield (_raised(CylinderSpec, centre=(0, 0, 0), radius=-1.0, z_min=-3, z_max=13, height=8, width=8),
           "CylinderError", "radius", None)
    yield _raised(DetailOptions, stride=0), "DetailError", "detail.stride", None
    yield (_raised(convert.rig_from_nerfstudio, {"frames": [{"w": 64}]}), "ConversionError", "transform_matrix",
           "transforms.json: frames[0]")
    yield (_raised(convert.cameras_from_nerfstudio_path, {"render_width": 0}), "ConversionError", "render_width",
           "camera_path.json")
    yield _raised(parse_matrix, ["1", "2"], "--cam-to-world"), "PoseArgError", "--cam-to-world", None
    yield _raised(parse_pairs, "a", ["a", "b"]), "_Usage", "--pairs", None


def test_raise_sites_state_field_and_where(tmp_path):
    for e, cls, field, where in _cases(tmp_path):
        assert (type(e).__name__, e.field, e.where) == (cls, field, where), (type(e).__name__, str(e))
        assert str(e) == (f"{where}: {field}: {e.message}" if where else f"{field}: {e.message}")
        assert e.message and not e.message.startswith(f"{field}:"), str(e)     # the field is not said twice
        again = pickle.loads(pickle.dumps(e))
        assert (type(again), again.field, again.message, again.where) == (type(e), e.field, e.message, e.where)


def test_scene_names_its_rig_camera_and_field(tmp_path):
    """A scene whose rig is invalid: the camera's field, the scene file and the camera as ``where``."""
    from xyzcyl.runtime.scene import JSON_NAME, SCENE_FORMAT, Scene

    rig = _rig().to_dict()
    rig["cameras"][0]["K"][0][0] = -1.0
    (tmp_path / JSON_NAME).write_text(json.dumps({"format": SCENE_FORMAT, "rig": rig}))
    e = _raised(Scene.load, tmp_path)
    assert (e.field, e.where) == ("K[0][0]", f"scene {str(tmp_path / JSON_NAME)!r}: camera 'CAM_A'"), str(e)


_PARSES = re.compile(r"str\((?:e|exc|err|error)\)\s*\.\s*(?:split|rsplit|partition|startswith|removeprefix)|"
                     r"\.message\s*\.\s*(?:split|partition)\(")


def test_no_caller_parses_an_error_message_for_its_field():
    hits = []
    for folder in ("runtime", "server", "clients", "model_export"):
        for p in (REPO / folder).rglob("*.py"):
            for n, line in enumerate(p.read_text().splitlines(), 1):
                if _PARSES.search(line):
                    hits.append(f"{p.relative_to(REPO)}:{n}: {line.strip()}")
    assert hits == []
