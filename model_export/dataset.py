"""torch Datasets over the synthetic on-disk format (docs/data.md) and over real rig folders.

One item = one scene (the network is unbatched over scenes; use ``collate_scenes`` with a DataLoader):

    item["images"]      [N, 3, H, W] float32 0..1   input cameras, rig order (after the optional flip)
    item["depth"]       [N, 1, H, W] float32 metres along the optical axis, 0 where not depth_valid
    item["depth_valid"] [N, 1, H, W] bool           0 < depth <= max_depth (the ground plane is unbounded:
                                                    rays near the horizon hit it hundreds of metres away)
    item["sky"]         [N, 1, H, W] float32        1 = sky
    item["rig"]         xyzcyl.runtime.rig.Rig      input calibration (consistent with the images)
    item["targets"]     dict: images [T, 3, H, W], depth [T, H, W], depth_valid [T, H, W] bool, sky [T, H, W],
                        K [T, 3, 3] float64 pixels, cam_to_ego [T, 4, 4] float64, names list[str], width, height
    item["occupancy"]   [L_z, L_y, L_x] int64  0 empty / 1 occupied (grid of ``voxel_size``); with
                                               occupancy_labels "surface": 1 only for occupied voxels an input
                                               camera sees, 255 (OCC_UNKNOWN) for hidden occupied voxels —
                                               select voxels with ``== 1``, never ``.bool()``; "surface+ego":
                                               as "surface", and the ego car's voxels are 1 (no input camera
                                               sees the car the rig is on, but it is always there)
    item["bev"]         [L_y, L_x] int64       1 where the column holds an occupied voxel that is not ground
                                               (road / sidewalk / terrain): the obstacle map
    item["lifting"]     dict of float32 tensors (runtime.lifting.build_lifting_inputs) if a model config is given,
                        plus item["targets"]["background_grid"] [T, H, W, 2] for ZNet_bg
    item["scene"]       scene folder name; item["flipped"] bool

Randomness (target subset, colour jitter, flip) comes from numpy's default_rng((seed, epoch, index)), so an
item is reproducible and ``set_epoch`` draws new subsets per epoch. The per-camera input augmentation draws from
a child of that generator (``Generator.spawn``), so switching it on changes neither the targets nor the flip;
the camera drop (``camera_drop``) draws from the next child, likewise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.rig import Rig, load_rig, read_image

from .config import ConfigError, _Frozen
from .data.classes import EGO, ROAD, SIDEWALK, TERRAIN

GROUND_CLASSES = (ROAD, SIDEWALK, TERRAIN)   # BEV target: a column is "occupied" if it holds anything else

SETTINGS = ("ego-forward", "ego-inward")
MIXED = "both"   # DatasetConfig.setting: draw the T targets from the union of both settings' cameras
OCCUPANCY_LABELS = ("solid", "surface", "surface+ego")
OCC_UNKNOWN = 255   # occupancy label ignored by every loss (losses.IGNORE_INDEX)
# xyzcyl train --camera-aug S: DatasetConfig fields at S = 1 (each scaled by S)
CAMERA_AUG_PRESET = {"camera_exposure": 0.3, "camera_white_balance": 0.1, "vignetting": 0.4, "blur": 0.3,
                     "jpeg": 0.5, "noise": 0.02}


class DataError(ValueError):
    """A data folder is malformed; the message names the file and field."""


@dataclass(frozen=True)
class DatasetConfig(_Frozen):
    setting: str = "ego-forward"        # which targets.json setting supervises rendering ("both": either)
    num_targets: int = 4                # T: random target views per item (all if fewer exist)
    voxel_size: float = 0.8             # occupancy grid to load (tag in occupancy.npz, e.g. 0.8 -> "0p8")
    pc_range: tuple[float, float, float, float, float, float] | None = None  # must match the file when given
    seed: int = 0
    skip_occluded: bool = True          # drop targets the generator marked "occluded" (camera inside geometry)
    brightness: float = 0.0             # colour jitter: factor drawn from [1 - b, 1 + b] (0 = off)
    contrast: float = 0.0               # blend with the image mean, factor in [1 - c, 1 + c]
    saturation: float = 0.0             # blend with grey, factor in [1 - s, 1 + s]
    flip_prob: float = 0.0              # mirror the scene across the ego x-z plane (y -> -y) with this probability
    max_depth: float = 80.0             # metres: deeper pixels (far ground near the horizon) are not depth-valid
    target_scale: float = 1.0           # targets resampled to this fraction of their size (cheaper rendering)
    occupancy_labels: str = "solid"     # "surface": only occupied voxels the input cameras see, hidden ones 255;
                                        # "surface+ego": also the ego car's voxels (class EGO) occupied
    surface_dilation: int = 0           # "surface": also occupied voxels within this many voxels (26-neighbours)
    camera_exposure: float = 0.0        # input cameras only, per camera: gain drawn from [1 - e, 1 + e]
    camera_white_balance: float = 0.0   # per camera and channel: gain drawn from [1 - w, 1 + w]
    vignetting: float = 0.0             # per camera: gain 1 - s (r / r_corner)^2, s drawn from [0, v]
    blur: float = 0.0                   # per camera: probability of a Gaussian blur, sigma drawn from [0.3, 1.2] px
    jpeg: float = 0.0                   # per camera: probability of a JPEG re-encode, quality drawn from [40, 95]
    noise: float = 0.0                  # per camera: Gaussian noise, sigma drawn from [0, n]
    camera_drop: float = 0.0            # probability that an item loses a sector of adjacent input cameras (a rig
                                        # with a blind side, e.g. 5 front/side cameras); targets are kept
    camera_drop_max: int = 2            # a dropped sector is 1..this many cameras adjacent in azimuth; at least
                                        # CAMERA_DROP_MIN_KEEP cameras stay (smaller rigs never drop)
    lens_zoom: float = 0.0              # per input camera: probability of a narrower lens (a crop of its image,
                                        # depth and sky resampled to the full size, K to match); targets kept
    lens_zoom_max: float = 1.4          # zoom factor drawn from [1, this] (1.4: a 65 deg camera becomes ~49 deg)
    lidar_input: float = 0.0            # probability that an item's inputs carry a simulated LiDAR sweep, turned
                                        # into the depth input as the runtime does (simulate_lidar; training.md)

    def __post_init__(self):
        if self.setting not in SETTINGS + (MIXED,):
            raise ConfigError(f"setting: must be one of {', '.join(SETTINGS + (MIXED,))}, got {self.setting!r}")
        if isinstance(self.num_targets, bool) or not isinstance(self.num_targets, int) or self.num_targets < 1:
            raise ConfigError(f"num_targets: must be a positive integer, got {self.num_targets!r}")
        if not self.voxel_size > 0:
            raise ConfigError(f"voxel_size: must be > 0, got {self.voxel_size!r}")
        for n in ("brightness", "contrast", "saturation"):
            v = getattr(self, n)
            if not 0 <= v < 1:
                raise ConfigError(f"{n}: must be in [0, 1), got {v!r}")
        if not self.max_depth > 0:
            raise ConfigError(f"max_depth: must be > 0, got {self.max_depth!r}")
        if not 0 <= self.flip_prob <= 1:
            raise ConfigError(f"flip_prob: must be in [0, 1], got {self.flip_prob!r}")
        if not 0 < self.target_scale <= 1:
            raise ConfigError(f"target_scale: must be in (0, 1], got {self.target_scale!r}")
        if self.occupancy_labels not in OCCUPANCY_LABELS:
            raise ConfigError(f"occupancy_labels: must be one of {', '.join(OCCUPANCY_LABELS)}, "
                              f"got {self.occupancy_labels!r}")
        d = self.surface_dilation
        if isinstance(d, bool) or not isinstance(d, int) or d < 0:
            raise ConfigError(f"surface_dilation: must be an integer >= 0, got {d!r}")
        for n, top in (("camera_exposure", "1)"), ("camera_white_balance", "1)"), ("vignetting", "1]"),
                       ("blur", "1]"), ("jpeg", "1]"), ("noise", "1]")):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 <= v < 1 or (top == "1]" and v == 1)):
                raise ConfigError(f"{n}: must be in [0, {top}, got {v!r}")

        v = self.camera_drop
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1:
            raise ConfigError(f"camera_drop: must be in [0, 1], got {self.camera_drop!r}")
        m = self.camera_drop_max
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ConfigError(f"camera_drop_max: must be an integer >= 1, got {m!r}")
        v = self.lens_zoom
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1:
            raise ConfigError(f"lens_zoom: must be in [0, 1], got {self.lens_zoom!r}")
        v = self.lens_zoom_max
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1 <= v <= 4:
            raise ConfigError(f"lens_zoom_max: must be in [1, 4], got {self.lens_zoom_max!r}")
        v = self.lidar_input
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1:
            raise ConfigError(f"lidar_input: must be in [0, 1], got {self.lidar_input!r}")

    @property
    def camera_aug(self) -> bool:
        """Whether any per-camera input augmentation is on."""
        return any(getattr(self, n) for n in CAMERA_AUG_PRESET)

    def without_augmentation(self) -> DatasetConfig:
        """The same data with every augmentation off (flip, colour jitter, camera effects, camera drop, lens
        zoom): for validation."""
        return self.replace(flip_prob=0.0, brightness=0.0, contrast=0.0, saturation=0.0, camera_drop=0.0,
                            lens_zoom=0.0, lidar_input=0.0, **{n: 0.0 for n in CAMERA_AUG_PRESET})

    @property
    def settings(self) -> tuple[str, ...]:
        """The targets.json settings whose cameras are drawn from."""
        return SETTINGS if self.setting == MIXED else (self.setting,)

    @property
    def voxel_tag(self) -> str:
        return f"{self.voxel_size:g}".replace(".", "p")


# ---------------------------------------------------------------------------------------------- augmentation


def colour_jitter(images: np.ndarray, rng: np.random.Generator, brightness: float, contrast: float,
                  saturation: float) -> np.ndarray:
    """One random photometric change applied to every image of a scene (inputs and targets alike, so the
    render targets stay consistent with the inputs). images [M, H, W, 3] float32 0..1 -> same, clipped."""
    b = rng.uniform(1 - brightness, 1 + brightness)
    c = rng.uniform(1 - contrast, 1 + contrast)
    s = rng.uniform(1 - saturation, 1 + saturation)
    x = images * b
    mean = x.mean(axis=(1, 2, 3), keepdims=True)
    x = mean + c * (x - mean)
    grey = (x @ np.array([0.299, 0.587, 0.114], np.float32))[..., None]
    x = grey + s * (x - grey)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def camera_aug_fields(strength: float) -> dict[str, float]:
    """The DatasetConfig fields of ``xyzcyl train --camera-aug S``: CAMERA_AUG_PRESET scaled by S in [0, 1]."""
    if isinstance(strength, bool) or not isinstance(strength, (int, float)) or not 0 <= strength <= 1:
        raise ConfigError(f"camera_aug: must be in [0, 1], got {strength!r}")
    return {k: v * strength for k, v in CAMERA_AUG_PRESET.items()}


@dataclass(frozen=True)
class CameraAug:
    """One input camera's drawn augmentation (``draw_camera_aug``); the defaults change nothing."""
    vignetting: float = 0.0                           # s: gain 1 - s (r / r_corner)^2
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)   # exposure x white balance, per RGB channel
    blur_sigma: float = 0.0                           # pixels; 0 = no blur
    noise_sigma: float = 0.0                          # 0..1 image units; 0 = no noise
    jpeg_quality: int = 0                             # 0 = no JPEG re-encode


