"""`near_cars`: traffic beside the ego (real rigs see parked cars 2-3 m from a side camera; v1 kept every car
>= 8 m away). Off by default and then the generator is unchanged; on, cars sit beside the ego, never in its lane
and never overlapping it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from synth_helpers import check_probability_field
from xyzcyl.model_export.data import classes as C
from xyzcyl.model_export.data.occupancy import inside_any
from xyzcyl.model_export.data.scene import BOX, SceneConfig, sample_scene


def _cars(scene):
    """[K, 2] (x, y) ego-frame centres of the non-ego car bodies (half length > 1.5 m: not wheels or cabins)."""
    body = (scene.cls == C.VEHICLE) & (scene.kind == BOX) & (scene.geo[:, 3] > 1.5) & ~scene.ego
    return scene.geo[body, :2]


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a.arrays().values(), b.arrays().values(), strict=True))


def test_zero_is_the_v1_generator_byte_for_byte():
    for i in range(4):
        assert _same(sample_scene(7, i), sample_scene(7, i, SceneConfig(near_cars=0.0)))


def test_near_scenes_have_cars_beside_the_ego_and_keep_its_lane_clear():
    near_dist, v1_dist = [], []
    for i in range(12):
        v1 = sample_scene(7, i)
        s = sample_scene(7, i, SceneConfig(near_cars=1.0))
        for cars, out in ((_cars(v1), v1_dist), (_cars(s), near_dist)):
            d = np.hypot(cars[:, 0] - 1.3, cars[:, 1])  # from the ego's body centre
            out.append(d.min() if len(d) else np.inf)
        # nothing in the ego lane within 10 m (lane half-width >= 1.5 m; ego-forward targets move <= 3 m)
        cars = _cars(s)
        assert not np.any((np.abs(cars[:, 1]) < 1.4) & (np.abs(cars[:, 0]) < 9.0))
        # no other solid reaches into the ego car's body box (grid of points inside it, 0.9 m up)
        others = replace(s, **{k: getattr(s, k)[~s.ego] for k in ("kind", "geo", "cls", "tex", "col", "col2",
                                                                   "par", "ego")})
        ex, ey = np.meshgrid(np.linspace(-0.7, 3.3, 9), np.linspace(-0.85, 0.85, 5))
        pts = np.stack([ex.ravel(), ey.ravel(), np.full(ex.size, 0.9)], 1)
        assert not np.any(inside_any(others, pts)), f"scene {i}: a solid overlaps the ego car"
    assert min(v1_dist) > 8.0  # v1: the 6 m discs keep cars away
    # most near scenes get a car within 6 m (each neighbouring lane: probability 0.7)
    assert np.mean(np.array(near_dist) < 6.0) >= 0.5


def test_probability_draws_per_scene():
    cfg = SceneConfig(near_cars=0.5)
    near = [not _same(sample_scene(3, i), sample_scene(3, i, cfg)) for i in range(40)]
    assert 8 <= sum(near) <= 32  # binomial(40, 0.5): outside this range with probability < 1e-4


def test_config_validation_cli_and_index(tmp_path, capsys):
    # out-of-range values refused naming the field; index.json records it; an older folder resumes as 0
    check_probability_field(tmp_path, capsys, "near_cars")
