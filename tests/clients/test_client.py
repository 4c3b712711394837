"""xyzcyl.clients.Client against the app in process (issue 13, Tests): a fastapi TestClient is the client's
http_client. One app and one reconstruction of the example rig are shared by the module. Retries and the error
mapping of statuses the app does not easily produce use an httpx.MockTransport. The app's reconstruction
workers are spawned processes: nothing runs at import."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
pytest.importorskip("fastapi")

from client_helpers import multipart_parts
from xyzcyl.clients import (
    AuthError,
    BusyError,
    Client,
    ConnectionFailed,
    InvalidArgumentError,
    InvalidRequestError,
    NotFoundError,
    NotReadyError,
    SceneInfo,
    ServerError,
    StorageFullError,
    WaitTimeout,
    XyzcylError,
)
from xyzcyl.clients import client as cmod

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "synth_nuscenes"
RIG = EXAMPLE / "rig.json"
READY_S = 60.0


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from fastapi.testclient import TestClient
    from xyzcyl.server import Settings, create_app

    app = create_app(Settings(store=str(tmp_path_factory.mktemp("store")), render_threads=2, ort_threads=1))
    with TestClient(app) as tc:
        c = Client(http_client=tc)
        t0 = time.monotonic()
        while not c.ready():
            assert time.monotonic() - t0 < READY_S, "the app did not become ready"
            time.sleep(0.1)
        yield c


@pytest.fixture(scope="module")
def scene(client) -> SceneInfo:
    sent = []
    info = client.reconstruct(RIG, progress=lambda done, total: sent.append((done, total)))
    assert sent and sent[-1][0] == sent[-1][1] > 500_000         # the six PNGs went through the progress hook
    return info


def rig_doc() -> dict:
    return json.loads(RIG.read_text())


# ----------------------------------------------------------------------------------------------- in process

def test_reconstruct_returns_the_ready_scene(client, scene):
    assert isinstance(scene, SceneInfo)
    assert scene.ready and scene.state == "ready" and scene.error is None
    assert scene.camera_names == [c["name"] for c in rig_doc()["cameras"]]
    assert scene.gaussians == scene.counts["total"] > 0
    assert set(scene.bbox) == {"min", "max"} and scene.model["name"]
    assert scene.links["render"] == f"/v1/scenes/{scene.id}/render"
    assert client.scene(scene.id) == scene                      # dataclass equality (raw is not compared)


def test_second_scene_from_arrays_bytes_wait_paging_delete(client, scene):
    import cv2

    doc = rig_doc()
    images = {}
    for i, cam in enumerate(doc["cameras"]):
        path = EXAMPLE / cam["image"]
        # half the cameras as RGB arrays (sent as PNG), half as the file's bytes
        images[cam["name"]] = (cv2.imread(str(path))[..., ::-1].copy() if i % 2 == 0 else path.read_bytes())
    queued = client.reconstruct(doc, images=images, wait=False)
    assert queued.state in ("queued", "running")
    ready = client.wait(queued.id, timeout=120)
    assert ready.ready and ready.gaussians > 0
    ids = [s.id for s in client.scenes(page_size=1)]           # one scene per page: the pages are followed
    assert ids[:2] == [queued.id, scene.id]                     # newest first
    client.delete(queued.id)
    with pytest.raises(NotFoundError) as e:
        client.scene(queued.id)
    assert (e.value.status, e.value.code, e.value.field) == (404, "not_found", "id")
    assert queued.id not in [s.id for s in client.scenes()]


def test_render_camera_name_equals_its_opencv_K_and_pose(client, scene):
    from xyzcyl.runtime.rig import load_rig

    by_name = client.render(scene.id, "CAM_FRONT_LEFT")
    cam = next(c for c in rig_doc()["cameras"] if c["name"] == "CAM_FRONT_LEFT")
    by_dict = client.render(scene.id, {"K": cam["K"], "cam_to_ego": cam["cam_to_ego"], "width": cam["width"],
                                       "height": cam["height"]})
    by_object = client.render(scene.id, load_rig(RIG).camera("CAM_FRONT_LEFT"))   # a runtime Camera
    assert by_name.shape == (cam["height"], cam["width"], 3) and by_name.dtype == np.float32
    assert 0.0 <= by_name.min() and by_name.max() <= 1.0 and by_name.std() > 0.02
    np.testing.assert_array_equal(by_name, by_dict)
    np.testing.assert_array_equal(by_name, by_object)
    # RGB order: the view of the input camera resembles its input image (cv2 reads BGR)
    import cv2

    src = cv2.imread(str(EXAMPLE / cam["image"]))[..., ::-1].astype(np.float32) / 255.0
    assert np.abs(by_name - src).mean() < np.abs(by_name - src[..., ::-1]).mean()


def test_render_depth_in_metres_and_alpha(client, scene):
    png = client.render(scene.id, "CAM_FRONT", output="depth")
    exr = client.render(scene.id, "CAM_FRONT", output="depth", format="exr")
    alpha = client.render(scene.id, "CAM_FRONT", output="alpha", width=400)
    assert png.shape == exr.shape == (450, 800) and png.dtype == exr.dtype == np.float32
    hit = (exr > 0.5) & (exr < 60.0)
    assert hit.mean() > 0.3
    assert np.abs(png[hit] - exr[hit]).max() <= 0.0006                # millimetres -> metres, rounded
    assert 1.0 < float(np.median(exr[hit])) < 60.0                    # a street: metres, not millimetres
    assert alpha.shape == (225, 400) and 0.0 <= alpha.min() and alpha.max() <= 1.0


def test_render_carla_pose_and_batch_carla_sensor_agree(client, scene):
    pose = {"x": 2.0, "y": 0.0, "z": 1.6, "pitch": -5.0, "yaw": 10.0, "roll": 0.0, "fov": 90.0}
    view = client.render(scene.id, pose, width=320, height=240)
    sensor = {"transform": {"location": {"x": 2.0, "y": 0.0, "z": 1.6},
                            "rotation": {"pitch": -5.0, "yaw": 10.0, "roll": 0.0}},
              "fov": 90.0, "image_size_x": 320, "image_size_y": 240}
    assert view.shape == (240, 320, 3)
    np.testing.assert_array_equal(view, client.render(scene.id, sensor))
    with client.render_path(scene.id, [sensor]) as frames:
        [(name, frame)] = list(frames)
    assert name == "frame_00000.png"
    np.testing.assert_array_equal(view, frame)


def test_render_path_file_frames_progress_and_bytes(client, scene, tmp_path):
    cam = rig_doc()["cameras"][0]
    fov_cam = {"fov": 70.0, "cam_to_ego": cam["cam_to_ego"], "width": 320, "height": 180}
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"cameras": [{"camera": "CAM_FRONT"}, fov_cam, {"camera": "CAM_BACK", "width": 200}]}))
    seen = []
    batch = client.render_path(scene.id, path, progress=lambda k, n: seen.append((k, n)))
    assert seen == [(1, 3), (2, 3), (3, 3)]
    assert len(batch) == 3 and batch.output == "rgb" and batch.format == "png"
    assert [f["width"] for f in batch.index["frames"]] == [800, 320, 200]
    frames = dict(batch)
    assert list(frames) == ["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    np.testing.assert_array_equal(frames["frame_00000.png"], client.render(scene.id, "CAM_FRONT"))
    np.testing.assert_array_equal(frames["frame_00001.png"], client.render(scene.id, fov_cam))
    assert frames["frame_00002.png"].shape == (112, 200, 3)       # 200 x 450/800, rounded
    raw = dict(client.render_path(scene.id, path, format="jpeg", decode=False))
    assert raw["frame_00001.jpg"] == client.render_bytes(scene.id, fov_cam, format="jpeg")


def test_render_path_nerfstudio_camera_path(client, scene):
    from xyzcyl.runtime.convert import cameras_to_nerfstudio_path
    from xyzcyl.runtime.rig import Camera

    front = np.array(rig_doc()["cameras"][0]["cam_to_ego"])
    f = 320 / (2 * np.tan(np.radians(35)))
    K = [[f, 0, 159.5], [0, f, 89.5], [0, 0, 1]]
    cams = [Camera(name=f"c{k}", width=320, height=180, K=K, cam_to_ego=front @ _shift(k)) for k in range(3)]
    doc = cameras_to_nerfstudio_path(cams)
    frames = [a for _, a in client.render_path(scene.id, doc)]
    assert len(frames) == 3
    for cam, frame in zip(cams, frames):
        direct = client.render(scene.id, {"K": K, "cam_to_ego": cam.cam_to_ego, "width": 320, "height": 180})
        assert np.abs(frame - direct).max() <= 1.5 / 255    # same view up to the path's float round trip


def _shift(k: int) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = float(k)          # k metres along the camera's optical axis
    return T


def test_gaussians_ply_and_splat_written_atomically(client, scene, tmp_path):
    got = []
    ply = client.gaussians(scene.id, tmp_path / "scene.ply", progress=lambda n, t: got.append((n, t)))
    assert ply.read_bytes()[:3] == b"ply"
    assert got[-1][0] == got[-1][1] == ply.stat().st_size
    splat = client.gaussians(scene.id, tmp_path / "scene.splat")
    assert splat.stat().st_size == 32 * scene.gaussians
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply", "scene.splat"]    # no .part left
    with pytest.raises(NotFoundError):
        client.gaussians("no-such-scene", tmp_path / "x.ply")
    assert not (tmp_path / "x.ply").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply", "scene.splat"]


def test_server_errors_map_to_typed_exceptions(client, scene):
    with pytest.raises(NotFoundError) as e:
        client.render("AAAAAAAAAAAAAAAAAAAAAA", "CAM_FRONT")
    assert (e.value.status, e.value.code, e.value.field) == (404, "not_found", "id")
    with pytest.raises(InvalidRequestError) as e:
        client.render(scene.id, "NOPE")
    assert (e.value.status, e.value.code, e.value.field) == (422, "invalid", "camera")
    assert "NOPE" in e.value.message and str(e.value).startswith("camera: ")
    with pytest.raises(InvalidRequestError) as e:
        client.render(scene.id, "CAM_FRONT", output="depth", format="jpeg")
    assert e.value.field == "format"
    with pytest.raises(InvalidRequestError) as e:
        client.render_path(scene.id, [{"camera": "CAM_FRONT"}, {"fov": 200, "cam_to_ego": np.eye(4).tolist(),
                                                                  "width": 8, "height": 8}])
    assert (e.value.status, e.value.field) == (422, "cameras[1].fov")
    doc = rig_doc()
    doc["cameras"][0]["K"][0][0] = -1.0
    with pytest.raises(InvalidRequestError) as e:
        client.reconstruct(doc, images={c["name"]: EXAMPLE / c["image"] for c in doc["cameras"]})
    assert (e.value.status, e.value.field) == (422, "rig") and "fx" in e.value.message


def test_reconstruct_sends_the_rigs_lidar_file(client, tmp_path):
    """A rig whose lidar block names a file: the client uploads it as the 'lidar' part (the server then makes the
    cameras' depth from it); lidar=False leaves it out; a missing file is refused before any upload."""
    import shutil

    d = tmp_path / "rig"
    shutil.copytree(EXAMPLE, d)
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-1.0, 4.0, 30))
    wall = np.stack([15 * np.cos(az).ravel(), 15 * np.sin(az).ravel(), z.ravel(), np.ones(az.size)], axis=1)
    np.concatenate([wall, np.zeros((len(wall), 1))], axis=1).astype("<f4").tofile(d / "sweep.pcd.bin")  # nuScenes
    doc = rig_doc()
    doc["lidar"] = {"file": "sweep.pcd.bin", "lidar_to_ego": np.eye(4).tolist()}
    (d / "rig.json").write_text(json.dumps(doc))
    with_lidar = client.reconstruct(d / "rig.json")
    assert with_lidar.counts["lidar_cameras"] == 6
    without = client.reconstruct(d / "rig.json", lidar=False)
    assert "lidar_cameras" not in without.counts
    (d / "sweep.pcd.bin").unlink()
    with pytest.raises(InvalidRequestError) as e:
        client.reconstruct(d / "rig.json")
    assert e.value.code == "file_missing" and e.value.field == "lidar"
    for s in (with_lidar, without):
        client.delete(s.id)


