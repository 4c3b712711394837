"""The base of every xyzcyl error that names its field as an attribute (no caller parses a message to recover
it): ``FieldError(field, message, where=None)``. It lives here, in the package that imports nothing else of
xyzcyl, because the client's flag parser (common.poses.PoseArgError) and the runtime's errors (runtime.errors:
RigError, CameraError, ViewError, SceneError, ...) share it.

- ``field``: the field at fault, as a path into the input ("K", "K[0][0]", "cam_to_ego", "cameras[3].fov",
  "--cam-to-world"); ``root_field`` is its first name ("K", "cameras");
- ``message``: what is wrong with it, without the field;
- ``where``: optionally, the thing the field belongs to, as people name it ("camera 'CAM_FRONT'", "rig").

``str(e)`` is ``"<where>: <field>: <message>"``, or ``"<field>: <message>"`` without ``where``.
"""

from __future__ import annotations

import re

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


__all__ = ["FieldError"]