def draw_camera_aug(rng: np.random.Generator, cfg: DatasetConfig) -> CameraAug:
    """Draw one camera's augmentation. Every parameter is drawn whatever the config, in a fixed order, so each
    operation's draw does not depend on which others are on."""
    s = rng.uniform(0.0, cfg.vignetting)
    e = rng.uniform(1 - cfg.camera_exposure, 1 + cfg.camera_exposure)
    wb = rng.uniform(1 - cfg.camera_white_balance, 1 + cfg.camera_white_balance, size=3)
    do_blur, sigma = rng.random() < cfg.blur, rng.uniform(0.3, 1.2)
    n = rng.uniform(0.0, cfg.noise)
    do_jpeg, q = rng.random() < cfg.jpeg, int(rng.integers(40, 96))
    return CameraAug(vignetting=float(s), gain=tuple(float(e * w) for w in wb),
                     blur_sigma=float(sigma) if do_blur else 0.0, noise_sigma=float(n),
                     jpeg_quality=q if do_jpeg else 0)


def apply_camera_aug(image: np.ndarray, aug: CameraAug, rng: np.random.Generator | None = None) -> np.ndarray:
    """Apply ``aug`` to one image [H, W, 3] float32 0..1 (RGB) in the physical order vignetting, exposure / white
    balance, blur, noise (drawn from ``rng``; default_rng(0) when None), clip to [0, 1], JPEG. Returns a new
    float32 array."""
    import cv2

    x = np.array(image, np.float32)
    h, w = x.shape[:2]
    if aug.vignetting:
        yy, xx = np.mgrid[:h, :w].astype(np.float32)
        cy, cx = (h - 1) / 2, (w - 1) / 2
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / max(cx * cx + cy * cy, 1e-12)
        x *= (1 - aug.vignetting * r2)[..., None]
    if aug.gain != (1.0, 1.0, 1.0):
        x *= np.asarray(aug.gain, np.float32)
    if aug.blur_sigma:
        x = cv2.GaussianBlur(x, (0, 0), sigmaX=aug.blur_sigma, sigmaY=aug.blur_sigma,
                             borderType=cv2.BORDER_REFLECT_101)
    if aug.noise_sigma:
        rng = rng if rng is not None else np.random.default_rng(0)
        x += aug.noise_sigma * rng.standard_normal(x.shape, dtype=np.float32)
    x = np.clip(x, 0.0, 1.0)
    if aug.jpeg_quality:
        bgr = np.ascontiguousarray(np.round(x[..., ::-1] * 255).astype(np.uint8))
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(aug.jpeg_quality)])
        if not ok:
            raise DataError("jpeg: cv2.imencode failed")
        x = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
    return np.ascontiguousarray(x, dtype=np.float32)


