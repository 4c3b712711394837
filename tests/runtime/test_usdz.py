"""`xyzcyl export SCENE --format usdz` (runtime.usdz): an AlpaSim scene artifact, checked against the format as
AlpaSim's loader (NVlabs/alpasim src/utils/alpasim_utils: artifact.py, scenario.py, scene_metadata.py) parses it:
the members it opens by name, metadata.yaml's required fields, rig_trajectories.json (a 4x4 world_to_nre, camera
calibrations with logical sensor names, integer microsecond timestamps strictly rising, 4x4 rig -> world poses,
[start, end] microsecond frame windows with end > start, rig_bbox present), sequence_tracks.json (per track: an id,
a label, flags, strictly rising microsecond times, rows of xyz + a unit scipy-order quaternion, box dims), the
meshes (PLY vertices + faces); and the NuRec volume (its float16 tensors decode to the scene's Gaussians) and USD
layers (opened with usd-core); the archive's USDZ rules (stored members, data 64-byte aligned, the root layer
first). A scene without a drive exports one frame, and refusals name the flag."""

from __future__ import annotations

import gzip
import io
import json
import zipfile

import numpy as np
import pytest
from xyzcyl.runtime.actors import Actors
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.rotations import quat_to_rotmat
from xyzcyl.runtime.scene import Scene
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import pose

T0 = 1557539956.5                     # the drive's first frame (seconds on the rigs' clock)
GROUND_Z = -0.3                       # the synthetic road, scene frame (metres)
MEMBERS = ("default.usda", "gauss.usda", "scene.nurec", "metadata.yaml", "rig_trajectories.json",
           "sequence_tracks.json", "mesh_ground.ply", "mesh.ply")


def _E() -> np.ndarray:
    """The first frame's ego -> world: turned 30 degrees, 100 m from the world's origin."""
    E = np.array(pose(100.0, -40.0, 30.0), float)
    E[2, 3] = 2.0
    return E


def _ground(rng) -> Gaussians:
    """A 60 x 30 m road of opaque flat Gaussians at GROUND_Z (every 0.5 m) and a few above it (SH degree 1)."""
    x, y = np.meshgrid(np.arange(-20, 40, 0.5), np.arange(-15, 15, 0.5), indexing="ij")
    road = np.stack([x.ravel(), y.ravel(), np.full(x.size, GROUND_Z)], 1)
    above = rng.uniform([-10, -10, 1], [30, 10, 5], (200, 3))
    means = np.concatenate([road, above]).astype(np.float32)
    n = len(means)
    sh = rng.normal(0, 0.3, (n, 4, 3)).astype(np.float32)
    return Gaussians(means, rng.normal(size=(n, 4)).astype(np.float32), np.full((n, 3), -2.5, np.float32),
                     np.full(n, 4.0, np.float32), sh)


def _actors() -> Actors:
    """"car" annotated at the three frames, moving 2 m/s along x; "walker" annotated once (frame 1)."""
    g = Gaussians(np.zeros((2, 3), np.float32), np.tile(np.float32([1, 0, 0, 0]), (2, 1)),
                  np.full((2, 3), -2.0, np.float32), np.zeros(2, np.float32), np.zeros((2, 4, 3), np.float32))
    times = [T0, T0 + 0.5, T0 + 1.0]
    poses = [pose(10 + 2 * (t - T0), 3.0, 5.0) for t in times] + [pose(5.0, -4.0, 90.0)]
    return Actors(track_id=("car", "walker"), track_label=("Car", "Pedestrian"),
                  track_size=np.array([[4.0, 2.0, 1.5], [0.6, 0.6, 1.8]]), pose_track=np.array([0, 0, 0, 1]),
                  pose_time=np.array(times + [T0 + 0.5]), pose=np.array(poses, float),
                  copy_track=np.array([0, 1]), copy_time=np.array([T0, T0 + 0.5]), copy_start=np.array([0, 1, 2]),
                  gaussians=g)


