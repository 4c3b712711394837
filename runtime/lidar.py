"""LiDAR points of a rig, and the depth check of a reconstruction against them (`xyzcyl lidar-eval`).

Input-view PSNR cannot show whether a reconstruction put its surfaces at the right distance: a model that
paints each input image onto a sphere scores well at the input cameras. A LiDAR sweep of the same timestamp can.

The rig.json `lidar` block (docs/conventions.md "rig.json", kept in `Rig.extra`):

    "lidar": {"file": "sweep.pcd.bin", "lidar_to_ego": 4x4, "columns": 5}

- `file` (relative to the rig.json): `.npy` (real numbers [N, C], C >= 3) or raw little-endian float32 `.bin`
  ([N, C] row-major: nuScenes `.pcd.bin` has C = 5, a KITTI `.bin` has C = 4; a `.bin` whose bytes start with the
  .npy magic is read as .npy). The first three columns are x, y, z in metres in the LiDAR frame. `read_points` is
  the one check of the file, for the command line and the HTTP upload: an empty file, a `.npy` name on bytes that
  are not .npy, no rows, or no row with a finite x, y and z is refused, naming the file as the user gave it; rows
  with a non-finite coordinate are left out and counted (`LidarPoints.nonfinite`).
- `lidar_to_ego` (optional, default identity): maps LiDAR points to the ego frame.
- `columns` (optional, `.bin` only): C. Without it, a name ending in `.pcd.bin` means 5, any other `.bin` 4.

The check (`lidar_depth_check`), per input camera at a reduced evaluation width:
1. The LiDAR points (ego frame) are projected with the camera's own model at that size (its lens included,
   Camera.project), and each pixel keeps its nearest point (`lidar_depth_map`): the camera's depth, metres
   (Camera.depth_is_distance: camera z, or the distance for a fisheye or f-theta lens).
2. Points the camera cannot see are dropped where a point within `OCCLUSION_RADIUS` pixels is nearer by more
   than the δ threshold (`occlusion_filter`): the LiDAR sits higher and further back than the cameras and sees
   surfaces behind what the camera sees.
3. The reconstruction is rendered at the same camera (Gaussians only: expected depth, `runtime.render`; a camera
   with a lens along its pixels' true rays, `runtime.raydepth.render_ray_depth`).
   Pixels with alpha < `ALPHA_MIN` count as not covered.
4. On the covered pixels: AbsRel, RMSE, δ < 1.25 and the median ratio rendered / LiDAR (Eigen et al. 2014),
   for each camera, for all cameras together, and per range bin.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .camera import Camera, check_pose
from .errors import FieldError, RigError, plain
from .rig import Rig

MIN_DEPTH = 1.0   # m camera z: nearer returns are the ego vehicle's own body or sensor mounts, not the scene
MAX_DEPTH = 80.0  # m camera z: the usual cap of driving depth benchmarks (KITTI, Eigen split)
DELTA = 1.25      # the δ1 threshold of the depth literature, also the occlusion filter's depth ratio
OCCLUSION_RADIUS = 2   # pixels at the evaluation size: the window (2r+1)^2 in which a nearer point hides another
ALPHA_MIN = 0.5   # rendered alpha below this: the reconstruction has no surface at that pixel (not covered)
RANGE_BINS = (0.0, 10.0, 20.0, 40.0, 80.0)  # m, LiDAR depth bins of the per-range table
MAX_POINTS = 20_000_000  # refuse larger sweeps (a 128-beam sweep has ~0.3 M points; this guards memory)
NPY_MAGIC = b"\x93NUMPY"  # the first 6 bytes of every .npy file (numpy.lib.format)


class LidarError(FieldError):
    """Invalid or missing LiDAR input: ``field`` "lidar" (the sweep file as a whole), "columns" (``where``
    "lidar"), the rig's lidar block ("lidar", "lidar.file", "lidar.lidar_to_ego"; ``where`` "rig") or "width"."""


