"""render_lidar over gRPC and GET /v1/scenes/{id}/lidar (runtime.lidarsim; docs/simulators.md "LiDAR"), against an
app run in process (TestClient: its lifespan starts the gRPC SensorsimService on a free port) whose store holds one
tiny scene: a cylinder of Gaussians 10 m around the scene's origin, the scene's ego at ``ego_pose()`` in the
simulator's local frame. No reconstruction worker is started (the test needs none): the module takes ~2 s."""

from __future__ import annotations

import io

import numpy as np
import pytest

grpc = pytest.importorskip("grpc")

from fastapi.testclient import TestClient  # noqa: E402
from xyzcyl.server.sensorsim import common_pb2, frames  # noqa: E402
from xyzcyl.server.sensorsim import sensorsim_pb2 as pb  # noqa: E402
from xyzcyl.server.sensorsim.sensorsim_pb2_grpc import SensorsimServiceStub  # noqa: E402
from xyzcyl.testing.lidarscene import GREY_LUMA, cylinder_scene  # noqa: E402
from xyzcyl.testing.sensorsim import ego_pose  # noqa: E402

NAME = "lidar-cylinder"
TIMEOUT = 30.0
Code = grpc.StatusCode
# a coarser cylinder than tests/runtime/test_lidarsim.py's (faster): its plates overlap over 0.17 m, and the expected
# depth's front-to-back blend reads short by up to ~0.1 m off a sector camera's axis (that file's RANGE_TOL)
RANGE_TOL = 0.15


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    from xyzcyl.server import Settings, create_app
    from xyzcyl.server.store import FolderStore, new_scene_id

    root = tmp_path_factory.mktemp("lidar-store")
    store = FolderStore(root)
    store.open()
    sid = new_scene_id()
    work = store.work_dir()
    cylinder_scene(work / "scene", ego_to_world=ego_pose(), n_around=360, n_up=30)
    store.create(sid, {"name": NAME, "cameras": [{"name": "front", "width": 64, "height": 48, "model": "pinhole"}]})
    store.commit(sid, work / "scene", model={}, counts={}, timings={}, bbox=None, gaussians=0, background=False)
    work.rmdir()
    app = create_app(Settings(store=str(root), grpc_port=0, warm_up=False, render_threads=1,
                              render_cache_bytes=0))
    service = app.state.service

    async def no_workers():         # this module reconstructs nothing
        return 0.0
    service.reconstructions.start = no_workers
    with TestClient(app) as client:
        with grpc.insecure_channel(f"127.0.0.1:{app.state.grpc_port}") as channel:
            yield client, SensorsimServiceStub(channel), sid


def lidar_request(start: np.ndarray, end: np.ndarray | None = None, kind: int = pb.PANDAR128,
                  scene: str = NAME, **kw) -> pb.LidarRenderRequest:
    """AlpaSim's LidarRenderRequest with the LiDAR at ``start`` / ``end`` (lidar -> local frame)."""
    pair = pb.PosePair(start_pose=frames.pose_message(start),
                       end_pose=frames.pose_message(start if end is None else end))
    return pb.LidarRenderRequest(scene_id=scene, lidar_config=pb.LidarSpec(lidar_type=kind), frame_start_us=1_000_000,
                                 frame_end_us=1_100_000, sensor_pose=pair, **kw)


def fails(stub, request, code, field=None):
    with pytest.raises(grpc.RpcError) as e:
        stub.render_lidar(request, timeout=TIMEOUT)
    assert e.value.code() == code, (e.value.code(), e.value.details())
    if field is not None:
        assert field in e.value.details(), e.value.details()
        assert ("xyzcyl-field", field) in tuple(e.value.trailing_metadata() or ()), e.value.trailing_metadata()


def _on_cylinder(points_lidar: np.ndarray, lidar_to_local: np.ndarray) -> np.ndarray:
    """|horizontal distance - 10| of LiDAR-frame points taken into the scene's (ego) frame."""
    to_ego = np.linalg.inv(ego_pose()) @ lidar_to_local
    p = points_lidar.astype(np.float64) @ to_ego[:3, :3].T + to_ego[:3, 3]
    return np.abs(np.hypot(p[:, 0], p[:, 1]) - 10.0)


def test_render_lidar_answers_points_in_the_end_of_spin_frame(live):
    """A PANDAR128 sweep from 1.8 m above the scene's origin, moving 0.5 m forward during the spin: every ray hits
    the cylinder; the points, taken from the end-of-spin frame to the scene, lie on it; they come as the buffers alone
    (under gRPC's default 4 MB receive limit); intensities are the grey's luminance."""
    _, stub, _ = live
    E = ego_pose()
    start = E.copy()
    start[:3, 3] += E[:3, 2] * 1.8
    end = start.copy()
    end[:3, 3] += E[:3, 0] * 0.5
    got = stub.render_lidar(lidar_request(start, end), timeout=TIMEOUT)
    assert got.num_points == 128 * 1800
    xyz = np.frombuffer(got.point_xyzs_buffer, "<f4").reshape(-1, 3)
    assert len(xyz) == got.num_points and not got.point_xyzs and not got.point_intensities     # the buffers alone
    inten = np.frombuffer(got.point_intensities_buffer, "<f4")
    assert len(inten) == got.num_points
    np.testing.assert_allclose(inten, GREY_LUMA, atol=2e-3)
    assert _on_cylinder(xyz, end).max() < RANGE_TOL
    assert _on_cylinder(xyz, start).max() > 0.3               # not the start frame's


