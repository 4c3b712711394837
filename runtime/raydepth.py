"""The Gaussians' depth and alpha at every pixel of an input camera, whatever its lens: what the LiDAR fusion
(runtime.inference.Reconstructor.lidar_depths) and the detail layer (runtime.detail.model_grid_depth) read from the
model's reconstruction. The renderer draws ideal pinhole and equirectangular cameras; a camera with a lens is
read from an equirectangular panorama rendered at its centre and orientation, sampled along each pixel's true ray
(Camera.pixel_rays): no undistort-and-crop, and a fisheye's rays beyond 90 degrees get a depth too.

Depth is the camera's (Camera.depth_is_distance): camera z for an ideal pinhole or an opencv lens, the distance
from the camera centre for a fisheye or f-theta lens.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera
from .render import Gaussians, render

MIN_PANORAMA = 64      # pixels: the narrowest panorama rendered for a lens camera
MAX_PANORAMA = 2048    # pixels: the widest (2048 px around: 5.7 px per degree)


def panorama_width(camera: Camera, max_width: int = MAX_PANORAMA) -> int:
    """Width of the panorama that resolves ``camera``'s pixels at its centre: 2 pi x its mean paraxial focal (pixels
    per radian), even, clamped to [MIN_PANORAMA, max_width]."""
    fx, fy = camera.paraxial_focal
    w = 2.0 * math.pi * 0.5 * (fx + fy)
    return int(min(max(2 * math.ceil(w / 2.0), MIN_PANORAMA), max_width))


def render_ray_depth(gaussians: Gaussians, camera: Camera, max_width: int = MAX_PANORAMA
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W], alpha [H, W]) float32 of ``gaussians`` at each pixel of ``camera``: depth the camera's
    (Camera.depth_is_distance), 0 where alpha is 0 or the pixel has no ray. An ideal pinhole or equirectangular
    camera is rendered directly; a camera with a lens samples an equirectangular panorama
    (``panorama_width(camera, max_width)`` wide) at its centre and orientation along each pixel's ray, bilinearly
    (at a depth edge, where the bilinear value differs from the nearest one by more than 10 %, the nearest)."""
    if camera.is_ideal:
        r = render(gaussians, Camera(width=camera.width, height=camera.height, cam_to_ego=camera.cam_to_ego,
                                     K=camera.K, model=camera.model))
        return r.depth, r.alpha
    import cv2

    w = panorama_width(camera, max_width)
    pano = Camera(model="equirectangular", width=w, height=w // 2, cam_to_ego=camera.cam_to_ego)
    r = render(gaussians, pano)
    _, d = camera.pixel_rays()                                 # [H, W, 3] ego, NaN where no ray
    ok = np.all(np.isfinite(d), axis=-1)
    uv, _, _ = pano.project(camera.position + np.where(ok[..., None], d, [1.0, 0.0, 0.0]))
    # one wrapped column each side: longitude wraps, the poles' rows are replicated
    depth = np.concatenate([r.depth[:, -1:], r.depth, r.depth[:, :1]], axis=1)
    alpha = np.concatenate([r.alpha[:, -1:], r.alpha, r.alpha[:, :1]], axis=1)
    mx = (uv[..., 0] + 1.0).astype(np.float32)
    my = uv[..., 1].astype(np.float32)
    lin = cv2.remap(depth, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    near = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    dist = np.where(np.abs(lin - near) > 0.1 * near, near, lin)
    a = cv2.remap(alpha, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if not camera.depth_is_distance:                           # opencv lens: camera z = distance x cos
        dist = dist * np.clip(d @ camera.rotation[:, 2], 0.0, None).astype(np.float32)
    dist = np.where(ok & (a > 0), dist, 0.0).astype(np.float32)
    return dist, np.where(ok, a, 0.0).astype(np.float32)


__all__ = ["MAX_PANORAMA", "MIN_PANORAMA", "panorama_width", "render_ray_depth"]