def camera_augment(images: np.ndarray, rng: np.random.Generator, cfg: DatasetConfig) -> np.ndarray:
    """Independent real-camera effects per input camera (docs/training.md): images [N, H, W, 3] float32 0..1 ->
    same. Camera k draws from the k-th child of ``rng`` (parameters first, then its noise)."""
    out = []
    for img, g in zip(images, rng.spawn(len(images))):
        out.append(apply_camera_aug(img, draw_camera_aug(g, cfg), g))
    return np.stack(out)


_MIRROR_Y = np.diag([1.0, -1.0, 1.0, 1.0])   # ego (x, y, z) -> (x, -y, z)
_FLIP_X_CAM = np.diag([-1.0, 1.0, 1.0, 1.0])  # camera-frame x flip (image columns reversed)


def zoom_camera(camera: Camera, zoom: float, x0: float, y0: float) -> tuple[Camera, np.ndarray]:
    """A narrower lens on the same mount: the image window [x0, x0 + W/zoom) x [y0, y0 + H/zoom) (pixel-edge
    coordinates of ``camera``'s image) seen at the full W x H. Returns (the new camera: fx' = zoom fx, cx' = zoom
    (cx + 1/2 - x0) - 1/2, likewise fy, cy; pose unchanged; the [2, 3] affine map from the new pixel centres to
    the old ones, for cv2.warpAffine with WARP_INVERSE_MAP)."""
    import dataclasses

    K = np.array(camera.K, np.float64)
    K2 = K.copy()
    K2[0, 0], K2[1, 1] = zoom * K[0, 0], zoom * K[1, 1]
    K2[0, 2], K2[1, 2] = zoom * (K[0, 2] + 0.5 - x0) - 0.5, zoom * (K[1, 2] + 0.5 - y0) - 0.5
    # new pixel centre u' -> old u = x0 + (u' + 1/2) / zoom - 1/2 (the inverse of cx' above)
    inv = np.array([[1 / zoom, 0.0, x0 + 0.5 / zoom - 0.5], [0.0, 1 / zoom, y0 + 0.5 / zoom - 0.5]])
    return dataclasses.replace(camera, K=K2), inv


