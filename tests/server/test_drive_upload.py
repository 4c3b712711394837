"""A recorded drive through POST /v1/scenes (docs/api.md "Drives"; issue 37 item 1): a 'drive' part (each frame's rig
and the tracks inline) and each frame's files as ``frames/<frame>/<name>`` parts reach a ready scene that records
the drive (frames, keyframes); every refusal of the drive, its parts or the keyframe query answers 422 naming the
field (runtime.drive's as "drive.<its field>"), a body over the limit 413; a rig posted alone answers as before.
Posted through the app and through the Python client (the session's ``env`` app of conftest.py).

The drives are three frames of the example rig as 400x225 JPEGs (``small``), reconstructed at detail stride 16 or
with one keyframe without the detail layer: a drive's keyframes are reconstructed one after another in the worker,
and CI time is scarce."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from api_helpers import err
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import pose, write_drive
from xyzcyl.testing.rigs import drive_files, make_rig, rig_files

T0 = 1557539956.5                   # the drive's first frame, seconds on the rigs' clock (PandaSet's)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> list[dict]:
    """The example rig's cameras as 400x225 JPEGs (files by absolute path)."""
    rig_json = make_rig(tmp_path_factory.mktemp("small"), 400, 225)
    cams = json.loads(rig_json.read_text())["cameras"]
    for c in cams:
        c["image"] = str(rig_json.parent / c["image"])
    return cams


def _drive(tmp: Path, small: list[dict], poses=None, times=None, edit=None, tracks=None, lidar_frame=None) -> Path:
    """Three frames (default: 1 m apart along x, 0.5 s apart) of the small example rig; ``lidar_frame``: that
    frame names a LiDAR sweep (ground points ahead), as its rig's lidar block."""
    poses = [pose(0), pose(1), pose(2)] if poses is None else poses
    times = [T0, T0 + 0.5, T0 + 1.0] if times is None else times
    if lidar_frame is not None:
        rng = np.random.default_rng(0)
        pts = np.c_[rng.uniform(3, 30, 4000), rng.uniform(-10, 10, 4000), np.zeros(4000), np.ones(4000)]
        np.save(tmp / "sweep.npy", pts.astype(np.float32))

    def ed(i, rig):
        rig["cameras"] = json.loads(json.dumps(small))
        if i == lidar_frame:
            rig["lidar"] = {"file": str(tmp / "sweep.npy")}
        if edit is not None:
            edit(i, rig)

    return write_drive(tmp / "drive", poses, times, ed, tracks)


def _track(frames=(0, 1), stationary=True) -> dict:
    return {"tracks": [{"id": "car-1", "label": "Car", "size": [4.5, 1.9, 1.6], "stationary": stationary,
                        "poses": [{"frame": f, "object_to_world": pose(12.0)} for f in frames]}]}


def _post(client, files, params=None):
    return client.post("/v1/scenes", params=params or {}, files=files)


def test_a_drive_reaches_a_ready_scene_that_records_its_frames(env, client, tmp_path, small):
    """Defaults: the keyframes are the first frame and the one 2 m on (1.5 m spacing); a sweep in frame 0 goes
    with its frame, the tracks inline; the scene renders at a time of the drive."""
    files = drive_files(_drive(tmp_path, small, lidar_frame=0, tracks=_track()))
    assert "frames/0/lidar" in dict(files) and "frames/2/CAM_BACK" in dict(files)
    r = _post(client, files, {"wait": 60, "detail_stride": 16})
    assert r.status_code == 201, r.text
    scene = r.json()
    sid = scene["id"]
    try:
        want = {"frames": 3, "keyframes": [0, 2], "keyframe_spacing": 1.5, "keyframe_gap": 2.0, "timestamp_s": T0,
                "duration_s": 1.0, "tracks": 1, "stationary_actors": False}
        assert scene["drive"] == want
        assert scene["counts"]["keyframes"] == 2 and scene["counts"]["frames"] == 3, scene["counts"]
        assert "actors" not in scene["counts"]                   # its one track is stationary: the static scene's
        assert [(c["name"], c["width"]) for c in scene["cameras"]] == [(c["name"], 400) for c in small]
        got = client.get(f"/v1/scenes/{sid}").json()
        assert got["drive"] == want and got["state"] == "ready"
        view = client.get(f"/v1/scenes/{sid}/render", params={"camera": "CAM_FRONT", "width": 64, "time": T0 + 1})
        assert view.status_code == 200 and view.headers["content-type"] == "image/png"
        # the service's scene reads its shared Gaussians tile by tile (runtime.tiles), never whole for a view
        loaded = env.service.load_scene(sid)
        assert loaded.tiles is not None and loaded.tiles.lazy and loaded.__dict__["_gaussians"] is None
        assert 0 < len(loaded.tiles._cache) <= len(loaded.tiles)
    finally:
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    # a view that was reading the scene's tiles when it was deleted answers 404, not 500
    from xyzcyl.runtime.tiles import TileError
    from xyzcyl.server.errors import NotFound

    def gone():
        raise TileError("tiles[0]", "rows 0..10: [Errno 2] No such file or directory")

    with pytest.raises(NotFound, match="deleted"):
        env.service._reading(sid, gone)
    with pytest.raises(TileError):         # a ready scene's unreadable tile is the store's fault: not hidden
        env.service._reading(env.sid, gone)
    from xyzcyl.runtime.cameralayers import CameraLayerError

    def gone_layer():                      # a camera layer's file (runtime.cameralayers) alike
        raise CameraLayerError("camera_layers.keyframes[0]", "rows 0..10: [Errno 2] No such file or directory")

    with pytest.raises(NotFound, match="deleted"):
        env.service._reading(sid, gone_layer)


