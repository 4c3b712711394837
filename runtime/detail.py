"""Detail Gaussians: pixel-aligned Gaussians at (a stride of) each input camera's native resolution.

The model's pixel Gaussians live on the cylinder lattice (112 x 1024 for the shipped model: ~2.8 columns per
degree), while a 1920x1080 camera with a 50 degree lens has ~37 pixels per degree. The detail layer gives every
input camera its own Gaussians at its own resolution (docs/inference.md, "Detail Gaussians", has the table of
steps and settings; docs/results.md "Detail Gaussians" the measurements behind the defaults):

1. A grid camera per input camera (``grid_camera``: the camera resized by 1/stride, its lens kept; a cell's centre
   is its stride x stride block's centre); a cell's colour is the block's area mean, unsharp-masked
   (``grid_colours``). Where each cell looks (its true ray, its footprint) is ``cell_geometry``: an ideal pinhole by
   K, a camera with a lens by its exact inverse (Camera.depth_rays), so no image is undistorted or cropped.
2. A depth per cell (the camera's depth, Camera.depth_is_distance: camera z for an ideal pinhole or an opencv lens,
   the distance for a fisheye or f-theta lens; metres), in ``camera_detail``:
   - LiDAR: the sweep projected into the grid, nearest return per cell, returns hidden behind a nearer one within a
     fixed angle dropped (``lidar_grid_depth``), spread edge-aware over the image (``densify``: normalised fast
     global smoothing, OpenCV ximgproc); a cell within ``support_deg`` of a return is LiDAR-supported;
   - ground: cells the LiDAR does not reach whose ray meets the ground plane (``fit_ground``, ``ground_depth``)
     take its depth unless something is clearly in front: the sweep's plane, or camera only the plane of the
     model's opaque Gaussians (``model_ground``; without it the road beside the car, which the model's Gaussians
     do not cover, went to the far sphere: camera-only depth AbsRel 1.44 against 0.56 for the model alone);
   - model: other cells with a model surface take the model's depth (its Gaussians rendered at the grid,
     ``model_grid_depth``; a lens camera along its cells' rays, runtime.raydepth; scaled by the median LiDAR / model
     ratio when a sweep is given);
   - far: cells with no depth (sky) or beyond ``max_depth`` sit on one sphere about the ego origin
     (``sphere_depth``).
3. No Gaussian spans a depth edge: the cells between the two sides of a jump are dropped (``edge_keep``).
4. One Gaussian per kept cell (``cell_gaussians``, one numba pass; ``cell_gaussians_reference`` is its numpy
   definition): on the cell's ray at its depth, a disc covering the cell's footprint, in the surface's tangent plane
   where the neighbouring cells give one (``surface_discs``), else facing the camera (parallel to the image plane;
   a lens: across the cell's ray, sized by its angular footprint); the cell's colour.
5. Fusion (``fuse_details``, called by ``Reconstructor.reconstruct``; runtime.drive fuses keyframes with the same
   parts): ``cull_covered`` drops the model's Gaussians that would veil a detail surface; ``carve_details`` drops
   the cells that another camera contradicts (it saw through them) or resolves more finely on the same surface.
   Each has a slow reference the tests compare it with.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace

import numba
import numpy as np
from xyzcyl.common.wire import detail_stride_error

from .camera import Camera
from .errors import FieldError, plain
from .imageio import LUMA_BT601
from .numba_cache import njit, threadsafe
from .render import Gaussians
from .render.gaussians import SH_C0, concat_gaussians, concat_gaussians_reference
from .rotations import quat_to_rotmat, rotmat_to_quat, rotmats_to_quats


class DetailError(FieldError):
    """An invalid detail setting: ``field`` "detail.<setting>" ("detail.stride")."""


@dataclass(frozen=True)
class DetailOptions:
    """The detail layer's settings (docs/inference.md, "Detail Gaussians", gives the measurements behind each
    default)."""

    stride: int = 2                 # input pixels per detail cell along each axis (1 = every pixel)
    footprint: float = 0.5          # disc standard deviation, in cell footprints (depth x stride / focal)
    thickness: float = 0.1          # standard deviation along the disc's normal, as a fraction of the disc's
    surface_stretch: float = 30.0   # > 0: discs lie in the surface's tangent plane (from the neighbouring cells) where
    #                                 its tangents are at most this x the image-plane footprint (a road 20 m ahead of
    #                                 a camera 1.5 m up: ~13x); 0: all discs face their camera (seen from above, the
    #                                 road's discs are then slivers with gaps: contour-line moire)
    sharpen: float = 0.5            # unsharp mask of the cell colours (amount; its blur = the disc's footprint):
    #                                 pre-compensates the blur of overlapping discs
    split: float = 0.03             # a cell with a quarter whose luma strays from the cell's by more than this
    #                                 (BT.601 of sRGB 0..1) is drawn as its four quarters on the cell's disc
    #                                 (split_cells; at stride 2 the pixels); 0: never
    opacity: float = 0.95           # opacity of a cell whose depth LiDAR supports
    model_opacity: float = 0.95     # opacity of a cell placed by the model's depth alone
    model_depth: bool = True        # give cells without LiDAR support the model's (scaled) depth; False: no cell
    edge_ratio: float = 0.1         # drop a cell farther than (1 + edge_ratio) x the nearest of its 3x3 neighbours
    support_deg: float = 1.5        # a cell is LiDAR-supported when a LiDAR return lies within this angle
    occlusion_deg: float = 0.4      # LiDAR occlusion window half-size (a return behind a nearer one within it goes)
    smooth_lambda: float = 200.0    # fast global smoother: strength of the smoothing (OpenCV's lambda)
    smooth_sigma: float = 6.0       # fast global smoother: colour distance (0..255) that stops it (edge-aware)
    cull_tolerance: float = 0.15    # fusion: a coarse Gaussian within this fraction behind a detail cell is culled
    dedupe: float = 0.7             # fusion: a cell another camera resolves at most this x its footprint, on the same
    #                                 surface, is dropped (0: no cell is dropped for that reason)
    min_depth: float = 1.0          # metres, the camera's depth: nearer cells are the ego's own body
    max_depth: float = 150.0        # metres, the camera's depth: farther are not trusted (the cell goes to far_depth)
    ground: bool = True             # cells LiDAR does not reach that look at the ground get the ground plane's
    #                                 depth (the LiDAR sees no ground within a few metres of the car): the LiDAR's
    #                                 plane, camera only the plane of the model's opaque Gaussians (model_ground)
    ground_max: float = 40.0        # metres camera z: the ground plane is used up to this depth
    far_depth: float = 300.0        # metres from the ego origin: cells with no depth (sky, beyond max_depth) sit
    #                                 on this sphere (one surface for every camera); 0 = no cell there (the model's
    #                                 background panorama shows)

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> DetailError:
            return DetailError(f"detail.{name}", f"{why} (got {plain(getattr(self, name))!r})")

        why = detail_stride_error(self.stride)
        if why is not None:
            raise bad("stride", why)
        for name in ("model_depth", "ground"):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, "must be true or false")
        for f in fields(self):
            if f.name in ("stride", "model_depth", "ground"):
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(f.name, "must be a finite number")
        for name in ("footprint", "thickness", "smooth_lambda", "smooth_sigma", "support_deg", "occlusion_deg",
                     "min_depth"):
            if getattr(self, name) <= 0:
                raise bad(name, "must be > 0")
        for name in ("opacity", "model_opacity"):
            if not 0 < getattr(self, name) < 1:
                raise bad(name, "must be in (0, 1)")
        for name in ("edge_ratio", "cull_tolerance", "far_depth", "ground_max", "sharpen", "dedupe",
                     "surface_stretch", "split"):
            if getattr(self, name) < 0:
                raise bad(name, "must be >= 0")
        if self.max_depth <= self.min_depth:
            raise bad("max_depth", "must exceed min_depth")
        if 0 < self.far_depth <= self.max_depth:
            raise bad("far_depth", "must be 0 or exceed max_depth")


# ------------------------------------------------------------------------------------------- grid and colour


def grid_camera(cam: Camera, stride: int) -> Camera:
    """The camera whose pixels are ``cam``'s stride x stride blocks: ``cam.resized(round(W / s), round(H / s))``
    (pixel-centre convention of Camera.resized; a lens is kept, Lens.resized)."""
    w, h = max(1, round(cam.width / stride)), max(1, round(cam.height / stride))
    return cam.resized(w, h)


@dataclass(frozen=True, eq=False)
class CellGeometry:
    """Where a grid camera's cells look (``cell_geometry``): what the Gaussians, the fusion and the depth sources
    read, one definition for an ideal pinhole and for a lens."""

    rays: np.ndarray       # [h, w, 3] float64 camera frame: the cell's point at depth d is d * rays (pinhole:
    #                        ((u - cx) / fx, (v - cy) / fy, 1); a lens: Camera.depth_rays); NaN where no ray
    has_ray: np.ndarray    # [h, w] bool
    f: float               # pixels per radian at the axis (the mean of fx and fy; a lens: its paraxial focal)
    scale: np.ndarray      # [h, w] float64: the cell's footprint over depth / f (pinhole: 1, the image-plane
    #                        footprint; a lens: f |rays| x the cell's angular size, from its true rays: across it)
    quats: np.ndarray      # [h, w, 4] float64 wxyz, ego frame: a disc facing the cell (pinhole: the camera's
    #                        rotation, parallel to the image plane; a lens: its local z along the cell's ray)
    across: np.ndarray     # [h, w] float64: the cell's size across its ray per metre of depth (cell_footprint)


_GEOMETRY: dict[tuple, CellGeometry] = {}                     # by geometry_key, the last GEOMETRY_CACHE
_RAYS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}       # grid_rays by geometry_key, the last RAYS_CACHE
_UNIT: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}       # their camera-frame unit rays by lens_key, as many
_PINHOLE: dict[tuple, tuple] = {}                             # an ideal pinhole's CellGeometry but its quats, by
#                                                               lens_key, as many as GEOMETRY_CACHE
_CACHE_LOCK = threading.Lock()          # the cameras of a rig are made in threads (Reconstructor.camera_details)
GEOMETRY_CACHE = 16     # grid cameras whose CellGeometry is kept: two rigs of up to 8 (~21 MB each at 960 x 540)
RAYS_CACHE = 8          # and whose grid_rays are kept (16 MB each at 960 x 540): a rig of up to 8 cameras


def geometry_key(grid: Camera) -> tuple:
    """What a grid camera's cell geometry and rays depend on, by value: its model, size, K, lens and cam_to_ego (a
    drive's keyframes make new grid cameras of the same rig: their geometry is made once, not once a keyframe)."""
    return lens_key(grid) + (np.ascontiguousarray(grid.cam_to_ego, np.float64).tobytes(),)


def lens_key(grid: Camera) -> tuple:
    """What a grid camera's rays in its own frame depend on, by value: its model, size, K and lens. A recorded
    drive's extrinsics move by millimetres from frame to frame (PandaSet's are calibrated per frame), so its
    keyframes' grid cameras share these and not geometry_key."""
    K = b"" if grid.K is None else np.ascontiguousarray(grid.K, np.float64).tobytes()
    return (grid.model, grid.width, grid.height, grid.distortion, K)


def _cached(table: dict, size: int, key: tuple, make: Callable[[], object]):
    """table[key], made by ``make`` when missing (outside the lock: two threads may both make it, one is kept); the
    oldest entries dropped beyond ``size``."""
    with _CACHE_LOCK:
        hit = table.get(key)
    if hit is not None:
        return hit
    value = make()
    with _CACHE_LOCK:
        table[key] = value
        while len(table) > size:
            table.pop(next(iter(table)))
    return value


def _frozen(*arrays: np.ndarray) -> None:
    """Mark cached arrays read-only: every caller shares them."""
    for a in arrays:
        a.flags.writeable = False


def cell_geometry(grid: Camera) -> CellGeometry:
    """The CellGeometry of a grid camera (cached by its values: geometry_key)."""
    return _cached(_GEOMETRY, GEOMETRY_CACHE, geometry_key(grid), lambda: _make_geometry(grid))


def _make_geometry(grid: Camera) -> CellGeometry:
    h, w = grid.height, grid.width
    fx, fy = grid.paraxial_focal
    f = 0.5 * (fx + fy)
    if grid.is_ideal:
        rays, scale, across, has = _cached(_PINHOLE, GEOMETRY_CACHE, lens_key(grid), lambda: _pinhole_cells(grid))
        quats = np.broadcast_to(rotmat_to_quat(grid.rotation), (h, w, 4))      # a read-only view
        return CellGeometry(rays, has, f, scale, quats, across)
    rays = grid.depth_rays()
    has = np.all(np.isfinite(rays), axis=-1)
    length = np.linalg.norm(rays, axis=-1)
    across = np.where(has, length * _cell_angles(grid), 1.0 / f)   # finite on cells a point may round onto
    scale = f * across
    R = np.einsum("ij,hwjk->hwik", grid.rotation, _facing(rays / length[..., None]))
    quats = rotmats_to_quats(R.reshape(-1, 3, 3)).reshape(h, w, 4)
    _frozen(rays, has, scale, quats, across)
    return CellGeometry(rays, has, f, scale, quats, across)