def lens_zoom_views(cameras: list[Camera], images: np.ndarray, depth: np.ndarray, sky: np.ndarray,
                    rng: np.random.Generator, prob: float, zoom_max: float
                    ) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray]:
    """Per input camera, with probability ``prob``: a lens zoom (``zoom_camera``) by U(1, zoom_max) at a uniform
    window position. images [N, H, W, 3] (bilinear), depth [N, H, W] metres and sky [N, H, W] (nearest: no
    depth blended across an edge) resampled, the camera's K changed to match (pinhole cameras only; others are
    kept); returns new arrays. Each camera
    draws from its own child of ``rng`` (do, zoom, x, y, always all four), so one camera's draws do not depend on
    the others'. Teaches the focal-aware depth head lenses the data set's rig does not have."""
    import cv2

    cams, imgs, deps, skies = list(cameras), images.copy(), depth.copy(), sky.copy()
    for k, g in enumerate(rng.spawn(len(cams))):
        do, z, fx, fy = g.random() < prob, g.uniform(1.0, zoom_max), g.random(), g.random()
        if not do or z == 1.0 or cams[k].model != "pinhole":
            continue
        c = cams[k]
        w, h = c.width, c.height
        cams[k], inv = zoom_camera(c, z, fx * (w - w / z), fy * (h - h / z))
        flags = cv2.WARP_INVERSE_MAP
        imgs[k] = cv2.warpAffine(np.ascontiguousarray(images[k]), inv, (w, h), flags=cv2.INTER_LINEAR | flags,
                                 borderMode=cv2.BORDER_REPLICATE)
        deps[k] = cv2.warpAffine(np.ascontiguousarray(depth[k], np.float32), inv, (w, h),
                                 flags=cv2.INTER_NEAREST | flags, borderMode=cv2.BORDER_REPLICATE)
        skies[k] = cv2.warpAffine(np.ascontiguousarray(sky[k]).astype(np.uint8), inv, (w, h),
                                  flags=cv2.INTER_NEAREST | flags, borderMode=cv2.BORDER_REPLICATE).astype(sky.dtype)
    return cams, imgs, deps, skies


CAMERA_DROP_MIN_KEEP = 3   # fewer than 3 cameras cannot surround the ego car at all: no rig we serve has fewer


def camera_azimuth(camera: Camera) -> float:
    """Azimuth of the camera's optical axis in the ego x-y plane, radians (0: ego +x, forward; +pi/2: +y, left)."""
    z = camera.cam_to_ego[:3, 2]
    return float(np.arctan2(z[1], z[0]))


def draw_camera_drop(cameras: list[Camera], rng: np.random.Generator, prob: float, max_drop: int) -> list[int]:
    """Indices (rig order) of the input cameras an item keeps. With probability ``prob`` a sector of k cameras
    adjacent in azimuth (k uniform in 1..max_drop, at most len - CAMERA_DROP_MIN_KEEP, a uniform starting
    camera on the ring) is dropped, so the rest of the rig has one blind side, like a rig without rear cameras.
    All indices when nothing is dropped."""
    n = len(cameras)
    top = min(max_drop, n - CAMERA_DROP_MIN_KEEP)
    if top < 1 or not rng.random() < prob:
        return list(range(n))
    k = int(rng.integers(1, top + 1))
    ring = np.argsort([camera_azimuth(c) for c in cameras], kind="stable")
    start = int(rng.integers(n))
    drop = {int(ring[(start + j) % n]) for j in range(k)}
    return [i for i in range(n) if i not in drop]


def mirror_camera_y(camera: Camera) -> Camera:
    """The camera that sees the world mirrored across the ego x-z plane (y -> -y) in the horizontally flipped
    image: a point P seen at pixel (u, v) by ``camera`` is seen at (W - 1 - u, v), same depth, after P -> M P.
    cam_to_ego' = M cam_to_ego F (M = diag(1, -1, 1), F = camera x flip; det stays +1); cx' = W - 1 - cx.
    Only undistorted pinhole cameras (DataError otherwise). Files (image/depth) are dropped: the arrays are
    flipped by the caller."""
    if camera.model != "pinhole" or camera.distortion is not None:
        raise DataError(f"camera {camera.name!r}: model: only undistorted pinhole cameras can be mirrored")
    K = camera.K.copy()
    K[0, 2] = camera.width - 1 - K[0, 2]
    return Camera(name=camera.name, width=camera.width, height=camera.height, K=K,
                  cam_to_ego=_MIRROR_Y @ camera.cam_to_ego @ _FLIP_X_CAM, extra=dict(camera.extra))


def mirror_order(n: int) -> list[int]:
    """Camera order after a mirror: the first camera stays first, the ring direction is restored."""
    return [0] + list(range(n - 1, 0, -1))


