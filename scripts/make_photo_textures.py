"""Cut the photo texture bank of `xyzcyl data synth --photo-textures` (docs/data.md) out of the two CC0 Poly Haven
panoramas in ../shared/data/real (their 8-bit tonemapped previews), and write a contact sheet.

    .venv/bin/python scripts/make_photo_textures.py [--real ../shared/data/real] [--sheet sheet.png]

Each crop is a rectangle of the equirectangular image (x0, y0, x1, y1 pixels, 1024 x 512, row 0 = zenith) that
shows one real surface: a building facade or a ground surface. Crops are resized to TILE x TILE (the physical
size of a tile is drawn per surface by the generator) and written to model_export/data/photos/<kind>_<name>.png.
The panoramas are CC0 1.0 (public domain), so the crops ship in the package.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

TILE = 128
PANOS = {"potsdamer": "pano_potsdamer_platz/potsdamer_platz_1k_tonemapped.png",
         "venice": "pano_venice_sunset/venice_sunset_1k_tonemapped.png"}
# kind_name: (panorama, x0, y0, x1, y1)
CROPS = {
    "facade_brick_tower": ("potsdamer", 526, 104, 562, 226),
    "facade_glass_tower": ("potsdamer", 452, 140, 500, 240),
    "facade_curved_glass": ("potsdamer", 736, 96, 800, 226),
    "facade_beige_tower": ("potsdamer", 881, 152, 912, 214),
    "facade_white_tower": ("potsdamer", 60, 190, 97, 234),
    "facade_office_block": ("potsdamer", 212, 214, 288, 252),
    "facade_villa": ("venice", 910, 186, 1005, 268),
    "facade_venice_row": ("venice", 108, 224, 190, 265),
    "ground_asphalt": ("potsdamer", 290, 348, 440, 395),
    "ground_red_paving": ("potsdamer", 600, 440, 880, 500),
    "ground_stone_paving": ("venice", 20, 390, 260, 480),
    "ground_cobbles": ("venice", 20, 290, 180, 340),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "model_export" / "data" / "photos")
    ap.add_argument("--sheet", type=Path, default=None, help="also write the crops side by side into this PNG")
    args = ap.parse_args()
    panos = {}
    for key, rel in PANOS.items():
        img = cv2.imread(str(args.real / rel), cv2.IMREAD_COLOR)
        if img is None:
            ap.error(f"--real: no panorama at {args.real / rel}")
        panos[key] = img
    args.out.mkdir(parents=True, exist_ok=True)
    tiles = []
    for name, (pano, x0, y0, x1, y1) in CROPS.items():
        tile = cv2.resize(panos[pano][y0:y1, x0:x1], (TILE, TILE), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(args.out / f"{name}.png"), tile)
        tiles.append(tile)
    if args.sheet:
        cv2.imwrite(str(args.sheet), np.concatenate(tiles, axis=1))
    print(f"{len(tiles)} tiles -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
