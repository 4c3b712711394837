"""A drive scored on its own frames (`xyzcyl eval-real --drive`): the drive reconstructed whole against one frame
alone and against not moving.

Keyframes are every ``every``th frame of the drive (of ``--frames A:B``: frames A..B-1, renumbered from 0 inside,
reported by their number in the drive file); the drive of those keyframes is reconstructed once
(runtime.drive.reconstruct_drive) and each keyframe that is the nearest to a scored frame alone once
(Reconstructor.reconstruct; one at a time, in the order they are needed). Every other frame is scored (``max_views``:
that many of them, evenly spread), with all its cameras (or ``cameras``) at ``width`` pixels (aspect kept; default
the cameras' own), three ways against its own images:

- drive: the drive's scene rendered at the frame's cameras (placed in the first frame's ego frame) and time (its
  moving objects where the tracks put them then);
- one: the nearest keyframe (ties: the earlier) reconstructed alone, rendered at the frame's cameras (in that
  keyframe's ego frame);
- still: "not moving", the nearest keyframe's own image of that camera.

Scores: PSNR, SSIM and the sharpness ratio of runtime.realeval, over the pixels that are not the ego's own body:
the camera's ``ego_mask`` where its rig gives one (the frame's rig's mask), else the body the drive's reconstruction
found over its frames (runtime.egobody), resampled to the scored size (a pixel any part of which is the ego's is
left out); the same pixels for all three. One picture sheet per scored frame (ground truth | drive | one frame alone
| not moving, a row per camera) and the report (evaluate_drive); method_lines are the summary lines the command
prints (the keys benchmarks/drive_eval.py printed: docs/results.md "Drives")."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from .drive import Drive, DriveError, Track, find_drive_ego_body, reconstruct_drive

METHODS = ("drive", "one", "still")
METRICS = ("psnr", "ssim", "sharpness")
TITLES = ("ground truth", "drive", "one frame alone", "not moving")
PICTURE_WIDTH = 480


def sub_drive(drive: Drive, start: int, stop: int) -> Drive:
    """Frames start..stop-1 of ``drive`` as a drive of their own (renumbered from 0), with each track's poses at
    those frames (renumbered too; a track with none there left out). DriveError naming ``frames`` when the range is
    not within the drive or holds no frame."""
    n = len(drive)
    if not 0 <= start < stop <= n:
        raise DriveError("frames", f"{start}:{stop} is not a range of the drive's frames (0:{n}: frames 0..{n - 1})")
    frames = tuple(replace(f, index=i) for i, f in enumerate(drive.frames[start:stop]))
    tracks = []
    for t in drive.tracks:
        poses = {k - start: m for k, m in t.poses.items() if start <= k < stop}
        if poses:
            tracks.append(Track(t.id, t.label, t.size, t.stationary, poses))
    return Drive(drive.path, frames, tuple(tracks))


def plan(n_frames: int, every: int, max_views: int | None = None) -> tuple[list[int], list[int]]:
    """(keyframes, scored frames) of a drive of ``n_frames``: keyframes every ``every``th frame from the first, every
    other frame scored; ``max_views``: that many scored frames, evenly spread from the first to the last (the
    selection benchmarks/drive_eval.py made). DriveError naming ``every`` / ``max_views`` for values < 1."""
    if every < 1:
        raise DriveError("every", f"must be >= 1 (got {every})")
    if max_views is not None and max_views < 1:
        raise DriveError("max_views", f"must be >= 1 (got {max_views})")
    keys = list(range(0, n_frames, every))
    scored = [k for k in range(n_frames) if k not in keys]
    if max_views and scored:
        scored = sorted({scored[round(i * (len(scored) - 1) / max(1, max_views - 1))]
                         for i in range(min(max_views, len(scored)))})
    return keys, scored


def nearest_keyframe(keys: Sequence[int], k: int) -> int:
    """The keyframe nearest frame k (ties: the earlier)."""
    return min(keys, key=lambda j: (abs(j - k), j))


def camera_at(drive: Drive, k_from: int, k_to: int, cam, width: int | None = None):
    """Rig camera ``cam`` of frame k_to as a render camera in frame k_from's ego frame
    (inv(ego_to_world_from) @ ego_to_world_to @ cam_to_ego), at ``width`` pixels (aspect kept; None: its own)."""
    from .camera import rig_camera

    T = np.linalg.inv(drive.frames[k_from].ego_to_world) @ drive.frames[k_to].ego_to_world @ cam.cam_to_ego
    T[3] = (0.0, 0.0, 0.0, 1.0)
    c = rig_camera(cam.replace(cam_to_ego=T))
    if width and width != c.width:
        c = c.resized(width, max(1, round(c.height * width / c.width)))
    return c


def scored_mask(rig, cam, size: tuple[int, int], found: np.ndarray | None = None) -> np.ndarray | None:
    """[H, W] bool at ``size`` (W, H): the pixels to score of rig camera ``cam``, i.e. not its ``ego_mask`` (a pixel
    any part of which is the ego's body is left out), else not ``found`` ([H, W] bool at the camera's size: the
    body runtime.egobody found over the drive); None when the camera has neither."""
    mask_file = cam.extra.get("ego_mask")
    if mask_file is None and found is None:
        return None
    import cv2

    from .detail import read_ego_mask

    ego = (read_ego_mask(rig.path(mask_file), cam) if mask_file is not None else found).astype(np.float32)
    if (ego.shape[1], ego.shape[0]) != tuple(size):
        ego = cv2.resize(ego, tuple(size), interpolation=cv2.INTER_AREA)
    return ego <= 0.0


def _fit(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)


def _mean(rows: Sequence[dict[str, Any]], key: str, sel: Callable[[dict[str, Any]], bool] = lambda r: True) -> float:
    v = [r[key] for r in rows if sel(r) and np.isfinite(r[key])]
    return float(np.mean(v)) if v else float("nan")


def evaluate_drive(rec, drive: Drive, keys: Sequence[int], scored: Sequence[int], out: str | Path, *,
                   lidar: bool = True, detail: Any = None, width: int | None = None,
                   cameras: Sequence[str] | None = None, first: int = 0,
                   say: Callable[[str], None] = lambda msg: None, bar: Any = None, stereo: bool = True,
                   ego_body: bool = True, exposure: bool = True) -> dict[str, Any]:
    """Score ``drive`` (module docstring) with runtime.inference.Reconstructor ``rec``: keyframes ``keys`` and
    frames ``scored`` (indices into ``drive``), each keyframe's LiDAR sweep when ``lidar`` and it has one, the detail
    layer ``detail`` (runtime.detail.DetailOptions; None: the model's Gaussians only), the drive's keyframes
    without a sweep with depth from the motion between frames when ``stereo`` (runtime.stereo; one frame alone has
    none), the ego's own body found over the drive when ``ego_body`` (runtime.egobody; off, it is found for the
    scores only), exposure harmonised when ``exposure`` (runtime.exposure), the size ``width``, the
    cameras ``cameras`` (names; None: all). ``first``: the number of the drive's frame 0 in its drive file (frames
    are reported by that number). Writes a picture sheet per scored frame into ``out`` (frame_NN.jpg) and returns the
    report; ``bar`` (a tqdm-like object with update()/close(), or None) advances once per scored frame."""
    import cv2

    from .inference import rgb_images
    from .lidar import has_lidar, load_lidar
    from .realeval import image_metrics, sheet
    from .scene import render_view

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    def sweep(k: int):
        rig = drive.frames[k].rig
        return load_lidar(rig).points if lidar and has_lidar(rig) else None

    def images(k: int) -> list[np.ndarray]:
        return rgb_images(drive.frames[k].rig)

    def shot(scene, cam, time_s=None) -> np.ndarray:
        rgb, _, _ = render_view(scene, cam, time_s=time_s)
        return np.clip(rgb, 0.0, 1.0)

    say(f"reconstruct the drive: {len(keys)} keyframes of {len(drive)} frames")
    t0 = time.perf_counter()
    whole = reconstruct_drive(rec, drive, keyframes=list(keys), lidar=lidar, detail=detail, progress=say,
                              stereo=stereo, ego_body=ego_body, exposure=exposure)
    t_drive = time.perf_counter() - t0
    # the same pixels are scored with the body used or not: off, it is still found, for the scores only
    found = (whole.ego_body.masks if whole.ego_body is not None else
             find_drive_ego_body(drive, lidar).masks if len(keys) > 1 or drive.tracks else {})

    rows: list[dict[str, Any]] = []
    pictures: list[str] = []
    ego_masked: dict[str, float] = {}
    singles_n: dict[int, int] = {}
    t_single: dict[int, float] = {}
    single = None                      # (keyframe, its scene alone, its images): one at a time
    for b in scored:
        near = nearest_keyframe(keys, b)
        if single is None or single[0] != near:
            single = None
            imgs_k = images(near)
            say(f"reconstruct keyframe {first + near} alone")
            t1 = time.perf_counter()
            scene = rec.reconstruct(drive.frames[near].rig, images=imgs_k, lidar=sweep(near), detail=detail,
                                    exposure=exposure)
            t_single[near] = time.perf_counter() - t1
            singles_n[near] = int((scene.gaussians.opacity_logits > -20).sum())
            single = (near, scene, imgs_k)
        _, alone, imgs_k = single
        fb = drive.frames[b]
        pics = []
        for cam, gt, still in zip(fb.rig.cameras, images(b), imgs_k):
            if cameras is not None and cam.name not in cameras:
                continue
            c_drive = camera_at(drive, 0, b, cam, width)
            c_one = camera_at(drive, near, b, cam, width)
            size = (c_drive.width, c_drive.height)
            gt_s, still_s = _fit(gt, size), _fit(still, size)
            mask = scored_mask(fb.rig, cam, size, found.get(cam.name))
            if mask is not None:
                ego_masked[cam.name] = round(float(1.0 - mask.mean()), 6)
            r_drive, r_one = shot(whole, c_drive, fb.timestamp_s), shot(alone, c_one)
            row: dict[str, Any] = {"frame": first + b, "keyframe": first + near, "camera": cam.name}
            for name, img in zip(METHODS, (r_drive, r_one, still_s)):
                row.update({f"{name}_{k}": v for k, v in image_metrics(img, gt_s, mask).items()})
            rows.append(row)
            pics.append((cam.name, [gt_s, r_drive, r_one, still_s]))
        if pics:
            pic = out / f"frame_{first + b:02d}.jpg"
            if not cv2.imwrite(str(pic), sheet(pics, TITLES, PICTURE_WIDTH)[..., ::-1].copy(),
                               [cv2.IMWRITE_JPEG_QUALITY, 88]):
                raise OSError(f"could not write {str(pic)!r}")
            pictures.append(pic.name)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()

    cams = sorted({r["camera"] for r in rows})
    methods = {}
    for m in METHODS:
        methods[m] = {k: _mean(rows, f"{m}_{k}") for k in METRICS}
        methods[m]["per_camera"] = {c: _mean(rows, f"{m}_psnr", lambda r, c=c: r["camera"] == c) for c in cams}
    return {
        "frames": len(drive), "first_frame": first, "keyframes": [first + k for k in keys],
        "scored_frames": [first + k for k in scored],
        "lidar_keyframes": [first + k for k in keys if lidar and frame_has_lidar(drive, k)],
        "width": width, "cameras": list(cameras) if cameras is not None else None, "ego_masked": ego_masked,
        "gaussians": {"drive": len(whole.gaussians) + (whole.viewpoints.count if whole.viewpoints else 0),
                      "drive_shared": len(whole.gaussians),
                      "drive_camera_layers": whole.camera_layers.count if whole.camera_layers else 0,
                      "one_frame": {str(first + k): v for k, v in singles_n.items()}},
        "seconds": {"drive": round(t_drive, 2), "one_frame_each": [round(t, 2) for t in t_single.values()],
                    "drive_stages": whole.timings},
        "drive_counts": whole.counts, "methods": methods, "pictures": pictures, "rows": rows,
    }


def frame_has_lidar(drive: Drive, k: int) -> bool:
    from .lidar import has_lidar

    return has_lidar(drive.frames[k].rig)


def method_lines(report: dict[str, Any]) -> list[dict[str, Any]]:
    """The summary lines of a report: one per method ({"method", "psnr", "ssim", "sharpness", "per_camera"}), then
    {"gaussians", "seconds"} (the lines benchmarks/drive_eval.py printed)."""
    lines = [{"method": m, **report["methods"][m]} for m in METHODS]
    lines.append({"gaussians": report["gaussians"], "seconds": report["seconds"]})
    return lines


__all__ = ["METHODS", "camera_at", "evaluate_drive", "frame_has_lidar", "method_lines", "nearest_keyframe", "plan",
           "scored_mask", "sub_drive"]