def _drive_scene(tmp_path) -> Scene:
    """A three-frame drive (0.5 s apart, the ego 5 m further each) of the example rig, saved and loaded."""
    scene = Scene(gaussians=_ground(np.random.default_rng(0)), background=None, rig=load_rig(EXAMPLE_RIG),
                  drive={"frames": 3, "keyframes": [0], "timestamp_s": T0, "times_s": [0.0, 0.5, 1.0],
                         "ego_to_world": _E().tolist(), "trajectory": [pose(5.0 * i, 0.0, 2.0 * i) for i in range(3)],
                         "tracks": 2},
                  actors=_actors())
    scene.save(tmp_path / "drive")
    return Scene.load(tmp_path / "drive")


def _export(folder, out, scene_id="drive-1"):
    from xyzcyl.runtime.usdz import export_usdz

    return export_usdz(folder, out, scene_id)


def _matrix(row) -> np.ndarray:
    """A track pose row (x, y, z, qx, qy, qz, qw) as a 4x4, the way AlpaSim's Pose reads it."""
    q = np.array(row[3:], float)
    assert abs(q @ q - 1.0) <= 1e-4                    # utils_rs refuses quaternions further from unit length
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(np.array([q[3], *q[:3]]))
    T[:3, 3] = row[:3]
    return T


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("usdz")
    scene = _drive_scene(tmp)
    report = _export(tmp / "drive", tmp / "drive.usdz")
    return scene, report, zipfile.ZipFile(tmp / "drive.usdz")


def test_the_archive_keeps_the_usdz_rules(drive):
    _, report, z = drive
    infos = z.infolist()
    assert tuple(i.filename for i in infos) == MEMBERS             # the root layer first
    raw = open(z.filename, "rb").read()
    for i in infos:
        assert i.compress_type == zipfile.ZIP_STORED, i.filename
        name_len, extra_len = np.frombuffer(raw[i.header_offset + 26:i.header_offset + 30], "<u2")
        start = i.header_offset + 30 + int(name_len) + int(extra_len)
        assert start % 64 == 0, i.filename
        assert raw[start:start + i.file_size] == z.read(i.filename)
    assert report.bytes == len(raw) and report.frames == 3 and report.tracks == 2 and report.cameras == 6


def test_metadata_has_the_fields_alpasims_dataclass_requires(drive):
    yaml = pytest.importorskip("yaml")
    scene, _, z = drive
    meta = yaml.safe_load(z.read("metadata.yaml"))                   # JSON written: read as YAML, as AlpaSim does
    for key, kind in (("scene_id", str), ("version_string", str), ("training_date", str), ("dataset_hash", str),
                      ("uuid", str), ("is_resumable", bool), ("sensors", dict), ("logger", dict),
                      ("time_range", dict)):
        assert isinstance(meta[key], kind), key
    assert meta["scene_id"] == "drive-1"
    assert meta["sensors"] == {"camera_ids": list(scene.rig.names), "lidar_ids": []}
    assert set(meta["logger"]) <= {"name", "run_id", "run_url"}
    assert meta["time_range"] == {"start": round(T0 * 1e6) - 500, "end": round((T0 + 1.0) * 1e6) + 500}


def test_the_trajectory_and_cameras_as_alpasim_parses_them(drive):
    scene, _, z = drive
    rig = json.loads(z.read("rig_trajectories.json"))
    E = _E()
    assert np.array(rig["world_to_nre"]["matrix"]).shape == (4, 4)
    np.testing.assert_allclose(np.array(rig["world_to_nre"]["matrix"]) @ E, np.eye(4), atol=1e-9)
    (traj,) = rig["rig_trajectories"]
    assert traj["sequence_id"] == "drive-1" and "rig_bbox" in traj and traj["rig_bbox"] is None
    us = traj["T_rig_world_timestamps_us"]
    assert all(isinstance(t, int) for t in us) and all(b > a for a, b in zip(us, us[1:]))
    assert us == [round((T0 + dt) * 1e6) for dt in (0.0, 0.5, 1.0)]
    times, poses = scene.timeline()
    np.testing.assert_allclose(np.array(traj["T_rig_worlds"]), poses, atol=1e-9)
    np.testing.assert_allclose(poses[1], E @ np.array(pose(5.0, 0.0, 2.0)), atol=1e-9)
    cams = rig["camera_calibrations"]
    assert set(traj["cameras_frame_timestamps_us"]) == set(cams) == set(scene.rig.names)
    for cam in scene.rig.cameras:
        assert cams[cam.name]["logical_sensor_name"] == cam.name
        np.testing.assert_allclose(cams[cam.name]["T_sensor_rig"], cam.cam_to_ego, atol=1e-12)
        windows = traj["cameras_frame_timestamps_us"][cam.name]
        assert len(windows) == 3
        for (start, end), t in zip(windows, times):
            assert isinstance(start, int) and isinstance(end, int) and end > start
            assert (start + end) // 2 == round(t * 1e6)          # the example rig's cameras have no own times


