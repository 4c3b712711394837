"""The base class of the runtime's errors that name their field as an attribute (no caller parses a message to
recover it): ``FieldError(field, message, where=None)``.

- ``field``: the field at fault, as a path into the input ("K", "K[0][0]", "cam_to_ego", "width", "cameras",
  "cameras[3].fov", "camera_path[2].camera_to_world"); ``root_field`` is its first name ("K", "cameras");
- ``message``: what is wrong with it, without the field;
- ``where``: optionally, the thing the field belongs to, as people name it ("camera 'CAM_FRONT'", "rig").

``str(e)`` is ``"<where>: <field>: <message>"``, or ``"<field>: <message>"`` without ``where``.
runtime.views.ViewError (render requests), CameraError (cameras and their lenses; runtime.camera and runtime.lenses)
and RigError (rigs) derive from it. ``plain`` is the one place that turns numpy values into plain Python for a message.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np


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
    """Invalid rig or camera (runtime.rig, CameraError derives from it): ``where`` is "rig" or the
    camera ("camera 'CAM_FRONT'"), ``field`` the rig.json field at fault."""


class CameraError(RigError):
    """Invalid camera or lens: ``field`` ("K[0][0]", "cam_to_ego", "width", "model", "distortion.k1", ...),
    ``message``, and ``where`` ("camera 'CAM_FRONT'", "camera #2") when the camera has a name or an index. Defined
    here so that runtime.camera and runtime.lenses raise the one class."""


def plain(value: Any) -> Any:
    """``value`` for an error message's ``{...!r}``: numpy scalars and arrays as plain Python numbers and lists
    (numpy 2 writes a scalar as ``np.float64(-633.0)``); anything else unchanged. The validators' one place for it."""
    return value.tolist() if isinstance(value, (np.generic, np.ndarray)) else value


__all__ = ["CameraError", "FieldError", "RigError", "plain"]
