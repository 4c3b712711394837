"""The gRPC SensorsimService (issue 29) against a live `xyzcyl serve --grpc-port 0` on loopback, through a client
built from the project's stubs (server/sensorsim/*_pb2*.py): every rpc; a render over gRPC equals the HTTP render
of the same camera and pose byte for byte (PNG); a batch of six cameras; bad inputs -> the status codes (field in
the message and in the ``xyzcyl-field`` trailing metadata); API keys from metadata; a full render pool ->
RESOURCE_EXHAUSTED; gRPC and HTTP under load together with nothing lost.

One server for the module (render_threads 1, render_queue 0 so the pool fills deterministically; render cache off
so every render is rendered; an API key), the example rig posted once with a name and an ego_to_world, and a small
drive's scene (two frames of the example rig with a moving car, reconstructed at detail stride 8) put in its store
before it starts: time over gRPC (the middle of the exposure) and the drive's trajectory."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

grpc = pytest.importorskip("grpc")
httpx = pytest.importorskip("httpx")

from api_helpers import decode  # noqa: E402
from xyzcyl.server.sensorsim import common_pb2, frames  # noqa: E402
from xyzcyl.server.sensorsim import sensorsim_pb2 as pb  # noqa: E402
from xyzcyl.server.sensorsim.sensorsim_pb2_grpc import SensorsimServiceStub  # noqa: E402
from xyzcyl.testing.rigs import example_rig, rig_files  # noqa: E402
from xyzcyl.testing.sensorsim import ego_pose, grpc_port, rgb_request, rig_with_pose, view_query  # noqa: E402
from xyzcyl.testing.serve import serve  # noqa: E402

KEY = "grpc-test-key-1"
AUTH = (("x-api-key", KEY),)
NAME = "clipgt-026d6a39-bd8f-4175-bc61-fe50ed0403a3"
TIMEOUT = 60.0
Code = grpc.StatusCode
DRIVE = "drive-scene-1"
T0 = 1557539956.5                       # the drive's first frame (seconds on the rigs' clock, PandaSet's)
DRIVE_DT = 2.5                          # its second frame, this much later


@dataclass
class Live:
    url: str
    http: httpx.Client
    stub: SensorsimServiceStub
    sid: str
    E: np.ndarray
    cameras: list
    log: Path
    drive_sid: str


def _store_drive_scene(tmp: Path, store_dir: Path, E: np.ndarray) -> str:
    """A drive's scene (the example rig at ``E`` at T0 and T0 + DRIVE_DT, a car 12 m ahead moving 3 m) written into
    the folder store through its own API before the server opens it; its id."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.server.store import FolderStore, new_scene_id
    from xyzcyl.testing import SHIPPED_MODEL
    from xyzcyl.testing.drives import moving_car, write_drive

    path = write_drive(tmp / "drive", [E, E], [T0, T0 + DRIVE_DT], tracks=moving_car(E, 12.0, 3.0))
    scene = reconstruct_drive(Reconstructor.load(SHIPPED_MODEL, threads=2), load_drive(path),
                              detail=DetailOptions(stride=8))
    assert scene.actors is not None
    store = FolderStore(store_dir)
    store.open()
    sid = new_scene_id()
    work = store.work_dir()
    scene.save(work / "scene")
    store.create(sid, {"name": DRIVE, "cameras": [{"name": c.name, "width": c.width, "height": c.height,
                                                   "model": c.model} for c in scene.rig.cameras]})
    meta = scene.to_json()
    store.commit(sid, work / "scene", model=meta["model"], counts=meta["counts"], timings=meta["timings"],
                 bbox=meta["bbox"], gaussians=meta["gaussians"]["count"], background=True)
    work.rmdir()
    return sid


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("grpc")
    log = tmp / "serve.log"
    drive_sid = _store_drive_scene(tmp, tmp / "store", ego_pose())
    args = ["--grpc-port", "0", "--api-keys", KEY, "--render-threads", "1", "--render-queue", "0",
            "--render-cache-bytes", "0"]
    with serve(tmp / "store", log, args) as server:
        port = grpc_port(server.output())
        with httpx.Client(base_url=server.url, headers={"x-api-key": KEY}, timeout=120.0) as http, \
                grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
            E = ego_pose()
            r = http.post("/v1/scenes", params={"wait": 120, "name": NAME},
                          files=rig_files(rig_with_pose(example_rig(), E)))
            assert r.status_code == 201, r.text
            assert r.json()["name"] == NAME
            stub = SensorsimServiceStub(channel)
            cams = stub.get_available_cameras(pb.AvailableCamerasRequest(scene_id=NAME), metadata=AUTH,
                                              timeout=TIMEOUT).available_cameras
            yield Live(server.url, http, stub, r.json()["id"], E, list(cams), log, drive_sid)
        server.stop(check=False)


