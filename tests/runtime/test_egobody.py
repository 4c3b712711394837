"""The ego's own body found over a drive's frames (runtime.egobody): a hood that stays put over a road that moves
is found; the road, the sky, a frozen camera and a still ego are not."""

from pathlib import Path

import numpy as np
import pytest
from xyzcyl.runtime import egobody as E
from xyzcyl.runtime.camera import Camera

PANDASET_DRIVE = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"

W, H = 320, 180
HOOD_ROW = 150          # the hood covers rows 150..179: the bottom sixth


def _camera() -> Camera:
    """A forward camera 1.5 m above the ground, level, 90 degrees wide."""
    K = np.array([[160.0, 0, 159.5], [0, 160.0, 89.5], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)      # OpenCV camera -> ego (x fwd, z up)
    T[:3, 3] = (1.0, 0.0, 1.5)
    return Camera(K=K, cam_to_ego=T, width=W, height=H, name="front")


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


_rng = np.random.default_rng(0)
_TEX = _rng.uniform(0.2, 0.8, size=(64, 64))          # the road's texture: 0.25 m cells, wrapping


def _frame(cam: Camera, x: float, hood: bool = True) -> np.ndarray:
    """[H, W, 3] the ray-traced view from ego position x: a textured road (z = 0), a sky, and a hood (a fixed
    patch with a dark edge and a badge) over the bottom rows."""
    o, d = cam.pixel_rays()
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[..., 2] / d[..., 2]
    ground = np.isfinite(t) & (t > 0)
    p = o + d * np.where(ground, t, 0.0)[..., None]
    gx, gy = p[..., 0] + x, p[..., 1]
    i, j = np.floor(gx / 0.25).astype(int) % 64, np.floor(gy / 0.25).astype(int) % 64
    road = _TEX[i, j]
    img = np.where(ground, road, 0.9)[..., None] * np.array([1.0, 1.0, 1.0])
    img[~ground] = (0.5, 0.7, 0.95)
    if hood:
        img[HOOD_ROW:] = (0.8, 0.1, 0.1)
        img[HOOD_ROW:HOOD_ROW + 3] = (0.2, 0.02, 0.02)                   # its edge
        img[165:172, 150:170] = (0.95, 0.95, 0.95)                      # a badge
    return img.astype(np.float32)


def _find(xs, hood=True, skip=()):
    cam = _camera()
    poses = [_pose(x) for x in xs]
    frames = {k: [_frame(cam, x, hood)] for k, x in enumerate(xs)}
    return E.find_ego_body([cam], lambda k: frames[k], np.array([T[:3, 3] for T in poses]), poses, 0.0, skip=skip)


def test_spread_frames_counts_a_still_stretch_once():
    pos = np.array([[0, 0, 0]] * 5 + [[x, 0, 0] for x in np.linspace(0.5, 4.0, 8)], float)
    frames, total = E.spread_frames(pos, count=5)
    assert total == pytest.approx(4.0)
    assert frames[0] == 0 and frames[-1] == len(pos) - 1
    assert not set(frames) & {1, 2, 3, 4}                  # the still stretch: its first frame only
    assert E.spread_frames(np.zeros((4, 3))) == ([0], 0.0)


def test_world_flow_moves_the_road_and_leaves_the_horizon():
    """Forward 2 m: a road pixel's flow is where the same ground point projects from the new position (worked
    out here by the pinhole formula); a pixel above the horizon (at infinity) does not move."""
    cam = _camera()
    flow = E.world_flow(cam, _pose(0.0), _pose(2.0), 0.0)
    u, v = 200, 110                                        # below the horizon (row 89.5): the road 1.5 / tan(.)
    dist = 1.5 * 160.0 / (v - 89.5)                        # metres ahead of the camera
    lateral = -(u - 159.5) * dist / 160.0                  # metres to the left (ego y)
    dist2 = dist - 2.0
    u2, v2 = 159.5 - lateral * 160.0 / dist2, 89.5 + 1.5 * 160.0 / dist2
    np.testing.assert_allclose(flow[v, u], (u2 - u, v2 - v), atol=1e-6)   # exact arithmetic both ways
    np.testing.assert_allclose(flow[40, 100], 0.0, atol=1e-6)
    assert np.isnan(flow[179, 0]).all()                    # that ground point leaves the view (under the car)


def test_texture_change_sees_texture_not_uniform_surfaces():
    flow = np.zeros((20, 30, 2))
    flow[..., 1] = 10.0
    flat = np.full((20, 30, 3), 0.5, np.float32)
    assert np.abs(E.texture_change(flat, flow)).max() < 1e-6
    stripes = np.repeat((np.arange(20) // 3 % 2 * 0.6 + 0.2)[:, None, None], 30, 1).repeat(3, 2).astype(np.float32)
    assert E.texture_change(stripes, flow)[5:15].mean() > E.TEXTURE_LEVEL


def test_a_hood_that_stays_put_is_found_and_the_road_is_not():
    eb = _find(np.linspace(0.0, 4.0, 12))
    assert set(eb.masks) == {"front"} and not eb.notes
    m = eb.masks["front"]
    truth = np.zeros((H, W), bool)
    truth[HOOD_ROW:] = True
    iou = (m & truth).sum() / (m | truth).sum()
    assert iou >= 0.9, iou                                  # the growth adds GROW_FRAC x W = 2 px at the edge
    assert not m[: HOOD_ROW - 4].any()                      # no road, no sky


def test_no_body_without_motion_a_frozen_camera_or_a_given_mask():
    still = _find(np.linspace(0.0, 1.0, 12))               # under MIN_TRAVEL_M
    assert not still.masks and still.travelled_m == pytest.approx(1.0)
    cam = _camera()
    one = _frame(cam, 0.0)                                  # the same image at every position
    xs = np.linspace(0.0, 4.0, 12)
    poses = [_pose(x) for x in xs]
    frozen = E.find_ego_body([cam], lambda k: [one], xs[:, None] * [1, 0, 0], poses)
    assert not frozen.masks and frozen.notes["front"].startswith("frozen")
    assert not _find(xs, skip=["front"]).masks              # the rig's own ego_mask wins
    assert not _find(xs, hood=False).masks                  # a road alone has no body


@pytest.mark.skipif(not PANDASET_DRIVE.is_file(), reason="the shared PandaSet drive is not here")
def test_pandaset_back_camera_trunk_is_found():
    """The real drive (2.6 m travelled): the back camera's trunk (its bottom ~23 %) is found, the other five
    cameras have no body. The docs picture (docs/pictures/ego_body_pandaset.jpg) is this result."""
    from xyzcyl.runtime.drive import find_drive_ego_body, load_drive

    eb = find_drive_ego_body(load_drive(PANDASET_DRIVE))
    assert set(eb.masks) == {"back_camera"}, eb.summary()
    m = eb.masks["back_camera"]
    assert 0.15 <= m.mean() <= 0.30, m.mean()
    assert m[-50:, 200:1700].mean() > 0.95                  # the trunk's middle, just above the bottom edge
    assert not m[: m.shape[0] // 2].any()                   # nothing in the upper half