@dataclass(frozen=True)
class LidarPoints:
    points: np.ndarray   # [N, 3] float64 metres, ego frame (finite)
    nonfinite: int       # points of the file with a non-finite x, y or z, left out (reported, never silent)
    source: str          # the file they came from

    def counts(self) -> dict[str, int]:
        """What a scene's counts record of its sweep: lidar_points (used), lidar_nonfinite (left out)."""
        return {"lidar_points": int(len(self.points)), "lidar_nonfinite": int(self.nonfinite)}


def lidar_format(name: str, head: bytes, sniff: bool = False) -> str | None:
    """The format of a LiDAR file called ``name`` (the user's name for it) whose first bytes are ``head``: "npy",
    "pcd.bin" (raw float32, 5 columns by default) or "bin" (4), None for a name of neither kind.

    A name ending in .npy is read as .npy (refused later when the bytes are not one). A .bin name whose bytes start
    with the .npy magic is a .npy array: the Python client sends a sweep given as bytes as 'lidar.bin'
    (docs/client.md); raw float32 rows cannot start so (x would be 2.2e8 m). ``sniff``: a name of neither kind is
    read by its bytes too (the HTTP part's file name is optional) instead of being None."""
    n = name.lower()
    if n.endswith(".npy"):
        return "npy"
    if not (n.endswith(".bin") or sniff):
        return None
    if head.startswith(NPY_MAGIC):
        return "npy"
    return "pcd.bin" if n.endswith(".pcd.bin") else "bin"


def _check_rows(shape: tuple[int, int], label: str) -> None:
    """Refuse a sweep of ``shape`` [N, C] with no rows or more than MAX_POINTS."""
    if shape[0] == 0:
        raise LidarError("lidar", f"{label} holds no points (shape {list(shape)})")
    if shape[0] > MAX_POINTS:
        raise LidarError("lidar", f"{label} has {shape[0]} points, more than {MAX_POINTS}")


def _read_npy(p: Path, head: bytes, columns: int | None, label: str) -> np.ndarray:
    """[N, C] real numbers (memory-mapped) of the .npy file ``p`` whose first bytes are ``head``."""
    if columns is not None:
        raise LidarError("columns", "applies to .bin files only (a .npy file has its own shape)", "lidar")
    if not head.startswith(NPY_MAGIC):
        raise LidarError("lidar", f"{label} is not a .npy array (it does not start with the .npy magic bytes)")
    try:
        a = np.load(p, allow_pickle=False, mmap_mode="r")
    except (ValueError, OSError, EOFError) as exc:
        raise LidarError("lidar", f"{label} is not a readable .npy array ({exc})") from None
    real = np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
    if a.ndim != 2 or a.shape[1] < 3 or not real:
        raise LidarError("lidar", f"{label} must hold real numbers of shape [N, C >= 3] (got {a.dtype} "
                                  f"{list(a.shape)})")
    _check_rows(a.shape, label)
    return a


