"""Photo texture bank (`SceneConfig.photo_textures`, `xyzcyl data synth --photo-textures P`): real surfaces for
the procedural streets, so the depth head also learns from real-looking facades and pavements.

The tiles in ``photos/`` are crops of the two CC0 Poly Haven street panoramas of ../shared/data/real, cut by
scripts/make_photo_textures.py (which names every crop). Each tile is an 8-bit sRGB PNG, TILE x TILE pixels.

``photo_bank()`` -> (bank [N, TILE, TILE, 3] float64, names): each tile divided by its mean luminance, so a
surface's albedo is ``bank[i] * L`` with L the surface's own luminance: the photo gives the texture and hue, the
scene keeps its brightness distribution. Facade tiles are first, then ground tiles (FACADES, GROUNDS: indices).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

PHOTO_DIR = Path(__file__).with_name("photos")
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance weights of RGB


@lru_cache(maxsize=1)
def photo_bank() -> tuple[np.ndarray, tuple[str, ...]]:
    """(bank [N, T, T, 3] float64 RGB with mean luminance 1 per tile, tile names); facades first."""
    files = sorted(PHOTO_DIR.glob("facade_*.png")) + sorted(PHOTO_DIR.glob("ground_*.png"))
    if not files:
        raise FileNotFoundError(f"photo_textures: no tiles in {PHOTO_DIR} (scripts/make_photo_textures.py)")
    tiles = []
    for f in files:
        bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"photo_textures: unreadable tile {f}")
        rgb = bgr[..., ::-1].astype(np.float64) / 255.0
        tiles.append(rgb / max(float((rgb @ LUMA).mean()), 1e-6))
    shapes = {t.shape for t in tiles}
    if len(shapes) != 1:
        raise ValueError(f"photo_textures: tiles differ in size {sorted(shapes)}")
    bank = np.ascontiguousarray(np.stack(tiles))
    return bank, tuple(f.stem for f in files)


def photo_indices() -> tuple[np.ndarray, np.ndarray]:
    """(facade tile indices, ground tile indices) into photo_bank()."""
    names = photo_bank()[1]
    return (np.array([i for i, n in enumerate(names) if n.startswith("facade_")]),
            np.array([i for i, n in enumerate(names) if n.startswith("ground_")]))


# the bank the tracer gets when a scene uses no photo tile (never read then; numba needs an array of the bank's type)
NO_PHOTOS = np.zeros((1, 2, 2, 3), np.float64)