def render_request(live: Live, cam, w=512, h=320, fmt=pb.PNG, move: float = 0.0,
                   scene=NAME) -> pb.RGBRenderRequest:
    """AlpaSim's request for camera ``cam`` with the ego at its recorded pose, moving ``move`` metres forward
    during the exposure."""
    end = live.E.copy()
    end[:3, 3] += live.E[:3, 0] * move
    return rgb_request(cam, live.E, end, scene=scene, width=w, height=h, image_format=fmt)


def http_render(live: Live, params: dict, sid: str | None = None) -> bytes:
    r = live.http.get(f"/v1/scenes/{sid or live.sid}/render", params=params)
    assert r.status_code == 200, r.text
    return r.content


def fails(call, request, code, field: str | None = None, metadata=AUTH):
    with pytest.raises(grpc.RpcError) as e:
        call(request, metadata=metadata, timeout=TIMEOUT)
    assert e.value.code() == code, (e.value.code(), e.value.details())
    if field is not None:
        assert field in e.value.details(), e.value.details()
        assert ("xyzcyl-field", field) in tuple(e.value.trailing_metadata() or ()), e.value.trailing_metadata()
    return e.value


# ----------------------------------------------------------------------------------------------- the catalogue


def test_version_scenes_cameras_ego_masks(live):
    v = live.stub.get_version(common_pb2.Empty(), timeout=TIMEOUT)           # open, as the HTTP metadata paths
    assert v.version_id.startswith("xyzcyl ") and v.grpc_api_version.minor == 1
    scenes = live.stub.get_available_scenes(common_pb2.Empty(), metadata=AUTH, timeout=TIMEOUT).scene_ids
    assert NAME in scenes and live.sid not in scenes                          # a named scene is listed by name
    rig = example_rig()
    assert [c.logical_id for c in live.cameras] == [c["name"] for c in rig["cameras"]]
    for cam, rc in zip(live.cameras, rig["cameras"]):
        assert cam.intrinsics.logical_id == rc["name"]
        assert (cam.intrinsics.resolution_w, cam.intrinsics.resolution_h) == (rc["width"], rc["height"])
        p = cam.intrinsics.opencv_pinhole_param
        assert [p.focal_length_x, p.focal_length_y, p.principal_point_x, p.principal_point_y] == pytest.approx(
            [rc["K"][0][0], rc["K"][1][1], rc["K"][0][2], rc["K"][1][2]])
        assert np.allclose(frames.pose_matrix(cam.rig_to_camera, "r"), rc["cam_to_ego"], atol=2e-6)
    by_id = live.stub.get_available_cameras(pb.AvailableCamerasRequest(scene_id=live.sid), metadata=AUTH,
                                            timeout=TIMEOUT).available_cameras
    assert list(by_id) == live.cameras                                        # the id resolves too
    assert not live.stub.get_available_ego_masks(common_pb2.Empty(), metadata=AUTH,
                                                 timeout=TIMEOUT).ego_mask_metadata
    fails(live.stub.get_available_cameras, pb.AvailableCamerasRequest(scene_id="clipgt-nope"), Code.NOT_FOUND,
          "scene_id")


def test_unimplemented(live):
    # render_lidar is implemented: tests/server/test_grpc_lidar.py
    fails(live.stub.render_lidar, pb.LidarRenderRequest(scene_id=NAME), Code.INVALID_ARGUMENT, "sensor_pose")
    fails(live.stub.render_aggregated, pb.AggregatedRenderRequest(), Code.UNIMPLEMENTED)


def test_api_key_from_metadata(live):
    fails(live.stub.get_available_scenes, common_pb2.Empty(), Code.UNAUTHENTICATED, metadata=())
    fails(live.stub.render_rgb, render_request(live, live.cameras[0]), Code.UNAUTHENTICATED,
          metadata=(("x-api-key", "wrong-key-123"),))
    ok = live.stub.get_available_scenes(common_pb2.Empty(), metadata=(("authorization", f"Bearer {KEY}"),),
                                        timeout=TIMEOUT)
    assert NAME in ok.scene_ids


def test_trajectories_of_a_drive_and_of_a_one_rig_scene(live):
    """get_available_trajectories: a drive's every frame (rig -> the local frame, at its time in microseconds on
    the rigs' clock); a one-rig scene its one frame (its ego_to_world; no timestamp_s: 0)."""
    def trajectory(scene):
        got = live.stub.get_available_trajectories(pb.AvailableTrajectoriesRequest(scene_id=scene), metadata=AUTH,
                                                   timeout=TIMEOUT).available_trajectories
        assert len(got) == 1
        return [(p.timestamp_us, frames.pose_matrix(p.pose, "pose")) for p in got[0].trajectory.poses]

    drive = trajectory(DRIVE)
    assert [t for t, _ in drive] == [round(T0 * 1e6), round((T0 + DRIVE_DT) * 1e6)]
    for _, pose in drive:
        np.testing.assert_allclose(pose, live.E, atol=2e-5)                   # float32 on the wire
    (t, pose), = trajectory(NAME)
    assert t == 0
    np.testing.assert_allclose(pose, live.E, atol=2e-5)
    fails(live.stub.get_available_trajectories, pb.AvailableTrajectoriesRequest(scene_id="clipgt-nope"),
          Code.NOT_FOUND, "scene_id")