def test_at128_sees_forward_and_render_aggregated_stays_unimplemented(live):
    _, stub, _ = live
    got = stub.render_lidar(lidar_request(ego_pose(), kind=pb.AT128), timeout=TIMEOUT)
    xyz = np.frombuffer(got.point_xyzs_buffer, "<f4").reshape(-1, 3)
    assert got.num_points == 128 * 1200 == len(xyz)
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    assert az.min() > -60.0 and az.max() <= 60.0 + 1e-3
    with pytest.raises(grpc.RpcError) as e:
        stub.render_aggregated(pb.AggregatedRenderRequest(), timeout=TIMEOUT)
    assert e.value.code() == Code.UNIMPLEMENTED


def test_bad_requests_name_the_field(live):
    _, stub, _ = live
    E = ego_pose()
    fails(stub, lidar_request(E, scene=""), Code.INVALID_ARGUMENT, "scene_id")
    fails(stub, lidar_request(E, scene="no-such-scene"), Code.NOT_FOUND, "scene_id")
    fails(stub, lidar_request(E, kind=7), Code.INVALID_ARGUMENT, "lidar_config.lidar_type")
    fails(stub, pb.LidarRenderRequest(scene_id=NAME), Code.INVALID_ARGUMENT, "sensor_pose")
    bad = lidar_request(E)
    bad.sensor_pose.start_pose.quat.w = 3.0
    fails(stub, bad, Code.INVALID_ARGUMENT, "sensor_pose.start_pose.quat")
    nan = lidar_request(E)
    nan.sensor_pose.end_pose.vec.x = float("nan")
    fails(stub, nan, Code.INVALID_ARGUMENT, "sensor_pose.end_pose.vec")
    early = lidar_request(E)
    early.frame_end_us = 10
    fails(stub, early, Code.INVALID_ARGUMENT, "frame_end_us")
    car = pb.DynamicObject(track_id="car-1", pose_pair=pb.PosePair(start_pose=frames.pose_message(E)))
    fails(stub, lidar_request(E, dynamic_objects=[car]), Code.INVALID_ARGUMENT, "dynamic_objects[0].track_id")
    assert common_pb2.Empty() is not None


def test_http_lidar_ply_and_npy(live):
    from plyfile import PlyData

    client, _, sid = live
    pose = ",".join(str(v) for v in np.eye(4).ravel())           # lidar -> the scene's (ego) frame
    r = client.get(f"/v1/scenes/{sid}/lidar", params={"pose": pose, "model": "pandar64", "azimuth_step": 1.0})
    assert r.status_code == 200, r.text
    assert r.headers["x-lidar-points"] == str(64 * 360) == r.headers["x-lidar-rays"]
    v = PlyData.read(io.BytesIO(r.content))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    assert _on_cylinder(xyz, ego_pose()).max() < RANGE_TOL
    assert set(np.unique(v["ring"])) == set(range(64))
    r = client.get(f"/v1/scenes/{sid}/lidar", params={"pose": pose, "model": "at128", "format": "npy",
                                                      "azimuth_step": 1.0, "max_range": 9.0})
    assert r.status_code == 200, r.text
    a = np.load(io.BytesIO(r.content))
    assert a.shape == (0, 4)                                          # the cylinder is 10 m away: beyond 9 m


@pytest.mark.parametrize("params, field", [
    ({"pose": "1,2,3"}, "pose"),
    ({"pose": ",".join(["2"] * 16)}, "pose"),
    ({"model": "velodyne"}, "model"),
    ({"azimuth_step": 0.001}, "azimuth_step"),
    ({"azimuth_step": 0.03}, "azimuth_step"),                          # too many rays
    ({"max_range": -5}, "max_range"),
    ({"time": "nan"}, "time"),
    ({"format": "las"}, "format"),
    ({"cam_to_ego": "1"}, "cam_to_ego"),                                # not a parameter of this route
    ({"actors": "["}, "actors"),                                         # not JSON
    ({"actors": '[{"id": "car-1"}]'}, "actors[0]"),                     # no edit in it
    ({"actors": "scene.json"}, "actors"),                               # JSON text only: never a file's name
    ({"actors": '[{"id": "car-1", "hide": true}]'}, "actors[0].id"),    # the cylinder scene has no actors
])
def test_http_lidar_refusals_are_422_naming_the_field(live, params, field):
    client, _, sid = live
    q = {"pose": ",".join(str(v) for v in np.eye(4).ravel()), **params}
    r = client.get(f"/v1/scenes/{sid}/lidar", params=q)
    assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
    r = client.get("/v1/scenes/no-such-scene/lidar", params={"pose": q["pose"]})
    assert r.status_code == 404, r.text