def test_the_tracks_as_alpasim_parses_them(drive):
    from xyzcyl.runtime.usdz import CONTROLLABLE

    scene, _, z = drive
    tracks = json.loads(z.read("sequence_tracks.json"))
    assert list(tracks) == ["drive-1"]                               # one sequence, the scene id
    data = tracks["drive-1"]["tracks_data"]
    dims = tracks["drive-1"]["cuboidtracks_data"]["cuboids_dims"]
    assert data["tracks_id"] == ["car", "walker"] and data["tracks_label_class"] == ["Car", "Pedestrian"]
    assert all(CONTROLLABLE in f for f in data["tracks_flags"])     # AlpaSim moves them (not static)
    np.testing.assert_allclose(dims, scene.actors.track_size)
    E = _E()
    car_t, car_rows = data["tracks_timestamps_us"][0], data["tracks_poses"][0]
    assert car_t == [round((T0 + dt) * 1e6) for dt in (0.0, 0.5, 1.0)]
    for row, T in zip(car_rows, scene.actors.pose[:3]):
        assert len(row) == 7
        np.testing.assert_allclose(_matrix(row), E @ T, atol=1e-9)
    # annotated once: the pose at both ends of the span a render draws it in (its time +- half a frame interval)
    walker_t, walker_rows = data["tracks_timestamps_us"][1], data["tracks_poses"][1]
    assert walker_t == [round((T0 + 0.25) * 1e6), round((T0 + 0.75) * 1e6)]
    for row in walker_rows:
        np.testing.assert_allclose(_matrix(row), E @ scene.actors.pose[3], atol=1e-9)


def test_the_ground_mesh_lies_on_the_road(drive):
    from plyfile import PlyData

    _, report, z = drive
    assert z.read("mesh.ply") == z.read("mesh_ground.ply")
    ply = PlyData.read(io.BytesIO(z.read("mesh_ground.ply")))
    v = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(float)
    f = np.stack(ply["face"]["vertex_indices"])
    assert len(v) == report.mesh_vertices and len(f) == report.mesh_faces > 1000
    assert f.min() >= 0 and f.max() < len(v)
    local = (v - _E()[:3, 3]) @ _E()[:3, :3]                         # back into the scene frame
    on_road = (local[:, 0] > -15) & (local[:, 0] < 35) & (np.abs(local[:, 1]) < 10)
    # float32 vertices 100 m from the world's origin: 1e-5 m; the road is exactly flat
    np.testing.assert_allclose(local[on_road, 2], GROUND_Z, atol=1e-4)
    tri = v[f]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normals[:, 2] > 0).all()                                 # faces seen from above: upward normals


def test_the_nurec_volume_decodes_to_the_scenes_gaussians(drive):
    msgpack = pytest.importorskip("msgpack")
    scene, _, z = drive
    doc = msgpack.unpackb(gzip.decompress(z.read("scene.nurec")), raw=False)["nre_data"]
    state = doc["state_dict"]
    g = scene.gaussians
    n = len(g)

    def tensor(name):
        key = f".gaussians_nodes.gaussians.{name}"
        return np.frombuffer(state[key], np.float16).reshape(state[key + ".shape"]).astype(np.float64)

    layers = doc["config"]["layers"]["gaussians"]
    assert layers["density_activation"] == "sigmoid" and layers["scale_activation"] == "exp"

    def close(got, want):
        # float16 rounds to the nearest of 11 significant bits: within 2^-11 of the value, relative
        want = np.asarray(want, np.float64)
        assert np.all(np.abs(got - want) <= np.abs(want) * 2.0 ** -11 + 1e-7)

    close(tensor("positions"), g.means)
    close(tensor("rotations"), g.quats)
    close(tensor("scales"), g.log_scales)
    close(tensor("densities"), g.opacity_logits[:, None])
    close(tensor("features_albedo"), g.sh[:, 0])
    spec = tensor("features_specular").reshape(n, 15, 3)
    close(spec[:, :3], g.sh[:, 1:])
    assert not spec[:, 3:].any()                                     # degree 1 here: the rest zero
    assert np.frombuffer(state[".gaussians_nodes.gaussians.n_active_features"], np.int64)[0] == 1