def test_reconstruct_of_a_cut_image_is_refused_naming_the_camera(client, tmp_path):
    """Regression (issue 27, defect 1): a rig whose JPEG was cut short was reconstructed (the decoder filled the rest
    with grey). The server refuses the upload: InvalidRequestError (422) naming the camera, no scene made."""
    import shutil

    import cv2

    d = tmp_path / "rig"
    shutil.copytree(EXAMPLE, d)
    doc = rig_doc()
    back = next(c for c in doc["cameras"] if c["name"] == "CAM_BACK")
    jpeg = cv2.imencode(".jpg", cv2.imread(str(d / back["image"])))[1].tobytes()
    back["image"] = "images/CAM_BACK.jpg"
    (d / back["image"]).write_bytes(jpeg[: len(jpeg) * 2 // 3])
    (d / "rig.json").write_text(json.dumps(doc))
    before = sum(1 for _ in client.scenes())
    with pytest.raises(InvalidRequestError) as e:
        client.reconstruct(d / "rig.json")
    assert (e.value.status, e.value.code, e.value.field) == (422, "invalid", "CAM_BACK"), e.value
    assert "cut short" in e.value.message and str(d) not in e.value.message, e.value.message
    assert str(e.value).startswith("part 'CAM_BACK': the image is cut short") and str(e.value).count("CAM_BACK") == 1
    assert sum(1 for _ in client.scenes()) == before


def test_client_side_refusals_name_the_field(client, tmp_path):
    doc = rig_doc()
    (tmp_path / "rig.json").write_text(json.dumps(doc))      # its images are not beside this copy
    with pytest.raises(InvalidRequestError) as e:
        client.reconstruct(tmp_path / "rig.json")
    assert e.value.status is None and e.value.code == "file_missing" and e.value.field == "CAM_FRONT"
    with pytest.raises(InvalidRequestError) as e:
        client.reconstruct(RIG, images={"CAM_X": b""})
    assert e.value.field == "CAM_X"
    with pytest.raises(InvalidRequestError) as e:
        client.render("id", {"cam_to_ego": np.eye(4), "width": 10, "height": 10})     # neither K nor fov
    assert e.value.field == "camera.K"
    with pytest.raises(InvalidRequestError) as e:
        client.render("id", {"x": 0, "y": 0, "z": 1, "pitch": 0, "yaw": 0, "roll": 0, "width": 8, "height": 8})
    assert e.value.field == "camera.fov"


def test_reconstruct_without_the_detail_layer(client, scene):
    """detail=False reaches the server: no detail Gaussians, and the scene says so (the default scene has them)."""
    assert scene.detail.model_dump() == {"enabled": True, "stride": 2} and scene.counts["detail"] > 0
    off = client.reconstruct(RIG, detail=False)
    assert off.ready and off.detail.model_dump() == {"enabled": False, "stride": None} and "detail" not in off.counts
    assert off.gaussians < scene.gaussians
    client.delete(off.id)


# ----------------------------------------------------------------------------------------------- mocked transport

def _mock(handler, **kw) -> Client:
    return Client(http_client=httpx.Client(transport=httpx.MockTransport(handler), base_url="http://mock"), **kw)


def _error(status: int, code: str, field=None, headers=None) -> httpx.Response:
    return httpx.Response(status, json={"error": {"code": code, "message": f"{code} here", "field": field}},
                          headers=headers)


SCENE_JSON = {"id": "s1", "state": "ready", "created": "2026-11-25T17:34:37+00:00",
              "updated": "2026-11-25T17:34:42+00:00",
              "cameras": [{"name": "A", "width": 8, "height": 8, "model": "pinhole"}], "links": {"self": "/v1/scenes/s1"}}


@pytest.fixture
def sleeps(monkeypatch):
    slept: list[float] = []
    monkeypatch.setattr(cmod, "_sleep", slept.append)
    return slept


def test_reconstruct_sends_the_detail_query(sleeps):
    seen = []

    def handler(request):
        seen.append(dict(request.url.params))
        return httpx.Response(202, json={**SCENE_JSON, "state": "queued", "detail": {"enabled": True, "stride": 4}})

    c = _mock(handler)
    assert c.reconstruct(RIG, wait=False).state == "queued"
    assert c.reconstruct(RIG, wait=False, detail_stride=4).detail.model_dump() == {"enabled": True, "stride": 4}
    c.reconstruct(RIG, wait=False, detail=False)
    c.reconstruct(RIG, wait=False, detail_stride=np.int64(16), detail=True)
    assert seen == [{}, {"detail_stride": "4"}, {"detail": "false"}, {"detail_stride": "16"}]


def test_reconstruct_sends_the_rigs_ego_masks(sleeps, tmp_path):
    """A camera's ego_mask (relative to rig.json) goes up as the 'ego_mask:<camera>' part, like depth files;
    ego_masks={} sends none, ego_masks={camera: array} sends a PNG; a missing file is refused before any request,
    naming the camera and the field."""
    import cv2

    doc = rig_doc()
    for cam in doc["cameras"]:
        cam["image"] = str(EXAMPLE / cam["image"])                      # absolute: kept as they are
    doc["cameras"][0]["ego_mask"] = "masks/front.png"
    front = doc["cameras"][0]["name"]
    mask = np.zeros((doc["cameras"][0]["height"], doc["cameras"][0]["width"]), np.uint8)
    mask[300:] = 255
    (tmp_path / "masks").mkdir()
    png = cv2.imencode(".png", mask)[1].tobytes()
    (tmp_path / "masks" / "front.png").write_bytes(png)
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    sent = []

    def handler(request):
        sent.append(multipart_parts(request))
        return httpx.Response(202, json={**SCENE_JSON, "state": "queued"})

    c = _mock(handler)
    c.reconstruct(tmp_path / "rig.json", wait=False)
    c.reconstruct(tmp_path / "rig.json", wait=False, ego_masks={})
    back = doc["cameras"][-1]["name"]
    c.reconstruct(tmp_path / "rig.json", wait=False, ego_masks={back: mask.astype(bool)})
    masks = [{k: v for k, v in p.items() if k.startswith("ego_mask:")} for p in sent]
    assert masks[0] == {f"ego_mask:{front}": ("image/png", png)}
    assert json.loads(sent[0]["rig"][1])["cameras"][0]["ego_mask"] == "masks/front.png"
    assert masks[1] == {}
    assert list(masks[2]) == [f"ego_mask:{back}"] and masks[2][f"ego_mask:{back}"][0] == "image/png"
    got = cv2.imdecode(np.frombuffer(masks[2][f"ego_mask:{back}"][1], np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got > 0, mask > 0)
    (tmp_path / "masks" / "front.png").unlink()
    with pytest.raises(InvalidRequestError) as e:
        c.reconstruct(tmp_path / "rig.json", wait=False)
    assert e.value.status is None and e.value.code == "file_missing" and e.value.field == f"ego_mask:{front}"
    assert f"camera {front!r}: ego_mask: " in e.value.message and "front.png" in e.value.message
    assert len(sent) == 3                                               # nothing was sent for the missing file


@pytest.mark.parametrize("kw,field_name", [
    ({"detail_stride": 0}, "detail_stride"), ({"detail_stride": 17}, "detail_stride"),
    ({"detail_stride": 2.0}, "detail_stride"), ({"detail_stride": "4"}, "detail_stride"),
    ({"detail_stride": True}, "detail_stride"), ({"detail": "no"}, "detail"),
    ({"detail_stride": 4, "detail": False}, "detail_stride")])
def test_bad_detail_arguments_are_refused_before_sending(kw, field_name):
    def handler(request):
        raise AssertionError("nothing may be sent")

    with pytest.raises(ValueError) as e:
        _mock(handler).reconstruct(RIG, **kw)
    assert isinstance(e.value, InvalidArgumentError) and isinstance(e.value, InvalidRequestError)
    assert e.value.status is None and e.value.field == field_name and str(e.value).startswith(f"{field_name}: ")
    if len(kw) == 2:
        assert "detail=False" in str(e.value)


def test_retries_429_and_503_honouring_retry_after(sleeps):
    answers = [_error(503, "busy", headers={"Retry-After": "2"}), _error(429, "rate", headers={"Retry-After": "3"}),
               _error(503, "busy", headers={"Retry-After": "1000"}), httpx.Response(200, json=SCENE_JSON)]
    seen = []

    def handler(request):
        seen.append(request)
        return answers[len(seen) - 1]

    c = _mock(handler, api_key="k" * 12)
    assert c.scene("s1").id == "s1"
    assert len(seen) == 4
    assert sleeps == [2.0, 3.0, 30.0]                          # Retry-After honoured, capped at 30 s
    assert all(r.headers["authorization"] == "Bearer " + "k" * 12 for r in seen)


def test_busy_after_the_last_retry_and_posts_retried_on_503(sleeps):
    seen = []

    def handler(request):
        seen.append(request.method)
        return _error(503, "busy", headers={"Retry-After": "1"})

    with pytest.raises(BusyError) as e:
        _mock(handler, retries=2).reconstruct(RIG, wait=False)  # a 503 means nothing was done: POST retried
    assert seen == ["POST"] * 3 and sleeps == [1.0, 1.0]
    assert (e.value.status, e.value.code, e.value.retry_after) == (503, "busy", 1.0)


def test_connection_errors_retried_for_get_but_not_for_post_scenes(sleeps):
    seen = []

    def handler(request):
        seen.append(request.method)
        if len(seen) < 3:
            raise httpx.ConnectError("connection refused", request=request)
        return httpx.Response(200, json=SCENE_JSON)

    c = _mock(handler)
    assert c.scene("s1").ready                                  # GET: two refusals, then the answer
    assert seen == ["GET"] * 3 and len(sleeps) == 2
    seen.clear()
    with pytest.raises(ConnectionFailed) as e:
        c.reconstruct(RIG, wait=False)                          # POST /v1/scenes: not repeated
    assert seen == ["POST"] and e.value.status is None and e.value.field == "server"

    def always_down(request):
        seen.append(request.method)
        raise httpx.ConnectError("connection refused", request=request)

    seen.clear()
    with pytest.raises(ConnectionFailed):
        _mock(always_down, retries=3).delete("s1")
    assert seen == ["DELETE"] * 4


@pytest.mark.parametrize("status,code,cls", [
    (401, "unauthorized", AuthError), (404, "not_found", NotFoundError), (409, "not_ready", NotReadyError),
    (413, "too_large", InvalidRequestError), (415, "unsupported_media_type", InvalidRequestError),
    (422, "invalid", InvalidRequestError), (503, "busy", BusyError), (507, "storage_full", StorageFullError),
    (500, "internal", ServerError), (405, "method_not_allowed", XyzcylError)])
def test_error_mapping(status, code, cls, sleeps):
    c = _mock(lambda request: _error(status, code, "some.field"), retries=0)
    with pytest.raises(cls) as e:
        c.scene("s1")
    assert (e.value.status, e.value.code, e.value.field, e.value.message) == (status, code, "some.field",
                                                                              f"{code} here")
    assert isinstance(e.value, XyzcylError)


def test_wait_polls_until_failed_or_deadline(sleeps, monkeypatch):
    states = iter(["running", "running", "failed"])

    def handler(request):
        if request.method == "POST":
            return httpx.Response(202, json={**SCENE_JSON, "state": "queued"}, headers={"Location": "/v1/scenes/s1"})
        state = next(states)
        err = {"code": "invalid_input", "message": "no sky"} if state == "failed" else None
        return httpx.Response(200, json={**SCENE_JSON, "state": state, "error": err})

    with pytest.raises(InvalidRequestError) as e:
        _mock(handler).reconstruct(RIG)
    assert (e.value.status, e.value.code, e.value.scene_id) == (422, "invalid_input", "s1")
    assert len(sleeps) == 2

    clock = iter(range(0, 1000, 10))
    monkeypatch.setattr(cmod, "_monotonic", lambda: float(next(clock)))
    with pytest.raises(WaitTimeout) as e:
        _mock(lambda r: httpx.Response(200, json={**SCENE_JSON, "state": "running"})).wait("s1", timeout=25)
    assert e.value.scene_id == "s1" and isinstance(e.value, NotReadyError)