def test_the_client_posts_a_drive_file_with_its_keyframe_knobs(env, tmp_path, small):
    """Client.reconstruct of a drive file: keyframe_spacing / keyframe_gap reach the server (far apart: the first
    frame alone is the keyframe), and stationary_actors makes its stationary track an actor."""
    from xyzcyl.clients import Client

    path = _drive(tmp_path, small, tracks=_track())
    sent = []
    c = Client(http_client=env.client)
    info = c.reconstruct_drive(path, detail=False, keyframe_spacing=100, keyframe_gap=100, timeout=60,
                               progress=lambda done, total: sent.append((done, total)), stationary_actors=True)
    try:
        assert info.ready and info.drive is not None, info.raw
        assert (info.drive.frames, info.drive.keyframes, info.drive.tracks) == (3, [0], 1)
        assert info.drive.stationary_actors and info.raw["counts"]["actors"] == 1, info.raw
        assert (info.drive.keyframe_spacing, info.drive.keyframe_gap) == (100.0, 100.0)
        assert sent and sent[-1][0] == sent[-1][1]
        assert c.scene(info.id).drive == info.drive
    finally:
        c.delete(info.id)


def _edit_rig(frame: int, change):
    def edit(i, rig):
        if i == frame:
            change(rig)
    return edit


