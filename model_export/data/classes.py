"""Semantic class table of the synthetic scenes (semantic images, occupancy grids, BEV maps).

Id 0 means "sky" in semantic images and "free" in occupancy grids. Ids are stable across generator versions
(a new class gets a new id). `PRIORITY` decides the class of a voxel touched by several solids: the higher
priority wins (thin or small things over the ground they stand on and the walls they touch).
"""

from __future__ import annotations

import numpy as np

SKY = FREE = 0
ROAD = 1
SIDEWALK = 2
TERRAIN = 3
BUILDING = 4
VEHICLE = 5
VEGETATION = 6
POLE = 7
TRAFFIC_SIGN = 8
FENCE = 9
EGO = 10

# id -> (name, display colour RGB 0..255)
CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    SKY: ("sky/free", (0, 0, 0)),
    ROAD: ("road", (128, 64, 128)),
    SIDEWALK: ("sidewalk", (244, 35, 232)),
    TERRAIN: ("terrain", (152, 251, 152)),
    BUILDING: ("building", (70, 70, 70)),
    VEHICLE: ("vehicle", (0, 0, 142)),
    VEGETATION: ("vegetation", (107, 142, 35)),
    POLE: ("pole", (153, 153, 153)),
    TRAFFIC_SIGN: ("traffic_sign", (220, 220, 0)),
    FENCE: ("fence", (190, 153, 153)),
    EGO: ("ego_vehicle", (255, 0, 0)),
}
NUM_CLASSES = len(CLASSES)

PRIORITY = np.array([0, 1, 3, 2, 4, 7, 5, 8, 9, 6, 10], dtype=np.int32)  # indexed by class id

PALETTE = np.zeros((256, 3), dtype=np.uint8)  # class id -> colour, for visualisation
for _i, (_n, _c) in CLASSES.items():
    PALETTE[_i] = _c
