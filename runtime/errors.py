"""The base class of the runtime's errors that name their field as an attribute (no caller parses a message to
recover it): ``FieldError(field, message, where=None)``.

- ``field``: the field at fault, as a path into the input ("K", "K[0][0]", "cam_to_ego", "width", "cameras",
  "cameras[3].fov", "camera_path[2].camera_to_world"); ``root_field`` is its first name ("K", "cameras");
- ``message``: what is wrong with it, without the field;
- ``where``: optionally, the thing the field belongs to, as people name it ("camera 'CAM_FRONT'", "rig").

``str(e)`` is ``"<where>: <field>: <message>"``, or ``"<field>: <message>"`` without ``where``.

Every runtime error that reports bad input derives from it (tests/runtime/test_errors.py walks them): RigError
(rigs) and runtime.camera.CameraError (cameras), runtime.convert.ConversionError (foreign records: ``where``
the record, "transforms.json: frames[3]"), runtime.views.ViewError (render requests), runtime.scene.SceneError,
runtime.lidar.LidarError, runtime.detail.DetailError, runtime.inference.ModelError and InferenceError,
runtime.render.GaussianError (``where`` "PLY 'g.ply'"), runtime.cylinder.CylinderError and the command-line
flags' errors (runtime.commands.pose_flags.PoseArgError, eval-real's: ``field`` the flag, "--cam-to-world").
A caller that maps an error to an HTTP field or a flag reads ``field`` / ``root_field``, never the message.
``plain`` is the one place that turns numpy values into plain Python for a message.
"""

from __future__ import annotations

import re
from typing import Any

# Fields, by convention: the name the user wrote, as a path into what they wrote -- a rig.json / scene.json /
# model.json key ("K[0][0]", "lidar.lidar_to_ego", "graphs.encode.file"), a PLY property or header entry
# ("rot_0", "element vertex"), a request field ("cameras[3].fov") or a command-line flag ("--detail-stride").
# Where no single field is at fault (a whole file missing, unreadable, of another format, altered or too large),
# the field is the file's role -- "scene", "model", "lidar", "splat" -- and the message names the file:
# "scene: '/s/scene.json' is missing (not a scene folder)".


class FieldError(ValueError):
    """An input that cannot be honoured: ``field``, ``message`` and optional ``where`` (module docstring)."""

    def __init__(self, field: str, message: str, where: str | None = None):
        super().__init__(f"{where}: {field}: {message}" if where else f"{field}: {message}")
        self.field = field
        self.message = message
        self.where = where

    @property
    def root_field(self) -> str:
        """The field path's first name: "K" for "K[0][0]", "cameras" for "cameras[3].fov"."""
        return re.split(r"[\[.]", self.field, maxsplit=1)[0]

    def __reduce__(self):  # picklable with every argument (worker processes)
        return (type(self), (self.field, self.message, self.where))


class RigError(FieldError):
    """Invalid rig or camera (runtime.rig, runtime.camera.CameraError derives from it): ``where`` is "rig" or the
    camera ("camera 'CAM_FRONT'"), ``field`` the rig.json field at fault."""


def plain(value: Any) -> Any:
    """``value`` for an error message's ``{...!r}``: numpy scalars and arrays as plain Python numbers and lists
    (numpy 2 writes a scalar as ``np.float64(-633.0)``); anything else unchanged. The validators' one place for it.
    (numpy imported here: the pose flags import this module for the client, numpy-free at import.)"""
    import numpy as np

    return value.tolist() if isinstance(value, (np.generic, np.ndarray)) else value


__all__ = ["FieldError", "RigError", "plain"]
