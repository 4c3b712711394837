"""Render cameras. Camera frame is OpenCV (x right, y down, z forward); `cam_to_world` maps camera points to
world (ego) points, metres. See docs/renderer.md for the equirectangular pixel convention."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FieldError
from ..rotations import ORTHO_TOL


class CameraError(FieldError):
    """Invalid camera: ``field`` ("K", "cam_to_world", "width", "height") and ``message`` (runtime.errors)."""


def _check_pose(m) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise CameraError("cam_to_world", f"expected shape [4, 4], got {list(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise CameraError("cam_to_world", f"{int(np.count_nonzero(~np.isfinite(m)))} non-finite values")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise CameraError("cam_to_world", "last row must be [0, 0, 0, 1]")
    r = m[:3, :3]
    # ORTHO_TOL: the rig's tolerance too (runtime/rotations.py), so no camera of a valid rig is refused here
    if not np.allclose(r.T @ r, np.eye(3), atol=ORTHO_TOL, rtol=0.0) or np.linalg.det(r) < 0:
        raise CameraError("cam_to_world", "rotation block must be orthonormal with determinant +1")
    return m


def _check_size(width, height) -> tuple[int, int]:
    for name, v in (("width", width), ("height", height)):
        if int(v) != v or int(v) < 1 or int(v) > 32768:
            raise CameraError(name, f"must be an integer in 1..32768, got {v!r}")
    return int(width), int(height)


class _Posed:
    """Pose helpers shared by both camera models (they hold `cam_to_world` [4, 4])."""

    cam_to_world: np.ndarray

    @property
    def world_to_cam(self) -> np.ndarray:  # [4, 4] world -> OpenCV camera
        return np.linalg.inv(self.cam_to_world)

    @property
    def centre(self) -> np.ndarray:  # [3] camera centre, world metres
        return self.cam_to_world[:3, 3].copy()


@dataclass(frozen=True)
class PinholeCamera(_Posed):
    """K: [3, 3] pixels, OpenCV (pixel (u, v) is evaluated at exactly x = u, y = v); no skew.
    cam_to_world: [4, 4] OpenCV camera -> world (ego), metres. width, height: pixels."""

    K: np.ndarray
    cam_to_world: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        k = np.asarray(self.K, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise CameraError("K", f"expected a finite [3, 3] matrix, got shape {list(k.shape)}")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise CameraError("K", "focal lengths K[0][0], K[1][1] must be > 0")
        if k[0, 1] != 0 or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            raise CameraError("K", "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "cam_to_world", _check_pose(self.cam_to_world))
        w, h = _check_size(self.width, self.height)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)


@dataclass(frozen=True)
class EquirectCamera(_Posed):
    """Full 360x180 equirectangular panorama in the OpenCV camera frame (x right, y down, z forward).

    azimuth phi = atan2(x, z) (0 = forward, positive to the right), polar angle theta = angle from up (-y).
    Pixel (u, v) looks at phi = 2*pi*(u + 0.5)/width - pi, theta = pi*(v + 0.5)/height: column 0's left edge
    is straight back (phi = -pi), the image centre looks forward, row 0's top edge is the zenith."""

    cam_to_world: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "cam_to_world", _check_pose(self.cam_to_world))
        w, h = _check_size(self.width, self.height)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)

    def pixel_rays(self) -> np.ndarray:
        """[H, W, 3] unit ray directions in the camera frame for every pixel centre."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        phi = 2 * np.pi * u / self.width - np.pi
        theta = np.pi * v / self.height
        th, ph = np.meshgrid(theta, phi, indexing="ij")
        return np.stack([np.sin(th) * np.sin(ph), -np.cos(th), np.sin(th) * np.cos(ph)], axis=-1)