def _read_bin(p: Path, fmt: str, columns: int | None, label: str) -> np.ndarray:
    """[N, C] float32 rows of the raw little-endian float32 file ``p`` (C: ``columns``, else 5 for "pcd.bin",
    else 4); the file is not empty."""
    c = columns if columns is not None else (5 if fmt == "pcd.bin" else 4)
    if not isinstance(c, int) or isinstance(c, bool) or c < 3:
        raise LidarError("columns", f"must be an integer >= 3 (got {plain(c)!r})", "lidar")
    size = p.stat().st_size
    if size % (4 * c):
        raise LidarError("lidar", f"{label} has {size} bytes, not a whole number of {c}-column float32 rows "
                                  f"(set columns)")
    _check_rows((size // (4 * c), c), label)
    return np.fromfile(p, dtype="<f4").reshape(-1, c)


def read_points(path: str | os.PathLike, columns: int | None = None,
                label: str | None = None) -> tuple[np.ndarray, int]:
    """[N, 3] float64 x, y, z (the file's frame; N >= 1) and the count of rows left out for a non-finite
    coordinate. The one check of a LiDAR file's bytes, for the command line and the HTTP upload.

    path: `.npy` (real numbers [N, C], C >= 3) or raw float32 `.bin` (C columns: `columns`, else 5 for
    `*.pcd.bin`, else 4), as its name says (lidar_format). ``label``: how messages name the file (default: the
    path, quoted), e.g. the upload's part and file name. Refused (LidarError, field "lidar"):
    a missing, empty, unreadable or misshaped file, a file named .npy that is not one, no rows, no row with a finite
    x, y and z, more than MAX_POINTS rows."""
    p = Path(path)
    label = label or repr(str(p))
    if not p.is_file():
        raise LidarError("lidar", f"{label} does not exist")
    with open(p, "rb") as f:
        head = f.read(len(NPY_MAGIC))
    fmt = lidar_format(p.name, head)
    if fmt is None:
        raise LidarError("lidar", f"{label}: unknown format (use .npy or a float32 .bin)")
    if not head:
        raise LidarError("lidar", f"{label} is empty (0 bytes)")
    a = _read_npy(p, head, columns, label) if fmt == "npy" else _read_bin(p, fmt, columns, label)
    xyz = np.asarray(a[:, :3], dtype=np.float64)
    ok = np.all(np.isfinite(xyz), axis=1)
    if not ok.any():
        rows = f"{ok.size} rows" if ok.size > 1 else "1 row"
        raise LidarError("lidar", f"{label} holds no point with a finite x, y and z (a non-finite coordinate in "
                                  f"every one of its {rows})")
    return np.ascontiguousarray(xyz[ok]), int((~ok).sum())


def has_lidar(rig: Rig) -> bool:
    """Whether the rig names a LiDAR file (a `lidar` block with a `file`)."""
    block = rig.extra.get("lidar")
    return isinstance(block, dict) and block.get("file") is not None


def load_lidar(rig: Rig, file: str | os.PathLike | None = None, columns: int | None = None,
               label: str | None = None) -> LidarPoints:
    """The LiDAR points of a rig in its ego frame, from the rig's `lidar` block, or from `file` (then in the ego
    frame already unless the rig's block gives lidar_to_ego). `columns` overrides the block's; ``label`` names the
    file in messages (read_points)."""
    block = rig.extra.get("lidar")
    if block is not None and not isinstance(block, dict):
        raise LidarError("lidar", f"must be an object (got {type(block).__name__})", "rig")
    block = block or {}
    if file is None:
        if "file" not in block:
            raise LidarError("lidar.file", "rig has no lidar.file (pass the LiDAR file explicitly)")
        if not isinstance(block["file"], str):
            raise LidarError("lidar.file", f"must be a string (got {block['file']!r:.60})", "rig")
        path = rig.path(block["file"])
    else:
        path = Path(file)
    if columns is None and "columns" in block:
        columns = block["columns"]
    T = np.eye(4)
    if "lidar_to_ego" in block:
        try:
            T = check_pose(block["lidar_to_ego"], "rig", "lidar.lidar_to_ego")
        except RigError as exc:
            raise LidarError(exc.field, exc.message, exc.where) from None
    xyz, bad = read_points(path, columns, label)
    ego = xyz @ T[:3, :3].T + T[:3, 3]
    return LidarPoints(points=ego, nonfinite=bad, source=str(path))


def eval_camera(cam: Camera, width: int) -> Camera:
    """The camera the check projects and renders with: ``cam`` (its lens kept) resized to ``width`` pixels wide
    (height rounded to keep the aspect ratio)."""
    if not isinstance(width, int) or width < 8:
        raise LidarError("width", f"must be an integer >= 8 (got {plain(width)!r})")
    height = max(1, round(cam.height * width / cam.width))
    return cam.resized(width, height)


def lidar_depth_map(points: np.ndarray, cam: Camera, min_depth: float = MIN_DEPTH,
                    max_depth: float = MAX_DEPTH) -> np.ndarray:
    """[H, W] float32 metres: the nearest LiDAR point per pixel, in the camera's depth (Camera.project_depth: camera
    z for a pinhole or an opencv lens, the distance for a fisheye, f-theta or equirect camera), 0 where no point
    lands. points [N, 3] metres, ego frame, projected through the camera's lens; a point counts when min_depth <=
    depth <= max_depth and its projection rounds to a pixel of ``cam`` (pixel u's centre at u,
    docs/conventions.md)."""
    uv, z, front = cam.project_depth(points)
    px = np.rint(uv).astype(np.int64)
    ok = front & (z >= min_depth) & (z <= max_depth)
    ok &= (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    flat = px[ok, 1] * cam.width + px[ok, 0]
    zk = z[ok]
    out = np.zeros(cam.height * cam.width, np.float32)
    if flat.size:
        order = np.lexsort((zk, flat))            # by pixel, then nearest first
        first = np.ones(order.size, bool)
        first[1:] = flat[order][1:] != flat[order][:-1]
        out[flat[order][first]] = zk[order][first]
    return out.reshape(cam.height, cam.width)


def lidar_depth_map_reference(points: np.ndarray, cam: Camera, min_depth: float = MIN_DEPTH,
                              max_depth: float = MAX_DEPTH) -> np.ndarray:
    """`lidar_depth_map` point by point (slow, obviously correct; for the tests)."""
    out = np.zeros((cam.height, cam.width), np.float32)
    for p in np.asarray(points, np.float64):
        uv, z, front = cam.project_depth(p[None])
        u, v, z = int(np.rint(uv[0, 0])), int(np.rint(uv[0, 1])), float(z[0])
        if not front[0] or not min_depth <= z <= max_depth or not (0 <= u < cam.width and 0 <= v < cam.height):
            continue
        if out[v, u] == 0 or np.float32(z) < out[v, u]:
            out[v, u] = z
    return out


def occlusion_filter(depth: np.ndarray, radius: int = OCCLUSION_RADIUS, ratio: float = DELTA) -> np.ndarray:
    """[H, W] bool: the LiDAR pixels (depth > 0) kept. A pixel is dropped when another LiDAR pixel within the
    (2 radius + 1)^2 window is nearer than depth / ratio: that return lies behind a surface the camera sees."""
    import cv2

    d = np.where(depth > 0, depth, np.inf).astype(np.float32)
    near = cv2.erode(d, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return (depth > 0) & ~(near * ratio < depth)


def occlusion_filter_reference(depth: np.ndarray, radius: int = OCCLUSION_RADIUS, ratio: float = DELTA) -> np.ndarray:
    """`occlusion_filter` pixel by pixel (slow, obviously correct; for the tests)."""
    H, W = depth.shape
    keep = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            if depth[y, x] <= 0:
                continue
            win = depth[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
            win = win[win > 0]
            keep[y, x] = not np.any(win * np.float32(ratio) < depth[y, x])
    return keep


def depth_errors(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Depth errors of pred [M] against gt [M] (metres, gt > 0): points M; abs_rel = mean |pred − gt| / gt;
    rmse = sqrt(mean (pred − gt)^2) metres; delta1 = fraction with max(pred / gt, gt / pred) < 1.25;
    median_ratio = median(pred / gt) (1 = no scale bias). NaN for M = 0."""
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.size == 0:
        nan = float("nan")
        return {"points": 0, "abs_rel": nan, "rmse": nan, "delta1": nan, "median_ratio": nan}
    r = pred / gt
    return {"points": int(pred.size),
            "abs_rel": float(np.mean(np.abs(pred - gt) / gt)),
            "rmse": float(math.sqrt(np.mean((pred - gt) ** 2))),
            "delta1": float(np.mean(np.maximum(r, 1.0 / np.maximum(r, 1e-12)) < DELTA)),
            "median_ratio": float(np.median(r))}


@dataclass(frozen=True)
class CameraDepth:
    """One camera's evaluation arrays, all at the evaluation size."""

    camera: Camera          # the evaluation camera (eval_camera)
    lidar: np.ndarray       # [H, W] float32 metres, 0 = no point (after the occlusion filter)
    depth: np.ndarray       # [H, W] float32 metres, rendered (0 where alpha is 0)
    alpha: np.ndarray       # [H, W] float32 rendered alpha
    occluded: int           # LiDAR pixels dropped by the occlusion filter


def camera_depths(scene: Any, points: np.ndarray, width: int = 400, min_depth: float = MIN_DEPTH,
                  max_depth: float = MAX_DEPTH, occlusion_radius: int = OCCLUSION_RADIUS) -> list[CameraDepth]:
    """Render ``scene`` (runtime.scene.Scene) at each camera of its rig and project ``points`` ([N, 3] metres, ego
    frame) there. With occlusion_radius 0 no point is dropped."""
    from .camera import rig_camera
    from .raydepth import render_ray_depth

    out = []
    for cam in scene.rig.cameras:
        ec = eval_camera(cam, width)
        lid = lidar_depth_map(points, ec, min_depth, max_depth)
        keep = occlusion_filter(lid, occlusion_radius) if occlusion_radius > 0 else lid > 0
        occluded = int((lid > 0).sum() - keep.sum())
        lid = np.where(keep, lid, 0).astype(np.float32)
        if ec.is_ideal:
            _, depth, alpha = scene.render(rig_camera(ec))
        else:
            depth, alpha = render_ray_depth(scene.gaussians_for(ec), ec)
        out.append(CameraDepth(ec, lid, depth, alpha, occluded))
    return out


def summarise(views: list[CameraDepth], alpha_min: float = ALPHA_MIN, bins=RANGE_BINS) -> dict[str, Any]:
    """{"cameras": [{name, lidar_pixels, occluded, covered, <depth_errors>}], "all": {...}, "ranges": [{from, to,
    ...}]}. covered = the fraction of LiDAR pixels where the rendered alpha is at least alpha_min; the errors are
    over those pixels."""
    rows, preds, gts = [], [], []
    for v in views:
        has = v.lidar > 0
        cov = has & (v.alpha >= alpha_min)
        p, g = v.depth[cov], v.lidar[cov]
        preds.append(p)
        gts.append(g)
        rows.append({"camera": v.camera.name, "lidar_pixels": int(has.sum()), "occluded": v.occluded,
                     "covered": float(cov.sum() / has.sum()) if has.any() else float("nan"),
                     **depth_errors(p, g)})
    p, g = np.concatenate(preds), np.concatenate(gts)
    n_all = sum(r["lidar_pixels"] for r in rows)
    total = {"camera": "all", "lidar_pixels": n_all, "occluded": sum(r["occluded"] for r in rows),
             "covered": float(p.size / n_all) if n_all else float("nan"), **depth_errors(p, g)}
    ranges = []
    for lo, hi in itertools.pairwise(bins):
        m = (g >= lo) & (g < hi)
        ranges.append({"from": lo, "to": hi, **depth_errors(p[m], g[m])})
    return {"cameras": rows, "all": total, "ranges": ranges}


def _depth_colours(d: np.ndarray, max_depth: float) -> np.ndarray:
    """[..., 3] uint8 RGB turbo colours of depths d (metres) on a log scale from MIN_DEPTH to max_depth."""
    import cv2

    t = np.log(np.clip(d, MIN_DEPTH, max_depth) / MIN_DEPTH) / math.log(max_depth / MIN_DEPTH)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return lut[np.clip(np.rint(255 * (1 - t)), 0, 255).astype(np.uint8)]   # near = red, far = blue


def depth_sheet(views: list[CameraDepth], images: list[np.ndarray], alpha_min: float = ALPHA_MIN,
                max_depth: float = MAX_DEPTH) -> np.ndarray:
    """[H, W, 3] uint8 RGB contact sheet, one row per camera: the input image with the LiDAR points coloured by
    depth; the rendered depth in the same colours (black where alpha < alpha_min); each covered point coloured by
    its relative error |rendered − LiDAR| / LiDAR (green 0, yellow 0.25, red >= 0.5). images: [H, W, 3] float
    RGB in [0, 1] per camera, any size (area-resized)."""
    import cv2

    rows = []
    for v, img in zip(views, images):
        h, w = v.lidar.shape
        base = cv2.resize(np.clip(img, 0, 1).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        base = np.rint(base * 255).astype(np.uint8)
        ys, xs = np.nonzero(v.lidar > 0)
        pts = base.copy()
        for y, x, c in zip(ys, xs, _depth_colours(v.lidar[ys, xs], max_depth)):
            cv2.circle(pts, (int(x), int(y)), 1, tuple(int(k) for k in c), -1)
        rend = _depth_colours(v.depth, max_depth)
        rend[v.alpha < alpha_min] = 0
        err = (base * 0.35).astype(np.uint8)
        cov = (v.lidar > 0) & (v.alpha >= alpha_min)
        ys, xs = np.nonzero(cov)
        e = np.clip(np.abs(v.depth[ys, xs] - v.lidar[ys, xs]) / v.lidar[ys, xs] / 0.5, 0, 1)
        for y, x, t in zip(ys, xs, e):
            colour = (int(255 * min(1.0, 2 * t)), int(255 * min(1.0, 2 * (1 - t))), 0)
            cv2.circle(err, (int(x), int(y)), 1, colour, -1)
        row = np.concatenate([pts, rend, err], axis=1)
        cv2.putText(row, v.camera.name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    head = np.zeros((20, width, 3), np.uint8)
    w3 = width // 3
    for i, text in enumerate(("input + LiDAR (depth: red near, blue far)", "rendered depth (same colours)",
                              "rel. error: green 0, red >= 0.5")):
        cv2.putText(head, text, (4 + i * w3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([head, *rows], axis=0)


# -- LiDAR as the depth input ------------------------------------------------------------------------------------

def fuse_depth(lidar: np.ndarray, head: np.ndarray, head_alpha: np.ndarray, alpha_min: float = ALPHA_MIN,
               min_cells: int = 20) -> tuple[np.ndarray, float]:
    """One camera's depth input [h, w] float32 metres (0 = sky / no surface) from a LiDAR map and the model's own
    depth, both at the network's depth size: LiDAR where a cell has a point (lidar > 0); elsewhere the model's
    rendered depth (head, where head_alpha >= alpha_min) times s = the median of lidar / head over the cells that
    have both, so the unscanned parts (above the top beam, beyond the range) keep the model's shape at the LiDAR's
    scale; 0 where neither has a surface. s = 1 when fewer than ``min_cells`` cells have both. Returns (map, s)."""
    both = (lidar > 0) & (head > 0) & (head_alpha >= alpha_min)
    s = float(np.median(lidar[both] / head[both])) if both.sum() >= min_cells else 1.0
    out = np.where(head_alpha >= alpha_min, head * np.float32(s), 0).astype(np.float32)
    out[lidar > 0] = lidar[lidar > 0]
    return out, s


__all__ = [
    "ALPHA_MIN",
    "DELTA",
    "MAX_DEPTH",
    "MIN_DEPTH",
    "NPY_MAGIC",
    "OCCLUSION_RADIUS",
    "RANGE_BINS",
    "CameraDepth",
    "LidarError",
    "LidarPoints",
    "camera_depths",
    "depth_errors",
    "depth_sheet",
    "eval_camera",
    "fuse_depth",
    "has_lidar",
    "lidar_depth_map",
    "lidar_depth_map_reference",
    "lidar_format",
    "load_lidar",
    "occlusion_filter",
    "occlusion_filter_reference",
    "read_points",
    "summarise",
]