def downscale_views(cams: list[Camera], images: np.ndarray, depth: np.ndarray, sky: np.ndarray, scale: float,
                    max_depth: float) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray]:
    """Resample views to ``scale`` x their size (area averaging, cv2.INTER_AREA) with matching calibrations
    (``Camera.resized``). images [M, H, W, 3], depth [M, H, W] metres (0 / non-finite / > max_depth = unknown),
    sky [M, H, W] -> [M, h, w, 3], [M, h, w] (the mean depth of output pixels whose every input pixel has a
    known depth, else 0: no depth is invented across a silhouette or the horizon), [M, h, w] float32 sky fraction.
    W * scale and H * scale must be whole numbers."""
    import cv2

    m, H, W = depth.shape
    w, h = W * scale, H * scale
    if abs(w - round(w)) > 1e-6 or abs(h - round(h)) > 1e-6:
        raise DataError(f"target_scale: {scale:g} x {W}x{H} pixels is not a whole number of pixels")
    w, h = round(w), round(h)
    valid = (np.isfinite(depth) & (depth > 0) & (depth <= max_depth)).astype(np.float32)
    known = np.where(valid > 0, depth, 0).astype(np.float32)
    out_i, out_d, out_s = [], [], []
    for k in range(m):
        out_i.append(cv2.resize(images[k], (w, h), interpolation=cv2.INTER_AREA))
        frac = cv2.resize(valid[k], (w, h), interpolation=cv2.INTER_AREA)
        mean = cv2.resize(known[k], (w, h), interpolation=cv2.INTER_AREA) / np.maximum(frac, 1e-6)
        out_d.append(np.where(frac > 1 - 1e-5, mean, 0).astype(np.float32))  # 1e-5: float32 area weights
        out_s.append(cv2.resize(sky[k].astype(np.float32), (w, h), interpolation=cv2.INTER_AREA))
    return [c.resized(w, h) for c in cams], np.stack(out_i), np.stack(out_d), np.stack(out_s)


def can_flip(cameras: list[Camera], pc_range) -> bool:
    """Flips need undistorted pinhole cameras and an occupancy y range symmetric about 0."""
    return (all(c.model == "pinhole" and c.distortion is None for c in cameras)
            and abs(pc_range[1] + pc_range[4]) < 1e-6)


# ------------------------------------------------------------------------------------------- occupancy labels


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """Binary dilation by a (2k+1)^3 cube (k steps of the 26-neighbourhood), separable along the axes."""
    for ax in range(mask.ndim):
        out = mask.copy()
        for s in range(1, k + 1):
            lo = [slice(None)] * mask.ndim
            hi = [slice(None)] * mask.ndim
            lo[ax], hi[ax] = slice(None, -s), slice(s, None)
            out[tuple(lo)] |= mask[tuple(hi)]
            out[tuple(hi)] |= mask[tuple(lo)]
        mask = out
    return mask


def surface_hits(shape: tuple[int, int, int], pc_range, voxel_size: float, cameras: list[Camera],
                 depth: np.ndarray, valid: np.ndarray, stride: int = 1, eps: float = 2e-3) -> np.ndarray:
    """[L_z, L_y, L_x] bool: voxels holding the ego point X = cam_to_ego @ [d inv(K) [u, v, 1], 1] of some
    valid input pixel (u, v) with depth d (every ``stride``-th pixel per row and column). X is pushed ``eps``
    metres further along its ray, so a hit on a solid's face that lies on a voxel boundary lands in the voxel
    behind it (the solid's side). depth / valid [N, H, W]. Pinhole cameras only (distortion allowed)."""
    lz, ly, lx = shape
    lo = np.asarray(pc_range[:3], np.float64)
    hit = np.zeros(lz * ly * lx, bool)
    for cam, d, m in zip(cameras, depth, valid):
        if cam.model != "pinhole":
            raise DataError(f"camera {cam.name!r}: model: surface occupancy labels need pinhole depth maps")
        m = m[::stride, ::stride]
        vv, uu = np.nonzero(m)
        if not len(vv):
            continue
        vv, uu = vv * stride, uu * stride
        z = d[vv, uu].astype(np.float64)
        if cam.distortion is None:      # ray = R inv(K) [u, v, 1] (camera z = 1), X = c + z ray, one axis at a time
            A = cam.rotation @ np.linalg.inv(cam.K)
            ze = z + eps                                                # >= eps metres further along the ray
            idx = np.zeros(len(vv), np.int64)
            ok = np.ones(len(vv), bool)
            for j, (size, mul) in enumerate(((lx, 1), (ly, lx), (lz, lx * ly))):
                x = cam.position[j] - lo[j] + ze * (A[j, 0] * uu + A[j, 1] * vv + A[j, 2])
                k = np.floor(x / voxel_size).astype(np.int64)
                ok &= (k >= 0) & (k < size)
                idx += k * mul
            hit[idx[ok]] = True
            continue
        _, ray = cam.pixel_rays(np.stack([uu, vv], -1).astype(np.float64))   # unit rays, ego frame
        p = cam.position + ray * (z / (ray @ cam.rotation[:, 2]) + eps)[:, None]
        ijk = np.floor((p - lo) / voxel_size).astype(np.int64)         # (x, y, z)
        ok = ((ijk >= 0) & (ijk < (lx, ly, lz))).all(axis=1)
        ijk = ijk[ok]
        hit[(ijk[:, 2] * ly + ijk[:, 1]) * lx + ijk[:, 0]] = True
    return hit.reshape(shape)


def surface_labels(occupied: np.ndarray, pc_range, voxel_size: float, cameras: list[Camera], depth: np.ndarray,
                   valid: np.ndarray, dilation: int = 0, stride: int = 1,
                   keep: np.ndarray | None = None) -> np.ndarray:
    """Visibility-carved occupancy labels [L_z, L_y, L_x] uint8 from the solid grid occupied [L_z, L_y, L_x]:
    1 = occupied voxel holding a point an input camera sees (``surface_hits``; with ``dilation`` k also occupied
    voxels within k voxels of one, 26-neighbourhood), OCC_UNKNOWN = 255 = occupied voxel no camera sees (inside
    a building, behind a facade: the network cannot know it, so no loss), 0 = free (the generator's exact
    geometry, wherever it is; the space in front of every hit is free). depth / valid [N, H, W] as in the item.
    keep [L_z, L_y, L_x] bool: occupied voxels that are 1 whether a camera sees them or not (the ego car)."""
    hit = surface_hits(occupied.shape, pc_range, voxel_size, cameras, depth, valid, stride)
    if dilation:
        hit = _dilate(hit, dilation)
    out = np.zeros(occupied.shape, np.uint8)
    out[occupied] = OCC_UNKNOWN
    out[occupied & hit] = 1
    if keep is not None:
        out[occupied & keep] = 1
    return out