def _cut(data: bytes) -> bytes:
    return data[: len(data) // 2]


def _png(w: int, h: int) -> bytes:
    import cv2

    return cv2.imencode(".png", np.zeros((h, w, 3), np.uint8))[1].tobytes()


def _replace(name: str, change):
    """A change of the parts: the part ``name``'s (filename, bytes, media type) through ``change``."""
    return lambda files: [(n, change(v) if n == name else v) for n, v in files]


# each: (how the drive or its parts differ, the error's field)
BAD = {
    "frames out of time order": (dict(times=[T0, T0 + 1.0, T0 + 0.5]), "drive.frames[2].timestamp_s"),
    "frames at one time": (dict(times=[T0, T0 + 0.5, T0 + 0.5]), "drive.frames[2].timestamp_s"),
    "a frame without ego_to_world": (dict(poses=[pose(0), None, pose(2)]), "drive.frames[1].rig"),
    "a frame without a time": (dict(times=[T0, None, T0 + 1]), "drive.frames[1].timestamp_s"),
    "a jump of 5 km": (dict(poses=[pose(0), pose(1), pose(5000)]), "drive.frames[2].rig"),
    "other cameras": (dict(edit=_edit_rig(1, lambda r: r.update(cameras=r["cameras"][:5]))), "drive.frames[1].rig"),
    "a bad calibration": (dict(edit=_edit_rig(1, lambda r: r["cameras"][0]["K"][0].__setitem__(0, -1.0))),
                          "drive.frames[1].rig"),
    "a track naming no frame": (dict(tracks=_track((0, 7))), "drive.tracks[0].poses[1].frame"),
    "a track of no size": (dict(tracks={"tracks": [{**_track()["tracks"][0], "size": [4, 0, 1]}]}),
                           "drive.tracks[0].size"),
    "tracks named by a file": (dict(doc=lambda d: d.update(tracks="tracks.json")), "drive.tracks"),
    "a frame's rig named by a file": (dict(doc=lambda d: d["frames"][0].update(rig="frame_00/rig.json")),
                                      "drive.frames[0].rig"),
    "no frames": (dict(doc=lambda d: d.update(frames=[])), "drive.frames"),
    "too many frames": (dict(doc=lambda d: d.update(frames=[{}] * 201)), "drive.frames"),
    "a drive that is not JSON": (dict(parts=lambda f: [("drive", ("drive.json", b"{", "application/json"))] + f[1:]),
                                 "drive"),
    "a missing image": (dict(drop=("frames/1/CAM_BACK",)), "frames/1/CAM_BACK"),
    "a part of no frame": (dict(extra=[("frames/3/CAM_FRONT", "image")]), "frames/3/CAM_FRONT"),
    "a part with a leading zero": (dict(extra=[("frames/01/CAM_FRONT", "image")]), "frames/01/CAM_FRONT"),
    "a part of no camera": (dict(extra=[("frames/0/CAM_TOP", "image")]), "frames/0/CAM_TOP"),
    "a one-rig part in a drive": (dict(extra=[("CAM_FRONT", "image")]), "CAM_FRONT"),
    "a part twice": (dict(extra=[("frames/0/CAM_FRONT", "image")]), "frames/0/CAM_FRONT"),
    "a rig part too": (dict(extra=[("rig", "rig")]), "drive"),
    "a cut image": (dict(parts=_replace("frames/1/CAM_FRONT", lambda v: (v[0], _cut(v[1]), v[2]))),
                    "frames/1/CAM_FRONT"),
    "an image of another size": (dict(parts=_replace("frames/2/CAM_BACK", lambda v: ("x.png", _png(64, 36),
                                                                                      "image/png"))),
                                 "frames/2/CAM_BACK"),
    "an empty sweep": (dict(extra=[("frames/0/lidar", ("sweep.npy", b"", "application/octet-stream"))]),
                       "frames/0/lidar"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_bad_drive_is_refused_naming_the_field(client, env, tmp_path, small, case):
    kw, field = BAD[case]
    kw = dict(kw)
    doc, drop, extra, parts = kw.pop("doc", None), kw.pop("drop", ()), kw.pop("extra", []), kw.pop("parts", None)
    files = drive_files(_drive(tmp_path, small, **kw), edit=doc, drop=drop)
    image = dict(files)["frames/0/CAM_FRONT"]
    rig = ("rig.json", EXAMPLE_RIG.read_bytes(), "application/json")
    files += [(n, image if v == "image" else rig if v == "rig" else v) for n, v in extra]
    if parts is not None:
        files = parts(files)
    before = set((env.store_root / "tmp").iterdir())
    e = err(_post(client, files), 422, field, "invalid")
    assert field in e["message"] or field.split(".", 1)[-1] in e["message"], e
    assert str(env.store_root) not in e["message"] and "/tmp/" not in e["message"], e    # never our paths
    assert set((env.store_root / "tmp").iterdir()) <= before                             # the upload was removed


@pytest.mark.parametrize("params, field", [
    ({"keyframe_spacing": "0"}, "keyframe_spacing"),
    ({"keyframe_gap": "-1"}, "keyframe_gap"),
    ({"keyframe_gap": "inf"}, "keyframe_gap"),
    ({"keyframe_spacing": "nan"}, "keyframe_spacing"),
    ({"keyframe_gap": "soon"}, "keyframe_gap"),
    ({"keyframe_gap": ["1", "2"]}, "keyframe_gap"),
])
def test_bad_keyframe_parameters_are_refused_before_the_body(client, params, field):
    e = err(client.post("/v1/scenes", params=params, files=[("drive", ("d.json", b"{}", "application/json"))]),
            422, field, "invalid")
    assert e["message"].startswith(f"{field}: "), e


def test_a_rig_answers_as_before_and_refuses_the_keyframe_parameters(env, client):
    """The session's rig scene records no drive; keyframe knobs with a rig, and a drive's part names in a rig's
    upload, answer 422 naming them."""
    assert env.created.json()["drive"] is None
    assert client.get(f"/v1/scenes/{env.sid}").json()["drive"] is None
    e = err(_post(client, rig_files(), {"keyframe_gap": "1"}), 422, "keyframe_gap", "invalid")
    assert "drive" in e["message"]
    e = err(_post(client, rig_files(), {"stationary_actors": "true"}), 422, "stationary_actors", "invalid")
    assert "drive" in e["message"]
    first = rig_files()[1][1]
    e = err(_post(client, rig_files(extra=[("frames/0/CAM_FRONT", first)])), 422, "frames/0/CAM_FRONT")
    assert "names no camera of the rig" in e["message"]


def test_a_drive_over_the_body_limit_is_413(client, tmp_path):
    """Three frames of the example rig's PNGs (~2.9 MB) over the session app's 2 MiB limit: refused from its
    Content-Length, before anything is read."""
    files = drive_files(write_drive(tmp_path, [pose(0), pose(1), pose(2)], [T0, T0 + 0.5, T0 + 1.0]))
    err(_post(client, files), 413, code="too_large")