# ----------------------------------------------------------------------------------------------- renders


def test_a_drive_renders_at_the_middle_of_the_exposure(live):
    """A drive's scene over gRPC at the request's time (the middle of frame_start_us..frame_end_us, the rigs'
    clock): the moving car is elsewhere at another time; the image equals GET ?time= of the same pose and time;
    outside the car's annotated span it is not drawn (the static scene alone, either side); a one-rig scene
    looks the same at every time."""
    front = live.cameras[0]
    exposure = 30_000

    def render(t_s: float, scene=DRIVE) -> tuple[pb.RGBRenderRequest, bytes]:
        start = round(t_s * 1e6) - exposure // 2           # the exposure centred on t_s
        req = rgb_request(front, live.E, scene=scene, width=160, height=100, time_us=start, exposure_us=exposure)
        return req, live.stub.render_rgb(req, metadata=AUTH, timeout=TIMEOUT).image_bytes

    req0, at0 = render(T0)
    req1, at1 = render(T0 + 1.0)
    a0, a1 = decode(at0).astype(float), decode(at1).astype(float)
    moved = np.abs(a0 - a1).max(axis=2) > 8
    assert moved.mean() > 0.01, moved.mean()                    # the car moved 1.2 m between the two times
    params = view_query(req1, live.E)
    assert float(params["time"]) == pytest.approx(T0 + 1.0, abs=1e-6)
    assert http_render(live, params, live.drive_sid) == at1     # GET ?time= of the same pose and time
    _, before = render(T0 - 100.0)
    _, after = render(T0 + 100.0)
    assert before != at0 and after != at1                       # no car outside its span: the static scene alone,
    # whichever side (each time drawn from its nearest keyframe's copy first, Scene.primary_keyframe: the ego stood
    # still, tests/runtime/render/test_render_drive_layers.py)
    _, static0 = render(T0, NAME)
    _, static1 = render(T0 + 1.0, NAME)
    assert static0 == static1
    bad = rgb_request(front, live.E, scene=DRIVE, width=160, height=100, time_us=2_000_000)
    bad.frame_end_us = 1_000_000
    fails(live.stub.render_rgb, bad, Code.INVALID_ARGUMENT, "frame_end_us")


def test_render_equals_the_http_render_byte_for_byte(live):
    front = live.cameras[0]
    req = render_request(live, front, move=0.4)                   # a rolling exposure: rendered at mid-exposure
    got = live.stub.render_rgb(req, metadata=AUTH, timeout=TIMEOUT).image_bytes
    assert got[:8] == b"\x89PNG\r\n\x1a\n" and decode(got).shape == (320, 512, 3)
    params = view_query(req, live.E)
    c2e = np.array([float(v) for v in params["cam_to_ego"].split(",")]).reshape(4, 4)
    rig_c2e = np.array(example_rig()["cameras"][0]["cam_to_ego"])
    assert np.allclose(c2e[:3, 3], rig_c2e[:3, 3] + [0.2, 0, 0], atol=1e-4)   # half the move, along ego x
    assert http_render(live, params) == got
    # with the ego standing at its recorded pose the camera is the rig's CAM_FRONT resized (float32 poses apart)
    still = live.stub.render_rgb(render_request(live, front), metadata=AUTH, timeout=TIMEOUT).image_bytes
    rig_view = http_render(live, {"camera": "CAM_FRONT", "width": 512, "height": 320})
    diff = np.abs(decode(still).astype(float) - decode(rig_view).astype(float))
    assert diff.mean() < 0.5, diff.mean()