def _pinhole_cells(grid: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An ideal pinhole grid camera's CellGeometry rays, scale, across and has_ray (read-only): its intrinsics'."""
    h, w = grid.height, grid.width
    fx, fy = grid.paraxial_focal
    K = grid.K
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    rays = np.empty((h, w, 3))
    rays[..., 0], rays[..., 1], rays[..., 2] = x[None, :], y[:, None], 1.0
    scale = np.ones((h, w))
    across = np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2) / (0.5 * (fx + fy))
    has = np.ones((h, w), bool)
    _frozen(rays, scale, across, has)
    return rays, scale, across, has


def _cell_angles(grid: Camera) -> np.ndarray:
    """[h, w] radians: the angular size of each cell of a lens camera, sqrt(a_u a_v) with a_u the angle between the
    rays through its left and right edge midpoints (one-sided, doubled, where one of them has no ray), a_v likewise;
    1 / f (the paraxial pixel) where neither side has one."""
    vv, uu = np.meshgrid(np.arange(grid.height, dtype=np.float64), np.arange(grid.width, dtype=np.float64),
                         indexing="ij")
    centre = grid.pixel_rays(np.stack([uu, vv], -1))[1]
    fx, fy = grid.paraxial_focal
    sizes = []
    for du, dv, fallback in ((0.5, 0.0, 1.0 / fx), (0.0, 0.5, 1.0 / fy)):
        a = grid.pixel_rays(np.stack([uu + du, vv + dv], -1))[1]
        b = grid.pixel_rays(np.stack([uu - du, vv - dv], -1))[1]
        angle = lambda p, q: 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(p - q, axis=-1), 0.0, 1.0))  # noqa: E731
        both = angle(a, b)
        one = 2.0 * np.where(np.isfinite(a).all(-1), angle(a, centre), angle(centre, b))
        sizes.append(np.where(np.isfinite(both), both, np.where(np.isfinite(one), one, fallback)))
    return np.sqrt(sizes[0] * sizes[1])


def _facing(d: np.ndarray) -> np.ndarray:
    """[..., 3, 3] camera-frame rotations whose third column is the unit ray d [..., 3] (the smallest rotation from
    the optical axis; a half turn about x for a ray straight back); identity where d is NaN."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    ok = np.isfinite(z)
    x, y, z = np.where(ok, x, 0.0), np.where(ok, y, 0.0), np.where(ok, z, 1.0)
    k = 1.0 / np.maximum(1.0 + z, 1e-12)
    R = np.stack([np.stack([1 - x * x * k, -x * y * k, x], -1),
                  np.stack([-x * y * k, 1 - y * y * k, y], -1),
                  np.stack([-x, -y, z], -1)], -2)
    back = z < -1 + 1e-9
    R[back] = np.diag([1.0, -1.0, -1.0])
    return R


def grid_colours(image: np.ndarray, grid: Camera, sharpen: float = 0.0, footprint: float = 0.5) -> np.ndarray:
    """[h, w, 3] float32 0..1: the area mean of each cell's block of ``image`` ([H, W, 3] float32 0..1), with an
    unsharp mask of amount ``sharpen`` (c + sharpen (c - G * c), G a Gaussian of ``footprint`` cells) when > 0."""
    import cv2

    if image.shape[:2] == (grid.height, grid.width):
        c = np.ascontiguousarray(image, np.float32)
    else:
        c = cv2.resize(image, (grid.width, grid.height), interpolation=cv2.INTER_AREA)
    if sharpen > 0:
        blur = cv2.GaussianBlur(c, (0, 0), footprint, borderType=cv2.BORDER_REFLECT)
        c = np.clip(c + np.float32(sharpen) * (c - blur), 0.0, 1.0)
    return c


def _angle_pixels(grid: Camera, degrees: float) -> float:
    """Pixels of ``grid`` that ``degrees`` of view angle span at the image centre (a lens: its paraxial focal)."""
    fx, fy = (grid.K[0, 0], grid.K[1, 1]) if grid.is_ideal else grid.paraxial_focal
    f = 0.5 * (fx + fy)
    return f * math.tan(math.radians(degrees))


# ------------------------------------------------------------------------------------------- LiDAR depth


def lidar_grid_depth(points: np.ndarray, grid: Camera, occlusion_deg: float, min_depth: float = 1.0,
                     max_depth: float = 150.0) -> np.ndarray:
    """[h, w] float32 camera z (metres) of the nearest LiDAR return per cell of ``grid``, 0 = none, after the
    occlusion filter: a return is dropped when another return within ``occlusion_deg`` (a square window of
    2r + 1 cells, r = that angle in cells, at least 1) is nearer by more than runtime.lidar.DELTA (it lies behind
    a surface the camera sees: the LiDAR sits above and behind the cameras). points [P, 3] metres, ego frame."""
    from .lidar import lidar_depth_map, occlusion_filter

    d = lidar_depth_map(points, grid, min_depth, max_depth)
    r = max(1, round(_angle_pixels(grid, occlusion_deg)))
    return np.where(occlusion_filter(d, radius=r), d, 0).astype(np.float32)


def _guide(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(image, np.float32) * 255), 0, 255).astype(np.uint8)


@functools.cache
def one_thread_opencv():
    """The cv2 module, its thread pool set to one thread for the whole process (cv2.setNumThreads(1)), once.
    OpenCV's fast global smoother (densify) gives another result for each way its pool splits the image: one
    thread's, two threads', and, when another thread's OpenCV work holds the pool, the caller's alone (measured:
    9 of 20 calls from two threads at once differed, 20 of 20 beside another thread's blur). A keyframe's cameras
    are made two at a time, and a drive's next keyframe beside its fusion: with one OpenCV thread, the same bits
    every time (0 of 30), and no measured cost (the threads are the parallelism; a PandaSet frame 2.49 / 2.51 s)."""
    import cv2

    cv2.setNumThreads(1)
    return cv2


def edge_smoother(image: np.ndarray, smooth_lambda: float, smooth_sigma: float):
    """OpenCV's fast global smoother guided by ``image`` ([h, w, 3] float 0..1), for densify's calls on that image
    (a camera's LiDAR and its model's depth share one: its weights, made from the guide, are a third of a call's
    time; the same bits as a smoother made for each call, tests/runtime/test_detail.py)."""
    cv2 = one_thread_opencv()
    return cv2.ximgproc.createFastGlobalSmootherFilter(_guide(image), smooth_lambda, smooth_sigma)


def densify(sparse: np.ndarray, image: np.ndarray, smooth_lambda: float, smooth_sigma: float,
            smoother=None) -> np.ndarray:
    """[h, w] float32: ``sparse`` (0 = no value) spread edge-aware over the image ([h, w, 3] float 0..1) by
    normalised fast global smoothing: FGS(values) / FGS(mask). The smoothing stops at colour edges, so a depth is
    carried along a surface and not across an image edge. Log depth is smoothed (a near and a far value mix in
    ratio, not metres). Cells the smoothing does not reach get 0. OpenCV runs one thread from the first call on
    (one_thread_opencv). smoother: edge_smoother(image, smooth_lambda, smooth_sigma) when already made."""
    m = (sparse > 0).astype(np.float32)
    if not m.any():
        return np.zeros_like(sparse, np.float32)
    fgs = smoother if smoother is not None else edge_smoother(image, smooth_lambda, smooth_sigma)
    v = np.where(m > 0, np.log(np.maximum(sparse, 1e-6)), 0).astype(np.float32)
    num = fgs.filter(v)
    den = fgs.filter(m)
    # den below 1e-4: the smoothing carried (almost) no sample here; the quotient is noise
    ok = den > 1e-4
    out = np.zeros_like(sparse, np.float32)
    out[ok] = np.exp(num[ok] / den[ok])
    keep = m > 0
    out[keep] = sparse[keep]                 # the measured cells keep their measured depth
    return out