# ------------------------------------------------------------------------------------------------- reading


def _read_mask(path: Path, what: str) -> np.ndarray:
    return read_image(path, what, channels=1)[..., 0] > 0.5


def _read_depth(path: Path, what: str) -> np.ndarray:
    d = read_image(path, what, channels=1, scale=False)[..., 0]
    if np.isnan(d).any():
        raise DataError(f"{what}: depth {path} contains NaN")
    return d.astype(np.float32)


def _view_arrays(root: Path, cams: list[dict[str, Any]], where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """images [M, H, W, 3], depth [M, H, W] (0 = unknown/sky), sky [M, H, W] bool of camera entries."""
    imgs, depths, skies = [], [], []
    for c in cams:
        name = c.get("name", "?")
        for key in ("image", "depth", "sky"):
            if not isinstance(c.get(key), str):
                raise DataError(f"{where}: camera {name!r}: {key} file missing from the entry")
        img = read_image(root / c["image"], f"{where}: camera {name!r}: image")
        if img.shape[:2] != (c["height"], c["width"]):
            raise DataError(f"{where}: camera {name!r}: image is {img.shape[1]}x{img.shape[0]}, "
                            f"declared {c['width']}x{c['height']}")
        imgs.append(img)
        depths.append(_read_depth(root / c["depth"], f"{where}: camera {name!r}: depth"))
        skies.append(_read_mask(root / c["sky"], f"{where}: camera {name!r}: sky"))
    return np.stack(imgs), np.stack(depths), np.stack(skies)


def _chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))