def test_the_usd_layers_open_with_usd_core(drive, tmp_path):
    pytest.importorskip("pxr", reason="usd-core (the dev extra) opens the layers")
    from pxr import Usd, UsdGeom, UsdVol

    _, _, z = drive
    stage = Usd.Stage.Open(z.filename)                               # the .usdz itself: its root layer first
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    vol = stage.GetPrimAtPath("/World/gauss/gauss")
    assert vol.GetTypeName() == "Volume" and vol.GetAttribute("omni:nurec:isNuRecVolume").Get()
    M = np.array(UsdGeom.Xformable(vol).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    np.testing.assert_allclose(M.T, _E(), atol=1e-12)               # row vectors in USD: E transposed
    fields = UsdVol.Volume(vol).GetFieldPaths()
    assert set(fields) == {"density", "emissiveColor"}
    for path in fields.values():
        assert stage.GetPrimAtPath(path).GetAttribute("filePath").Get().path == "./scene.nurec"


def test_a_scene_without_a_drive_exports_one_frame(tmp_path):
    rig = load_rig(EXAMPLE_RIG)
    Scene(gaussians=_ground(np.random.default_rng(1)), background=None, rig=rig).save(tmp_path / "one")
    report = _export(tmp_path / "one", tmp_path / "one.usdz", "one")
    assert report.frames == 1 and report.tracks == 0 and any("one frame" in n for n in report.notes)
    z = zipfile.ZipFile(tmp_path / "one.usdz")
    (traj,) = json.loads(z.read("rig_trajectories.json"))["rig_trajectories"]
    assert len(traj["T_rig_worlds"]) == len(traj["T_rig_world_timestamps_us"]) == 1
    tracks = json.loads(z.read("sequence_tracks.json"))["one"]
    assert tracks["tracks_data"]["tracks_id"] == [] and tracks["cuboidtracks_data"]["cuboids_dims"] == []


def test_the_command_line(tmp_path, capsys):
    from xyzcyl import cli

    rig = load_rig(EXAMPLE_RIG)
    Scene(gaussians=_ground(np.random.default_rng(2)), background=None, rig=rig).save(tmp_path / "scene")
    assert cli.main(["export", str(tmp_path / "scene"), "--format", "usdz", "--out", str(tmp_path / "s.usdz")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scene_id"] == "scene" and out["frames"] == 1 and (tmp_path / "s.usdz").stat().st_size == out["bytes"]
    for argv, says in (([str(tmp_path / "scene"), "--format", "gltf", "--out", "x.usdz"], "a gltf file's"),
                       ([str(tmp_path / "scene"), "--format", "obj", "--out", "x.usdz"], "--format: 'obj'"),
                       ([str(tmp_path / "scene"), "--out", str(tmp_path / "s.zip")], "--out: "),
                       ([str(tmp_path / "scene"), "--out", str(tmp_path / "no" / "s.usdz")], "does not exist"),
                       ([str(tmp_path), "--out", str(tmp_path / "t.usdz")], "SCENE_DIR: "),
                       ([str(tmp_path / "scene"), "--out", str(tmp_path / "t.usdz"), "--scene-id", ""], "scene_id")):
        assert cli.main(["export", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("xyzcyl export: ") and says in err, (argv, err)
    assert not (tmp_path / "t.usdz").exists() and not list(tmp_path.glob(".t.usdz*"))   # nothing half written