def support_mask(sparse: np.ndarray, radius_px: float) -> np.ndarray:
    """[h, w] bool: cells with a sample (sparse > 0) within ``radius_px`` cells (Euclidean)."""
    import cv2

    if not (sparse > 0).any():
        return np.zeros(sparse.shape, bool)
    dist = cv2.distanceTransform((sparse <= 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist <= radius_px


def edge_keep(depth: np.ndarray, edge_ratio: float) -> np.ndarray:
    """[h, w] bool: cells with a depth (> 0) that are not "flying" across a depth edge: a cell is dropped when it is
    both farther than (1 + edge_ratio) x the nearest and nearer than 1 / (1 + edge_ratio) x the farthest positive
    depth of its 3x3 neighbourhood (a depth between the two sides of a jump: the mixed cells a smoothing or an
    upsampling leaves there). The near side and the far side of an edge keep their cells."""
    import cv2

    k = np.ones((3, 3), np.uint8)
    r = np.float32(1.0 + edge_ratio)
    near = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
    far = cv2.dilate(np.where(depth > 0, depth, 0).astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
    return (depth > 0) & ~((depth > near * r) & (depth * r < far))


def edge_keep_reference(depth: np.ndarray, edge_ratio: float) -> np.ndarray:
    """`edge_keep` cell by cell (slow, obviously correct; for the tests)."""
    H, W = depth.shape
    out = np.zeros((H, W), bool)
    r = np.float32(1.0 + edge_ratio)
    for y in range(H):
        for x in range(W):
            if depth[y, x] <= 0:
                continue
            win = depth[max(0, y - 1):y + 2, max(0, x - 1):x + 2]
            win = win[win > 0]
            flying = depth[y, x] > win.min() * r and depth[y, x] * r < win.max()
            out[y, x] = not flying
    return out


GROUND_BAND = 0.15        # metres: LiDAR returns within this of the ground plane are ground (road roughness, noise)
GROUND_SHARE = 0.08      # the plane must carry this share of the 3-25 m returns (measured on the real sweeps:
#                          0.63 nuScenes, 0.19-0.21 PandaSet; a shallow plane across a steep slope carries a strip)
GROUND_RANGE = (3.0, 25.0)  # metres horizontal from the ego origin: the returns the plane is fitted to


def fit_ground(points: np.ndarray, min_points: int = 200, seed: int = 0) -> np.ndarray | None:
    """The ground plane of a LiDAR sweep: [4] (n, d) with n . x + d = 0, n a unit normal pointing up (ego z), or
    None when too few returns look like ground. points [P, 3] metres, ego frame (x forward, y left, z up).

    The returns 3-25 m away horizontally; RANSAC (seeded, deterministic): 256 planes through three of the lowest
    half of the returns, each scored by the returns within GROUND_BAND of it, planes steeper than 10 degrees
    refused (that is not a road under the car); then twice least squares on the best plane's returns within
    GROUND_BAND. A plane that carries less than GROUND_SHARE of the returns is refused too."""
    p = np.asarray(points, np.float64)
    r = np.hypot(p[:, 0], p[:, 1])
    p = p[(r >= GROUND_RANGE[0]) & (r <= GROUND_RANGE[1])]
    if len(p) < min_points:
        return None
    rng = np.random.default_rng(seed)
    low = p[p[:, 2] <= np.median(p[:, 2])]                   # the ground is among the lower returns
    sample = p[rng.choice(len(p), min(len(p), 20_000), replace=False)]
    tri = low[rng.integers(0, len(low), (256, 3))]           # [256, 3 points, 3]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n[ok] / norm[ok, None]
    n *= np.sign(n[:, 2:3] + 1e-12)                          # pointing up
    d = -np.einsum("ij,ij->i", n, tri[ok, 0])
    ok = n[:, 2] >= math.cos(math.radians(10.0))
    if not ok.any():
        return None
    n, d = n[ok], d[ok]
    dist = sample @ n.T                                      # [S, planes]: in place, counted without a sum
    dist += d                                                # of bools (the same values: 3-6x less time)
    np.abs(dist, out=dist)
    score = np.count_nonzero(dist <= GROUND_BAND, axis=0)
    best = int(np.argmax(score))
    if score[best] < GROUND_SHARE * len(sample):
        return None                                          # no plane carries the sweep: not a road
    plane = np.array([*n[best], d[best]])
    for _ in range(2):
        near = p[np.abs(p @ plane[:3] + plane[3]) <= GROUND_BAND]
        if len(near) < min_points:
            return None
        # z = a x + b y + c by least squares
        A = np.column_stack([near[:, 0], near[:, 1], np.ones(len(near))])
        (a, b, c), *_ = np.linalg.lstsq(A, near[:, 2], rcond=None)
        nv = np.array([-a, -b, 1.0])
        k = np.linalg.norm(nv)
        plane = np.array([*(nv / k), -c / k])
    if plane[2] < math.cos(math.radians(10.0)):
        return None
    return plane


def model_ground(coarse: Gaussians, min_opacity: float = 0.5) -> np.ndarray | None:
    """The ground plane of the model's Gaussians, for a reconstruction without LiDAR: fit_ground of the means of
    the Gaussians at least ``min_opacity`` opaque (ego frame). [4] or None. On the real rigs it lies 0.25-0.45 m
    below the LiDAR's (the model's depth overestimates the road's, so the plane is the model's own ground)."""
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(coarse.opacity_logits, np.float64)))
    return fit_ground(np.asarray(coarse.means, np.float64)[opacity >= min_opacity])


def grid_rays(grid: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(unit directions [h, w, 3] float64, ego frame, of the cells' rays; cos [h, w]: the factor that turns a
    distance along the ray into the camera's depth: the cosine with the optical axis (camera z), 1 for a camera
    whose depth is the distance). NaN where a lens cell has no ray. Cached by the camera's values (read-only)."""
    return _cached(_RAYS, RAYS_CACHE, geometry_key(grid), lambda: _make_rays(grid))


def _make_rays(grid: Camera) -> tuple[np.ndarray, np.ndarray]:
    unit, cos = _cached(_UNIT, RAYS_CACHE, lens_key(grid), lambda: _unit_rays(grid))
    d = unit @ grid.rotation.T
    _frozen(d)
    return d, cos


def _unit_rays(grid: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(unit directions [h, w, 3] float64, camera frame, of a grid camera's cells' rays; cos [h, w]: grid_rays'),
    read-only: its intrinsics'."""
    rays = cell_geometry(grid).rays
    if not grid.is_ideal:
        n = np.linalg.norm(rays, axis=-1)
    else:
        x, y = rays[0, :, 0], rays[:, 0, 1]         # (u - cx) / fx along a row, (v - cy) / fy down a column
        n = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    unit, cos = rays / n[..., None], 1.0 / n
    _frozen(unit, cos)
    return unit, cos


def sphere_depth(grid: Camera, radius: float, rays: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """[h, w] float32 the camera's depth (metres; 0 where a lens cell has no ray) where each cell's ray leaves the
    sphere of ``radius`` about the ego origin (the camera must be inside it). rays: grid_rays(grid), if at hand."""
    d, cos = rays or grid_rays(grid)
    c = grid.position
    b = d @ c
    t = -b + np.sqrt(np.maximum(b * b - (c @ c - radius * radius), 0.0))
    z = t * cos
    return (z if grid.is_ideal else np.where(np.isfinite(z), z, 0.0)).astype(np.float32)


def ground_depth(grid: Camera, plane: np.ndarray, rays: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """[h, w] float32 the camera's depth (metres) where each cell's ray meets the plane ([4], n . x + d = 0, ego
    frame), 0 where it does not (the ray parallel to it or pointing away, or no ray). rays: grid_rays(grid), if already at hand."""
    d, cos = rays or grid_rays(grid)
    n, off = plane[:3], plane[3]
    denom = d @ n
    t = -(grid.position @ n + off) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
    z = t * cos                                               # distance along the ray -> camera z
    return np.where(np.isfinite(z) & (t > 0), z, 0).astype(np.float32)


# ------------------------------------------------------------------------------------------- Gaussians


def surface_discs(points: np.ndarray, keep: np.ndarray, f: float, max_stretch: float,
                  unit: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Discs in the surface's tangent plane that cover each kept cell's footprint on it.

    points [h, w, 3] camera-frame points of the cells (metres); keep [h, w] bool; f: the grid's focal (pixels);
    unit [h, w]: the cells' footprint in metres (None: z / f, the image-plane footprint of an ideal pinhole).
    The tangents t_u, t_v are the point steps to the neighbouring cells (central differences where both neighbours
    are kept, one-sided where one is); the disc's covariance is t_u t_u^T + t_v t_v^T (the cell's footprint on the
    plane: it projects back onto the cell as a circle), its normal t_u x t_v. A cell gets no disc (ok False: it
    stays parallel to the image plane) when it has no neighbour along u or v, or a tangent is longer than
    ``max_stretch`` x its footprint (a grazing surface or a depth step).
    Returns, for the kept cells in np.nonzero order: rotation [M, 3, 3] (columns: the two disc axes, the normal
    towards the camera; camera frame), the disc's standard deviations along its axes per unit footprint [M, 2]
    (metres), ok [M] bool."""
    h, w = keep.shape
    ys, xs = np.nonzero(keep)
    P = points

    def step(dy: int, dx: int) -> tuple[np.ndarray, np.ndarray]:
        yp, xp = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
        ym, xm = np.clip(ys - dy, 0, h - 1), np.clip(xs - dx, 0, w - 1)
        kp = keep[yp, xp] & ((yp != ys) | (xp != xs))
        km = keep[ym, xm] & ((ym != ys) | (xm != xs))
        c = P[ys, xs]
        t = np.where((kp & km)[:, None], 0.5 * (P[yp, xp] - P[ym, xm]),
                     np.where(kp[:, None], P[yp, xp] - c, c - P[ym, xm]))
        return t, kp | km

    tu, oku = step(0, 1)
    tv, okv = step(1, 0)
    z = P[ys, xs, 2]
    L0 = z / f if unit is None else unit[ys, xs]
    n = np.cross(tu, tv)
    nn = np.linalg.norm(n, axis=1)
    lu, lv = np.linalg.norm(tu, axis=1), np.linalg.norm(tv, axis=1)
    ok = oku & okv & (nn > 1e-12) & (lu <= max_stretch * L0) & (lv <= max_stretch * L0) & (lu > 0)
    n = n / np.maximum(nn, 1e-12)[:, None]
    n = np.where((np.einsum("ij,ij->i", n, P[ys, xs]) > 0)[:, None], -n, n)     # towards the camera
    e1 = tu / np.maximum(lu, 1e-12)[:, None]
    e2 = np.cross(n, e1)
    a, b, c = lu, np.einsum("ij,ij->i", tv, e1), np.einsum("ij,ij->i", tv, e2)
    m00, m11, m01 = a * a + b * b, c * c, b * c
    phi = 0.5 * np.arctan2(2 * m01, m00 - m11)
    mid, rad = 0.5 * (m00 + m11), np.sqrt((0.5 * (m00 - m11)) ** 2 + m01 * m01)
    sd = np.sqrt(np.maximum(np.stack([mid + rad, mid - rad], axis=1), 1e-24))
    cp, sp = np.cos(phi)[:, None], np.sin(phi)[:, None]
    ax1, ax2 = cp * e1 + sp * e2, -sp * e1 + cp * e2
    return np.stack([ax1, ax2, n], axis=2), sd, ok


def _logit(p: np.ndarray) -> np.ndarray:
    return np.log(p / (1.0 - p))


@njit(inline="always")
def _step(depth, keep, rays, yp, xp, ym, xm, c0, c1, c2):
    """The step to the neighbouring cells (yp, xp) and (ym, xm) of the cell at camera point (c0, c1, c2), as
    surface_discs takes it: (whether there is one, (t0, t1, t2)). Scalars in and out (inlined: no temporary arrays
    between the cell loop and this, 178 -> 103 ms for a 960x540 grid's cells on one thread, the same bits)."""
    h, w = keep.shape
    kp = 0 <= yp < h and 0 <= xp < w and keep[yp, xp]
    km = 0 <= ym < h and 0 <= xm < w and keep[ym, xm]
    if kp and km:
        zp, zm = depth[yp, xp], depth[ym, xm]
        return True, (0.5 * (rays[yp, xp, 0] * zp - rays[ym, xm, 0] * zm),
                      0.5 * (rays[yp, xp, 1] * zp - rays[ym, xm, 1] * zm),
                      0.5 * (rays[yp, xp, 2] * zp - rays[ym, xm, 2] * zm))
    if kp:
        zp = depth[yp, xp]
        return True, (rays[yp, xp, 0] * zp - c0, rays[yp, xp, 1] * zp - c1, rays[yp, xp, 2] * zp - c2)
    if km:
        zm = depth[ym, xm]
        return True, (c0 - rays[ym, xm, 0] * zm, c1 - rays[ym, xm, 1] * zm, c2 - rays[ym, xm, 2] * zm)
    return False, (0.0, 0.0, 0.0)


@njit(cache=True)
def _quat(R, q):
    """rotmats_to_quats for one matrix (the same branch choice)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    best, c = tr, 0
    if R[0, 0] > best:
        best, c = R[0, 0], 1
    if R[1, 1] > best:
        best, c = R[1, 1], 2
    if R[2, 2] > best:
        c = 3
    if c == 0:
        s4 = 2.0 * math.sqrt(1.0 + tr)
        q[0], q[1], q[2], q[3] = 0.25 * s4, (R[2, 1] - R[1, 2]) / s4, (R[0, 2] - R[2, 0]) / s4, (R[1, 0] - R[0, 1]) / s4
    elif c == 1:
        s4 = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-12))
        q[0], q[1], q[2], q[3] = (R[2, 1] - R[1, 2]) / s4, 0.25 * s4, (R[0, 1] + R[1, 0]) / s4, (R[0, 2] + R[2, 0]) / s4
    elif c == 2:
        s4 = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-12))
        q[0], q[1], q[2], q[3] = (R[0, 2] - R[2, 0]) / s4, (R[0, 1] + R[1, 0]) / s4, 0.25 * s4, (R[1, 2] + R[2, 1]) / s4
    else:
        s4 = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-12))
        q[0], q[1], q[2], q[3] = (R[1, 0] - R[0, 1]) / s4, (R[0, 2] + R[2, 0]) / s4, (R[1, 2] + R[2, 1]) / s4, 0.25 * s4
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    for k in range(4):
        q[k] /= n


@njit(cache=True, parallel=True, nogil=True)
def _cells_kernel(depth, keep, row_start, rays, f, scale, Rce, tce, qcell, footprint, thickness, stretch,
                  means, quats, log_scales):
    """cell_gaussians_reference's geometry for the kept cells, one image row per task; row_start[y] = the index of
    row y's first kept cell (np.nonzero order). The row's work is a plain (serial) function: inlined into the
    prange body, the same code gave wrong tangents (the surface branch's variables, measured: discs flat)."""
    for y in numba.prange(keep.shape[0]):
        _cells_row(depth, keep, y, row_start[y], rays, f, scale, Rce, tce, qcell, footprint, thickness, stretch,
                   means, quats, log_scales)


@njit(cache=True, nogil=True)
def _cells_row(depth, keep, y, i, rays, f, scale, Rce, tce, qcell, footprint, thickness, stretch, means, quats,
               log_scales):
    """One image row of _cells_kernel, its first kept cell at index i."""
    w = keep.shape[1]
    per_cell = 0 if qcell.shape[0] * qcell.shape[1] == 1 else 1     # [1, 1, 4]: one quat for every cell
    Rl = np.empty((3, 3))
    Re = np.empty((3, 3))
    q = np.empty(4)
    for x in range(w):
        if not keep[y, x]:
            continue
        z = depth[y, x]
        c0, c1, c2 = rays[y, x, 0] * z, rays[y, x, 1] * z, rays[y, x, 2] * z
        for r in range(3):
            means[i, r] = Rce[r, 0] * c0 + Rce[r, 1] * c1 + Rce[r, 2] * c2 + tce[r]
        s = footprint * z / f * scale[y, x]
        ok = False
        if stretch > 0:
            oku, tu = _step(depth, keep, rays, y, x + 1, y, x - 1, c0, c1, c2)
            okv, tv = _step(depth, keep, rays, y + 1, x, y - 1, x, c0, c1, c2)
            if oku and okv:
                nx = tu[1] * tv[2] - tu[2] * tv[1]
                ny = tu[2] * tv[0] - tu[0] * tv[2]
                nz = tu[0] * tv[1] - tu[1] * tv[0]
                nn = math.sqrt(nx * nx + ny * ny + nz * nz)
                lu = math.sqrt(tu[0] * tu[0] + tu[1] * tu[1] + tu[2] * tu[2])
                lv = math.sqrt(tv[0] * tv[0] + tv[1] * tv[1] + tv[2] * tv[2])
                L0 = z / f * scale[y, x]
                ok = nn > 1e-12 and lu <= stretch * L0 and lv <= stretch * L0 and lu > 0
        if ok:
            nx, ny, nz = nx / nn, ny / nn, nz / nn
            if nx * c0 + ny * c1 + nz * c2 > 0:
                nx, ny, nz = -nx, -ny, -nz
            e1x, e1y, e1z = tu[0] / lu, tu[1] / lu, tu[2] / lu
            e2x, e2y, e2z = ny * e1z - nz * e1y, nz * e1x - nx * e1z, nx * e1y - ny * e1x
            a = lu
            b = tv[0] * e1x + tv[1] * e1y + tv[2] * e1z
            cc = tv[0] * e2x + tv[1] * e2y + tv[2] * e2z
            m00, m11, m01 = a * a + b * b, cc * cc, b * cc
            mid = 0.5 * (m00 + m11)
            rad = math.sqrt((0.5 * (m00 - m11)) ** 2 + m01 * m01)
            # the reference's phi = atan2(2 m01, m00 - m11) / 2 in (-pi/2, pi/2], by the half-angle formulas from
            # cos 2phi = (m00 - m11) / (2 rad) (cos phi >= 0; sin phi takes 2 m01's sign, a signed zero as atan2
            # does): two square roots for atan2, cos and sin
            if rad > 0:
                c2 = min(max(0.5 * (m00 - m11) / rad, -1.0), 1.0)
                cp = math.sqrt(0.5 * (1.0 + c2))
                sp = math.copysign(math.sqrt(0.5 * (1.0 - c2)), m01)
            else:
                cp, sp = 1.0, 0.0
            sd1 = math.sqrt(max(mid + rad, 1e-24))
            sd2 = math.sqrt(max(mid - rad, 1e-24))
            Rl[0, 0], Rl[1, 0], Rl[2, 0] = cp * e1x + sp * e2x, cp * e1y + sp * e2y, cp * e1z + sp * e2z
            Rl[0, 1], Rl[1, 1], Rl[2, 1] = -sp * e1x + cp * e2x, -sp * e1y + cp * e2y, -sp * e1z + cp * e2z
            Rl[0, 2], Rl[1, 2], Rl[2, 2] = nx, ny, nz
            for r in range(3):
                for k in range(3):
                    Re[r, k] = Rce[r, 0] * Rl[0, k] + Rce[r, 1] * Rl[1, k] + Rce[r, 2] * Rl[2, k]
            _quat(Re, q)
            for k in range(4):
                quats[i, k] = q[k]
            log_scales[i, 0] = math.log(footprint * sd1)
            log_scales[i, 1] = math.log(footprint * sd2)
        else:
            for k in range(4):
                quats[i, k] = qcell[y * per_cell, x * per_cell, k]
            log_scales[i, 0] = math.log(s)
            log_scales[i, 1] = math.log(s)
        log_scales[i, 2] = math.log(thickness * s)
        i += 1


def cell_gaussians(grid: Camera, colours: np.ndarray, depth: np.ndarray, opacity: np.ndarray, keep: np.ndarray,
                   footprint: float, thickness: float, sh_degree: int = 0, surface_stretch: float = 0.0
                   ) -> Gaussians:
    """cell_gaussians_reference, its geometry in one numba pass over the cells (the same Gaussians, in the same
    order; tested against it)."""
    keep = np.ascontiguousarray(keep, bool)
    counts = keep.sum(axis=1)
    n = int(counts.sum())
    row_start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    # float32 written by the kernel (its float64 values rounded on assignment, as astype(np.float32) rounds them)
    means = np.empty((n, 3), np.float32)
    quats = np.empty((n, 4), np.float32)
    log_s = np.empty((n, 3), np.float32)
    geo = cell_geometry(grid)
    if n:
        _cells_kernel(np.ascontiguousarray(depth, np.float64), keep, row_start, np.ascontiguousarray(geo.rays),
                      float(geo.f), np.ascontiguousarray(geo.scale), np.ascontiguousarray(grid.rotation, np.float64),
                      np.ascontiguousarray(grid.position, np.float64), _cell_quats(geo.quats),
                      float(footprint), float(thickness), float(surface_stretch), means, quats, log_s)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3), np.float32)
    sh[:, 0, :] = (_at_cells(colours, keep) - 0.5) / SH_C0
    return Gaussians(means=means, quats=quats, log_scales=log_s,
                     opacity_logits=_logit(_at_cells(opacity, keep)).astype(np.float32), sh=sh)


def _cell_quats(quats: np.ndarray) -> np.ndarray:
    """CellGeometry.quats for _cells_kernel: [h, w, 4] float64 contiguous, or [1, 1, 4] when every cell has the
    same one (a pinhole's: a broadcast view, not made into 16 MB of copies)."""
    if quats.strides[:2] == (0, 0):
        return np.array(quats[:1, :1], np.float64)          # a writable copy: one signature of the kernel
    return np.ascontiguousarray(quats, np.float64)


def cell_gaussians_reference(grid: Camera, colours: np.ndarray, depth: np.ndarray, opacity: np.ndarray,
                             keep: np.ndarray, footprint: float, thickness: float, sh_degree: int = 0,
                             surface_stretch: float = 0.0) -> Gaussians:
    """One Gaussian per kept cell of ``grid`` (ego frame).

    colours [h, w, 3] 0..1; depth [h, w] the camera's depth, metres (camera z, or the distance for a fisheye or
    f-theta lens); opacity [h, w] in (0, 1); keep [h, w] bool (cells of a lens camera need a ray). Centre: the cell's
    point at its depth, depth x CellGeometry.rays (an ideal pinhole: the OpenCV camera point (x z, y z, z) with
    x = (u - cx) / fx, y = (v - cy) / fy; a lens: along the cell's true ray), moved to ego by cam_to_ego; a disc
    facing the cell (an ideal pinhole: parallel to the image plane; a lens: across the cell's ray) with standard
    deviation footprint x the cell's footprint (depth / f x CellGeometry.scale: z / f for an ideal pinhole, f the
    mean focal of ``grid`` in pixels; a lens: the distance x the cell's angular size) and thickness x that along
    its normal; SH of degree ``sh_degree`` with only
    the DC term set (colour = SH_C0 dc + 0.5). surface_stretch > 0: a cell whose neighbours give it a tangent plane
    (surface_discs, tangents at most surface_stretch x the image-plane footprint) lies in that plane instead, as the
    footprint of the cell on the surface (footprint x its extents; thickness along the normal): it looks the same
    from its own camera and keeps its shape on the surface from elsewhere."""
    ys, xs = np.nonzero(keep)
    z = depth[ys, xs].astype(np.float64)
    geo = cell_geometry(grid)
    q = geo.rays[ys, xs] * z[:, None]
    means = q @ grid.rotation.T + grid.position
    f = geo.f
    s = footprint * z / f * geo.scale[ys, xs]
    log_s = np.log(np.stack([s, s, thickness * s], axis=-1))
    quat = geo.quats[ys, xs]
    if surface_stretch > 0 and len(z):
        d = depth.astype(np.float64)
        P = geo.rays * d[..., None]
        R, sd, ok = surface_discs(P, keep, f, surface_stretch, None if grid.is_ideal else d / f * geo.scale)
        if ok.any():
            log_s = log_s.copy()
            log_s[ok] = np.log(np.concatenate([footprint * sd[ok], thickness * s[ok, None]], axis=1))
            quat = quat.copy()
            quat[ok] = rotmats_to_quats(np.einsum("ij,njk->nik", grid.rotation, R[ok]))
    sh = np.zeros((len(z), (sh_degree + 1) ** 2, 3), np.float32)
    sh[:, 0, :] = (colours[ys, xs] - 0.5) / SH_C0
    return Gaussians(means=means.astype(np.float32), quats=np.ascontiguousarray(quat, np.float32),
                     log_scales=log_s.astype(np.float32), opacity_logits=_logit(opacity[ys, xs]).astype(np.float32),
                     sh=sh)


@dataclass(frozen=True, eq=False)
class SplitCells:
    """The kept cells of one camera's detail layer that are drawn as their four quarters (split_cells): a cell at
    stride s holds s x s pixels, and where its quarters differ the cell's one colour (their mean) loses their detail
    (at stride 2 the quarters are the pixels)."""

    index: np.ndarray     # [S] int64: the cells, as indices into the detail's Gaussians (np.nonzero(keep) order)
    means: np.ndarray     # [S, 4, 3] float32 metres, ego frame: each quarter's ray met with its cell's disc plane
    colours: np.ndarray   # [S, 4, 3] float32 sRGB 0..1: the quarters' colours (unsharp as the cells'), rows first

    def moved(self, T: np.ndarray) -> SplitCells:
        """These cells moved by the rigid [4, 4] ``T`` (metres)."""
        R = np.asarray(T[:3, :3], np.float64)
        m = (self.means.astype(np.float64) @ R.T + np.asarray(T[:3, 3], np.float64)).astype(np.float32)
        return replace(self, means=m)

    def divided(self, gain: np.ndarray) -> SplitCells:
        """These cells with their colours divided by ``gain`` ([3] per channel; runtime.exposure.apply_gain's)."""
        return replace(self, colours=(self.colours / np.asarray(gain, np.float32)).astype(np.float32))


def split_cells(cam: Camera, image: np.ndarray, grid: Camera, g: Gaussians, keep: np.ndarray, threshold: float,
                sharpen: float, footprint: float) -> SplitCells | None:
    """The kept cells of ``grid`` (cam's grid_camera at an even stride s) whose four quarters (s/2 x s/2 pixel
    blocks of ``image``, [H, W, 3] float32 0..1, cam's) hold one whose area mean's luma (BT.601: cameras and JPEG
    keep colour at half the luma's resolution, and the eye and the sharpness ratio look at luma) is farther than
    ``threshold`` from the four's mean; None when there are none, s is odd, or the grid does not tile the image in whole
    blocks (cam's size not s x the grid's). ``g``: the cells' Gaussians (ego frame, np.nonzero(keep) order). Each
    quarter sits where its ray (cam's grid at stride s/2, through the quarter's centre) meets the plane of its cell's
    disc (the disc's third axis its normal), or, where that is more than a quarter off the cell's distance (a ray
    grazing the plane), at the cell's distance along the ray; its colour is grid_colours at stride s/2 (the unsharp
    mask of amount ``sharpen``, its blur ``footprint`` quarters, as the cells')."""
    s = int(round(cam.width / grid.width))
    h, w = grid.height, grid.width
    if threshold <= 0 or s < 2 or s % 2 or cam.width != s * w or cam.height != s * h or not len(g):
        return None
    import cv2

    fine = grid_camera(cam, s // 2)                                 # 2w x 2h: the quarters
    quarters = grid_colours(image, fine)
    stray = _stray_kernel(quarters, np.ascontiguousarray(keep, bool), np.float32(threshold), LUMA_BT601)
    idx = np.flatnonzero(stray[keep])
    if not len(idx):
        return None
    ys, xs = np.nonzero(stray)
    qy = ys[:, None] * 2 + np.array([0, 0, 1, 1])[None, :]          # [S, 4] the quarters, rows first
    qx = xs[:, None] * 2 + np.array([0, 1, 0, 1])[None, :]
    colours = quarters[qy, qx]
    if sharpen > 0:          # grid_colours' unsharp mask at the quarters, evaluated only where they are drawn
        blur = cv2.GaussianBlur(quarters, (0, 0), footprint, borderType=cv2.BORDER_REFLECT)[qy, qx]
        colours = np.clip(colours + np.float32(sharpen) * (colours - blur), 0.0, 1.0)
    if fine.is_ideal:           # the pinhole's rays (x, y, 1) at the quarters' centres, turned to ego
        K = fine.K
        rays = np.stack([(qx - K[0, 2]) / K[0, 0], (qy - K[1, 2]) / K[1, 1], np.ones(qx.shape)], axis=-1)
        rays = (rays.reshape(-1, 3) @ fine.rotation.T).reshape(rays.shape)     # one [4S, 3] product, not S of them
    else:                       # a lens: its true rays (NaN where none)
        rays = fine.pixel_rays(np.stack([qx, qy], axis=-1).astype(np.float64))[1]
    means = np.empty((len(idx), 4, 3), np.float32)
    _quarters_kernel(np.ascontiguousarray(g.means[idx], np.float64), np.ascontiguousarray(g.quats[idx], np.float64),
                     np.ascontiguousarray(rays, np.float64), np.ascontiguousarray(cam.position, np.float64), means)
    return SplitCells(index=idx.astype(np.int64), means=means, colours=colours.astype(np.float32))


@njit(cache=True, parallel=True, nogil=True)
def _quarters_kernel(centre, quats, rays, origin, means):
    """split_cells' quarter centres: means[s, k] (float32) where rays[s, k] from ``origin`` (any length; ego frame)
    meets the plane through centre[s] normal to the third axis of quats[s] (wxyz), unless that is more than a
    quarter off the centre's distance (then at that distance along the ray); no ray (NaN): the centre."""
    for s in numba.prange(centre.shape[0]):
        w, x, y, z = quats[s, 0], quats[s, 1], quats[s, 2], quats[s, 3]
        nq = w * w + x * x + y * y + z * z
        n0, n1, n2 = 2.0 * (x * z + w * y) / nq, 2.0 * (y * z - w * x) / nq, 1.0 - 2.0 * (x * x + y * y) / nq
        c0, c1, c2 = centre[s, 0] - origin[0], centre[s, 1] - origin[1], centre[s, 2] - origin[2]
        dist = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        across = n0 * c0 + n1 * c1 + n2 * c2
        for k in range(4):
            r0, r1, r2 = rays[s, k, 0], rays[s, k, 1], rays[s, k, 2]
            length = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            if not (length > 0.0):                   # NaN (no ray) or zero
                for a in range(3):
                    means[s, k, a] = centre[s, a]
                continue
            dn = n0 * r0 + n1 * r1 + n2 * r2
            t = dist / length
            if dn != 0.0:
                tp = across / dn
                if abs(tp * length - dist) <= 0.25 * dist:
                    t = tp
            means[s, k, 0] = origin[0] + t * r0
            means[s, k, 1] = origin[1] + t * r1
            means[s, k, 2] = origin[2] + t * r2


@njit(cache=True, parallel=True, nogil=True)
def _stray_kernel(quarters, keep, threshold, luma):
    """[h, w] bool: the kept cells with a quarter (quarters [2h, 2w, 3], each cell's four in its 2x2 block) whose
    luma (weights ``luma`` [3]) is farther than ``threshold`` from the four's mean (split_cells)."""
    h, w = keep.shape
    out = np.zeros((h, w), np.bool_)
    for y in numba.prange(h):
        v = np.empty(4, np.float32)             # the row's own (one per task: rows run in parallel)
        for x in range(w):
            if not keep[y, x]:
                continue
            for k in range(4):
                yy, xx = 2 * y + k // 2, 2 * x + k % 2
                v[k] = luma[0] * quarters[yy, xx, 0] + luma[1] * quarters[yy, xx, 1] + luma[2] * quarters[yy, xx, 2]
            m = np.float32(0.25) * (v[0] + v[1] + v[2] + v[3])
            out[y, x] = max(abs(v[0] - m), abs(v[1] - m), abs(v[2] - m), abs(v[3] - m)) > threshold
    return out


def stray_reference(quarters: np.ndarray, keep: np.ndarray, threshold: float) -> np.ndarray:
    """_stray_kernel in numpy (slow, obviously correct; tests)."""
    h, w = keep.shape
    y = (np.asarray(quarters, np.float32) @ LUMA_BT601).reshape(h, 2, w, 2)
    mean = y.mean(axis=(1, 3), keepdims=True)
    return (np.abs(y - mean).max(axis=(1, 3)) > threshold) & keep


def quarters_reference(centre: np.ndarray, quats: np.ndarray, rays: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """_quarters_kernel in numpy (slow, obviously correct; tests): [S, 4, 3] float32."""
    centre = np.asarray(centre, np.float64)
    normal = quat_to_rotmat(quats)[:, :, 2]                         # the disc's normal: its third axis
    dist = np.linalg.norm(centre - origin, axis=1)[:, None]         # [S, 1]
    length = np.linalg.norm(rays, axis=-1)                          # [S, 4]
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = np.einsum("nk,nk->n", normal, centre - origin)[:, None] / np.einsum("nk,nsk->ns", normal, rays)
        t = np.where(np.abs(tp * length - dist) <= 0.25 * dist, tp, dist / length)
    means = origin + rays * t[..., None]
    no_ray = ~(length > 0)
    means[no_ray] = np.broadcast_to(centre[:, None, :], means.shape)[no_ray]
    return means.astype(np.float32)


def expand_split(g: Gaussians, d: CameraDetail, keep: np.ndarray | None = None) -> Gaussians:
    """One camera's detail Gaussians ``g`` (d's cells, in order) where ``keep`` ([M] bool, None: all) holds, each of
    d.split's cells replaced by its four quarters (expand_rows): the non-split cells first, in order, then the
    quarters."""
    keep = np.ones(len(g), bool) if keep is None else np.asarray(keep, bool)
    sp = d.split
    if sp is None or not len(sp.index):
        return g.subset(keep)
    return expand_rows(g.subset(keep), split_rows(len(g), sp)[keep], sp.means, sp.colours)


def expand_split_parts(g: Gaussians, d: CameraDetail, keep: np.ndarray) -> list[Gaussians]:
    """expand_split's Gaussians as the parts of their concatenation, not joined (each copied once: a drive writes
    them to a camera layer's file, runtime.cameralayers): the kept cells that do not split, then the quarters of
    those that do (a part left out when empty)."""
    keep = np.asarray(keep, bool)
    sp = d.split
    if sp is None or not len(sp.index):
        return [g.subset(keep)]
    rows = split_rows(len(g), sp)
    whole = keep & (rows < 0)
    out = [g.subset(whole)] if whole.any() else []
    quarters = _quarters(g, keep & (rows >= 0), rows, sp.means, sp.colours)
    return out + ([quarters] if len(quarters) else [])


def split_rows(n: int, sp: SplitCells) -> np.ndarray:
    """[n] int32: for each of a camera's n cells, its row in ``sp``'s arrays, -1 for a cell that does not split."""
    rows = np.full(n, -1, np.int32)
    rows[sp.index] = np.arange(len(sp.index), dtype=np.int32)
    return rows


def expand_rows(g: Gaussians, rows: np.ndarray, means: np.ndarray, colours: np.ndarray) -> Gaussians:
    """Cells ``g`` with each one whose ``rows`` ([N] int, -1: none) names a row of SplitCells arrays ``means`` /
    ``colours`` ([S, 4, 3]) replaced by its four quarters (the cell's rotation, opacity and SH degree, half its
    scales, the quarter's colour as the DC term): the other cells first, in order, then the quarters, cell by
    cell."""
    split = rows >= 0
    if not split.any():
        return g
    quarters = _quarters(g, split, rows, means, colours)
    return quarters if split.all() else concat_gaussians([g, quarters], [~split, None])


def _quarters(g: Gaussians, split: np.ndarray, rows: np.ndarray, means: np.ndarray, colours: np.ndarray) -> Gaussians:
    """The quarters (expand_rows) of the cells of ``g`` where ``split`` ([N] bool) holds, cell by cell; ``rows`` [N]
    their rows of the SplitCells arrays ``means`` / ``colours`` [S, 4, 3]."""
    r = rows[split]
    cells = np.flatnonzero(split)
    sh = np.zeros((len(r) * 4, g.sh.shape[1], 3), np.float32)
    sh[:, 0, :] = (colours[r].reshape(-1, 3) - 0.5) / SH_C0
    return Gaussians(means=means[r].reshape(-1, 3), quats=np.repeat(g.quats[cells], 4, axis=0),
                     log_scales=np.repeat(g.log_scales[cells], 4, axis=0) - np.float32(math.log(2.0)),
                     opacity_logits=np.repeat(g.opacity_logits[cells], 4), sh=sh)


# ------------------------------------------------------------------------------------------- fusion


CONF_MODEL, CONF_MEASURED = 1, 2   # cell confidence: the model's depth or the far layer / LiDAR or ground plane
PYRAMID_LEVELS = 7                  # window radii 1, 2, 4, ..., 64 cells for the coarse layer's footprints


@dataclass(frozen=True, eq=False)
class CameraDetail:
    """One input camera's detail layer: the cell maps at the grid camera's size and its Gaussians' per-cell data in
    the order of ``np.nonzero(keep)`` (the order cell_gaussians emits)."""

    grid: Camera              # the grid camera (ego frame)
    depth: np.ndarray         # [h, w] float32 the kept cells' depth (the camera's: Camera.depth_is_distance), metres,
    #                           0 elsewhere
    keep: np.ndarray          # [h, w] bool: cells that became Gaussians
    conf: np.ndarray          # [h, w] int8: CONF_MEASURED / CONF_MODEL for kept cells, 0 elsewhere
    means: np.ndarray         # [M, 3] float64 metres, ego frame: the kept cells' centres
    rank: np.ndarray          # [M] float64 metres: the cells' footprint (cell_footprint)
    colours: np.ndarray | None = None   # [h, w, 3] uint8 sRGB: the image at the grid (grid_colours), or None
    split: SplitCells | None = None     # the cells drawn one Gaussian per input pixel (split_cells), or None

    @classmethod
    def build(cls, grid: Camera, depth: np.ndarray, keep: np.ndarray, measured: np.ndarray, means: np.ndarray,
              colours: np.ndarray | None = None, split: SplitCells | None = None) -> CameraDetail:
        d = np.where(keep, depth, 0).astype(np.float32)
        conf = np.where(keep, np.where(measured, CONF_MEASURED, CONF_MODEL), 0).astype(np.int8)
        ys, xs = np.nonzero(keep)
        c8 = None if colours is None else np.clip(np.rint(colours * 255.0), 0, 255).astype(np.uint8)
        return cls(grid, d, keep, conf, np.asarray(means, np.float64), cell_footprint(grid, xs, ys, d[ys, xs]), c8,
                   split)

    def cell_colours(self) -> np.ndarray:
        """[M, 3] uint8: the kept cells' colours (their grid pixel's), in Gaussian order (made once: the maps are
        not changed after build, dataclasses.replace makes a new detail)."""
        return self._once("_cell_colours", lambda: _at_cells(self.colours, self.keep))

    def cell_conf(self) -> np.ndarray:
        """[M] int8: the kept cells' confidence, in Gaussian order (made once, as cell_colours)."""
        return self._once("_cell_conf", lambda: _at_cells(self.conf, self.keep))

    def _once(self, key: str, make: Callable[[], np.ndarray]) -> np.ndarray:
        v = self.__dict__.get(key)
        if v is None:
            v = self.__dict__[key] = make()     # a frozen dataclass: its __dict__ holds the memo
        return v

    def max_pyramid(self) -> list[np.ndarray]:
        """[PYRAMID_LEVELS] of [h, w] float32: level L holds the largest kept-cell depth within 2^L cells (square
        window; 0 where the window holds no kept cell). Each level dilates the one below by 2^(L-1) cells (a max
        of maxima: the same values as a window of 2^L around the depth, at half the kernel's width)."""
        import cv2

        out = [cv2.dilate(self.depth, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)]
        for L in range(1, PYRAMID_LEVELS):
            out.append(cv2.dilate(out[-1], np.ones((2 ** L + 1, 2 ** L + 1), np.uint8),
                                  borderType=cv2.BORDER_CONSTANT, borderValue=0))
        return out


def _at_cells(a: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """a[keep] for a map ``a`` [h, w, ...] and a mask ``keep`` [h, w]: the same values in the same (row-major) order,
    gathered by flat index (np.take: a quarter of the time of numpy's boolean indexing of a [h, w, 3] map)."""
    return np.take(a.reshape(keep.size, *a.shape[2:]), np.flatnonzero(keep), axis=0)


def cell_footprint(grid: Camera, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """[N] metres: the size of cell (u, v) of ``grid`` at depth ``z`` across its ray, z sqrt(1 + x^2 + y^2) / f
    (x, y normalised coordinates; a lens: z x CellGeometry.across, the distance x the cell's angular size): how
    finely that camera resolves the point (smaller = sharper)."""
    if not grid.is_ideal:
        return np.asarray(z, np.float64) * cell_geometry(grid).across[v, u]
    K = grid.K
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return np.asarray(z, np.float64) * np.sqrt(1.0 + x * x + y * y) / (0.5 * (K[0, 0] + K[1, 1]))


def _grid_pixels(grid: Camera, means: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(indices of the points that land on a cell, their cell column, row, depth (the camera's)) for means [N, 3]
    ego."""
    uv, z, front = grid.project_depth(means)
    px = np.rint(uv).astype(np.int64)
    ok = front & (px[:, 0] >= 0) & (px[:, 0] < grid.width) & (px[:, 1] >= 0) & (px[:, 1] < grid.height)
    idx = np.flatnonzero(ok)
    return idx, px[idx, 0], px[idx, 1], z[idx]


def coarse_radius_cells(log_scales: np.ndarray, grid: Camera, z: np.ndarray, u: np.ndarray | None = None,
                        v: np.ndarray | None = None) -> np.ndarray:
    """[N] the 3-sigma radius (largest axis) of Gaussians with ``log_scales`` [N, 3] at camera z ``z`` [N] (metres),
    in cells of ``grid``; a lens camera: at depth z on cells (u, v), over the cells' footprint there
    (cell_footprint)."""
    sigma3 = 3.0 * np.exp(log_scales.astype(np.float64).max(axis=1))
    if not grid.is_ideal:
        return sigma3 / np.maximum(cell_footprint(grid, u, v, z), 1e-9)
    f = 0.5 * (grid.K[0, 0] + grid.K[1, 1])
    return sigma3 * f / np.maximum(z, 1e-6)


def cull_covered(coarse: Gaussians, details: list[CameraDetail], tolerance: float,
                 pyramids: list[np.ndarray] | None = None) -> np.ndarray:
    """[N] bool: the coarse Gaussians to keep. A Gaussian is culled when, in some input camera, its centre projects
    onto the image and a kept detail cell within its footprint (3 sigma, as a window of 2^L cells, at most 64) lies
    behind it or within ``tolerance`` of it (its camera z < (1 + tolerance) x that cell's depth): composited in
    front of that cell, it would veil or blur a surface the camera saw sharply. What is left lies behind every
    detail surface its footprint touches (disocclusions) or where no camera has detail. pyramids: detail_pyramids
    of ``details``, when several sets are culled against the same details (else made here)."""
    keep = np.ones(len(coarse), bool)
    for i, d in enumerate(details):
        idx, u, v, z = _grid_pixels(d.grid, coarse.means)
        level = np.clip(np.ceil(np.log2(np.maximum(coarse_radius_cells(coarse.log_scales[idx], d.grid, z, u, v),
                                                   1.0))), 0, PYRAMID_LEVELS - 1).astype(np.int64)
        pyr = pyramids[i] if pyramids is not None else np.stack(d.max_pyramid())
        dmax = pyr[level, v, u]
        keep[idx[(dmax > 0) & (z < dmax * (1.0 + tolerance))]] = False
    return keep


def detail_pyramids(details: list[CameraDetail]) -> list[np.ndarray]:
    """[PYRAMID_LEVELS, h, w] float32 per detail: its max_pyramid stacked, as cull_covered takes them."""
    return [np.stack(d.max_pyramid()) for d in details]


def cull_covered_reference(coarse: Gaussians, details: list[CameraDetail], tolerance: float) -> np.ndarray:
    """`cull_covered` Gaussian by Gaussian, the window searched cell by cell (slow, obviously correct; tests)."""
    keep = np.ones(len(coarse), bool)
    for i, m in enumerate(np.asarray(coarse.means, np.float64)):
        sigma = math.exp(float(np.max(coarse.log_scales[i])))
        for d in details:
            hit = _cell_of(d.grid, m)
            if hit is None:
                continue
            u, v, z = hit
            r_cells = 3.0 * sigma * 0.5 * (d.grid.K[0, 0] + d.grid.K[1, 1]) / z if d.grid.is_ideal else \
                3.0 * sigma / (z * cell_geometry(d.grid).across[v, u])
            L = min(max(math.ceil(math.log2(max(r_cells, 1.0))), 0), PYRAMID_LEVELS - 1)
            r = 2 ** L
            win = d.depth[max(0, v - r):v + r + 1, max(0, u - r):u + r + 1][d.keep[max(0, v - r):v + r + 1,
                                                                              max(0, u - r):u + r + 1]]
            if win.size and z < win.max() * (1.0 + tolerance):
                keep[i] = False
    return keep


def _cell_of(grid: Camera, m: np.ndarray) -> tuple[int, int, float] | None:
    """(column, row, depth) of the cell of ``grid`` an ego point [3] lands on, None when it lands on none (for the
    references: an ideal pinhole by its formula, a lens camera through Camera.project_depth)."""
    if grid.is_ideal:
        q = grid.rotation.T @ (m - grid.position)
        if q[2] <= 1e-6:
            return None
        u = int(np.rint(grid.K[0, 0] * q[0] / q[2] + grid.K[0, 2]))
        v = int(np.rint(grid.K[1, 1] * q[1] / q[2] + grid.K[1, 2]))
        z = float(q[2])
    else:
        uv, dz, front = grid.project_depth(m[None])
        if not front[0]:
            return None
        u, v, z = int(np.rint(uv[0, 0])), int(np.rint(uv[0, 1])), float(dz[0])
    return (u, v, z) if 0 <= u < grid.width and 0 <= v < grid.height else None


@njit(cache=True, parallel=True, nogil=True)
def _carve_kernel(means, conf, rank, keep, free, photo, colour, R, t, K, hw, off, depth, cell_conf, image,
                  has_image, skip, tolerance, dedupe, p_abs, p_rel):
    """Clear keep[k] for the cells ``means`` [M, 3] (ego; confidence conf [M], footprint rank [M]) that one of the
    pinhole cameras c of a CarveCameras stack contradicts (see carve_details), camera ``skip`` left out (-1: none):
    world-to-camera rotations R [C, 3, 3] (rotation^T), centres t [C, 3], K [C, 4] (fx, fy, cx, cy), sizes hw [C, 2];
    their cell maps depth (float32) and cell_conf (int8, 0 = no cell) and images [.., 3] uint8 flat, camera c's
    pixel (u, v) at off[c] + v w + u. A cell dropped by one camera is not tested against the next (the tests are
    independent). ``photo``: the free-space drop only where the cell's colour (colour [M, 3] uint8) is not seen in
    camera c's image (has_image[c]) at the pixel or its 8 neighbours, within p_abs + p_rel x the larger value
    (colour_seen is its reference). ``free`` [M] bool (or [0]: none): cleared by the free-space rule alone, in the
    same pass (what a second pass with dedupe 0 would leave of it: carve_details_both). One pass over the cells for
    all the cameras: each cell read once, not once a camera."""
    track = free.shape[0] > 0
    for k in numba.prange(means.shape[0]):
        if not keep[k] and not (track and free[k]):
            continue
        mx, my, mz = means[k, 0], means[k, 1], means[k, 2]
        for c in range(R.shape[0]):
            if c == skip:
                continue
            px, py, pz = mx - t[c, 0], my - t[c, 1], mz - t[c, 2]
            z = R[c, 2, 0] * px + R[c, 2, 1] * py + R[c, 2, 2] * pz
            if z <= 1e-6:
                continue
            # the column first: most cells in front of a camera of the ring are left or right of its view (of
            # PandaSet's: 45 % of the (cell, camera) pairs in front, 16 % in its columns, 15 % in its view), and
            # those need no row (the same arithmetic as before, so the same cells: 20 PandaSet keyframes' carving
            # 13 % faster)
            fx, cx, w = K[c, 0], K[c, 2], hw[c, 1]
            x = (R[c, 0, 0] * px + R[c, 0, 1] * py + R[c, 0, 2] * pz) / z
            u = int(np.rint(fx * x + cx))
            if u < 0 or u >= w:
                continue
            fy, cy, h = K[c, 1], K[c, 3], hw[c, 0]
            y = (R[c, 1, 0] * px + R[c, 1, 1] * py + R[c, 1, 2] * pz) / z
            v = int(np.rint(fy * y + cy))
            if v < 0 or v >= h:
                continue
            at = off[c] + v * w + u
            if cell_conf[at] == 0 or cell_conf[at] < conf[k]:
                continue
            dc = depth[at]
            if z < dc * (1.0 - tolerance):
                if not (photo and has_image[c]) or not _seen_near(colour, k, image, off[c], h, w, u, v, p_abs,
                                                                  p_rel):
                    keep[k] = False
                    if track:
                        free[k] = False
                    break
            elif dedupe > 0.0 and keep[k] and abs(z - dc) <= tolerance * dc:
                # (dedupe 0, carve_against's: the footprint would be computed for a test that never drops; 20
                # PandaSet keyframes' carving against their neighbours ~23 % less CPU, the same cells)
                xi, yi = (u - cx) / fx, (v - cy) / fy
                rank_i = dc * math.sqrt(1.0 + xi * xi + yi * yi) / (0.5 * (fx + fy))
                if rank_i < dedupe * rank[k]:
                    keep[k] = False
                    if not (track and free[k]):     # the free-space rule is still to be tested for ``free``
                        break


_NO_COLOUR = np.zeros((0, 3), np.uint8)      # _carve_kernel's colour when it has no colour test
_NO_FREE = np.zeros(0, bool)                 # _carve_kernel's free when only keep is carved


@njit(inline="always")
def _seen_near(colour, k, image, off, h, w, u, v, p_abs, p_rel):
    """Whether a camera's image (its pixel (uu, vv) at image[off + vv w + uu], [h, w]) shows cell k's colour at pixel
    (u, v) or one of its 8 neighbours (_carve_kernel's photo)."""
    for dv in range(-1, 2):
        for du in range(-1, 2):
            uu, vv = u + du, v + dv
            if uu < 0 or uu >= w or vv < 0 or vv >= h:
                continue
            like = True
            at = off + vv * w + uu
            for c in range(3):
                a, b = float(colour[k, c]), float(image[at, c])
                if abs(a - b) > p_abs + p_rel * max(a, b):
                    like = False
            if like:
                return True
    return False


@dataclass(frozen=True, eq=False)
class CarveCameras:
    """Detail layers that carve others' cells (carve_details, carve_against), stacked for _carve_kernel: the ideal
    pinholes' poses, intrinsics and cell maps in flat arrays (built once, used for each carved camera), the lens
    cameras as they are (_carve_lens)."""

    pinholes: tuple[CameraDetail, ...]
    lenses: tuple[CameraDetail, ...]
    R: np.ndarray          # [C, 3, 3] float64: each pinhole's world-to-camera rotation (its rotation^T)
    t: np.ndarray          # [C, 3] float64 metres, ego frame: its centre
    K: np.ndarray          # [C, 4] float64 pixels: fx, fy, cx, cy
    hw: np.ndarray         # [C, 2] int64: its grid's height, width
    off: np.ndarray        # [C] int64: where its maps start in the flat arrays
    depth: np.ndarray      # [sum h w] float32: the cell maps' depths, camera after camera, row-major
    conf: np.ndarray       # [sum h w] int8
    image: np.ndarray      # [sum h w, 3] uint8: their colours (zeros for a camera without; [0, 3] without images)
    has_image: np.ndarray  # [C] bool

    @classmethod
    def of(cls, details: Sequence[CameraDetail], images: bool = True) -> CarveCameras:
        """``details`` stacked; ``images``: their colours too (the colour test's; False: no camera has one)."""
        pin = tuple(d for d in details if d.grid.is_ideal)
        sizes = np.array([d.depth.size for d in pin], np.int64)
        off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) if len(pin) else np.zeros(0, np.int64)
        image = np.zeros((int(sizes.sum()) if images else 0, 3), np.uint8)
        for d, o in zip(pin, off):
            if images and d.colours is not None:
                image[o:o + d.depth.size] = d.colours.reshape(-1, 3)
        return cls(pin, tuple(d for d in details if not d.grid.is_ideal),
                   np.array([d.grid.rotation.T for d in pin], np.float64).reshape(-1, 3, 3),
                   np.array([d.grid.position for d in pin], np.float64).reshape(-1, 3),
                   np.array([[d.grid.K[0, 0], d.grid.K[1, 1], d.grid.K[0, 2], d.grid.K[1, 2]] for d in pin],
                            np.float64).reshape(-1, 4),
                   np.array([d.depth.shape for d in pin], np.int64).reshape(-1, 2), off,
                   np.concatenate([d.depth.ravel() for d in pin]) if pin else np.zeros(0, np.float32),
                   np.concatenate([d.conf.ravel() for d in pin]) if pin else np.zeros(0, np.int8), image,
                   np.array([images and d.colours is not None for d in pin], bool))


def carve_details(details: list[CameraDetail], tolerance: float, dedupe: float = 1.0,
                  photo: tuple[float, float] | None = None) -> list[np.ndarray]:
    """Per camera j, [M_j] bool: its detail cells to keep. Camera j's cell is dropped when another camera i sees its
    centre on one of i's kept cells of at least the same confidence and
    - it lies in front of that cell (camera-i z < (1 - tolerance) x the cell's depth): i looked through the point
      and saw a surface behind it (free space), so j's depth there is wrong (with ``photo``: and i's image shows no
      colour like the cell's near there, as in carve_against); or
    - it lies on the same surface (within tolerance) and i resolves it more finely: i's cell_footprint there is
      below ``dedupe`` x j's (dedupe 1: the finer copy is kept, not two interleaved ones of different exposure;
      < 1: only a clearly finer camera takes over a cell, 0: never).
    A cell dropped by one camera is not tested against the next (the order does not matter: the tests are
    independent of each other)."""
    return _carve_all(details, tolerance, dedupe, photo, False)[0]


def carve_details_both(details: list[CameraDetail], tolerance: float, dedupe: float,
                       photo: tuple[float, float] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(carve_details(details, tolerance, dedupe, photo), carve_details(details, tolerance, 0.0, photo)) from one
    pass over the cells: the fused cells and each camera's cells that no other camera saw through (a drive's
    camera layers, runtime.cameralayers)."""
    return _carve_all(details, tolerance, dedupe, photo, True)


def _carve_all(details: list[CameraDetail], tolerance: float, dedupe: float, photo: tuple[float, float] | None,
               free: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """carve_details' keep masks, and with ``free`` the free-space rule's alone (else an empty list)."""
    keeps, frees = [], []
    stack = CarveCameras.of(details, images=photo is not None)
    for dj in details:
        keep = np.ones(len(dj.means), bool)
        f = np.ones(len(dj.means), bool) if free else None
        if len(dj.means):
            _carve_by(dj, stack, keep, tolerance, dedupe, photo, f)
        keeps.append(keep)
        if f is not None:
            frees.append(f)
    return keeps, frees


def carve_against(dj: CameraDetail, others: Sequence[CameraDetail] | CarveCameras, keep: np.ndarray,
                  tolerance: float, photo: tuple[float, float] | None = None) -> None:
    """Clear keep[k] ([M_j] bool, camera j's cells) where one of ``others``' cameras saw through cell k (carve_details'
    free-space rule alone: a surface is never handed over here). runtime.drive carves a keyframe's cells with the
    cameras of the neighbouring keyframes so. ``photo`` (abs, rel): and where that camera's image, within a cell of
    the spot, shows no colour like the cell's (colour_seen): what it saw there is not what the cell shows, so the
    cell is gone from its ray; a like colour keeps it (the same surface at a depth the two measured apart: glass, a
    fence, an edge). None (or a camera without colours): the depth alone decides. ``others`` as CarveCameras.of
    them when several cameras are carved by the same ones."""
    if len(dj.means):
        _carve_by(dj, others if isinstance(others, CarveCameras) else CarveCameras.of(others), keep, tolerance, 0.0,
                  photo)


def _carve_by(dj: CameraDetail, others: CarveCameras, keep: np.ndarray, tolerance: float, dedupe: float,
              photo: tuple[float, float] | None, free: np.ndarray | None = None) -> None:
    """carve_details' rules for camera j's cells against each of ``others`` but j itself (the colour test on the
    free-space rule where ``photo`` is given and both cameras have colours); ``free`` ([M_j] bool, or None): cleared
    by the free-space rule alone."""
    conf_j = np.ascontiguousarray(dj.cell_conf())
    col_j = np.ascontiguousarray(dj.cell_colours()) if photo is not None and dj.colours is not None else None
    if len(others.pinholes):
        skip = next((c for c, d in enumerate(others.pinholes) if d is dj), -1)
        _carve_kernel(dj.means, conf_j, dj.rank, keep, _NO_FREE if free is None else free, col_j is not None,
                      _NO_COLOUR if col_j is None else col_j,
                      others.R, others.t, others.K, others.hw, others.off, others.depth, others.conf, others.image,
                      others.has_image, skip, float(tolerance), float(dedupe),
                      0.0 if photo is None else float(photo[0]), 0.0 if photo is None else float(photo[1]))
    for di in others.lenses:
        if di is not dj:
            _carve_lens(dj.means, conf_j, dj.rank, di, float(tolerance), float(dedupe), keep,
                        (col_j, photo) if col_j is not None and di.colours is not None else None, free)


def colour_seen(cell: np.ndarray, image: np.ndarray, u: np.ndarray, v: np.ndarray, photo: tuple[float, float]
                ) -> np.ndarray:
    """[N] bool: whether ``image`` ([h, w, 3] uint8) shows the colour of ``cell`` ([N, 3] uint8) at pixel (u, v)
    or one of its 8 neighbours (a cell's slack for pose and edges): every channel within photo[0] + photo[1] x the
    larger of the two values (sRGB 0..255; the relative part for the exposure that harmonising leaves). The
    reference of _carve_kernel's colour test."""
    h, w = image.shape[:2]
    a = cell.astype(np.float64)
    seen = np.zeros(len(a), bool)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            b = np.zeros_like(a)
            b[ok] = image[vv[ok], uu[ok]]
            like = (np.abs(a - b) <= photo[0] + photo[1] * np.maximum(a, b)).all(axis=1)
            seen |= ok & like
    return seen


def _carve_lens(means: np.ndarray, conf: np.ndarray, rank: np.ndarray, di: CameraDetail, tolerance: float,
                dedupe: float, keep: np.ndarray, photo=None, free: np.ndarray | None = None) -> None:
    """_carve_kernel's rule for a camera i with a lens (numpy; its cells found through Camera.project_depth);
    ``photo`` (the cells' colours [M, 3] uint8, (abs, rel)): _carve_kernel's colour test (see carve_against);
    ``free``: _carve_kernel's."""
    idx, u, v, z = _grid_pixels(di.grid, means)
    c = di.conf[v, u]
    ok = (keep[idx] if free is None else keep[idx] | free[idx]) & (c != 0) & (c >= conf[idx])
    idx, u, v, z = idx[ok], u[ok], v[ok], z[ok]
    dc = di.depth[v, u].astype(np.float64)
    through = z < dc * (1.0 - tolerance)
    if photo is not None:
        colours, p = photo
        through &= ~colour_seen(colours[idx], di.colours, u, v, p)
    keep[idx[through]] = False
    if free is not None:
        free[idx[through]] = False
    if dedupe > 0:              # (a footprint is >= 0: with dedupe 0 the rule drops nothing)
        rank_i = cell_footprint(di.grid, u, v, dc)
        keep[idx[(np.abs(z - dc) <= tolerance * dc) & (rank_i < dedupe * rank[idx])]] = False


def carve_details_reference(details: list[CameraDetail], tolerance: float, dedupe: float = 1.0,
                            photo: tuple[float, float] | None = None) -> list[np.ndarray]:
    """`carve_details` cell by cell (slow, obviously correct; for the tests)."""
    out = []
    for j, dj in enumerate(details):
        keep = np.ones(len(dj.means), bool)
        _carve_by_reference(dj, [di for i, di in enumerate(details) if i != j], keep, tolerance, dedupe, photo)
        out.append(keep)
    return out


def carve_against_reference(dj: CameraDetail, others: list[CameraDetail], keep: np.ndarray, tolerance: float,
                            photo: tuple[float, float] | None = None) -> None:
    """`carve_against` cell by cell (slow, obviously correct; for the tests)."""
    _carve_by_reference(dj, others, keep, tolerance, 0.0, photo)


def _carve_by_reference(dj: CameraDetail, others: list[CameraDetail], keep: np.ndarray, tolerance: float,
                        dedupe: float, photo: tuple[float, float] | None) -> None:
    conf_j = dj.cell_conf()
    col_j = dj.cell_colours() if photo is not None and dj.colours is not None else None
    for k, m in enumerate(dj.means):
        for di in others:
            hit = _cell_of(di.grid, m)
            if not keep[k] or hit is None or not di.keep[hit[1], hit[0]] or di.conf[hit[1], hit[0]] < conf_j[k]:
                continue
            u, v, z = hit
            dc = float(di.depth[v, u])
            K = di.grid.K
            if di.grid.is_ideal:
                x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
                rank_i = dc * math.sqrt(1 + x * x + y * y) / (0.5 * (K[0, 0] + K[1, 1]))
            else:
                rank_i = dc * float(cell_geometry(di.grid).across[v, u])
            if abs(z - dc) <= tolerance * dc and rank_i < dedupe * dj.rank[k]:
                keep[k] = False
            if not z < dc * (1.0 - tolerance):
                continue
            if col_j is not None and di.colours is not None:
                like = False
                for vv in range(v - 1, v + 2):
                    for uu in range(u - 1, u + 2):
                        if 0 <= uu < di.grid.width and 0 <= vv < di.grid.height:
                            a, b = col_j[k].astype(float), di.colours[vv, uu].astype(float)
                            like |= all(abs(a[c] - b[c]) <= photo[0] + photo[1] * max(a[c], b[c]) for c in range(3))
                if like:
                    continue
            keep[k] = False


# ------------------------------------------------------------------------------------------- one camera


def model_grid_depth(coarse: Gaussians, grid: Camera, max_width: int = 480) -> tuple[np.ndarray, np.ndarray]:
    """(depth [h, w], alpha [h, w]) float32 of the coarse Gaussians rendered at ``grid`` (at most ``max_width``
    pixels wide, then resized to the grid: the coarse layer holds no finer detail than that), camera z metres. A
    grid camera with a lens: along its cells' true rays, in the camera's depth (runtime.raydepth, a panorama of at
    most MAX_PANORAMA pixels around)."""
    import cv2

    if not grid.is_ideal:
        from .raydepth import render_ray_depth

        return render_ray_depth(coarse, grid)

    from .camera import rig_camera
    from .render import render

    if grid.width > max_width:
        w = max_width
        h = max(1, round(grid.height * w / grid.width))
        r = render(coarse, rig_camera(grid.resized(w, h)))
        size = (grid.width, grid.height)
        # bilinear: a nearest-neighbour upsampling leaves a staircase of 2x2 (or larger) flat blocks, which from
        # other viewpoints (above the car) shows as contour lines; at a depth edge, where the bilinear value mixes
        # the two sides (it differs from the nearest one by more than 10 %), the nearest one is kept
        near = cv2.resize(r.depth, size, interpolation=cv2.INTER_NEAREST)
        depth = cv2.resize(r.depth, size, interpolation=cv2.INTER_LINEAR)
        mixed = np.abs(depth - near) > 0.1 * near
        depth[mixed] = near[mixed]
        alpha = cv2.resize(r.alpha, size, interpolation=cv2.INTER_LINEAR)
        return depth, alpha
    r = render(coarse, rig_camera(grid))
    return r.depth, r.alpha


MIN_COMMON_CELLS = 20   # cells with a depth sample and the model's depth before the samples scale the model's depth
#                         (runtime.lidar.fuse_depth's rule: fewer give no trustworthy scale)


def depth_samples(grid: Camera, coarse: Gaussians, points: np.ndarray | None, opts: DetailOptions
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(the model's depth [h, w] float32 at ``grid``'s cells, where it has one [h, w] bool, the points' nearest
    depth per cell [h, w] (lidar_grid_depth; 0 where none) or None without points): what camera_detail places its
    cells by. points [P, 3] metres, ego frame."""
    m_depth, m_alpha = model_grid_depth(coarse, grid)
    has_model = (m_alpha >= 0.5) & (m_depth > 0)
    sparse = None
    if points is not None and len(points):
        sparse = lidar_grid_depth(points, grid, opts.occlusion_deg, opts.min_depth, opts.max_depth)
    return m_depth, has_model, sparse


def rig_depth_scale(samples: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]]) -> float | None:
    """One factor for the model's depth in all of a keyframe's cameras from stereo points (runtime.stereo), given
    each camera's depth_samples: the median of point depth over model depth on all the cameras' cells that have
    both, pooled (None below MIN_COMMON_CELLS). The model's scale error is the model's, one a frame, while one camera's
    points can be a dozen on one car: on the PandaSet drive the front-left camera's 21-24 points said 1.14-1.22, its
    neighbours' 44-193 said 1.01-1.07, and the front camera (8-14 points, too few) kept 1; one factor for all put
    every camera above one frame alone (docs/results.md "Drives, camera only: one depth scale for the rig")."""
    ratios = []
    for m_depth, has_model, sparse in samples:
        if sparse is not None:
            both = (sparse > 0) & has_model
            ratios.append(sparse[both] / m_depth[both])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    return float(np.median(r)) if len(r) >= MIN_COMMON_CELLS else None


def camera_detail(cam: Camera, image: np.ndarray, coarse: Gaussians, opts: DetailOptions,
                  lidar: np.ndarray | None = None, ego_mask: np.ndarray | None = None,
                  ground: np.ndarray | None = None, sweep: bool = True, depth_scale: float | None = None,
                  samples: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
                  ) -> tuple[Gaussians, CameraDetail, dict[str, int]]:
    """The detail Gaussians of one input camera.

    image [H, W, 3] float32 0..1 (the camera's full-resolution input); coarse: the model's Gaussians (ego frame);
    lidar [P, 3] metres, ego frame, or None; ego_mask [H, W] bool, True = the ego's own body (no cell there);
    ground: the ground plane (fit_ground of the LiDAR, or model_ground) or None; sweep: whether ``lidar`` and
    ``ground`` are a LiDAR sweep's: its ground cells are then as trusted as LiDAR's (opacity, CONF_MEASURED), and its
    returns spread over the image say where a surface stands clearly in front of the ground. False: the ground is
    the model's, and ``lidar`` (if any) a few hundred points triangulated between frames (runtime.stereo) that
    place only the cells near them: spread over a whole image from a dozen points on one car they would tell every
    road cell beyond that car that it is behind a surface. depth_scale: the factor for the model's depth (None: the
    median of the samples' depth over the model's on this camera's cells that have both, at least MIN_COMMON_CELLS of
    them, else 1; stereo points get rig_depth_scale's, the rig's). samples: depth_samples of this camera's grid
    with ``lidar``, when already made (for rig_depth_scale).
    Returns (Gaussians, the camera's CameraDetail, counts {"lidar": cells placed by LiDAR, "ground": by the ground
    plane, "model": by the model's depth, "far": at far_depth, "edge": dropped at depth edges})."""
    import cv2

    grid = grid_camera(cam, opts.stride)
    colours = grid_colours(image, grid, opts.sharpen, opts.footprint)
    m_depth, has_model, sparse = samples if samples is not None else depth_samples(grid, coarse, lidar, opts)
    depth = np.zeros((grid.height, grid.width), np.float32)
    supported = np.zeros(depth.shape, bool)
    dense = np.zeros_like(depth)   # the LiDAR spread over the whole image (beyond the supported cells too)
    scale = 1.0 if depth_scale is None else float(depth_scale)
    smoother = functools.cache(lambda: edge_smoother(colours, opts.smooth_lambda, opts.smooth_sigma))
    if sparse is not None:
        supported = support_mask(sparse, _angle_pixels(grid, opts.support_deg))
        dense = densify(sparse, colours, opts.smooth_lambda, opts.smooth_sigma, smoother())
        supported &= dense > 0
        depth[supported] = dense[supported]
        both = (sparse > 0) & has_model
        if depth_scale is None and both.sum() >= MIN_COMMON_CELLS:   # fewer give no trustworthy scale
            scale = float(np.median(sparse[both] / m_depth[both]))
    md = np.zeros_like(depth)
    if opts.model_depth and (~supported & has_model).any():
        # the model's depth (blocky at the grid size) spread edge-aware like LiDAR samples would be
        md = densify(np.where(has_model, m_depth * np.float32(scale), 0).astype(np.float32), colours,
                     opts.smooth_lambda, opts.smooth_sigma, smoother())
        md[~has_model] = 0
    on_ground = np.zeros(depth.shape, bool)
    rays = None
    if ground is not None and opts.ground:
        rays = grid_rays(grid)
        gd = ground_depth(grid, ground, rays)
        # a cell LiDAR does not reach looks at the ground when the plane is near enough and neither the model nor
        # the LiDAR spread from the nearest returns puts a surface clearly in front of it (a car's flank below the
        # lowest beam). 0.8: the model's real-camera depth error is ~0.5 AbsRel, so only a clear margin counts
        nearer = (md > 0) & (md < 0.8 * gd)
        if sweep:
            nearer |= (dense > 0) & (dense < 0.8 * gd)
        on_ground = ~supported & (gd >= opts.min_depth) & (gd <= opts.ground_max) & ~nearer
        depth[on_ground] = gd[on_ground]
    from_model = ~supported & ~on_ground & (md > 0)
    depth[from_model] = md[from_model]
    beyond = depth > opts.max_depth                             # not trusted: far layer (or no cell)
    supported &= ~beyond
    on_ground &= ~beyond
    from_model &= ~beyond
    depth[(depth < opts.min_depth) & (depth > 0)] = -1          # the ego's own body: no cell, never far
    far = np.zeros(depth.shape, bool)
    if opts.far_depth > 0:
        far = (depth == 0) | (depth > opts.max_depth)
        depth[far] = sphere_depth(grid, opts.far_depth, rays)[far]
    else:
        depth[depth > opts.max_depth] = 0
    depth[depth < 0] = 0
    if ego_mask is not None:
        small = cv2.resize(ego_mask.astype(np.uint8), (grid.width, grid.height), interpolation=cv2.INTER_NEAREST)
        depth[small > 0] = 0
    if not grid.is_ideal:
        depth[~cell_geometry(grid).has_ray] = 0                 # outside a lens's image circle: no cell
    keep = edge_keep(depth, opts.edge_ratio)
    measured = (supported | on_ground) if sweep else np.zeros(depth.shape, bool)
    opacity = np.where(measured, opts.opacity, opts.model_opacity).astype(np.float64)
    g = cell_gaussians(grid, colours, depth, opacity, keep, opts.footprint, opts.thickness,
                       surface_stretch=opts.surface_stretch)
    split = split_cells(cam, image, grid, g, keep, opts.split, opts.sharpen, opts.footprint)
    counts = {"lidar": int((keep & supported).sum()), "ground": int((keep & on_ground).sum()),
              "model": int((keep & from_model).sum()), "far": int((keep & far).sum()),
              "edge": int(((depth > 0) & ~keep).sum())}
    return g, CameraDetail.build(grid, depth, keep, measured, g.means, colours, split), counts


def read_ego_mask(path, cam: Camera) -> np.ndarray:
    """[H, W] bool ego mask of ``cam`` from an image file (non-zero = the ego's own body); RigError naming the
    camera when the size differs."""
    from .rig import RigError, read_image

    a = read_image(path, "ego_mask", channels=1, scale=False, where=cam.where)
    a = np.asarray(a)
    if a.ndim == 3:
        a = a[..., 0]
    if a.shape != (cam.height, cam.width):
        raise RigError("ego_mask", f"has shape {list(a.shape)}, but the rig declares "
                       f"{cam.width}x{cam.height} (width x height)", cam.where)
    return a > 0


__all__ = [
    "CameraDetail",
    "DetailError",
    "DetailOptions",
    "camera_detail",
    "cell_gaussians",
    "cell_gaussians_reference",
    "concat_gaussians",
    "concat_gaussians_reference",
    "cull_covered",
    "cull_covered_reference",
    "densify",
    "edge_keep",
    "edge_keep_reference",
    "grid_camera",
    "grid_colours",
    "lidar_grid_depth",
    "model_grid_depth",
    "read_ego_mask",
    "rotmat_to_quat",
    "support_mask",
]


# ------------------------------------------------------------------------------------------- own views

HIDDEN_LOGIT = -30.0   # opacity logit of a Gaussian hidden in the default view: sigmoid 9e-14, below every
#                        renderer's 1/255 cut (ours, gsplat's, the web viewers'), so other tools draw nothing of it


@dataclass(frozen=True, eq=False)
class OwnViews:
    """What changes when a scene is seen from one of its input cameras' own poses (issue 35 item 2: "each camera's
    own view must win at its own pose"). The fusion (carve_details) keeps one copy of a surface two cameras see,
    the finer one, and drops cells another camera's depth contradicts; seen from a camera whose cells lost there,
    its own image came back covered by its neighbour's cells (another exposure, another depth: a ghosted building,
    white blotches, dotted holes along the image's side). A scene keeps every dropped cell as a hidden Gaussian
    (HIDDEN_LOGIT) and this record; camera c's own view (Scene.gaussians_for) shows its hidden cells at their
    opacity and hides the other cameras' cells that land on its cells, so it shows its own cells wherever it has
    them. Views from anywhere else are the default scene."""

    cameras: tuple[str, ...]   # the rig's camera names, in rig order (the camera index below)
    index: np.ndarray          # [E] int64: positions in the scene's Gaussians of the cells hidden by default
    logit: np.ndarray          # [E] float32: their opacity logits in their camera's own view
    owner: np.ndarray          # [E] int16: their camera
    hide: np.ndarray           # [H] int64: positions of Gaussians hidden in a camera's own view, camera by camera
    hide_offsets: np.ndarray   # [C + 1] int64: camera c's are hide[hide_offsets[c]:hide_offsets[c + 1]]

    def opacity_logits(self, base: np.ndarray, camera: int) -> np.ndarray:
        """[N] the scene's opacity logits (``base``) as camera ``camera``'s own view has them."""
        out = np.array(base, copy=True)
        out[self.hide[self.hide_offsets[camera]:self.hide_offsets[camera + 1]]] = HIDDEN_LOGIT
        own = self.owner == camera
        out[self.index[own]] = self.logit[own]
        return out

    def check(self, n: int, where: str) -> None:
        """Raise DetailError (field own_views.<array>) unless the arrays fit a scene of ``n`` Gaussians."""
        c = len(self.cameras)
        e = len(self.index)
        shapes = {"index": (e,), "logit": (e,), "owner": (e,), "hide_offsets": (c + 1,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise DetailError(f"own_views.{name}", f"expected shape {list(shape)}, got "
                                                       f"{list(getattr(self, name).shape)}", where)
        off = self.hide_offsets
        if self.hide.ndim != 1 or off[0] != 0 or off[-1] != len(self.hide) or np.any(np.diff(off) < 0):
            raise DetailError("own_views.hide_offsets", "must rise from 0 to the length of hide", where)
        for name in ("index", "hide"):
            a = getattr(self, name)
            if len(a) and (a.min() < 0 or a.max() >= n):
                raise DetailError(f"own_views.{name}", f"positions must lie in 0..{n - 1}", where)
        if len(self.owner) and (self.owner.min() < 0 or self.owner.max() >= c):
            raise DetailError("own_views.owner", f"must name a camera 0..{c - 1}", where)
        if not np.all(np.isfinite(self.logit)):
            raise DetailError("own_views.logit", "non-finite values", where)

    def save(self, path) -> None:
        np.savez(path, cameras=np.array(self.cameras, dtype=str), index=self.index, logit=self.logit,
                 owner=self.owner, hide=self.hide, hide_offsets=self.hide_offsets)

    @classmethod
    def load(cls, path, n: int) -> OwnViews:
        """Read a file of ``save`` (DetailError naming the file when it is not one) for a scene of n Gaussians."""
        where = f"own views {str(path)!r}"
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("cameras", "index", "logit", "owner", "hide", "hide_offsets")}
        except (OSError, ValueError, KeyError) as e:
            raise DetailError("own_views", f"not readable ({e})", where) from None
        out = cls(cameras=tuple(str(c) for c in arrays["cameras"]), index=arrays["index"].astype(np.int64),
                  logit=arrays["logit"].astype(np.float32), owner=arrays["owner"].astype(np.int16),
                  hide=arrays["hide"].astype(np.int64), hide_offsets=arrays["hide_offsets"].astype(np.int64))
        out.check(n, where)
        return out


OWN_VIEW_MARGIN = 2    # cells: a neighbour's cell centred this far outside a camera's image still reaches into
#                        it (a disc's 3 sigma is 1.5 cells, footprint 0.5), so its own view hides those too


def _own_cells(grid: Camera, keep: np.ndarray, means: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """[M] bool: which of the points ``means[cells]`` ([N, 3] ego; cells [M] int64 indices) ``grid`` sees in front
    of it on, or within OWN_VIEW_MARGIN cells outside the image of, a cell of ``keep`` (the nearest cell inside the
    image). An ideal pinhole grid in one numba pass (_own_cells_kernel: own_view_hide_reference's formula), a lens
    through Camera.project_depth."""
    if grid.is_ideal:
        out = np.empty(len(cells), np.bool_)
        K = grid.K
        _own_cells_kernel(np.ascontiguousarray(means), np.ascontiguousarray(cells, np.int64),
                          np.ascontiguousarray(grid.rotation, np.float64), np.ascontiguousarray(grid.position,
                                                                                                np.float64),
                          float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                          np.ascontiguousarray(keep, np.bool_), OWN_VIEW_MARGIN, out)
        return out
    means = means[cells]
    uv, _, front = grid.project_depth(means)
    px = np.rint(np.nan_to_num(uv, nan=-1e9)).astype(np.int64)
    m = OWN_VIEW_MARGIN
    ok = front & (px[:, 0] >= -m) & (px[:, 0] < grid.width + m) & (px[:, 1] >= -m) & (px[:, 1] < grid.height + m)
    u = np.clip(px[:, 0], 0, grid.width - 1)
    v = np.clip(px[:, 1], 0, grid.height - 1)
    return ok & keep[v, u]


@njit(cache=True, parallel=True, nogil=True)
def _own_cells_kernel(means, cells, R, pos, fx, fy, cx, cy, keep, margin, out):
    """_own_cells for an ideal pinhole grid (rotation R [3, 3] camera -> ego, centre pos [3], K's fx fy cx cy):
    out[t] for the point means[cells[t]], as own_view_hide_reference computes it (q = R^T (m - pos), in front when
    q_z > 1e-6, the pixel rint(f q / q_z + c))."""
    h, w = keep.shape
    for t in numba.prange(cells.shape[0]):
        k = cells[t]
        d0 = means[k, 0] - pos[0]
        d1 = means[k, 1] - pos[1]
        d2 = means[k, 2] - pos[2]
        qz = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        if not qz > 1e-6:
            out[t] = False
            continue
        qx = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        qy = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        u = np.rint(fx * qx / qz + cx)
        v = np.rint(fy * qy / qz + cy)
        if not (-margin <= u < w + margin and -margin <= v < h + margin):
            out[t] = False
            continue
        out[t] = keep[min(max(int(v), 0), h - 1), min(max(int(u), 0), w - 1)]


def own_view_hide(details: list[CameraDetail], kept: list[np.ndarray], starts: list[int]) -> list[np.ndarray]:
    """Per camera p (details[p]), the positions of the other cameras' kept cells that land on one of p's cells
    (before the fusion: p's whole detail layer; at the image's border, within OWN_VIEW_MARGIN cells outside it) at
    any depth: hidden in p's own view, where p's cell is the one to show (in front of it, the neighbour's cell
    would cover p's; behind it, it would show through p's 5 % of transparency). kept[j]: camera j's cells kept by
    the fusion; starts[j]: the position of its first cell in the scene's Gaussians."""
    out = []
    cells = [np.flatnonzero(k) for k in kept]
    ordered = bool(np.all(np.diff(np.asarray(starts)) >= 0))   # then the runs concatenate in ascending order
    for p, dp in enumerate(details):
        hide = []
        for j, dj in enumerate(details):
            if j == p or not len(cells[j]):
                continue
            hide.append(starts[j] + cells[j][_own_cells(dp.grid, dp.keep, dj.means, cells[j])])
        h = np.concatenate(hide).astype(np.int64, copy=False) if hide else np.zeros(0, np.int64)
        out.append(h if ordered else np.sort(h))
    return out


def own_view_hide_reference(details: list[CameraDetail], kept: list[np.ndarray], starts: list[int]
                            ) -> list[np.ndarray]:
    """`own_view_hide` cell by cell (slow, obviously correct; tests): an ideal grid by its pinhole formula."""
    out = []
    for p, dp in enumerate(details):
        g = dp.grid
        hide = []
        for j, dj in enumerate(details):
            if j == p:
                continue
            for k, m in enumerate(dj.means):
                q = g.rotation.T @ (m - g.position)
                if not kept[j][k] or q[2] <= 1e-6:
                    continue
                u = int(np.rint(g.K[0, 0] * q[0] / q[2] + g.K[0, 2]))
                v = int(np.rint(g.K[1, 1] * q[1] / q[2] + g.K[1, 2]))
                inside = -OWN_VIEW_MARGIN <= u < g.width + OWN_VIEW_MARGIN and \
                    -OWN_VIEW_MARGIN <= v < g.height + OWN_VIEW_MARGIN
                if inside and dp.keep[min(max(v, 0), g.height - 1), min(max(u, 0), g.width - 1)]:
                    hide.append(starts[j] + k)
        out.append(np.array(sorted(hide), np.int64))
    return out


def _shown_split(d: CameraDetail, shown: np.ndarray) -> np.ndarray:
    """[M] bool: d's split cells (SplitCells) among the ``shown`` ones."""
    return shown & (split_rows(len(shown), d.split) >= 0) if d.split is not None else np.zeros(len(shown), bool)


def _split_positions(first: int, split: list[np.ndarray], pieces: int = 4) -> Callable[[np.ndarray], np.ndarray]:
    """Where the cells of the cameras' detail layers end up when each camera's ``split`` cells ([M_j] bool) leave
    their run for ``pieces`` Gaussians each (their quarters) after every camera's cells (fuse_details): a function
    of positions counted with every cell in its run (runs from ``first``) that gives their positions in that layout,
    a moved cell's as its pieces', in the layout's order: ascending when the given positions are (no sort needed)."""
    n = [len(m) for m in split]
    old = first + np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
    left = [len(m) - int(m.sum()) for m in split]
    new_run = first + np.concatenate([[0], np.cumsum(left)]).astype(np.int64)
    px_run = new_run[-1] + np.concatenate([[0], np.cumsum([int(m.sum()) * pieces for m in split])]).astype(np.int64)
    before = [np.cumsum(m) - m for m in split]       # split cells before each cell of camera j (made once)

    def where(pos: np.ndarray) -> np.ndarray:
        pos = np.asarray(pos, np.int64)
        stay, moved_out = [pos[pos < first]], []
        for j, m in enumerate(split):
            i = pos[(pos >= old[j]) & (pos < old[j + 1])] - old[j]
            moved = m[i]
            stay.append(new_run[j] + i[~moved] - before[j][i[~moved]])
            r = before[j][i[moved]]                  # the moved cell's rank among camera j's split cells
            moved_out.append((px_run[j] + r[:, None] * pieces + np.arange(pieces)[None, :]).ravel())
        # the layout's order: the coarse Gaussians, every camera's cells that stay, then every camera's pieces
        return np.concatenate(stay + moved_out)

    return where


def fuse_details(coarse: Gaussians, parts: list[Gaussians], details: list[CameraDetail], owners: list[int],
                 cameras: tuple[str, ...], opts: DetailOptions) -> tuple[Gaussians, OwnViews, dict[str, int]]:
    """The scene's Gaussians from the model's (``coarse``) and the cameras' detail layers (parts[j], details[j] of
    rig camera owners[j]; ``cameras`` the rig's names): the coarse Gaussians a detail cell covers culled
    (cull_covered), then every camera's cells in order, those the fusion drops (carve_details) hidden at
    HIDDEN_LOGIT, the shown cells that split (SplitCells) taken out of their run and drawn as their pixels after
    every camera's cells (expand_split); with their OwnViews and the counts {detail (cells shown), carved (cells
    hidden), split (shown cells drawn as pixels), coarse, culled, total}."""
    from concurrent.futures import ThreadPoolExecutor

    # two steps at a time on a second thread (numpy, OpenCV and the numba kernels release the GIL): the coarse cull
    # (numpy and OpenCV) beside the carving, then the own views' hidden cells beside the split cells' quarters and the
    # concatenation (two threads launching numba kernels at once: only on a thread-safe layer)
    with ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-fuse") as side:
        culled = side.submit(cull_covered, coarse, details, opts.cull_tolerance)
        carved = carve_details(details, opts.cull_tolerance, opts.dedupe)
        keep = culled.result()
        first = int(keep.sum())
        starts = (first + np.concatenate([[0], np.cumsum([len(g) for g in parts])[:-1]])).astype(int).tolist()
        hidden = side.submit(own_view_hide, details, carved, starts) if threadsafe() else None
        shown = [g.with_opacity_logits(np.where(k, g.opacity_logits, HIDDEN_LOGIT)) for g, k in zip(parts, carved)]
        # a shown split cell is its quarters' Gaussians (expand_split), after every camera's cells; hidden ones stay
        # cells
        split = [_shown_split(d, k) for d, k in zip(details, carved)]
        quarters = [expand_split(g, d, m) for g, d, m in zip(parts, details, split)]
        out = concat_gaussians([coarse, *shown, *quarters], [keep, *[~m for m in split], *[None] * len(quarters)])
        hide = hidden.result() if hidden is not None else own_view_hide(details, carved, starts)
    where = _split_positions(first, split)
    per_camera = [np.zeros(0, np.int64)] * len(cameras)
    for owner, h in zip(owners, hide):
        per_camera[owner] = where(h) if len(h) else h      # h ascending (starts are): where(h) ascending too
    own = OwnViews(cameras=cameras,
                   index=where(np.concatenate([s0 + np.flatnonzero(~k) for s0, k in zip(starts, carved)])),
                   logit=np.concatenate([g.opacity_logits[~k] for g, k in zip(parts, carved)]).astype(np.float32),
                   owner=np.concatenate([np.full(int((~k).sum()), o, np.int16) for o, k in zip(owners, carved)]),
                   hide=np.concatenate(per_camera).astype(np.int64, copy=False),
                   hide_offsets=np.concatenate([[0], np.cumsum([len(h) for h in per_camera])]).astype(np.int64))
    own.check(len(out), "reconstruction")
    counts = {"detail": int(sum(k.sum() for k in carved)), "carved": int(sum(k.size - k.sum() for k in carved)),
              "split": int(sum(m.sum() for m in split)), "coarse": int(keep.sum()),
              "culled": int(keep.size - keep.sum()), "total": len(out)}
    return out, own, counts
