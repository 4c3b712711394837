"""Small scenes for the LiDAR simulation's tests (runtime.lidarsim; tests/runtime/test_lidarsim.py,
tests/server/test_grpc_lidar.py): a vertical cylinder of opaque Gaussians around a point, whose every ray from that
point returns at a known range (horizontal distance R, so range R / cos(elevation)), and a scene folder of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

GREY_LUMA = 0.5 * 0.28209479177387814 + 0.5   # the colour of SH DC 0.5 (colour = SH_C0 dc + 0.5): its luminance


def cylinder_gaussians(radius: float = 10.0, centre=(0.0, 0.0, 0.0), n_around: int = 720, n_up: int = 60,
                       half_height: float = 6.0, thickness: float = 0.01):
    """Opaque flat Gaussians tiling the vertical cylinder of ``radius`` (metres) about ``centre``, z within
    +-``half_height`` of it; each one tangent to the cylinder, ``thickness`` thick (its radial scale)."""
    from xyzcyl.runtime.render import Gaussians

    a, z = np.meshgrid(np.linspace(0, 2 * np.pi, n_around, endpoint=False),
                       np.linspace(-half_height, half_height, n_up), indexing="ij")
    a, z = a.ravel(), z.ravel()
    c = np.asarray(centre, np.float64)
    means = np.stack([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a), c[2] + z], 1).astype(np.float32)
    quats = np.stack([np.cos(a / 2), 0 * a, 0 * a, np.sin(a / 2)], 1).astype(np.float32)   # x -> radial
    steps = [thickness, 2 * np.pi * radius / n_around, 2 * half_height / (n_up - 1)]
    log_scales = np.log(np.tile([steps], (len(means), 1))).astype(np.float32)
    sh = np.full((len(means), 1, 3), 0.5, np.float32)
    return Gaussians(means, quats, log_scales, np.full(len(means), 8.0, np.float32), sh)


def cylinder_scene(folder: Path, radius: float = 10.0, ego_to_world: np.ndarray | None = None, **kw) -> Path:
    """A scene folder (runtime.scene.Scene.save) of cylinder_gaussians about the scene origin, with one small camera
    and the rig's ``ego_to_world``."""
    from xyzcyl.runtime.camera import look_rotation
    from xyzcyl.runtime.rig import Camera, Rig
    from xyzcyl.runtime.scene import Scene

    T = np.eye(4)
    T[:3, :3] = look_rotation(0.0)
    cam = Camera(name="front", width=64, height=48, K=np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1.0]]),
                 cam_to_ego=T)
    extra = {} if ego_to_world is None else {"ego_to_world": np.asarray(ego_to_world, np.float64).tolist()}
    rig = Rig(cameras=(cam,), extra=extra, ego_to_world=ego_to_world)     # a scene keeps the rig's extra keys
    Scene(gaussians=cylinder_gaussians(radius, **kw), background=None, rig=rig).save(folder)
    return folder


__all__ = ["GREY_LUMA", "cylinder_gaussians", "cylinder_scene"]
