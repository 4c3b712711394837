"""The runtime's errors: every one that reports bad input is a ``FieldError(field, message, where=None)`` (defined in
xyzcyl.common.errors, shared with the client's flag parser), naming its field as an attribute (no caller parses a
message to recover it).

- ``field``: the field at fault, as a path into the input ("K", "K[0][0]", "cam_to_ego", "width", "cameras",
  "cameras[3].fov", "camera_path[2].camera_to_world"); ``root_field`` is its first name ("K", "cameras");
- ``message``: what is wrong with it, without the field;
- ``where``: optionally, the thing the field belongs to, as people name it ("camera 'CAM_FRONT'", "rig").

``str(e)`` is ``"<where>: <field>: <message>"``, or ``"<field>: <message>"`` without ``where``.

Every runtime error that reports bad input derives from it (tests/runtime/test_errors.py walks them): RigError
(rigs) and CameraError (cameras and their lenses: runtime.camera, runtime.lenses; defined here),
runtime.convert.ConversionError (foreign records: ``where`` the record, "transforms.json: frames[3]"), runtime.views.ViewError (render requests), runtime.scene.SceneError,
runtime.lidar.LidarError, runtime.detail.DetailError, runtime.inference.ModelError and InferenceError,
runtime.render.GaussianError (``where`` "PLY 'g.ply'"), runtime.cylinder.CylinderError and the command-line
flags' errors (xyzcyl.common.poses.PoseArgError, eval-real's: ``field`` the flag, "--cam-to-world").
A caller that maps an error to an HTTP field or a flag reads ``field`` / ``root_field``, never the message.
``plain`` is the one place that turns numpy values into plain Python for a message.
"""

from __future__ import annotations

from typing import Any

from xyzcyl.common.errors import FieldError


class RigError(FieldError):
    """Invalid rig or camera (runtime.rig, CameraError derives from it): ``where`` is "rig" or the
    camera ("camera 'CAM_FRONT'"), ``field`` the rig.json field at fault."""


class CameraError(RigError):
    """Invalid camera or lens: ``field`` ("K[0][0]", "cam_to_ego", "width", "model", "distortion.k1", ...),
    ``message``, and ``where`` ("camera 'CAM_FRONT'", "camera #2") when the camera has a name or an index. Defined
    here so that runtime.camera and runtime.lenses raise the one class."""


def plain(value: Any) -> Any:
    """``value`` for an error message's ``{...!r}``: numpy scalars and arrays as plain Python numbers and lists
    (numpy 2 writes a scalar as ``np.float64(-633.0)``); anything else unchanged. The validators' one place for it.
    (numpy imported here: light at import, as the rest of this module.)"""
    import numpy as np

    return value.tolist() if isinstance(value, (np.generic, np.ndarray)) else value


__all__ = ["CameraError", "FieldError", "RigError", "plain"]
