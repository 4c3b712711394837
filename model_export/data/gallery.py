"""Contact sheet of a synthetic data set: per scene, the input ring (panorama order), then target views, the
depth and semantics of the front camera and the occupancy BEV."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from .classes import PALETTE
from .synth import read_exr


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"gallery: cannot read {path}")
    return img[..., ::-1] if img.ndim == 3 else img


def _depth_vis(depth: np.ndarray) -> np.ndarray:
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-3), 0.0)
    v = np.clip(inv / 0.5, 0, 1) ** 0.5  # 2 m -> 1, far -> 0
    col = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)[..., ::-1]
    col[depth <= 0] = 0
    return col


def _tile(img: np.ndarray, w: int, h: int, nearest: bool = False) -> np.ndarray:
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def _yaw(cam: dict) -> float:
    T = np.asarray(cam["cam_to_ego"])
    return math.atan2(T[1, 2], T[0, 2])


def scene_block(folder: Path, tile_w: int = 200, n_cols: int = 6) -> np.ndarray:
    """Two rows of `n_cols` tiles for one scene folder."""
    rig = json.loads((folder / "rig.json").read_text())
    # panorama order (clockwise seen from above, starting behind): back, back-left, ..., front, ..., back-right
    cams = sorted(rig["cameras"], key=lambda c: -(_yaw(c) + (2 * math.pi if _yaw(c) < -2.9 else 0.0)))
    h0, w0 = rig["cameras"][0]["height"], rig["cameras"][0]["width"]
    tile_h = int(round(tile_w * h0 / w0))
    row1 = [_tile(_read_rgb(folder / c["image"]), tile_w, tile_h) for c in cams[:n_cols]]
    row2 = []
    tj = folder / "targets.json"
    if tj.exists():
        settings = json.loads(tj.read_text())["settings"]
        picks = []
        for name, s in settings.items():
            cs = s["cameras"]
            step = max(1, len(cs) // 2)
            picks += cs[::step][:2] if name == "ego-inward" else [cs[0]]
        for c in picks[: n_cols - 3]:
            row2.append(_tile(_read_rgb(folder / c["image"]), tile_w, tile_h))
    front = min(rig["cameras"], key=lambda c: abs(_yaw(c)))
    row2.append(_tile(_depth_vis(read_exr(folder / front["depth"])), tile_w, tile_h))
    row2.append(_tile(PALETTE[_read_rgb(folder / front["semantic"])], tile_w, tile_h, nearest=True))
    occ = np.load(folder / "occupancy.npz")
    key = sorted((k for k in occ.files if k.startswith("bev_")), key=lambda k: float(k[4:].replace("p", ".")))[0]
    b = occ[key][::-1, ::-1]  # rows: x forward up; columns: y left on the left
    bev_img = PALETTE[b]
    bev_img = cv2.resize(bev_img, (tile_h, tile_h), interpolation=cv2.INTER_NEAREST)
    pad = np.zeros((tile_h, tile_w, 3), np.uint8)
    x0 = (tile_w - tile_h) // 2
    pad[:, x0:x0 + tile_h] = bev_img
    row2.append(pad)
    while len(row2) < n_cols:
        row2.insert(0, np.zeros((tile_h, tile_w, 3), np.uint8))
    while len(row1) < n_cols:
        row1.append(np.zeros((tile_h, tile_w, 3), np.uint8))
    return np.concatenate([np.concatenate(row1, 1), np.concatenate(row2[:n_cols], 1)], 0)


def contact_sheet(dataset: Path, scenes: int = 8, tile_w: int = 200) -> np.ndarray:
    """[H, W, 3] uint8 sheet of the first `scenes` scene folders of `dataset`."""
    folders = sorted(p for p in Path(dataset).glob("scene_*") if p.is_dir())[:scenes]
    if not folders:
        raise ValueError(f"dataset: no scene_* folders in {dataset}")
    blocks = []
    for f in folders:
        b = scene_block(f, tile_w)
        blocks.append(b)
        blocks.append(np.full((4, b.shape[1], 3), 255, np.uint8))
    return np.concatenate(blocks[:-1], 0)