def test_batch_of_six_cameras(live):
    items = [pb.BatchRGBRenderRequestItem(camera_name=c.logical_id, request=render_request(live, c))
             for c in live.cameras]
    items[4].request.image_format = pb.JPEG
    out = live.stub.batch_render_rgb(pb.BatchRGBRenderRequest(items=items), metadata=AUTH, timeout=TIMEOUT).items
    assert [i.camera_name for i in out] == [c.logical_id for c in live.cameras]
    assert all(i.success and not i.error_message for i in out), [i.error_message for i in out]
    for k, i in enumerate(out):
        assert i.result.image_bytes[:3] == (b"\xff\xd8\xff" if k == 4 else b"\x89PN")
        assert decode(i.result.image_bytes).shape == (320, 512, 3)
    assert out[1].result.image_bytes == http_render(live, view_query(items[1].request, live.E))
    # a bad item fails alone, answered in its place; the others render
    items[2].request.scene_id = "clipgt-nope"
    items[3].request.camera_intrinsics.opencv_pinhole_param.focal_length_x = -1.0
    out = live.stub.batch_render_rgb(pb.BatchRGBRenderRequest(items=items), metadata=AUTH, timeout=TIMEOUT).items
    assert [i.success for i in out] == [True, True, False, False, True, True]
    assert out[2].error_message.startswith("NOT_FOUND: items[2].request.scene_id: no scene 'clipgt-nope'")
    assert out[3].error_message.startswith("INVALID_ARGUMENT: items[3].request.camera_intrinsics."
                                           "opencv_pinhole_param.focal_length_x"), out[3].error_message
    assert not out[2].result.image_bytes and out[5].result.image_bytes
    fails(live.stub.batch_render_rgb, pb.BatchRGBRenderRequest(), Code.INVALID_ARGUMENT, "items")


def _bad(live, change, **kw):
    req = render_request(live, live.cameras[0], **kw)
    change(req)
    return req


LENSES = {
    "opencv_fisheye_param": pb.OpenCVFisheyeCameraParam(focal_length_x=300, focal_length_y=300, principal_point_x=399.5,
                                                        principal_point_y=224.5, radial_coeffs=[0.05, -0.01, 0, 0],
                                                        max_angle=math.radians(95)),
    "ftheta_param": pb.FthetaCameraParam(principal_point_x=399.5, principal_point_y=224.5,
                                         reference_poly=pb.FthetaCameraParam.PIXELDIST_TO_ANGLE,
                                         pixeldist_to_angle_poly=[0, 2.45e-3, 1.2e-7], max_angle=math.radians(80)),
}


@pytest.mark.parametrize("lens", ["opencv_fisheye_param", "ftheta_param", "opencv_pinhole_param"])
def test_lens_cameras_render(live, lens):
    """OpenCV-distorted, fisheye and f-theta cameras render through their true lens (issue 28) at the size asked:
    the picture differs from the lensless camera's at the same pose."""
    def change(r):
        if lens == "opencv_pinhole_param":
            r.camera_intrinsics.opencv_pinhole_param.radial_coeffs.extend([-0.05, 0.01])
        else:
            getattr(r.camera_intrinsics, lens).CopyFrom(LENSES[lens])
    req = _bad(live, change)
    got = live.stub.render_rgb(req, metadata=AUTH, timeout=TIMEOUT).image_bytes
    assert decode(got).shape == (320, 512, 3)
    lensless = live.stub.render_rgb(render_request(live, live.cameras[0]), metadata=AUTH, timeout=TIMEOUT)
    assert got != lensless.image_bytes                      # the lens changes the picture


