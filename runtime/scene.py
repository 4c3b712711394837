"""A reconstructed scene: Gaussians in the ego frame, the background panorama, metadata; its folder on disk, and
rendering a view of it. docs/inference.md states the folder format and the background decision.

    scene = Scene.load("/tmp/scene")
    rgb, depth, alpha = render_view(scene, Camera(K=K, cam_to_ego=cam_to_ego, width=1600, height=900))

Folder (written atomically: a temporary sibling folder renamed into place):
    scene.ply        standard 3DGS PLY (x y z nx ny nz f_dc_* [f_rest_*] opacity scale_* rot_*), ego frame
    background.exr   the sky/background panorama on the volume cylinder, float32 RGB (linear 0..1)
    background.png   the same as an 8-bit preview
    scene.json       format, rig (calibration only), model, counts, timings, bbox, background cylinder spec

Background panorama: column c covers the cylinder's normalised column u = 2s - 1 in [-1 + 2c/W, -1 + 2(c+1)/W]
(theta wraps); row r covers the normalised row v = 2p - 1 in [v0 + r dv, v0 + (r+1) dv], dv = (v1 - v0)/H, with
(v0, v1) = ``v_range`` reaching beyond the cylinder's top and bottom (v = -1, 1) by a few rows. A view ray is
intersected with the infinite cylinder of radius R_u (runtime.cylinder.ray_cylinder_intersection, paper_v=False,
the same rule as runtime.lifting.background_grid) and the panorama sampled bilinearly there, rows clamped
(rays that leave through the caps read the outermost row, as ZNet_bg's border padding does).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
from xyzcyl.common.files import atomic_folder
from xyzcyl.common.wire import ActorEdit, ViewError

from .actors import Actors, ActorsError
from .camera import Camera, rig_camera
from .cameralayers import CAMERA_LAYER_DEG, CAMERA_LAYER_M, CameraLayerError, CameraLayers
from .cylinder import CylinderSpec
from .detail import DetailError, OwnViews
from .egobody import EgoBody
from .errors import FieldError
from .files import read_json_doc
from .numba_cache import njit
from .render import Gaussians, render
from .rig import Rig
from .tiles import HORIZON_M, TileError, Tiles, in_tile_order
from .viewpoints import ViewpointError, Viewpoints

SCENE_FORMAT = "xyzcyl-scene"
SCENE_VERSION = 1
PLY_NAME, EXR_NAME, PNG_NAME, JSON_NAME = "scene.ply", "background.exr", "background.png", "scene.json"
EGO_BODY_DIR = "ego_body"           # a drive's ego body masks, one PNG per camera (runtime.egobody)
ACTORS_NAME = "actors.npz"         # runtime.actors.Actors (a drive's moving objects)
OWN_VIEWS_NAME = "own_views.npz"   # runtime.detail.OwnViews (scenes with the detail layer)
KEYFRAME_OF_NAME = "keyframe_of.npy"   # Scene.keyframe_of (drives of several keyframes)
EXPOSURE_CONE_DEG = 30.0           # a view within this of an input camera's axis gets its exposure (runtime.exposure)
ACTOR_REACH_M = 1000.0             # an edited actor is placed within this of the drive's path (a view's actors)
LAYER_COVER = 0.1                  # a drive view's layers behind the first: a 16x16 tile where those in front left no
#                                    pixel more than this of its light is theirs alone, renormalised (render's cover:
#                                    a detail cell of opacity 0.95 leaves each pixel ~5 % of its light, so the layers
#                                    behind were drawn over nearly the whole image for 5 %; PandaSet drive -0.01 dB,
#                                    synthetic -0.03 dB, views 1.24x faster: docs/results.md)
PRIMARY_SLACK_M = 0.25             # keyframes whose cameras stood within this of the nearest one's: the view's time
#                                    picks among them (a still ego's keyframes stand in one place)
OWN_POSE_TOL = (1e-3, 1e-4)        # (metres, rotation matrix entries): a view this close to an input camera's pose is
#                                    that camera's own view (a gRPC pose composed in float32 lands within 1e-5)


class SceneError(FieldError):
    """A scene folder is missing, incomplete or invalid: ``field`` "scene" (the folder or one of its files as a
    whole, the message naming the file), or the scene.json / PLY field at fault with ``where`` naming the file
    ("scene '/s/scene.json'", "scene PLY '/s/scene.ply'") and, for a rig camera, the camera."""


# ------------------------------------------------------------------------------------------- background


def bake_grid(height: int, width: int, margin: int, radius: int) -> tuple[np.ndarray, tuple[float, float], tuple]:
    """Sampling grid [height + 2 margin, width + 2 margin, 2] of the cylinder itself as a "view" for ZNet_bg:
    (u, v) = (2s - 1, 2p - 1) at height x width pixel centres, ``margin`` extra rows beyond the top and bottom
    (v outside [-1, 1]: ZNet's border padding reads the cap row there) and ``margin`` extra columns on each side
    with u wrapped (so the view-space 3x3 convolutions see theta's neighbours across the seam).

    Returns (grid, v_range, crop): crop = (row slice, column slice) of the synthesised image that is kept:
    all columns of the cylinder and the rows at least ``radius`` (the synthesis' receptive radius) away from the
    grid's outer edge, so no kept row saw the convolutions' zero padding; v_range = the kept rows' outer edges."""
    if margin <= radius:
        raise ValueError(f"margin: must exceed the receptive radius {radius}, got {margin}")
    r = np.arange(-margin, height + margin, dtype=np.float64)
    c = np.arange(-margin, width + margin, dtype=np.float64)
    v = -1.0 + (r + 0.5) * 2.0 / height
    u = -1.0 + (c + 0.5) * 2.0 / width
    u = np.mod(u + 1.0, 2.0) - 1.0
    grid = np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).astype(np.float32)   # [rows, cols, 2]
    keep = margin - radius
    v_range = (-1.0 - keep * 2.0 / height, 1.0 + keep * 2.0 / height)
    crop = (slice(radius, height + 2 * margin - radius), slice(margin, margin + width))
    return grid, v_range, crop


@dataclass(frozen=True, eq=False)
class Background:
    """The background (sky and far scene) baked into a panorama on the volume cylinder (see the module doc)."""

    image: np.ndarray                 # [H, W, 3] float32 linear RGB, 0..1
    cylinder: CylinderSpec            # centre, radius R_u and z range of the cylinder (ego frame)
    v_range: tuple[float, float]      # normalised rows (2p - 1) of the panorama's top and bottom edges
    dome: np.ndarray = field(init=False, repr=False)    # [4, W, 3] sky_dome(image): beyond the top and bottom

    def __post_init__(self) -> None:
        img = np.ascontiguousarray(self.image, np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise SceneError("image", f"must be [H, W, 3], got {list(img.shape)}", "background")
        if not np.all(np.isfinite(img)):
            raise SceneError("image", "has non-finite values", "background")
        object.__setattr__(self, "image", img)
        v0, v1 = (float(x) for x in self.v_range)
        if not (math.isfinite(v0) and math.isfinite(v1) and v1 > v0):
            raise SceneError("v_range", f"must be increasing finite numbers, got {self.v_range}", "background")
        object.__setattr__(self, "v_range", (v0, v1))
        object.__setattr__(self, "dome", sky_dome(img))

    def to_dict(self) -> dict[str, Any]:
        c = self.cylinder
        return {"file": EXR_NAME, "preview": PNG_NAME, "height": int(self.image.shape[0]),
                "width": int(self.image.shape[1]), "v_range": list(self.v_range),
                "cylinder": {"centre": c.centre.tolist(), "radius": c.radius, "z_min": c.z_min, "z_max": c.z_max,
                             "height": c.height, "width": c.width},
                "projection": "column c: u = 2s-1 in [-1 + 2c/W, -1 + 2(c+1)/W] (theta wraps); row r: v = 2p-1 in "
                              "v_range split into H rows; a view ray is intersected with the infinite cylinder of "
                              "radius R_u about the vertical axis through centre, u = -theta/pi, "
                              "v = -2 (z - centre_z) / (z_max - z_min); rows clamped"}

    def render(self, camera, step: int = 4) -> np.ndarray:
        """[H, W, 3] float32: the panorama seen by a runtime.camera.Camera (pinhole, with or without a lens, or
        equirectangular), through the same rays the renderer draws: a lens camera's are Camera.pixel_rays (the
        lens's exact inverse); pixels no ray reaches (outside a fisheye / f-theta image circle, beyond an opencv
        lens's fold) are black.

        ``step`` > 1: the rays are traced at 1/step of the resolution (the camera resized with the pixel-centre
        convention of Camera.resized, which scales an f-theta lens too) and the result resized back bilinearly
        (cv2.INTER_LINEAR, the same convention): the panorama is smooth at view scale (a 4x4 texel of the cylinder
        spans several view pixels at the usual sizes), and the trace costs ~1/step^2 (docs/inference.md gives the
        measured difference). The pixels outside an image circle are then set black again at full resolution
        (the resize blurs the circle's rim over a few pixels inside it)."""
        W, H = camera.width, camera.height
        if step > 1 and min(W, H) >= 4 * step:
            import cv2

            from .render.lensmap import image_circle

            w, h = math.ceil(W / step), math.ceil(H / step)
            small = camera.resized(w, h)
            img = cv2.resize(self._trace(small), (W, H), interpolation=cv2.INTER_LINEAR)
            inside = image_circle(camera)
            if inside is not None:
                img[~inside] = 0.0
            return img
        return self._trace(camera)

    def _trace(self, camera) -> np.ndarray:
        out = np.empty((camera.height, camera.width, 3), np.float32)
        c = self.cylinder
        T = np.ascontiguousarray(camera.cam_to_ego, np.float64)
        args = (self.image, self.dome, self.v_range[0], self.v_range[1], float(c.centre[0]), float(c.centre[1]),
                float(c.centre[2]), float(c.radius), float(c.Z_u))
        if camera.is_equirect or camera.distortion is not None:
            d = np.ascontiguousarray(camera.pixel_rays()[1], np.float64)      # NaN where no ray: black
            _bg_dirs(*args, T, d, out)
        else:
            K = camera.K
            _bg_pinhole(*args, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), T, out)
        return out


DOME_BAND = 0.1        # sky_dome: the top (bottom) tenth of the panorama's rows is the sky (ground) it continues
DOME_SIGMA = 1.0 / 12  # ... blurred around the horizon with a Gaussian of a twelfth of the circle (30 degrees)
DOME_SMOOTH = 0.25     # _sample: a quarter of the way to the zenith (nadir), the blurred colour has taken over


def sky_dome(pano: np.ndarray) -> np.ndarray:
    """[4, W, 3] float32 of a panorama [H, W, 3]: how the background continues above its top edge and below its
    bottom edge, where the cylinder's rows end (a wide lens sees there; clamping the edge rows drew vertical streaks
    converging on the zenith): rows 0 / 1 the mean of the top / bottom DOME_BAND of rows per column, blurred around
    the circle (DOME_SIGMA); rows 2 / 3 the zenith / nadir colour, the median of those columns (what the cameras saw
    highest / lowest), the same in every column. _sample blends from the edge row to the blurred row to the zenith
    (nadir) with the ray's elevation."""
    pano = np.asarray(pano, np.float64)
    H, W = pano.shape[:2]
    band = max(1, int(round(DOME_BAND * H)))
    f = np.fft.rfftfreq(W)                                       # cycles per column
    kernel = np.exp(-2.0 * (np.pi * DOME_SIGMA * W * f) ** 2)[:, None]    # the circular Gaussian's spectrum
    edges = (pano[:band].mean(axis=0), pano[H - band:].mean(axis=0))        # [W, 3] each
    rows = [np.fft.irfft(np.fft.rfft(e, axis=0) * kernel, n=W, axis=0) for e in edges]
    rows += [np.broadcast_to(np.median(e, axis=0), (W, 3)) for e in edges]
    return np.ascontiguousarray(np.clip(np.stack(rows), 0.0, None), np.float32)


@njit(cache=True, inline="always")
def _smoothstep(x):
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@njit(cache=True, inline="always")
def _sample(pano, dome, v0, v1, ox, oy, oz, dx, dy, dz, cx, cy, cz, R, Zu, out, y, x):
    """The panorama along the ray (ox, oy, oz) + t (dx, dy, dz) (ego frame) into out[y, x]: the cylinder's texel
    where the ray leaves it; beyond the panorama's top (bottom) rows, the dome (sky_dome): the edge row blended into
    the blurred edge colour and on to the zenith (nadir) as the ray climbs (falls) from the edge's elevation to
    90 degrees; a vertical ray, or one that never meets the cylinder, the zenith (nadir) colour."""
    H, W = pano.shape[0], pano.shape[1]
    px, py = ox - cx, oy - cy
    a = dx * dx + dy * dy
    b = px * dx + py * dy
    c = px * px + py * py - R * R
    disc = b * b - a * c
    t = -1.0
    if a > 0.0 and disc >= 0.0:
        t = (-b + math.sqrt(disc)) / a
    if t < 0.0:
        cap = 2 if dz >= 0.0 else 3
        for k in range(3):
            out[y, x, k] = dome[cap, 0, k]
        return
    u = -math.atan2(py + t * dy, px + t * dx) / math.pi
    v = -2.0 * (oz + t * dz - cz) / Zu
    col = (u + 1.0) * 0.5 * W - 0.5
    row = (v - v0) / (v1 - v0) * H - 0.5
    top = row < 0.0
    beyond = top or row > H - 1.0
    row = min(max(row, 0.0), H - 1.0)
    r0 = min(math.floor(row), H - 1)
    r1 = min(r0 + 1, H - 1)
    fr = row - r0
    cf = math.floor(col)
    fc = col - cf
    c0 = int(cf) % W
    c1 = (c0 + 1) % W
    w_blur, w_cap, side = 0.0, 0.0, 0
    if beyond:
        # the elevation of the ray and of the edge row's centre seen along it (its horizontal distance t sqrt(a))
        hd = t * math.sqrt(a)
        v_edge = v0 + (v1 - v0) * 0.5 / H if top else v1 - (v1 - v0) * 0.5 / H
        e_edge = math.atan2(cz - 0.5 * v_edge * Zu - oz, hd)
        e_ray = math.atan2(dz, math.sqrt(a))
        half = 0.5 * math.pi
        s = (e_ray - e_edge) / max(half - e_edge, 1e-6) if top else (e_edge - e_ray) / max(e_edge + half, 1e-6)
        w_blur = _smoothstep(s / DOME_SMOOTH)
        w_cap = _smoothstep(s)
        side = 0 if top else 1
    for k in range(3):
        hi = pano[r0, c0, k] * (1.0 - fc) + pano[r0, c1, k] * fc
        lo = pano[r1, c0, k] * (1.0 - fc) + pano[r1, c1, k] * fc
        val = hi * (1.0 - fr) + lo * fr
        if beyond:
            blur = dome[side, c0, k] * (1.0 - fc) + dome[side, c1, k] * fc
            val = (val * (1.0 - w_blur) + blur * w_blur) * (1.0 - w_cap) + dome[2 + side, 0, k] * w_cap
        out[y, x, k] = val


@njit(parallel=True, cache=True, nogil=True)
def _bg_pinhole(pano, dome, v0, v1, cx, cy, cz, R, Zu, fx, fy, ppx, ppy, T, out):
    H, W = out.shape[0], out.shape[1]
    for y in numba.prange(H):
        for x in range(W):
            a, b = (x - ppx) / fx, (y - ppy) / fy
            dx = T[0, 0] * a + T[0, 1] * b + T[0, 2]
            dy = T[1, 0] * a + T[1, 1] * b + T[1, 2]
            dz = T[2, 0] * a + T[2, 1] * b + T[2, 2]
            _sample(pano, dome, v0, v1, T[0, 3], T[1, 3], T[2, 3], dx, dy, dz, cx, cy, cz, R, Zu, out, y, x)


@njit(parallel=True, cache=True, nogil=True)
def _bg_dirs(pano, dome, v0, v1, cx, cy, cz, R, Zu, T, d, out):
    H, W = out.shape[0], out.shape[1]
    for y in numba.prange(H):
        for x in range(W):
            if not (np.isfinite(d[y, x, 0]) and np.isfinite(d[y, x, 1]) and np.isfinite(d[y, x, 2])):
                for k in range(3):
                    out[y, x, k] = 0.0          # no ray (outside a lens's image circle)
                continue
            _sample(pano, dome, v0, v1, T[0, 3], T[1, 3], T[2, 3], d[y, x, 0], d[y, x, 1], d[y, x, 2], cx, cy, cz,
                    R, Zu, out, y, x)


@njit(parallel=True, cache=True, nogil=True)
def _scale_rgb(rgb, gain):
    """rgb [H, W, 3] float32 *= gain [3] float32, in place, rows in parallel (numpy's broadcast over the last axis of
    3 took 5-8 ms of a 1920x1080 view; the same float32 products)."""
    for y in numba.prange(rgb.shape[0]):
        for x in range(rgb.shape[1]):
            for k in range(3):
                rgb[y, x, k] *= gain[k]


# ------------------------------------------------------------------------------------------- scene


def _calibration_rig(rig: Rig) -> Rig:
    """The rig without its image/depth file names (a scene keeps the calibration, not the inputs)."""
    return Rig(cameras=tuple(c.replace(image=None, depth=None) for c in rig.cameras), extra=rig.extra)


@dataclass(eq=False)
class Scene:
    """Gaussians (ego frame), the background panorama (or None) and metadata of one reconstruction."""

    gaussians: Gaussians
    background: Background | None
    rig: Rig
    model: dict[str, Any] = field(default_factory=dict)      # name, version, model_json_sha256
    counts: dict[str, int] = field(default_factory=dict)     # volume, pixel, pruned, total, voxels
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    lifting_cached: bool = False
    app_plane: np.ndarray | None = field(default=None, repr=False)   # in memory only (not saved)
    created: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).replace(microsecond=0)
                         .isoformat())
    own_views: OwnViews | None = field(default=None, repr=False)    # the input cameras' own views (detail layer)
    drive: dict[str, Any] | None = None     # a drive's frames, keyframes, times and ego poses (runtime.drive)
    actors: Actors | None = field(default=None, repr=False)     # a drive's moving objects (runtime.actors)
    # [N] int16: the keyframe (an index into drive["keyframes"]) each Gaussian came from, for drives of several
    # keyframes (runtime.drive); a view draws its primary keyframe's first (Scene.render)
    keyframe_of: np.ndarray | None = field(default=None, repr=False)
    # a drive's viewpoint chunks (runtime.viewpoints): each viewpoint group's own cells beyond the shared Gaussians
    viewpoints: Viewpoints | None = field(default=None, repr=False)
    # a drive's camera layers (runtime.cameralayers): per keyframe and camera, the camera's cells as it saw them
    camera_layers: CameraLayers | None = field(default=None, repr=False)
    # a drive's ego body found over its frames (runtime.egobody): its masks and what was looked at
    ego_body: EgoBody | None = field(default=None, repr=False)
    # a drive's shared Gaussians in spatial tiles (runtime.tiles): a view draws (and a loaded scene reads) only the
    # tiles its camera can see; None for a one-rig scene
    tiles: Tiles | None = field(default=None, repr=False)
    # a one-rig scene's exposure gains (runtime.exposure.Harmoniser.to_json: one keyframe); a drive keeps its own in
    # drive["exposure"]
    exposure: dict[str, Any] | None = field(default=None, repr=False)
    _saved_bbox: dict[str, list[float]] | None = field(default=None, init=False, repr=False, compare=False)
    # moving_at's last answer, (key, Gaussians or None): a rig's cameras at one time draw the same moving objects
    _moving_memo: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """A drive's Gaussians of several keyframes put in tile order (runtime.tiles.tile_order: tile after tile,
        within a tile keyframe after keyframe, otherwise as they were), so a tile's keyframe is one run that a view
        draws without copying it (Scene._layers); a scene folder written before the tiles is ordered here once.
        A scene loaded with its tiles (Scene.load) is in that order already and reads its Gaussians when used."""
        kf = self.keyframe_of
        if (self.tiles is not None or kf is None or not self.drive or len(self.drive.get("keyframes", ())) < 2
                or self.own_views is not None):
            return
        self.gaussians, self.keyframe_of, self.tiles = in_tile_order([self.gaussians], kf,
                                                                     len(self.drive["keyframes"]))

    def own_camera(self, camera) -> int | None:
        """The index of the input camera whose pose ``camera`` (runtime.camera.Camera) has (OWN_POSE_TOL), when
        the scene has own views; else None."""
        if self.own_views is None:
            return None
        T = np.asarray(camera.cam_to_ego, np.float64)
        for k, cam in enumerate(self.rig.cameras):
            R = np.asarray(cam.cam_to_ego, np.float64)
            if (np.abs(T[:3, 3] - R[:3, 3]).max() <= OWN_POSE_TOL[0]
                    and np.abs(T[:3, :3] - R[:3, :3]).max() <= OWN_POSE_TOL[1]):
                return k
        return None

    def render(self, camera: Camera, time_s: float | None = None, background: Any = "scene",
               actors: Sequence[ActorEdit] = (), **options) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb [H, W, 3], depth [H, W], alpha [H, W]) float32 of this scene seen by ``camera`` at ``time_s``
        (render_view), over ``background`` ("scene": the scene's panorama; else the renderer's: None, an RGB or an
        image). A drive's scene of several keyframes is drawn in layers, each over what the ones before leave open
        (I = I_1 + (1 - A_1) I_2, composite_layers): first the view's primary keyframe (primary_keyframe) as it saw
        the scene, i.e. its shared Gaussians and its own chunk (runtime.viewpoints), and the moving objects (a view
        standing at one of that keyframe's cameras draws that camera's cells first, with the moving objects: its camera
        layer, runtime.cameralayers, camera_layer); then the
        shared Gaussians of the other keyframes of its viewpoint group and of the two neighbouring groups, with those
        groups' first keyframes' chunks; last the other keyframes' shared Gaussians (these two layers only in the
        tiles within runtime.tiles.HORIZON_M of the camera: beyond, the primary's alone). (An ego that stands still
        is one group: a view is drawn from its keyframe nearest the view's time, whole, and a surface two of its
        keyframes saw at slightly different depths is not drawn as a patchwork of the two; a folder written before
        the chunks were per keyframe draws its group's first keyframe whole.) Each keyframe's cells agree with its
        own images, and another keyframe's copy of the same wall a few centimetres off (its depth, its exposure)
        would otherwise show through in patches; the nearer a keyframe stood, the closer its copy is to what the view
        sees. The others fill what the primary one did not see: behind parked cars, the road it had not reached. A scene
        without chunks (written before them) draws the primary keyframe's shared Gaussians over the rest.
        ``actors``: the view's edits of the moving objects (moving_at)."""
        if isinstance(background, str) and background == "scene":
            bg = self.background.render(camera) if self.background is not None else None
        else:
            bg = background
        k = self.primary_keyframe(camera, time_s)
        if k is None:
            moving = self.moving_at(time_s, actors)
            fill = self.fill_for(actors, time_s)
            r = render([self.gaussians_for(camera)] + [p for p in (moving, fill) if p is not None], camera,
                       background=bg, **options)
            rgb, depth, alpha = r.rgb, r.depth, r.alpha
        else:
            rgb, depth, alpha = self._layers(camera, k, time_s, bg, options, actors)
        gain = self.exposure_gain(camera, k)
        if gain is not None:
            _scale_rgb(rgb, gain.astype(np.float32))    # rgb is this view's own array (the render's result)
        return rgb, depth, alpha

    def exposure_gain(self, camera, k: int | None) -> np.ndarray | None:
        """[3] the per-channel gain of the input camera a view of ``camera`` stands in for at keyframe ``k`` (an
        index into drive.keyframes; None: a one-rig scene, its rig as it stood; runtime.exposure): the rig camera
        whose optical axis at that keyframe is nearest the view's, within EXPOSURE_CONE_DEG; None when none is, or
        the scene has no exposure block."""
        if k is None and self.exposure is None and self.drive and len(self.drive.get("keyframes", ())) == 1:
            k = 0                       # a drive fused from one keyframe: its gains are the drive's
        ex = self.exposure if k is None else (self.drive or {}).get("exposure")
        if not ex or (k or 0) >= len(ex["gains"]):
            return None
        if k is None:                   # one rig: its cameras as they stood, its one set of gains
            k, pose = 0, np.eye(4)
        else:
            key = int(self.drive["keyframes"][k])
            pose = np.asarray(self.drive["trajectory"], np.float64).reshape(-1, 4, 4)[key]
        best = self._rig_camera_along(camera, pose, EXPOSURE_CONE_DEG, names=ex["cameras"])
        if best is None:
            return None
        return np.asarray(ex["gains"][k][ex["cameras"].index(self.rig.cameras[best].name)], np.float64)

    def _rig_camera_along(self, camera, pose: np.ndarray, cone_deg: float, within_m: float | None = None,
                          names: Sequence[str] | None = None) -> int | None:
        """The index of the rig camera, its rig at ego pose ``pose`` ([4, 4], the scene's frame), whose optical axis
        is nearest ``camera``'s, within ``cone_deg`` degrees; only cameras whose centre stood within ``within_m``
        metres of ``camera``'s (None: any) and named in ``names`` (None: any). None when no camera is."""
        view = np.asarray(camera.cam_to_ego, np.float64)
        axis = view[:3, 2] / max(float(np.linalg.norm(view[:3, 2])), 1e-12)
        best, cos_best = None, math.cos(math.radians(cone_deg))
        for c, cam in enumerate(self.rig.cameras):
            T = pose @ np.asarray(cam.cam_to_ego, np.float64)
            cos = float(T[:3, 2] @ axis / max(float(np.linalg.norm(T[:3, 2])), 1e-12))
            if (cos >= cos_best and (names is None or cam.name in names)
                    and (within_m is None or float(np.linalg.norm(T[:3, 3] - view[:3, 3])) <= within_m)):
                best, cos_best = c, cos
        return best

    def _layers(self, camera: Camera, k: int, time_s: float | None, bg: Any, options: dict,
                actors: Sequence[ActorEdit] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A drive's view in layers (Scene.render) with primary keyframe ``k``, before the exposure gain. Each layer
        is a list of keyframes' runs of the (keyframe-sorted) Gaussians, chunks and moving objects, drawn as their
        concatenation without copying them (runtime.render: several sets)."""
        tiles = self.tiles
        seen = tiles.visible(camera, **options)     # the tiles this camera can see: the others are not read
        close = tiles.within(camera, HORIZON_M, seen)   # beyond, the primary keyframe's alone (HORIZON_M)
        moving = self.moving_at(time_s, actors)
        moving = [moving] if moving is not None else []
        fill = self.fill_for(actors, time_s)
        fill = [fill] if fill is not None else []       # behind everything: it never hides what a keyframe saw

        def runs(keys, everywhere: bool = False) -> list[Gaussians]:
            """The Gaussians of keyframes ``keys`` in the tiles seen within the horizon (``everywhere``: in all
            the tiles seen; beyond the horizon only these keyframes' rows are read), one view of each tile's run of
            consecutive keyframes among them (tile after tile)."""
            ks = sorted(keys)
            spans = [[ks[0], ks[0] + 1]] if ks else []
            for kk in ks[1:]:
                if kk == spans[-1][1]:
                    spans[-1][1] = kk + 1
                else:
                    spans.append([kk, kk + 1])
            out = []
            for t in seen:
                if t in close or everywhere:
                    s = tiles.key_starts[t]
                    out += [tiles.part(t, a, b, alone=t not in close) for a, b in spans if s[b] > s[a]]
            return out

        def draw(parts: list[Gaussians], background: Any, behind=None):
            # each layer's result only feeds the next: drawn into its arrays, not copies; the tiles those in front
            # covered are theirs (LAYER_COVER)
            return render(parts or [Gaussians.empty()], camera, background=background, behind=behind,
                          behind_inplace=behind is not None, cover=LAYER_COVER if behind is not None else 0.0,
                          **options)

        n_keys = tiles.n_keys
        # each layer drawn behind the ones before it, in the raster (render's behind: composite_layers' sum, but a
        # pixel the layers before covered is not drawn again); first the camera layer of a keyframe's camera the
        # view stands at, with the moving objects (runtime.cameralayers)
        front = None
        layer = self.camera_layer(camera, k)
        if layer is not None:
            front = draw([layer] + moving, None)
            moving = []
        if self.viewpoints is None:
            a = draw(runs([k], everywhere=True) + moving, None, front)
            b = draw(runs([kk for kk in range(n_keys) if kk != k]) + fill, bg, a)
            return b.rgb, b.depth, b.alpha
        vp = self.viewpoints
        i = vp.group_of(k)                      # k's chunk (a folder written before: its group's)
        mine = vp.chunks[i].keyframes[0]
        groups = vp.groups()
        g = groups.index(vp.chunks[i].group)
        near = [groups[j] for j in (g - 1, g + 1) if 0 <= j < len(groups)]     # neighbouring viewpoint groups
        beside = sorted({kk for h in (groups[g], *near) for kk in vp.group_keyframes(h)} - {mine})
        a = draw(runs([mine], everywhere=True) + [vp.gaussians(i)] + moving, None, front)
        b = draw(runs(beside) + [vp.gaussians(vp.group_of(h)) for h in near], None, a)
        c = draw(runs([kk for kk in range(n_keys) if kk != mine and kk not in beside]) + fill, bg, b)
        return c.rgb, c.depth, c.alpha

    def camera_layer(self, camera, k: int) -> Gaussians | None:
        """The camera layer (runtime.cameralayers) a view of ``camera`` draws first when its primary keyframe is
        ``k`` (an index into drive.keyframes): of the rig's cameras at that keyframe, the one whose optical axis is
        nearest the view's, within CAMERA_LAYER_DEG, when its centre stood within CAMERA_LAYER_M of the view's; None
        when none did, its layer is empty or the scene has no camera layers."""
        if self.camera_layers is None or not 0 <= k < len(self.camera_layers):
            return None
        key = int(self.drive["keyframes"][k])
        pose = np.asarray(self.drive["trajectory"], np.float64).reshape(-1, 4, 4)[key]
        best = self._rig_camera_along(camera, pose, CAMERA_LAYER_DEG, within_m=CAMERA_LAYER_M)
        if best is None:
            return None
        g = self.camera_layers.layer(k, best)
        return g if len(g) else None

    def primary_keyframe(self, camera, time_s: float | None = None) -> int | None:
        """The keyframe a view of ``camera`` draws first (Scene.render): of a drive's scene with keyframe_of, the
        keyframe one of whose cameras stood nearest ``camera``'s centre (the scene's frame); among keyframes within
        PRIMARY_SLACK_M of that distance, the one nearest ``time_s`` (default the drive's start). None for any other
        scene (one layer)."""
        if self.keyframe_of is None or not self.drive or len(self.drive.get("keyframes", ())) < 2:
            return None
        keys = np.asarray(self.drive["keyframes"], np.int64)
        poses = np.asarray(self.drive["trajectory"], np.float64).reshape(-1, 4, 4)[keys]          # [K, 4, 4]
        centres = np.array([np.asarray(c.cam_to_ego, np.float64)[:3, 3] for c in self.rig.cameras])  # [C, 3]
        seen_from = np.einsum("kij,cj->kci", poses[:, :3, :3], centres) + poses[:, None, :3, 3]      # [K, C, 3]
        at = np.asarray(camera.cam_to_ego, np.float64)[:3, 3]
        dist = np.linalg.norm(seen_from - at, axis=2).min(axis=1)                                 # [K]
        near = np.flatnonzero(dist <= dist.min() + PRIMARY_SLACK_M)
        if len(near) == 1:
            return int(near[0])
        t = self.start_time() if time_s is None else float(time_s)
        times = float(self.drive["timestamp_s"]) + np.asarray(self.drive["times_s"], np.float64)[keys]
        return int(near[np.argmin(np.abs(times[near] - t))])

    def start_time(self) -> float | None:
        """A drive's first frame's time (seconds, the rigs' clock), None for a one-rig scene."""
        return None if not self.drive else float(self.drive["timestamp_s"])

    def frame_interval(self) -> float:
        """A drive's median time between frames (seconds; 0.1 without frames): runtime.actors.frame_interval."""
        from .actors import frame_interval

        return frame_interval(self.drive.get("times_s", []) if self.drive else [])

    def timeline(self) -> tuple[np.ndarray, np.ndarray]:
        """(times_s [F] float64 seconds on the rigs' clock, ego_to_world [F, 4, 4]) of the scene's frames: a drive's
        every frame (scene.json's drive block: its first frame's ego_to_world composed with the trajectory in the
        scene's frame), a one-rig scene its one frame (the rig's ``timestamp_s``, 0 without; its ego_to_world,
        identity without). The poses are in the frame of the rigs' ``ego_to_world`` (the world)."""
        if self.drive:
            E0 = np.asarray(self.drive["ego_to_world"], np.float64)
            poses = E0 @ np.asarray(self.drive["trajectory"], np.float64).reshape(-1, 4, 4)
            times = float(self.drive["timestamp_s"]) + np.asarray(self.drive["times_s"], np.float64)
            return times, poses
        ts = self.rig.extra.get("timestamp_s")
        t = float(ts) if isinstance(ts, (int, float)) and not isinstance(ts, bool) and np.isfinite(ts) else 0.0
        pose = np.eye(4) if self.rig.ego_to_world is None else np.asarray(self.rig.ego_to_world, np.float64)
        return np.array([t]), pose[None].copy()

    def gaussians_at(self, camera, time_s: float | None = None, actors: Sequence[ActorEdit] = ()) -> Gaussians:
        """The Gaussians ``camera`` sees at ``time_s`` (seconds on the rigs' clock; default the drive's first frame):
        the static scene (gaussians_for) and the moving objects drawn at that time (moving_at, with the edits
        ``actors``). A scene without actors is the same at every time."""
        g = self.gaussians_for(camera)
        moving = self.moving_at(time_s, actors)
        if moving is None:
            return g
        from .detail import concat_gaussians

        return concat_gaussians([g, moving])

    def moving_at(self, time_s: float | None = None, actors: Sequence[ActorEdit] = ()) -> Gaussians | None:
        """A drive's moving objects drawn at ``time_s`` (runtime.actors; default the drive's first frame) with the
        view's edits ``actors`` (common.wire.ActorEdit: moved, hidden, inserted; check_actors' refusals), None when
        there are none then."""
        if self.actors is None:
            self.check_actors(actors, time_s)
            return None
        t = self.start_time() if time_s is None else float(time_s)
        key = (id(self.actors), t, tuple(e.model_dump_json() for e in actors))
        memo = self._moving_memo
        if memo is not None and memo[0] == key:
            return memo[1]
        moving, _ = self.actors.at(t, 0.5 * self.frame_interval(), actors, self.actor_reach())
        out = moving if len(moving) else None
        self._moving_memo = (key, out)
        return out

    def actor_list(self, time_s: float | None = None) -> dict[str, Any]:
        """common.wire.ActorList's fields: {"time": time_s, "actors": [runtime.actors.Actors.listing's rows]} (each
        actor's pose at ``time_s`` when given); no actors: an empty list."""
        rows = [] if self.actors is None else self.actors.listing(time_s, 0.5 * self.frame_interval())
        return {"time": time_s, "actors": rows}

    def fill_for(self, actors: Sequence[ActorEdit], time_s: float | None = None) -> Gaussians | None:
        """The ground fill (runtime.groundfill: the road under the moving objects that no frame saw, all of it: the
        road one hid is often the road the next one in the lane hid too) when the view's edits take an actor away
        from where it is at ``time_s`` (runtime.actors.Actors.cleared: hidden or moved), else None: a view as
        recorded draws none (it cost 0.13 dB there: docs/results.md "Actors")."""
        if self.actors is None or self.actors.fill is None or not actors:
            return None
        t = self.start_time() if time_s is None else float(time_s)
        return self.actors.fill if self.actors.cleared(actors, t, 0.5 * self.frame_interval()) else None

    def actor_reach(self) -> tuple[np.ndarray, float]:
        """(the drive's ego positions [F, 3] metres, scene frame; ACTOR_REACH_M): an edited actor is placed within
        that distance of one of them (runtime.actors.Actors.placements)."""
        traj = np.asarray((self.drive or {}).get("trajectory", np.eye(4)), np.float64).reshape(-1, 4, 4)
        return traj[:, :3, 3], ACTOR_REACH_M

    def check_actors(self, actors: Sequence[ActorEdit], time_s: float | None = None, field: str = "actors") -> None:
        """Refuse a view's actor edits this scene cannot honour (ViewError naming ``field``[i] and the key: an
        unknown id, an offset outside the actor's time span, a pose that is no rigid transform or farther than
        ACTOR_REACH_M from the drive, a new id already taken); the service asks before it renders."""
        if not actors:
            return
        if self.actors is None:
            raise ViewError(f"{field}[0].id", "this scene has no actors (a drive reconstructed with tracks has its "
                                              "moving objects as actors)")
        t = self.start_time() if time_s is None else float(time_s)
        self.actors.placements(t, 0.5 * self.frame_interval(), actors, self.actor_reach(), field)

    def gaussians_for(self, camera) -> Gaussians:
        """The Gaussians as ``camera`` sees them: at an input camera's own pose its own view (runtime.detail.OwnViews:
        its cells wherever it has them), elsewhere the scene's."""
        k = self.own_camera(camera)
        if k is None:
            return self.gaussians
        return self.gaussians.with_opacity_logits(self.own_views.opacity_logits(self.gaussians.opacity_logits, k))

    def bbox(self) -> dict[str, list[float]] | None:
        """Axis-aligned box (ego metres) of the Gaussians' centres whose opacity is at least 1/255."""
        if self.tiles is not None and self.tiles.lazy and self._saved_bbox is not None:
            return self._saved_bbox         # scene.json's: what the whole set gives, without reading it
        g = self.gaussians
        if len(g) == 0:
            return None
        vis = g.opacities >= 1.0 / 255.0
        if not vis.any():
            vis[:] = True
        # a column at a time: numpy's min/max over axis 0 of an [N, 3] array took 0.1 s for 2.16 M Gaussians
        cols = [g.means[:, c][vis] for c in range(3)]
        return {"min": [float(c.min()) for c in cols], "max": [float(c.max()) for c in cols]}

    def to_json(self) -> dict[str, Any]:
        g = self.__dict__.get("_gaussians")
        # a scene read tile by tile: the count and SH degree from its tiles, nothing read whole
        n, degree = (len(g), g.sh_degree) if g is not None else (self.tiles.count, self.tiles.sh_degree)
        out = {"format": SCENE_FORMAT, "format_version": SCENE_VERSION, "created": self.created,
                "frame": "ego: x forward, y left, z up, metres",
                "model": self.model, "rig": _calibration_rig(self.rig).to_dict(),
                "counts": self.counts, "timings": self.timings, "lifting_cached": self.lifting_cached,
                "bbox": self.bbox(),
                "gaussians": {"file": PLY_NAME, "count": n, "sh_degree": degree,
                              "layout": "3DGS PLY: logit opacity, log scale, quaternion wxyz, f_rest channel-major"},
                "background": None if self.background is None else self.background.to_dict(),
                "own_views": None if self.own_views is None else {
                    "file": OWN_VIEWS_NAME, "hidden": len(self.own_views.index),
                    "about": "cells hidden (opacity logit -30) except in their camera's own view"}}
        if self.drive is not None:           # a drive's scene (runtime.drive); a one-rig scene has no such key
            out["drive"] = self.drive
        if self.actors is not None:
            out["actors"] = {"file": ACTORS_NAME, "objects": len(self.actors), "copies": len(self.actors.copy_track),
                             "gaussians": len(self.actors.gaussians),
                             "about": "moving objects: per keyframe a copy in its box frame, drawn at a time"}
            if self.actors.fill is not None:     # the ground no frame saw under each, filled (runtime.groundfill)
                out["actors"]["filled_m2"] = {i: round(float(v), 2) for i, v in zip(self.actors.track_id,
                                                                                    self.actors.filled_m2()) if v > 0}
        if self.viewpoints is not None:
            out["viewpoints"] = self.viewpoints.to_json()
        if self.camera_layers is not None:
            out["camera_layers"] = self.camera_layers.to_json()
        if self.tiles is not None:
            out["tiles"] = self.tiles.to_json()
        if self.exposure is not None:
            out["exposure"] = self.exposure
        if self.ego_body is not None:
            out["ego_body"] = {**self.ego_body.summary(),
                               "files": {n: f"{EGO_BODY_DIR}/{n}.png" for n in self.ego_body.masks},
                               "about": "the ego's own body found over the drive's frames (white): no Gaussians "
                                        "there"}
        if self.keyframe_of is not None:
            out["keyframe_of"] = {"file": KEYFRAME_OF_NAME, "keyframes": len(self.drive["keyframes"]),
                                  "about": "each Gaussian's keyframe (int16, an index into drive.keyframes): a "
                                           "view draws its primary keyframe's first"}
        return out

    def save(self, folder: str | os.PathLike, overwrite: bool = True) -> Path:
        """Write the scene folder atomically: into a temporary sibling folder, then renamed to ``folder`` (an
        existing folder is replaced when ``overwrite``)."""
        out = Path(folder)
        if out.exists() and not overwrite:
            raise SceneError("scene", f"{str(out)!r} exists")
        with atomic_folder(out) as tmp:
            if self.__dict__.get("_gaussians") is None and self.tiles is not None:
                import shutil

                shutil.copyfile(self.tiles.ply, tmp / PLY_NAME)      # read from a folder, never read whole
            else:
                self.gaussians.save_ply(tmp / PLY_NAME)
            if self.own_views is not None:
                self.own_views.save(tmp / OWN_VIEWS_NAME)
            if self.actors is not None:
                self.actors.save(tmp / ACTORS_NAME)
            if self.viewpoints is not None:
                self.viewpoints.save(tmp)
            if self.camera_layers is not None:
                self.camera_layers.save(tmp)
            if self.ego_body is not None and self.ego_body.masks:
                _save_masks(tmp / EGO_BODY_DIR, self.ego_body.masks)
            if self.keyframe_of is not None:
                np.save(tmp / KEYFRAME_OF_NAME, np.asarray(self.keyframe_of, np.int16))
            if self.background is not None:
                from xyzcyl.common.media import write_exr

                from .imageio import write_png

                write_exr(tmp / EXR_NAME, self.background.image, ("R", "G", "B"))
                write_png(tmp / PNG_NAME, self.background.image)
            (tmp / JSON_NAME).write_text(json.dumps(self.to_json(), indent=1, allow_nan=False) + "\n")
        return out

    @classmethod
    def load(cls, folder: str | os.PathLike, max_points: int | None = None) -> Scene:
        """Read a scene folder (SceneError naming the file when something is missing or invalid)."""
        from .render import GaussianError
        from .render.gaussians import DEFAULT_MAX_POINTS, ply_rows_layout
        from .rig import RigError

        d = Path(folder)
        jp = d / JSON_NAME
        meta = read_json_doc(jp, SCENE_FORMAT, SceneError, "scene")
        try:
            rig = Rig.from_dict(meta["rig"])
        except KeyError:
            raise SceneError("rig", "is missing", f"scene {str(jp)!r}") from None
        except RigError as e:           # its where names the rig or the camera
            raise SceneError(e.field, e.message, f"scene {str(jp)!r}: {e.where}" if e.where else
                             f"scene {str(jp)!r}") from None
        pp = d / PLY_NAME
        if not pp.is_file():
            raise SceneError("scene", f"{str(pp)!r} is missing")
        n_keys = len((meta.get("drive") or {}).get("keyframes") or ())
        tiled = bool(meta.get("tiles")) and bool(meta.get("keyframe_of")) and n_keys >= 2
        try:
            if tiled:           # a drive in tiles: the header and size checked now, the tiles read when views
                # need them (Scene.load bounds the largest tile below, not the whole: it need not fit in memory)
                g, n = None, ply_rows_layout(pp)[0]
            else:
                g = Gaussians.load_ply(pp, max_points=max_points or DEFAULT_MAX_POINTS)
                n = len(g)
        except GaussianError as e:      # its where names the file by its name alone: here, by its path
            raise SceneError(e.field, e.message, f"scene PLY {str(pp)!r}") from None
        own = None
        if meta.get("own_views"):
            op = _scene_file(d, meta["own_views"], OWN_VIEWS_NAME)
            try:
                own = OwnViews.load(op, n)
            except DetailError as e:
                raise SceneError(e.field, e.message, e.where) from None
            if own.cameras != tuple(rig.names):
                raise SceneError("own_views.cameras", f"{list(own.cameras)} are not the rig's {rig.names}",
                                 f"scene {str(op)!r}")
        actors = None
        if meta.get("actors"):
            ap = _scene_file(d, meta["actors"], ACTORS_NAME)
            try:
                actors = Actors.load(ap)
            except ActorsError as e:
                raise SceneError(e.field, e.message, f"scene {str(ap)!r}") from None
        keyframe_of = None
        if meta.get("keyframe_of"):
            keyframe_of = _keyframe_of(_scene_file(d, meta["keyframe_of"], KEYFRAME_OF_NAME), n, n_keys)
        tiles = None
        if tiled:
            try:
                tiles = Tiles.from_json(meta["tiles"], pp, n, keyframe_of, n_keys)
            except TileError as e:
                raise SceneError(e.field, e.message, e.where) from None
            limit = max_points or DEFAULT_MAX_POINTS
            big = max((t.count for t in tiles.tiles), default=0)
            if big > limit:     # the memory guard the whole PLY has elsewhere: here per tile, read one at a time
                raise SceneError("tiles", f"a tile of {big} Gaussians, more than the maximum {limit}",
                                 f"scene {str(jp)!r}")
        viewpoints = None
        if meta.get("viewpoints"):
            if keyframe_of is None:
                raise SceneError("viewpoints", "needs keyframe_of (each shared Gaussian's keyframe)",
                                 f"scene {str(jp)!r}")
            try:
                viewpoints = Viewpoints.from_json(meta["viewpoints"], d,
                                                  len((meta.get("drive") or {}).get("keyframes") or ()))
            except ViewpointError as e:
                raise SceneError(e.field, e.message, e.where) from None
        layers = None
        if meta.get("camera_layers"):
            try:
                layers = CameraLayers.from_json(meta["camera_layers"], d, n_keys, rig.names)
            except CameraLayerError as e:
                raise SceneError(e.field, e.message, e.where) from None
        ego_body = _load_ego_body(d, meta["ego_body"], rig) if meta.get("ego_body") else None
        if (meta.get("drive") or {}).get("exposure") is not None:
            _check_exposure(meta["drive"]["exposure"], len(meta["drive"].get("keyframes") or ()), rig, jp)
        if meta.get("exposure") is not None:
            _check_exposure(meta["exposure"], 1, rig, jp, "exposure")
        bg = None
        b = meta.get("background")
        if b:
            from .imageio import read_exr

            ep = _scene_file(d, b, EXR_NAME)
            img = read_exr(ep)
            c = b["cylinder"]
            spec = CylinderSpec(centre=c["centre"], radius=c["radius"], z_min=c["z_min"], z_max=c["z_max"],
                                height=c["height"], width=c["width"])
            bg = Background(image=img[..., :3], cylinder=spec, v_range=tuple(b["v_range"]))
        scene = cls(gaussians=g, background=bg, rig=rig, model=meta.get("model") or {},
                    counts=meta.get("counts") or {}, timings=meta.get("timings") or {},
                    lifting_cached=bool(meta.get("lifting_cached", False)), created=meta.get("created", ""),
                    own_views=own, drive=meta.get("drive"), actors=actors, keyframe_of=keyframe_of,
                    viewpoints=viewpoints, camera_layers=layers, ego_body=ego_body, tiles=tiles,
                    exposure=meta.get("exposure"))
        if tiles is not None and isinstance(meta.get("bbox"), dict):
            scene._saved_bbox = meta["bbox"]
        return scene


def _check_exposure(block: Any, keyframes: int, rig: Rig, path: Path, name: str = "drive.exposure") -> None:
    """scene.json's ``name`` block (drive.exposure, or a one-rig scene's exposure: runtime.exposure.Harmoniser
    .to_json): the rig's cameras and a positive, finite gain [3] per keyframe and camera; SceneError naming the field
    otherwise."""
    where = f"scene {str(path)!r}"
    if not isinstance(block, dict) or block.get("cameras") != list(rig.names):
        raise SceneError(f"{name}.cameras", f"must be the rig's cameras {rig.names}", where)
    try:
        g = np.asarray(block.get("gains"), np.float64)
    except (TypeError, ValueError):
        g = np.zeros(0)
    if g.shape != (keyframes, len(rig.names), 3) or not np.all(np.isfinite(g)) or not np.all(g > 0):
        raise SceneError(f"{name}.gains", f"must be [{keyframes}][{len(rig.names)}][3] positive numbers "
                         "(per keyframe, camera and channel)", where)


def _save_masks(folder: Path, masks: dict[str, np.ndarray]) -> None:
    """Each [H, W] bool mask as folder/<camera>.png (8-bit grey, 255 = True)."""
    import cv2

    folder.mkdir()
    for name, m in masks.items():
        if not cv2.imwrite(str(folder / f"{name}.png"), np.where(m, 255, 0).astype(np.uint8)):
            raise OSError(f"could not write {str(folder / f'{name}.png')!r}")


def _load_ego_body(d: Path, block: Any, rig: Rig) -> EgoBody:
    """scene.json's ego_body block and its masks (SceneError naming the field or file when invalid)."""
    from .detail import read_ego_mask
    from .rig import RigError

    where = f"scene {str(d / JSON_NAME)!r}"
    files = block.get("files") if isinstance(block, dict) else None
    if not isinstance(files, dict):
        raise SceneError("ego_body.files", "must be an object: camera name -> mask file", where)
    masks = {}
    for name, rel in files.items():
        if name not in rig.names:
            raise SceneError(f"ego_body.files.{name}", f"is not a camera of the rig ({rig.names})", where)
        if not isinstance(rel, str) or not rel.startswith(EGO_BODY_DIR + "/") or ".." in Path(rel).parts:
            raise SceneError(f"ego_body.files.{name}", f"must be a file in {EGO_BODY_DIR}/ (got {rel!r})", where)
        try:
            masks[name] = read_ego_mask(_scene_file(d, {"file": rel}, rel), rig.cameras[rig.names.index(name)])
        except RigError as e:
            raise SceneError(f"ego_body.files.{name}", e.message, where) from None
    try:
        return EgoBody(masks=masks, fractions={k: float(v) for k, v in (block.get("fractions") or {}).items()},
                       notes=dict(block.get("notes") or {}), frames=tuple(int(f) for f in block.get("frames") or ()),
                       travelled_m=float(block.get("travelled_m") or 0.0))
    except (TypeError, ValueError, AttributeError) as e:
        raise SceneError("ego_body", f"invalid ({e})", where) from None


# ------------------------------------------------------------------------------------------- views


def _keyframe_of(path: Path, n: int, keyframes: int) -> np.ndarray:
    """A scene folder's keyframe_of.npy: [n] integers in 0..keyframes - 1 (SceneError naming the file else)."""
    where = f"scene {str(path)!r}"
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise SceneError("keyframe_of", f"not a .npy array ({e})", where) from None
    if a.shape != (n,) or a.dtype.kind not in "iu":
        raise SceneError("keyframe_of", f"must be [{n}] integers, one per Gaussian (got {a.dtype} {a.shape})", where)
    if n and (int(a.min()) < 0 or int(a.max()) >= keyframes):
        raise SceneError("keyframe_of", f"must index the drive's {keyframes} keyframes (got {int(a.min())}.."
                                        f"{int(a.max())})", where)
    return a.astype(np.int16)


def _scene_file(folder: Path, entry: Any, default: str) -> Path:
    """The file a scene.json entry ({"file": name}) names in ``folder``; SceneError when it is missing."""
    p = folder / (entry.get("file", default) if isinstance(entry, dict) else default)
    if not p.is_file():
        raise SceneError("scene", f"{str(p)!r} is missing")
    return p


def _scene_gaussians(self: Scene) -> Gaussians:
    """Scene.gaussians: the shared Gaussians (a loaded drive scene reads them whole when first asked: its views read
    only their tiles, runtime.tiles)."""
    g = self.__dict__.get("_gaussians")
    if g is None and self.tiles is not None:
        g = self.__dict__["_gaussians"] = self.tiles.whole()
    return g


def _set_scene_gaussians(self: Scene, g: Gaussians | None) -> None:
    self.__dict__["_gaussians"] = g


# a property over the dataclass's field: Scene(gaussians=...) sets it; a scene loaded with tiles starts with None
Scene.gaussians = property(_scene_gaussians, _set_scene_gaussians)


def composite_layers(*layers, cover: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb, depth, alpha) of render results (runtime.render.RenderResult) drawn front to back, the last over the
    background if any: for a over b, I = I_a + (1 - A_a) I_b, A = A_a + (1 - A_a) A_b, depth the alpha-weighted
    mean of the two (each result's depth is its own sum(w z) / alpha; 0 where A is 0). cover: where what lies in
    front of a layer leaves no pixel of a 16x16 tile (the renderer's, from the image's top left) more than this
    fraction of its light, the tile is the front's alone, renormalised: I_a / A_a, A = 1, its depth (render's
    ``cover``, of which this is the reference)."""
    from .render import kernels as K

    rgb, depth, alpha = (np.asarray(x, np.float64) for x in (layers[0].rgb, layers[0].depth, layers[0].alpha))
    for b in layers[1:]:
        ta = 1.0 - alpha
        wsum = alpha * depth + ta * b.alpha * b.depth
        done = np.zeros(ta.shape, bool)
        if cover > 0:
            H, W = ta.shape
            th, tw = -(-H // K.TILE), -(-W // K.TILE)
            left = np.zeros((th * K.TILE, tw * K.TILE))
            left[:H, :W] = ta
            tiles = left.reshape(th, K.TILE, tw, K.TILE).max(axis=(1, 3)) <= cover
            done = np.repeat(np.repeat(tiles, K.TILE, 0), K.TILE, 1)[:H, :W]
        front = np.where(done, alpha, 1.0)                # a covered tile: the front's light is all its light
        rgb = np.where(done[..., None], rgb / front[..., None], rgb + ta[..., None] * b.rgb)
        new_alpha = np.where(done, 1.0, alpha + ta * b.alpha)
        depth = np.where(done, depth, np.divide(wsum, new_alpha, out=np.zeros_like(wsum), where=new_alpha > 0))
        alpha = new_alpha
    return rgb.astype(np.float32), depth.astype(np.float32), alpha.astype(np.float32)


def render_view(scene: Scene, camera, **options) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [H, W, 3], depth [H, W], alpha [H, W]) float32 of ``scene`` seen by a runtime.camera.Camera
    (pinhole, with or without a lens, or equirectangular; docs/renderer.md): the Gaussians (Scene.gaussians_for: at
    an input camera's pose, its own view) composited over the background panorama (I = I_fg + (1 - A_fg) I_bg; black
    without a background). Depth and alpha are the Gaussians' (depth 0 where alpha is 0). ``options``: the
    renderer's (RenderOptions)."""
    return scene.render(camera, **options)


__all__ = ["Background", "Scene", "SceneError", "bake_grid", "composite_layers", "render_view", "rig_camera"]
