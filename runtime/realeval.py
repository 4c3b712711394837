"""Real-camera evaluation (`xyzcyl eval-real`): input views and novel views of real rigs, at full resolution.

- Input views: reconstruct a rig, render at each of its own cameras, compare with the posted images.
- Novel views (a folder of frames of one drive, each a rig.json with ``ego_to_world``): reconstruct frame A,
  render at the cameras of frame B (camera of B in A's ego frame: inv(ego_to_world_A) @ ego_to_world_B @
  cam_to_ego_B), compare with B's images, next to "not moving": A's image of the same camera, unchanged.

Metrics (full resolution, RGB in 0..1): PSNR; SSIM (Wang et al. 2004: 11x11 Gaussian window of sigma 1.5,
C1 = 0.01^2, C2 = 0.03^2, per channel then averaged); sharpness ratio = mean |gradient| of the luminance of the
image over that of the ground truth (central differences; 1 = as much fine detail as the camera, a smear < 1).
PSNR rewards blur; SSIM and the sharpness ratio do not. Each takes an optional ``mask`` ([H, W] bool, True = the
pixels scored; e.g. not the ego's own body): the means run over those pixels only (image_metrics also gives the
image the ground truth's values outside the mask, so that SSIM's windows and the gradients at the mask's edge see
no difference there).

Drives (`xyzcyl eval-real --drive`) are scored by runtime/drive_eval.py with these metrics and ``sheet``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .imageio import LUMA_BT601
from .rig import EGO_POSE_KEYS, Rig, RigError, load_rig

LUMA = LUMA_BT601                                    # ITU-R BT.601 luminance weights


# ------------------------------------------------------------------------------------------- metrics


def _masked_mean(a: np.ndarray, mask: np.ndarray | None) -> float:
    """Mean of [H, W] or [H, W, C] ``a`` over the pixels where ``mask`` ([H, W] bool) is True (all without a mask;
    NaN when none is)."""
    if mask is None:
        return float(np.mean(a))
    m = np.asarray(mask, bool)
    return float(np.mean(a[m])) if m.any() else math.nan


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """dB, images [H, W, 3] in 0..1 (inf when equal), over the pixels of ``mask`` when given."""
    mse = _masked_mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2, mask)
    if math.isnan(mse):
        return mse
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM of [H, W, 3] images in 0..1 (Wang et al. 2004 constants, Gaussian window 11 / sigma 1.5,
    'same' borders reflected, the per-channel maps averaged), over the pixels of ``mask`` when given."""
    import cv2

    x = np.asarray(pred, np.float64)
    y = np.asarray(gt, np.float64)
    c1, c2 = 0.01 ** 2, 0.03 ** 2

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return _masked_mean(m, mask)