P = "camera_intrinsics.opencv_pinhole_param"
BAD = {
    "empty scene id": (lambda r: setattr(r, "scene_id", ""), Code.INVALID_ARGUMENT, "scene_id"),
    "unknown scene": (lambda r: setattr(r, "scene_id", "clipgt-nope"), Code.NOT_FOUND, "scene_id"),
    "no camera model": (lambda r: r.camera_intrinsics.ClearField("opencv_pinhole_param"), Code.INVALID_ARGUMENT,
                        "camera_intrinsics.camera_param"),
    "negative focal length": (lambda r: setattr(r.camera_intrinsics.opencv_pinhole_param, "focal_length_y", -5.0),
                              Code.INVALID_ARGUMENT, f"{P}.focal_length_y"),
    "zero quaternion": (lambda r: r.sensor_pose.start_pose.ClearField("quat"), Code.INVALID_ARGUMENT,
                        "sensor_pose.start_pose.quat"),
    "no pose": (lambda r: r.ClearField("sensor_pose"), Code.INVALID_ARGUMENT, "sensor_pose"),
    "video format": (lambda r: setattr(r, "image_format", pb.AV1), Code.INVALID_ARGUMENT, "image_format"),
    "quality": (lambda r: setattr(r, "image_quality", 500.0), Code.INVALID_ARGUMENT, "image_quality"),
    "over the render limit": (lambda r: setattr(r, "resolution_w", 17000), Code.INVALID_ARGUMENT, "resolution_w"),
    "ego mask": (lambda r: setattr(r, "insert_ego_mask", True), Code.INVALID_ARGUMENT, "insert_ego_mask"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_inputs_answer_status_codes_naming_the_field(live, case):
    change, code, field = BAD[case]
    fails(live.stub.render_rgb, _bad(live, change), code, field)


def test_names_and_ego_poses_are_checked_at_the_upload(live):
    for name in ("two words", "-leading-dash", "A" * 201, "P5FbNUGPedOE_hYDE37TqA"):      # the last: an id's form
        r = live.http.post("/v1/scenes", params={"name": name}, files=rig_files())
        assert r.status_code == 422 and r.json()["error"]["field"] == "name", r.text
    bad = ego_pose()
    bad[:3, :3] *= 2.0                                        # not a rotation
    r = live.http.post("/v1/scenes", params={"name": "bad-pose"}, files=rig_files(rig_with_pose(example_rig(), bad)))
    assert r.status_code == 422 and r.json()["error"]["field"] == "rig" and "ego_to_world" in r.text, r.text
    assert live.http.get(f"/v1/scenes/{live.sid}").json()["name"] == NAME


def test_scene_not_ready_is_failed_precondition(live):
    r = live.http.post("/v1/scenes", params={"name": "pending-scene"}, files=rig_files())
    assert r.status_code == 202, r.text
    sid = r.json()["id"]
    try:
        req = render_request(live, live.cameras[0], scene="pending-scene")
        fails(live.stub.render_rgb, req, Code.FAILED_PRECONDITION, "scene_id")
        fails(live.stub.get_available_cameras, pb.AvailableCamerasRequest(scene_id=sid), Code.FAILED_PRECONDITION,
              "scene_id")
        assert "pending-scene" not in live.stub.get_available_scenes(common_pb2.Empty(), metadata=AUTH,
                                                                     timeout=TIMEOUT).scene_ids
    finally:
        deadline = time.monotonic() + 120
        while live.http.get(f"/v1/scenes/{sid}").json()["state"] in ("queued", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.2)
        scenes = live.stub.get_available_scenes(common_pb2.Empty(), metadata=AUTH, timeout=TIMEOUT).scene_ids
        assert scenes[:2] == ["pending-scene", NAME]            # ready now; newest first
        assert live.http.delete(f"/v1/scenes/{sid}").status_code == 204


def test_full_render_pool_is_resource_exhausted(live):
    """render_threads 1, render_queue 0: a long HTTP render holds the one slot, and gRPC renders are refused at
    once (RESOURCE_EXHAUSTED, as HTTP's 503), the batch before any item; after it, they render."""
    batch = pb.BatchRGBRenderRequest(items=[pb.BatchRGBRenderRequestItem(
        camera_name="CAM_FRONT", request=render_request(live, live.cameras[0]))])

    def refused(call, request) -> bool:
        try:
            call(request, metadata=AUTH, timeout=TIMEOUT)
        except grpc.RpcError as e:
            assert e.code() == Code.RESOURCE_EXHAUSTED, e.details()
            return True
        return False                                  # the slot was free again already

    held: list = []
    seen = []
    for width in (4096, 5400):                        # a longer render if the slot was free again too soon
        t = threading.Thread(target=lambda w=width: held.append(live.http.get(
            f"/v1/scenes/{live.sid}/render", params={"camera": "CAM_BACK", "width": w}).status_code))
        t.start()
        deadline = time.monotonic() + 30
        while 'xyzcyl_queue_depth{queue="render"} 1.0' not in httpx.get(live.url + "/metrics").text:
            assert time.monotonic() < deadline and t.is_alive()
            time.sleep(0.005)
        seen = [refused(live.stub.render_rgb, batch.items[0].request), refused(live.stub.batch_render_rgb, batch)]
        t.join(120)
        assert not t.is_alive() and held[-1] == 200
        if all(seen):
            break
    assert all(seen), "the HTTP render never held the slot long enough"
    assert live.stub.render_rgb(batch.items[0].request, metadata=AUTH, timeout=TIMEOUT).image_bytes


@pytest.mark.slow
def test_grpc_and_http_under_load_nothing_lost(live):
    """Two gRPC clients (batches of six) and three HTTP clients at once on a one-slot pool: every call is answered
    once, busy ones retried (bounded), and every gRPC image equals the HTTP render of the same view afterwards."""
    deadline = time.monotonic() + 240
    grpc_out: list = []
    http_out: list = []
    errors: list = []

    def grpc_client(k: int):
        for b in range(2):
            items = [pb.BatchRGBRenderRequestItem(camera_name=c.logical_id, request=render_request(
                live, c, w=256, h=160, move=0.1 * (k + 2 * b))) for c in live.cameras]
            while True:
                try:
                    out = live.stub.batch_render_rgb(pb.BatchRGBRenderRequest(items=items), metadata=AUTH,
                                                     timeout=TIMEOUT)
                    break
                except grpc.RpcError as e:
                    if e.code() != Code.RESOURCE_EXHAUSTED or time.monotonic() > deadline:
                        errors.append(e)
                        return
                    time.sleep(0.02)
            grpc_out.append((items, out.items))

    def http_client(k: int):
        with httpx.Client(base_url=live.url, headers={"x-api-key": KEY}, timeout=120.0) as c:
            for j in range(4):
                while True:
                    r = c.get(f"/v1/scenes/{live.sid}/render", params={"camera": live.cameras[j].logical_id,
                                                                      "width": 200 + 8 * k})
                    if r.status_code != 503 or time.monotonic() > deadline:
                        break
                    time.sleep(0.02)
                http_out.append(r.status_code)

    threads = [threading.Thread(target=grpc_client, args=(k,)) for k in range(2)]
    threads += [threading.Thread(target=http_client, args=(k,)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert not errors and not any(t.is_alive() for t in threads)
    assert http_out == [200] * 12
    assert len(grpc_out) == 4
    for items, out in grpc_out:
        assert [i.camera_name for i in out] == [it.camera_name for it in items]
        assert all(i.success for i in out), [i.error_message for i in out]
        for it, i in zip(items, out):
            assert i.result.image_bytes == http_render(live, view_query(it.request, live.E))


# ----------------------------------------------------------------------------------------------- actors


def test_actors_listed_edited_over_http_and_moved_by_dynamic_objects(live):
    """A drive scene's actors: listed with their pose at a time (GET .../actors); GET ?actors= and a batch item's
    "actors" hide or move them (another ETag), refusals named; over gRPC, a DynamicObject draws its track at the
    given box pose (the listed pose: the same picture as none given; 1.5 m to the side: another), unknown track
    ids and poses kilometres away are INVALID_ARGUMENT naming the field."""
    info = live.http.get(f"/v1/scenes/{live.drive_sid}")        # its counts hold an area (ground_filled_m2)
    assert info.status_code == 200 and isinstance(info.json()["counts"]["ground_filled_m2"], float), info.text
    from xyzcyl.common.wire import SceneInfo

    assert SceneInfo.model_validate(info.json()).counts["actors"] == 1        # what the client parses
    r = live.http.get(f"/v1/scenes/{live.drive_sid}/actors", params={"time": T0 + 1.0})
    assert r.status_code == 200, r.text
    (car,) = r.json()["actors"]
    assert car["id"] == "car-1" and car["label"] == "Car" and car["tracked"] and car["copies"] >= 1
    assert car["span_s"] == [pytest.approx(T0), pytest.approx(T0 + DRIVE_DT)] and len(car["pose"]) == 16
    assert live.http.get(f"/v1/scenes/{live.sid}/actors").json()["actors"] == []        # a one-rig scene: none

    base = {"camera": live.cameras[0].logical_id, "width": 160, "time": repr(T0 + 1.0)}
    shown = http_render(live, base, live.drive_sid)
    hide = '[{"id": "car-1", "hide": true}]'
    r = live.http.get(f"/v1/scenes/{live.drive_sid}/render", params={**base, "actors": hide})
    assert r.status_code == 200 and r.content != shown
    r0 = live.http.get(f"/v1/scenes/{live.drive_sid}/render", params=base)
    assert r.headers["etag"] != r0.headers["etag"]
    for actors, field in (('[{"id": "bus", "hide": true}]', "actors[0].id"),
                          ('[{"id": "car-1", "offset": [0, 5000, 0]}]', "actors[0].offset"),
                          ('[{"id": "car-1"}]', "actors[0]"), ("[", "actors")):
        r = live.http.get(f"/v1/scenes/{live.drive_sid}/render", params={**base, "actors": actors})
        assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
    item = {"camera": live.cameras[0].logical_id, "width": 160, "time": T0 + 1.0,
            "actors": [{"id": "car-1", "hide": True}]}
    r = live.http.post(f"/v1/scenes/{live.drive_sid}/render", json={"cameras": [item]})
    assert r.status_code == 200
    import io
    import zipfile

    assert zipfile.ZipFile(io.BytesIO(r.content)).read("frame_00000.png") == \
        live.http.get(f"/v1/scenes/{live.drive_sid}/render", params={**base, "actors": hide}).content
    r = live.http.post(f"/v1/scenes/{live.drive_sid}/render",
                       json={"cameras": [{**item, "actors": [{"id": "bus", "hide": True}]}]})
    assert r.status_code == 422 and r.json()["error"]["field"] == "cameras[0].actors[0].id", r.text

    # gRPC: the car where the recording has it, listed at that pose, and 1.5 m to its left
    front = live.cameras[0]
    box = live.E @ np.array(car["pose"], float).reshape(4, 4)            # box -> the local frame
    exposure = 30_000

    def req(*objects):
        q = rgb_request(front, live.E, scene=DRIVE, width=160, height=100,
                        time_us=round((T0 + 1.0) * 1e6) - exposure // 2, exposure_us=exposure)
        for tid, T in objects:
            q.dynamic_objects.add(track_id=tid, pose_pair=pb.PosePair(start_pose=frames.pose_message(T),
                                                                      end_pose=frames.pose_message(T)))
        return q

    def img(q):
        return decode(live.stub.render_rgb(q, metadata=AUTH, timeout=TIMEOUT).image_bytes).astype(float)

    plain, listed = img(req()), img(req(("car-1", box)))
    assert np.abs(plain - listed).max() <= 2          # the same pose (float32 on the wire): the same picture
    side = box.copy()
    side[:3, 3] += box[:3, 1] * 1.5
    assert (np.abs(img(req(("car-1", side))) - plain).max(axis=2) > 8).mean() > 0.005
    fails(live.stub.render_rgb, req(("bus-9", box)), Code.INVALID_ARGUMENT, "dynamic_objects[0].track_id")
    far = box.copy()
    far[:3, 3] += 1e4
    fails(live.stub.render_rgb, req(("car-1", far)), Code.INVALID_ARGUMENT, "dynamic_objects[0].pose_pair")
    fails(live.stub.render_rgb, req(("", box)), Code.INVALID_ARGUMENT, "dynamic_objects[0].track_id")


# ----------------------------------------------------------------------------------------------- CARLA's variant


def test_carlas_variant_of_the_protocol(live):
    """CARLA's NuRec integration speaks the protocol with extra fields (``trajectory_idx``: CameraSpec field 6,
    AvailableCamera field 4, AvailableTrajectory field 1), a ``shut_down`` rpc and an empty OpenCV pinhole message
    (docs/simulators.md "CARLA's variant"): its extra fields are unknown fields here and change nothing, shut_down
    answers and the server keeps serving, the empty pinhole message is refused naming its focal length."""
    front = live.cameras[0]
    plain = render_request(live, front, w=160, h=100)
    want = live.stub.render_rgb(plain, metadata=AUTH, timeout=TIMEOUT).image_bytes
    # CARLA's CameraSpec: ours with trajectory_idx = 7 (field 6, varint: tag 0x30) on the wire
    spec = pb.CameraSpec()
    spec.ParseFromString(plain.camera_intrinsics.SerializeToString() + b"\x30\x07")
    carla = pb.RGBRenderRequest()
    carla.CopyFrom(plain)
    carla.camera_intrinsics.CopyFrom(spec)
    assert carla.SerializeToString() != plain.SerializeToString()          # the unknown field travels
    assert live.stub.render_rgb(carla, metadata=AUTH, timeout=TIMEOUT).image_bytes == want
    # its answers parse on CARLA's side: our AvailableTrajectory has no field 1 (trajectory_idx there reads 0)
    traj = live.stub.get_available_trajectories(pb.AvailableTrajectoriesRequest(scene_id=NAME), metadata=AUTH,
                                                timeout=TIMEOUT)
    assert all(not t.trajectory.poses or t.HasField("trajectory") for t in traj.available_trajectories)
    # shut_down: answered, logged, and the server still renders
    assert live.stub.shut_down(common_pb2.Empty(), metadata=AUTH, timeout=TIMEOUT) == common_pb2.Empty()
    fails(live.stub.shut_down, common_pb2.Empty(), Code.UNAUTHENTICATED, metadata=())
    assert live.stub.render_rgb(plain, metadata=AUTH, timeout=TIMEOUT).image_bytes == want
    # CARLA's OpenCVPinholeCameraParam has no fields: chosen in the oneof, it reads as a pinhole without a focal
    empty = pb.RGBRenderRequest()
    empty.CopyFrom(plain)
    empty.camera_intrinsics.opencv_pinhole_param.Clear()
    empty.camera_intrinsics.opencv_pinhole_param.SetInParent()
    fails(live.stub.render_rgb, empty, Code.INVALID_ARGUMENT,
          "camera_intrinsics.opencv_pinhole_param.focal_length_x")
    for _ in range(50):                             # the log line is written as the call returns (bounded wait)
        if "shut_down asked by a client" in live.log.read_text():
            break
        time.sleep(0.1)
    assert "shut_down asked by a client" in live.log.read_text()


# ----------------------------------------------------------------------------------------------- AlpaSim's rollout


def test_an_exported_artifact_drives_a_rollout(live):
    """GET .../export?format=usdz of the drive scene (an AlpaSim scene artifact: runtime.usdz), then the requests
    AlpaSim's runtime builds from it: each recorded rig pose composed with the camera -> rig pose, the camera's
    recorded exposure window, every track at its pose then as a dynamic object (the artifact's rows, xyz + a
    scipy-order quaternion). At the recorded poses the picture is GET's of the same view (the frames of the
    artifact and of the gRPC front end agree); 1.5 m to the side of the trajectory it renders another. The
    artifact's scene id is the name get_available_scenes lists."""
    import io
    import json
    import zipfile

    from xyzcyl.runtime.rotations import quat_to_rotmat

    r = live.http.get(f"/v1/scenes/{live.drive_sid}/export", params={"format": "usdz"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/vnd.usdz+zip" and int(r.headers["content-length"]) == len(r.content)
    again = live.http.get(f"/v1/scenes/{live.drive_sid}/export", params={"format": "usdz"},
                          headers={"if-none-match": r.headers["etag"]})
    assert again.status_code == 304
    for params, field in (({"format": "obj"}, "format"), ({}, "format"), ({"format": "usdz", "x": "1"}, "x"),
                          ({"format": "usdz", "time": "1"}, "time")):
        bad = live.http.get(f"/v1/scenes/{live.drive_sid}/export", params=params)
        assert bad.status_code == 422 and bad.json()["error"]["field"] == field, bad.text
    z = zipfile.ZipFile(io.BytesIO(r.content))
    rig = json.loads(z.read("rig_trajectories.json"))
    tracks = json.loads(z.read("sequence_tracks.json"))
    sid = json.loads(z.read("metadata.yaml"))["scene_id"]       # JSON is YAML (runtime.usdz)
    scenes = live.stub.get_available_scenes(common_pb2.Empty(), metadata=AUTH, timeout=TIMEOUT).scene_ids
    assert sid == DRIVE and sid in scenes
    (traj,) = rig["rig_trajectories"]
    front = live.cameras[0]
    window = traj["cameras_frame_timestamps_us"][front.logical_id]
    np.testing.assert_allclose(rig["camera_calibrations"][front.logical_id]["T_sensor_rig"],
                               frames.pose_matrix(front.rig_to_camera, "rig_to_camera"), atol=2e-6)
    data = tracks[sid]["tracks_data"]

    def request(i: int, rig_pose: np.ndarray) -> pb.RGBRenderRequest:
        start, end = window[i]
        q = rgb_request(front, rig_pose, scene=sid, width=160, height=100, time_us=start, exposure_us=end - start)
        for tid, stamps, rows in zip(data["tracks_id"], data["tracks_timestamps_us"], data["tracks_poses"]):
            if stamps[0] <= (start + end) // 2 <= stamps[-1]:
                row = rows[int(np.argmin([abs(s - (start + end) // 2) for s in stamps]))]
                T = np.eye(4)
                T[:3, :3] = quat_to_rotmat(np.array([row[6], *row[3:6]]))     # scipy order -> wxyz
                T[:3, 3] = row[:3]
                pose = frames.pose_message(T)
                q.dynamic_objects.add(track_id=tid, pose_pair=pb.PosePair(start_pose=pose, end_pose=pose))
        return q

    for i, (t_us, rig_pose) in enumerate(zip(traj["T_rig_world_timestamps_us"], traj["T_rig_worlds"])):
        rig_pose = np.array(rig_pose)
        q = request(i, rig_pose)
        assert len(q.dynamic_objects) == 1                      # the car, annotated at both frames
        got = decode(live.stub.render_rgb(q, metadata=AUTH, timeout=TIMEOUT).image_bytes).astype(float)
        want = decode(http_render(live, view_query(q, live.E), live.drive_sid)).astype(float)
        assert np.abs(got - want).max() <= 2, i                 # the car's pose through float32 on the wire
        side = rig_pose.copy()
        side[:3, 3] += rig_pose[:3, 1] * 1.5                    # 1.5 m to the left of the recorded trajectory
        moved = decode(live.stub.render_rgb(request(i, side), metadata=AUTH, timeout=TIMEOUT).image_bytes)
        assert (np.abs(moved.astype(float) - got).max(axis=2) > 8).mean() > 0.01


def test_a_lidar_sweep_of_a_drive_draws_its_actors_where_the_edits_put_them(live):
    """GET .../lidar of the drive scene at the car's time: hiding the car (actors=, as GET render's) takes the
    returns off its box ahead of the ego and changes nothing behind it."""
    import io

    sensor = np.eye(4)
    sensor[2, 3] = 1.5                                                  # a roof LiDAR 1.5 m above the ego origin
    params = {"pose": ",".join(repr(float(v)) for v in sensor.ravel()), "model": "pandar64",
              "azimuth_step": 2.0, "time": repr(T0 + 1.0), "format": "npy"}

    def sweep(**extra):
        r = live.http.get(f"/v1/scenes/{live.drive_sid}/lidar", params={**params, **extra})
        assert r.status_code == 200, r.text
        return np.load(io.BytesIO(r.content))

    shown, hidden = sweep(), sweep(actors='[{"id": "car-1", "hide": true}]')
    # the car's box at T0 + 1 s: 5 m long, 6 m wide, 4 m high, centred 13.2 m ahead (testing.drives.moving_car),
    # points here in the LiDAR frame (1.5 m up); above the ground
    in_box = lambda p: ((np.abs(p[:, 0] - 13.2) < 2.5) & (np.abs(p[:, 1]) < 3.0) & (p[:, 2] > -1.2)).sum()  # noqa
    behind = lambda p: p[p[:, 0] < -2]                                   # noqa: E731
    assert in_box(shown) > in_box(hidden) + 20, (in_box(shown), in_box(hidden))
    np.testing.assert_array_equal(behind(shown), behind(hidden))