def list_scenes(root: Path) -> list[Path]:
    """Complete scene folders (scene_XXXXXX with rig.json, targets.json and occupancy.npz), sorted."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"data: {root} is not a folder")
    out = [p for p in sorted(root.glob("scene_*"))
           if p.is_dir() and all((p / f).is_file() for f in ("rig.json", "targets.json", "occupancy.npz"))]
    if not out:
        raise DataError(f"data: no complete scene_* folders in {root}")
    return out


class SceneDataset(torch.utils.data.Dataset):
    """Synthetic scenes (``xyzcyl data synth`` output). ``model_cfg`` (a ModelConfig) adds lifting inputs.
    ``root``: one data set folder, or several (their scenes in the order given, e.g. rigs of different camera
    counts mixed in one training run); each folder is checked like a single one."""

    def __init__(self, root: str | Path | list[str | Path] | tuple[str | Path, ...],
                 cfg: DatasetConfig = DatasetConfig(), model_cfg=None):
        self.roots = [Path(r) for r in root] if isinstance(root, (list, tuple)) else [Path(root)]
        if not self.roots:
            raise DataError("data: no data set folder given")
        self.cfg = cfg
        per_root = [list_scenes(r) for r in self.roots]
        self.scenes = [scene for scenes in per_root for scene in scenes]
        self.epoch = 0
        self.model_cfg = model_cfg
        self._lifting_params = None
        if model_cfg is not None:
            from xyzcyl.runtime.lifting import LiftingParams

            self._lifting_params = LiftingParams.from_config_dict(model_cfg.to_dict())
            grid = model_cfg.grid
            if abs(grid.voxel_size - cfg.voxel_size) > 1e-9:
                raise ConfigError(f"voxel_size: data {cfg.voxel_size} differs from the model grid {grid.voxel_size}")
        elif cfg.lidar_input:
            raise ConfigError("lidar_input: needs the model config (the depth input's size is the model's)")
        for scenes in per_root:                                 # fail early, not at the first validation
            self._check_first(scenes[0])

    def _check_first(self, scene: Path) -> None:
        """The targets' settings and the voxel grid this config needs are in ``scene`` (a folder's first)."""
        cfg = self.cfg
        first = json.loads((scene / "targets.json").read_text()).get("settings", {})
        for name in cfg.settings:
            if name not in first:
                raise DataError(f"{scene / 'targets.json'}: setting: no {name!r} targets "
                                f"(have {sorted(first)})")
        with np.load(scene / "occupancy.npz") as z:             # reads the zip directory only
            if f"semantic_{cfg.voxel_tag}" not in z.files:
                raise DataError(f"{scene / 'occupancy.npz'}: voxel_size: no {cfg.voxel_size:g} m grid "
                                f"(have {sorted(k[9:] for k in z.files if k.startswith('semantic_'))})")

    def __len__(self) -> int:
        return len(self.scenes)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _occupancy(self, folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, ...]]:
        """(occupied [L_z, L_y, L_x] bool, ego [L_z, L_y, L_x] bool (the ego car's voxels), bev [L_y, L_x] bool,
        range) from occupancy.npz."""
        z = np.load(folder / "occupancy.npz")
        key = f"semantic_{self.cfg.voxel_tag}"
        if key not in z:
            raise DataError(f"{folder / 'occupancy.npz'}: voxel_size: no grid {key!r} "
                            f"(have {sorted(k for k in z.files if k.startswith('semantic_'))})")
        rng_m = tuple(float(v) for v in z["range"])
        want = self.cfg.pc_range or (self.model_cfg.grid.pc_range if self.model_cfg is not None else None)
        if want is not None and not np.allclose(rng_m, want, atol=1e-6):
            raise DataError(f"{folder / 'occupancy.npz'}: pc_range: file has {rng_m}, expected {tuple(want)}")
        sem = z[key]                                           # [X, Y, Z] uint8, index 0 at the range minimum
        occ = sem.transpose(2, 1, 0) > 0                       # -> [L_z, L_y, L_x]
        ego = sem.transpose(2, 1, 0) == EGO
        bev = np.isin(sem, GROUND_CLASSES + (0,), invert=True).any(axis=2).T   # [L_y, L_x]
        return np.ascontiguousarray(occ), np.ascontiguousarray(ego), np.ascontiguousarray(bev), rng_m

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self.item(index, self.epoch)

    def item(self, index: int, epoch: int) -> dict[str, Any]:
        """Scene ``index`` as drawn in ``epoch`` (thread-safe: no shared state is changed)."""
        cfg = self.cfg
        folder = self.scenes[index]
        rng = np.random.default_rng((cfg.seed, int(epoch), index))
        rig = load_rig(folder / "rig.json", check_images=False)
        rig_doc = json.loads((folder / "rig.json").read_text())
        tdoc = json.loads((folder / "targets.json").read_text())
        tcams = []
        for name in cfg.settings:
            setting = tdoc.get("settings", {}).get(name)
            if setting is None:
                raise DataError(f"{folder / 'targets.json'}: settings: no {name!r} targets in this data set")
            tcams += [c for c in setting["cameras"] if not (cfg.skip_occluded and c.get("occluded", False))]
        if not tcams:
            raise DataError(f"{folder / 'targets.json'}: {cfg.setting}: no usable target camera")
        pick = np.sort(rng.choice(len(tcams), size=min(cfg.num_targets, len(tcams)), replace=False))
        tcams = [tcams[i] for i in pick]
        trig = Rig.from_dict({"cameras": tcams})

        img, depth, sky = _view_arrays(folder, rig_doc["cameras"], f"{folder.name}/rig.json")
        timg, tdepth, tsky = _view_arrays(folder, tcams, f"{folder.name}/targets.json")
        if cfg.brightness or cfg.contrast or cfg.saturation:
            both = colour_jitter(np.concatenate([img, timg]), rng, cfg.brightness, cfg.contrast, cfg.saturation)
            img, timg = both[:len(img)], both[len(img):]
        if cfg.camera_aug:      # inputs only, after the jitter; a child stream leaves rng's draws unchanged
            img = camera_augment(img, rng.spawn(1)[0], cfg)
        if cfg.camera_drop:     # after the camera effects' child (theirs stay the same), its own child stream
            keep = draw_camera_drop(list(rig.cameras), rng.spawn(1)[0], cfg.camera_drop, cfg.camera_drop_max)
            if len(keep) < len(rig.cameras):
                img, depth, sky = img[keep], depth[keep], sky[keep]
                rig = Rig(cameras=tuple(rig.cameras[i] for i in keep), root=rig.root, extra=rig.extra)
        if cfg.lens_zoom:       # after the drop's child, its own child stream
            zcams, img, depth, sky = lens_zoom_views(list(rig.cameras), img, depth, sky, rng.spawn(1)[0],
                                                     cfg.lens_zoom, cfg.lens_zoom_max)
            rig = Rig(cameras=tuple(zcams), root=rig.root, extra=rig.extra)
        occ, ego, bev, rng_m = self._occupancy(folder)
        if cfg.occupancy_labels != "solid":   # before the flip: unflipped cameras and depths, flipped below
            seen = np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_depth) & ~sky
            occ = surface_labels(occ, rng_m, cfg.voxel_size, list(rig.cameras), depth, seen, cfg.surface_dilation,
                                 keep=ego if cfg.occupancy_labels == "surface+ego" else None)

        in_cams, t_cams = list(rig.cameras), list(trig.cameras)
        flipped = bool(cfg.flip_prob > 0 and rng.random() < cfg.flip_prob and can_flip(in_cams + t_cams, rng_m))
        if flipped:
            order = mirror_order(len(in_cams))
            in_cams = [mirror_camera_y(in_cams[k]) for k in order]
            img, depth, sky = (a[order][:, :, ::-1] for a in (img, depth, sky))
            t_cams = [mirror_camera_y(c) for c in t_cams]
            timg, tdepth, tsky = (a[:, :, ::-1] for a in (timg, tdepth, tsky))
            occ, bev = occ[:, ::-1, :], bev[::-1, :]
            rig = Rig(cameras=tuple(in_cams), root=rig.root, extra=rig.extra)

        if cfg.target_scale != 1.0:
            t_cams, timg, tdepth, tsky = downscale_views(t_cams, timg, tdepth, tsky, cfg.target_scale, cfg.max_depth)
        dvalid = np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_depth)
        tvalid = np.isfinite(tdepth) & (tdepth > 0) & (tdepth <= cfg.max_depth)
        occ_t = torch.from_numpy(np.ascontiguousarray(occ).astype(np.int64))
        item: dict[str, Any] = {
            "scene": folder.name,
            "flipped": flipped,
            "rig": rig,
            "images": _chw(img),
            "depth": torch.from_numpy(np.ascontiguousarray(np.where(dvalid, depth, 0)[:, None], np.float32)),
            "depth_valid": torch.from_numpy(np.ascontiguousarray(dvalid[:, None])),
            "sky": torch.from_numpy(np.ascontiguousarray(sky[:, None], np.float32)),
            "targets": {
                "images": _chw(timg),
                "depth": torch.from_numpy(np.ascontiguousarray(np.where(tvalid, tdepth, 0), np.float32)),
                "depth_valid": torch.from_numpy(np.ascontiguousarray(tvalid)),
                "sky": torch.from_numpy(np.ascontiguousarray(tsky, np.float32)),
                "K": np.stack([c.K for c in t_cams]),
                "cam_to_ego": np.stack([c.cam_to_ego for c in t_cams]),
                "names": [c.name for c in t_cams],
                "width": int(t_cams[0].width), "height": int(t_cams[0].height),
            },
            "occupancy": occ_t,
            "bev": torch.from_numpy(np.ascontiguousarray(bev).astype(np.int64)),
        }
        if cfg.lidar_input:     # after the flip (the sweep follows the final cameras), its own child stream
            b = self.model_cfg.backbone
            lid = simulate_lidar(np.where(dvalid, depth, 0), sky, (b.input_height // b.feature_stride,
                                 b.input_width // b.feature_stride), rng.spawn(1)[0], cfg.lidar_input)
            if lid is not None:
                item["lidar_depth"], item["lidar_surface"] = (torch.from_numpy(np.ascontiguousarray(a)) for a in lid)
        if self._lifting_params is not None:
            add_lifting(item, self._lifting_params)
        return item


LIDAR_TOP_ROWS = (0.25, 0.5)   # the top beam's row, as a fraction of the height: rows above get no point
LIDAR_KEEP = (0.5, 1.0)        # fraction of the cells below it that hold a point (sparse rings, dark surfaces)


def simulate_lidar(depth: np.ndarray, sky: np.ndarray, size: tuple[int, int], rng: np.random.Generator,
                   prob: float) -> tuple[np.ndarray, np.ndarray] | None:
    """A simulated LiDAR sweep at the network's depth size, for training the depth input (``lidar_input``).

    depth [N, H, W] metres (0 = invalid), sky [N, H, W] bool of the input cameras; size (h, w). With probability
    ``prob`` (else None): (lidar [N, h, w] float32 metres, 0 = no point; surface [N, h, w] bool = not sky). Per
    camera: the nearest-sampled true depth (runtime.inference.resize_nearest, the depth input's rule) at cells
    with 1 m <= depth <= 80 m (runtime.lidar's range), below a top-beam row drawn from LIDAR_TOP_ROWS (a
    real sweep covers the road and the lower part of buildings, not their tops), each kept with a probability
    drawn from LIDAR_KEEP."""
    from xyzcyl.runtime.inference import resize_nearest
    from xyzcyl.runtime.lidar import MAX_DEPTH, MIN_DEPTH

    if not rng.random() < prob:
        return None
    h, w = size
    n = depth.shape[0]
    lidar = np.zeros((n, h, w), np.float32)
    surface = np.zeros((n, h, w), bool)
    rows = np.arange(h)[:, None]
    for k, g in enumerate(rng.spawn(n)):
        d = resize_nearest(depth[k].astype(np.float32), h, w)
        surface[k] = ~resize_nearest(sky[k], h, w).astype(bool)
        top = g.uniform(*LIDAR_TOP_ROWS) * h
        keep = g.random((h, w)) < g.uniform(*LIDAR_KEEP)
        ok = surface[k] & (d >= MIN_DEPTH) & (d <= MAX_DEPTH) & (rows >= top) & keep
        lidar[k][ok] = d[ok]
    return lidar, surface


def add_lifting(item: dict[str, Any], params) -> None:
    """Attach the rig's lifting inputs and the targets' background grids (float32 tensors) to ``item``."""
    from xyzcyl.runtime.lifting import background_grid, build_lifting_inputs

    lift = build_lifting_inputs(item["rig"], params)
    item["lifting"] = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in lift.items()}
    t = item.get("targets")
    if t is not None:
        spec = params.spec(item["rig"], "volume")
        grids = [background_grid(spec, K, T, t["width"], t["height"]) for K, T in zip(t["K"], t["cam_to_ego"])]
        t["background_grid"] = torch.from_numpy(np.stack(grids))


def collate_scenes(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """DataLoader collate: keep scenes as a list (each scene has its own rig and camera count)."""
    return list(items)


# ------------------------------------------------------------------------------------------ real rig folders


def load_rig_folder(folder: str | Path, model_cfg=None) -> dict[str, Any]:
    """A real rig folder (rig.json + images, optional per-camera depth; no targets) for inference smoke tests.

    Returns {"rig", "images" [N, 3, H, W] float32 0..1, "depth" [N, 1, H, W] float32 or None,
    "depth_mask" [N] float32 (1 = that camera has depth), "scene"} (+ "lifting" with ``model_cfg``).
    Images of different sizes are kept as a list of [3, H_n, W_n] tensors instead of one stacked tensor."""
    folder = Path(folder)
    path = folder / "rig.json" if folder.is_dir() else folder
    rig = load_rig(path)
    imgs = [torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1))) for a in rig.load_images()]
    same = len({tuple(i.shape) for i in imgs}) == 1
    depths = rig.load_depths()
    item: dict[str, Any] = {"scene": path.parent.name, "rig": rig,
                            "images": torch.stack(imgs) if same else imgs, "depth": None,
                            "depth_mask": torch.tensor([d is not None for d in depths], dtype=torch.float32)}
    if same and any(d is not None for d in depths):
        h, w = imgs[0].shape[1:]
        item["depth"] = torch.from_numpy(np.stack([d if d is not None else np.zeros((h, w), np.float32)
                                                   for d in depths])[:, None].astype(np.float32))
    if model_cfg is not None:
        from xyzcyl.runtime.lifting import LiftingParams

        add_lifting(item, LiftingParams.from_config_dict(model_cfg.to_dict()))
    return item