def ssim_reference(pred: np.ndarray, gt: np.ndarray) -> float:
    """`ssim` with the window written out as an explicit weighted sum per pixel (slow; for the tests)."""
    x = np.asarray(pred, np.float64)
    y = np.asarray(gt, np.float64)
    H, W, C = x.shape
    r = np.arange(-5, 6)
    g = np.exp(-(r ** 2) / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()

    def refl(i: int, n: int) -> int:   # BORDER_REFLECT: fedcba|abcdefgh|hgfedcb
        while i < 0 or i >= n:
            i = -i - 1 if i < 0 else 2 * n - i - 1
        return i

    total = 0.0
    for c in range(C):
        for yy in range(H):
            for xx in range(W):
                rows = [refl(yy + k, H) for k in r]
                cols = [refl(xx + k, W) for k in r]
                px, py = x[np.ix_(rows, cols, [c])][..., 0], y[np.ix_(rows, cols, [c])][..., 0]
                mx, my = (w * px).sum(), (w * py).sum()
                sxx = (w * px * px).sum() - mx * mx
                syy = (w * py * py).sum() - my * my
                sxy = (w * px * py).sum() - mx * my
                total += ((2 * mx * my + 1e-4) * (2 * sxy + 9e-4)) / ((mx * mx + my * my + 1e-4) * (sxx + syy + 9e-4))
    return total / (H * W * C)


def gradient_energy(img: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean |gradient| of the luminance of [H, W, 3] (0..1), central differences in the interior (over the interior
    pixels of ``mask`` when given)."""
    lum = np.asarray(img, np.float32) @ LUMA
    gx = 0.5 * (lum[1:-1, 2:] - lum[1:-1, :-2])
    gy = 0.5 * (lum[2:, 1:-1] - lum[:-2, 1:-1])
    return _masked_mean(np.sqrt(gx * gx + gy * gy), None if mask is None else np.asarray(mask, bool)[1:-1, 1:-1])


def sharpness_ratio(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """gradient_energy(pred) / gradient_energy(gt) (NaN for a flat ground truth), over ``mask`` when given."""
    e = gradient_energy(gt, mask)
    return gradient_energy(pred, mask) / e if e > 0 else float("nan")


def image_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """PSNR, SSIM and the sharpness ratio of ``pred`` against ``gt``; with ``mask`` ([H, W] bool, True = scored)
    over its pixels, ``pred`` taking ``gt``'s values outside it (the module docstring)."""
    if mask is not None:
        m = np.asarray(mask, bool)
        pred = np.where(m[..., None], np.asarray(pred, np.float32), np.asarray(gt, np.float32))
    return {"psnr": psnr(pred, gt, mask), "ssim": ssim(pred, gt, mask), "sharpness": sharpness_ratio(pred, gt, mask)}


# ------------------------------------------------------------------------------------------- frames and pairs


def ego_to_world(rig: Rig, where: str) -> np.ndarray:
    """[4, 4] the rig's ego pose (Rig.ego_to_world), RigError naming ``where`` when it has none."""
    if rig.ego_to_world is None:
        raise RigError(EGO_POSE_KEYS[0], f"is missing (or {' or '.join(EGO_POSE_KEYS[1:])}): needed to place "
                       "another frame's cameras", where)
    return rig.ego_to_world


@dataclass(frozen=True)
class Frame:
    name: str           # the frame's folder name
    rig: Rig
    pose: np.ndarray    # [4, 4] ego_to_world


def load_frames(folder: str | Path) -> list[Frame]:
    """The frames of a drive: each sub-folder of ``folder`` holding a rig.json with an ego pose, in name order."""
    root = Path(folder)
    if not root.is_dir():
        raise RigError("frames", f"{str(root)!r} is not a folder")
    out = []
    for sub in sorted(p for p in root.iterdir() if (p / "rig.json").is_file()):
        rig = load_rig(sub / "rig.json")
        out.append(Frame(sub.name, rig, ego_to_world(rig, f"frame {sub.name!r}: rig")))
    if len(out) < 2:
        raise RigError("frames", f"{str(root)!r} needs at least two sub-folders with a rig.json (found {len(out)})")
    return out


def frame_distance(a: Frame, b: Frame) -> float:
    """Metres between the ego origins of two frames."""
    return float(np.linalg.norm(b.pose[:3, 3] - a.pose[:3, 3]))


def pairs_within(frames: Sequence[Frame], lo: float, hi: float) -> list[tuple[Frame, Frame]]:
    """Ordered pairs (A reconstructed, B rendered) of distinct frames whose ego origins are lo..hi metres apart."""
    return [(a, b) for a, b in itertools.permutations(frames, 2) if lo <= frame_distance(a, b) <= hi]


def camera_in(a: Frame, b: Frame, name: str):
    """Camera ``name`` of frame b as a rig Camera in frame a's ego frame (inv(E_a) @ E_b @ cam_to_ego_b)."""
    cam = b.rig.camera(name)
    T = np.linalg.inv(a.pose) @ b.pose @ cam.cam_to_ego
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return cam.replace(cam_to_ego=T)


# ------------------------------------------------------------------------------------------- evaluation


def _render_rgb(scene, cam) -> np.ndarray:
    from .scene import render_view, rig_camera

    rgb, _, _ = render_view(scene, rig_camera(cam))
    return np.clip(rgb, 0.0, 1.0)


def _thumb(img: np.ndarray, width: int) -> np.ndarray:
    import cv2

    h = max(1, round(img.shape[0] * width / img.shape[1]))
    return cv2.resize(np.clip(img, 0, 1).astype(np.float32), (width, h), interpolation=cv2.INTER_AREA)


def sheet(rows: Sequence[tuple[str, Sequence[np.ndarray]]], titles: Sequence[str], width: int = 480) -> np.ndarray:
    """[H, W, 3] uint8: one row per (label, images) with the images side by side at ``width`` each."""
    import cv2

    out = []
    head = np.zeros((22, width * len(titles), 3), np.uint8)
    for i, t in enumerate(titles):
        cv2.putText(head, t, (6 + i * width, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    out.append(head)
    for label, imgs in rows:
        row = np.concatenate([_thumb(i, width) for i in imgs], axis=1)
        row = np.rint(row * 255).astype(np.uint8)
        cv2.putText(row, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
        out.append(row)
    return np.concatenate(out, axis=0)


def _mean(rows: Sequence[dict[str, Any]], key: str) -> float:
    v = [r[key] for r in rows if math.isfinite(r[key])]
    return float(np.mean(v)) if v else float("nan")


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Means over rows of every numeric metric key (render_* and still_*), and the PSNR gain over not moving."""
    keys = sorted({k for r in rows for k in r if k.startswith(("render_", "still_"))})
    out = {k: _mean(rows, k) for k in keys}
    if "still_psnr" in out:
        out["gain_psnr"] = out["render_psnr"] - out["still_psnr"]
        out["gain_ssim"] = out["render_ssim"] - out["still_ssim"]
    out["views"] = len(rows)
    return out


def evaluate_inputs(scene, images: Sequence[np.ndarray], say: Callable[[str], None] = lambda m: None
                    ) -> tuple[list[dict[str, Any]], list[tuple[str, list[np.ndarray]]]]:
    """Each camera of ``scene.rig`` rendered at its own pose and full size against its posted image (images: [H, W,
    3] float 0..1 in rig order). Returns (rows of metrics, picture rows (camera, [ground truth, render]))."""
    rows, pics = [], []
    for cam, gt in zip(scene.rig.cameras, images):
        say(f"render {cam.name} {cam.width}x{cam.height}")
        r = _render_rgb(scene, cam)
        rows.append({"camera": cam.name, **{f"render_{k}": v for k, v in image_metrics(r, gt).items()}})
        pics.append((cam.name, [gt, r]))
    return rows, pics


def evaluate_pair(scene, a: Frame, b: Frame, images_a: Sequence[np.ndarray], images_b: Sequence[np.ndarray],
                  say: Callable[[str], None] = lambda m: None
                  ) -> tuple[list[dict[str, Any]], list[tuple[str, list[np.ndarray]]]]:
    """Frame a's scene rendered at each camera of frame b (the cameras both rigs have, by name) against b's image,
    and a's own image of that camera ("not moving") against it. Returns (rows, picture rows (camera, [ground
    truth, render, not moving]))."""
    rows, pics = [], []
    names_a = a.rig.names
    for cam, gt in zip(b.rig.cameras, images_b):
        if cam.name not in names_a:
            continue
        still = images_a[names_a.index(cam.name)]
        if still.shape != gt.shape:
            continue
        say(f"{a.name} -> {b.name}: render {cam.name}")
        r = _render_rgb(scene, camera_in(a, b, cam.name))
        row = {"camera": cam.name, **{f"render_{k}": v for k, v in image_metrics(r, gt).items()},
               **{f"still_{k}": v for k, v in image_metrics(still, gt).items()}}
        rows.append(row)
        pics.append((cam.name, [gt, r, still]))
    return rows, pics


__all__ = ["Frame", "camera_in", "evaluate_inputs", "evaluate_pair", "frame_distance", "gradient_energy",
           "image_metrics", "load_frames", "pairs_within", "psnr", "sharpness_ratio", "sheet", "ssim",
           "ssim_reference", "summary"]
