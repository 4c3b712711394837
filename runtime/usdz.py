"""A scene folder as an AlpaSim scene artifact: one `.usdz` (`xyzcyl export SCENE --format usdz`, GET
/v1/scenes/{id}/export?format=usdz). docs/simulators.md "Scene artifacts (USDZ)" is the user's page.

AlpaSim cannot start a rollout without a scene artifact, even when the renderer is external (our gRPC front end): it
reads the rig's trajectory, the cameras, the tracks and a ground mesh from a `.usdz` per scene. What its loader
(NVlabs/alpasim, src/utils/alpasim_utils: artifact.py, scenario.py, scene_metadata.py) opens, and what we write
there (read from its code; none of it copied):

- `metadata.yaml`: its `Metadata` dataclass: scene_id, version_string, training_date, dataset_hash, uuid,
  is_resumable, sensors {camera_ids, lidar_ids}, logger {name, run_id, run_url}, time_range {start, end}
  (microseconds on the rigs' clock, as NRE's artifacts write it). Written as JSON, which is YAML (a flow mapping
  of double-quoted strings and numbers: PyYAML's safe_load reads it), so the export needs no YAML library.
- `rig_trajectories.json`: `world_to_nre.matrix` (4x4), `camera_calibrations` {unique camera id: {
  logical_sensor_name, ...}}, `rig_trajectories` [one: sequence_id, T_rig_world_timestamps_us (int
  microseconds, strictly increasing), T_rig_worlds (4x4 rig -> world per timestamp, row-major nested lists),
  cameras_frame_timestamps_us {unique camera id: [[start_us, end_us] per frame, end > start]}, rig_bbox (null: we
  do not know the ego vehicle's size; AlpaSim then uses its default vehicle or the user's)].
- `sequence_tracks.json`: {sequence_id: {tracks_data: {tracks_id, tracks_label_class, tracks_flags,
  tracks_timestamps_us, tracks_poses (per pose [x, y, z, qx, qy, qz, qw]: position and a scipy-order unit
  quaternion, box -> world)}, cuboidtracks_data: {cuboids_dims ([length, width, height] metres per track)}}}.
  A track whose flags contain "CONTROLLABLE" is one AlpaSim moves (it sends it back to the renderer as a
  dynamic_object); the others it treats as static.
- `mesh_ground.ply` and `mesh.ply` (its loader reads mesh.ply unless told to use the ground mesh; we make no mesh
  of the whole scene, so both hold the same ground mesh: ground_mesh).
- the Gaussians as a NuRec volume: `<name>.nurec` (gzip of msgpack: `nre_data` {version, model, config,
  state_dict}: the state dict's float16 tensors as raw bytes with their shapes) and the USD layers `gauss.usda`
  (a UsdVol Volume whose two OmniNuRecFieldAsset fields name the .nurec file) and `default.usda` (the root layer,
  first in the archive, referencing gauss.usda). NVIDIA's Apache-2.0 `ply_to_usdz_standalone.py` documents that
  layout; the USDA text is written here directly (usd-core is a 30 MB dependency; the tests open the layers with it).

Frames. "world" is the frame of the rigs' ``ego_to_world`` (E), the frame the gRPC front end takes sensor poses and
dynamic objects in (server/sensorsim/frames.py): the trajectory and the tracks are written in it, so what AlpaSim
reads here and sends back renders as recorded. The Gaussians stay in the scene's frame (the first frame's ego
frame) and the volume's transform is E; ``world_to_nre`` is inv(E) (NRE's frame is the volume's). Z up, metres.

Time: the drive's frames (scene.json ``drive.times_s`` after ``drive.timestamp_s``), each camera at its own offset
from its frame (the scene's rig: its camera's ``timestamp_s`` minus the rig's), as a nominal exposure of
2 x EXPOSURE_HALF_US around that time: the gRPC front end renders a request at its exposure's middle, so the frames
AlpaSim asks for render at the recorded times. A scene that is not a drive writes one frame (its rig's time, 0
without one) and says so (UsdzReport.notes).

What the volume holds: the scene's shared Gaussians (scene.ply), drawn by a NuRec renderer in one pass. xyzcyl's
own renders draw more (each view's keyframe layers first, the viewpoint chunks, the sky panorama, the moving
objects at their time): the artifact's volume is for viewers and tools, the pictures a simulation sees come from
`xyzcyl serve --grpc-port`. Positions are float16, NuRec's precision (steps of 1/1024 of the coordinate's power of
two: 3 cm at 30-60 m from the scene's origin)."""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import math
import os
import struct
import uuid
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .actors import frame_interval
from .errors import FieldError
from .render import Gaussians
from .rotations import rotmat_to_quat
from .scene import Scene

FORMAT_VERSION = "xyzcyl-usdz-1"     # what this module writes (metadata.yaml's version_string carries it)
EXPOSURE_HALF_US = 500               # half of the nominal exposure written around each camera frame's time
NUREC_NAME = "scene.nurec"
NUREC_VERSION = "0.2.576"            # the nre_data version of the layout the standalone converter documents
NUREC_SH_COLUMNS = 15                # the state dict's specular SH per colour: degree 3 (zero beyond ours)
ALIGN = 64                           # bytes: USDZ files start their data at multiples of 64 (the USDZ spec)
PAD_HEADER_ID = 0x1986               # the zip extra field that pads a member's data to ALIGN (an unregistered id)
MESH_CELL_M = 1.0                    # the ground mesh's grid (metres)
MESH_REACH_M = 40.0                  # the ground mesh covers this far (horizontally) from every trajectory pose
MESH_BAND_M = 0.4                    # Gaussians this close to a frame's ground plane are ground
MESH_MIN_HITS = 3                    # a cell needs this many ground Gaussians to take their height
# a cell's height: this quantile of its ground Gaussians' heights. Against the shared PandaSet drive's LiDAR (flat
# cells: docs/simulators.md "Scene artifacts"): the median is unbiased (0.00 m, |error| 0.09 m), the 20 %
# quantile 7 cm low (the Gaussians scatter about the surface both ways, they do not rest on it)
MESH_QUANTILE = 0.5
MESH_PLANE_EVERY_M = 10.0            # a ground plane fitted around a trajectory pose every this many metres
CONTROLLABLE = "CONTROLLABLE"        # the flag of a track AlpaSim moves


class UsdzError(FieldError):
    """A scene that cannot be exported: ``field`` what is at fault ("scene_id", "drive.times_s")."""


@dataclass(frozen=True)
class UsdzReport:
    path: Path
    scene_id: str
    bytes: int
    gaussians: int
    frames: int
    cameras: int
    tracks: int
    mesh_vertices: int
    mesh_faces: int
    seconds: float
    notes: tuple[str, ...]

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "scene_id": self.scene_id, "bytes": self.bytes, "gaussians": self.gaussians,
                "frames": self.frames, "cameras": self.cameras, "tracks": self.tracks,
                "mesh": {"vertices": self.mesh_vertices, "faces": self.mesh_faces},
                "seconds": round(self.seconds, 3), "notes": list(self.notes)}


# ------------------------------------------------------------------------------------------- time and poses

def to_us(t_s: float) -> int:
    """Whole microseconds of ``t_s`` seconds (the rigs' clock), as the protocol's frame times are."""
    return int(round(float(t_s) * 1e6))


def window(t_us: int) -> list[int]:
    """[start, end] microseconds: the nominal exposure around ``t_us`` (2 x EXPOSURE_HALF_US), moved to start at 0
    for a time nearer 0 than half of it (a scene without a clock: AlpaSim keeps times unsigned)."""
    start = max(0, int(t_us) - EXPOSURE_HALF_US)
    return [start, start + 2 * EXPOSURE_HALF_US]


def pose_row(T: np.ndarray) -> list[float]:
    """[x, y, z, qx, qy, qz, qw] of a rigid [4, 4]: AlpaSim's track pose row (a scipy-order quaternion)."""
    w, x, y, z = (float(v) for v in rotmat_to_quat(np.asarray(T, np.float64)[:3, :3]))     # w >= 0
    return [*(float(v) for v in np.asarray(T, np.float64)[:3, 3]), x, y, z, w]


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T, np.float64)]


def camera_offsets(scene: Scene) -> dict[str, float]:
    """Each camera's time after its frame's (seconds): its ``timestamp_s`` minus the rig's, 0 when either is
    missing."""
    t0 = scene.rig.extra.get("timestamp_s")
    out = {}
    for cam in scene.rig.cameras:
        tc = cam.extra.get("timestamp_s")
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (t0, tc))
        out[cam.name] = float(tc) - float(t0) if ok else 0.0
    return out


# ------------------------------------------------------------------------------------------- the JSON parts

def rig_trajectories(scene: Scene, sequence_id: str) -> dict[str, Any]:
    """rig_trajectories.json (module docstring)."""
    times, poses = scene.timeline()
    us = [to_us(t) for t in times]
    if any(b <= a for a, b in zip(us, us[1:])):
        raise UsdzError("drive.times_s", f"the scene's frame times are not strictly increasing in whole "
                                         f"microseconds: {us[:8]}")
    E = _ego_to_world(scene)
    offsets = camera_offsets(scene)
    calibrations, frames = {}, {}
    for cam in scene.rig.cameras:
        calibrations[cam.name] = {
            "logical_sensor_name": cam.name,
            "T_sensor_rig": _matrix(cam.cam_to_ego),     # camera (OpenCV axes) -> rig (x forward, y left, z up)
            "resolution": [int(cam.width), int(cam.height)],
            "xyzcyl_camera": cam.to_dict(),              # the camera as rig.json writes it (K, lens, cam_to_ego)
        }
        frames[cam.name] = [window(to_us(t + offsets[cam.name])) for t in times]
    return {
        "world_to_nre": {"matrix": _matrix(np.linalg.inv(E))},
        "camera_calibrations": calibrations,
        "rig_trajectories": [{
            "sequence_id": sequence_id,
            "T_rig_world_timestamps_us": us,
            "T_rig_worlds": [_matrix(T) for T in poses],
            "cameras_frame_timestamps_us": frames,
            "rig_bbox": None,
        }],
    }


def sequence_tracks(scene: Scene, sequence_id: str) -> dict[str, Any]:
    """sequence_tracks.json (module docstring): the scene's actors (runtime.actors), each a track of its annotated
    poses (box -> world); an actor annotated once gets that pose at both ends of the span a render draws it in
    (its time +- half a frame interval: runtime.actors.Actors.at's slack), since a track needs two times."""
    ids, labels, flags, stamps, rows, dims = [], [], [], [], [], []
    a = scene.actors
    if a is not None and len(a):
        E = _ego_to_world(scene)
        slack = 0.5 * frame_interval(scene.drive["times_s"]) if scene.drive else 0.05
        for k, track in enumerate(a.track_id):
            m = np.flatnonzero(a.pose_track == k)
            order = m[np.argsort(a.pose_time[m], kind="stable")]
            us, poses = [], []
            for i in order:
                t = to_us(a.pose_time[i])
                if us and t <= us[-1]:
                    continue                            # one pose per microsecond (a track's times strictly rise)
                us.append(t)
                poses.append(E @ a.pose[i])
            if len(us) == 1:
                t, T = us[0], poses[0]
                us = [max(0, t - to_us(slack)), t + to_us(slack)]
                poses = [T, T]
            ids.append(track)
            labels.append(a.track_label[k])
            flags.append([CONTROLLABLE])
            stamps.append(us)
            rows.append([pose_row(T) for T in poses])
            dims.append([float(v) for v in a.track_size[k]])
    return {sequence_id: {
        "tracks_data": {"tracks_id": ids, "tracks_label_class": labels, "tracks_flags": flags,
                        "tracks_timestamps_us": stamps, "tracks_poses": rows},
        "cuboidtracks_data": {"cuboids_dims": dims},
    }}


def metadata(scene: Scene, scene_id: str, scene_json_sha256: str) -> dict[str, Any]:
    """metadata.yaml's mapping (module docstring)."""
    from xyzcyl.common.version import __version__

    times, _ = scene.timeline()
    created = (scene.created or "")[:10] or _dt.date.today().isoformat()
    return {
        "scene_id": scene_id,
        "version_string": f"{FORMAT_VERSION} (xyzcyl {__version__}; model {scene.model.get('name', '?')} "
                          f"{scene.model.get('version', '?')})",
        "training_date": created,
        "dataset_hash": scene_json_sha256,
        "uuid": str(uuid.uuid5(uuid.NAMESPACE_URL, f"xyzcyl:{scene_id}:{scene_json_sha256}")),
        "is_resumable": False,
        "sensors": {"camera_ids": [c.name for c in scene.rig.cameras], "lidar_ids": []},
        "logger": {"name": "xyzcyl", "run_id": None, "run_url": None},
        "time_range": {"start": window(to_us(times[0]))[0], "end": window(to_us(times[-1]))[1]},
    }


def _ego_to_world(scene: Scene) -> np.ndarray:
    """[4, 4] E: the scene frame -> world (the first frame's ego pose; identity without one)."""
    return np.asarray(scene.timeline()[1][0], np.float64)


# ------------------------------------------------------------------------------------------- the ground mesh

def ground_mesh(scene: Scene) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(vertices [V, 3] float32 metres, world frame; faces [F, 3] int32; notes) of the ground along the drive: a
    MESH_CELL_M grid over everything within MESH_REACH_M (horizontally) of the trajectory. Each cell's height is
    the MESH_QUANTILE quantile of the heights of the opaque Gaussians within MESH_BAND_M of the nearest fitted
    ground plane (a plane per MESH_PLANE_EVERY_M of trajectory: runtime.detail.fit_ground on the Gaussians around
    that pose, in its ego frame), then the median of its 3 x 3 neighbours that have one; the plane's height where
    fewer than MESH_MIN_HITS Gaussians say otherwise."""
    from .detail import fit_ground

    notes: list[str] = []
    E = _ego_to_world(scene)
    _, world_poses = scene.timeline()
    poses = np.linalg.inv(E)[None] @ world_poses                 # ego -> scene frame per frame
    g = scene.gaussians
    opaque = g.opacities >= 0.5
    p = np.asarray(g.means, np.float64)[opaque]
    # the poses a plane is fitted at: the first, then one every MESH_PLANE_EVERY_M travelled
    centres = poses[:, :3, 3]
    picks, last = [0], centres[0]
    for i in range(1, len(centres)):
        if np.linalg.norm(centres[i] - last) >= MESH_PLANE_EVERY_M:
            picks.append(i)
            last = centres[i]
    planes = []                                                   # (xy of the pose, plane in the scene frame)
    for i in picks:
        T = poses[i]
        local = (p - T[:3, 3]) @ T[:3, :3]
        plane = fit_ground(local)
        if plane is None:
            continue
        n = T[:3, :3] @ plane[:3]
        planes.append((T[:2, 3], np.array([*n, plane[3] - n @ T[:3, 3]])))
    if not planes:
        near = p[np.hypot(*(p[:, :2] - centres[0, :2]).T) <= MESH_REACH_M] if len(p) else p
        z = float(np.percentile(near[:, 2], 5)) if len(near) else float(centres[0, 2])
        planes = [(centres[0, :2], np.array([0.0, 0.0, 1.0, -z]))]
        notes.append(f"no ground plane found in the Gaussians: the mesh is the level z = {z:.2f} m (scene frame)")
    # the grid
    lo = centres[:, :2].min(axis=0) - MESH_REACH_M
    hi = centres[:, :2].max(axis=0) + MESH_REACH_M
    nx, ny = (np.ceil((hi - lo) / MESH_CELL_M).astype(int) + 1)
    gx, gy = np.meshgrid(lo[0] + MESH_CELL_M * np.arange(nx), lo[1] + MESH_CELL_M * np.arange(ny), indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    # inside: within reach of some pose (a coarse trajectory: one pose per metre is plenty)
    keep, last = [centres[0, :2]], centres[0, :2]
    for c in centres[1:, :2]:
        if np.linalg.norm(c - last) >= 1.0:
            keep.append(c)
            last = c
    track = np.array(keep)
    inside = np.zeros(len(xy), bool)
    for c in track:
        inside |= np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1]) <= MESH_REACH_M
    # each vertex's plane: the nearest fitted one
    anchors = np.array([a for a, _ in planes])
    nearest = np.argmin(((xy[:, None, :] - anchors[None]) ** 2).sum(-1), axis=1)
    pl = np.array([q for _, q in planes])[nearest]                # [V, 4]
    z_plane = -(pl[:, 0] * xy[:, 0] + pl[:, 1] * xy[:, 1] + pl[:, 3]) / pl[:, 2]
    # the Gaussians' heights per vertex cell (the cell centred on the vertex)
    cell = np.floor((p[:, :2] - lo) / MESH_CELL_M + 0.5).astype(np.int64)
    ok = np.all((cell >= 0) & (cell < [nx, ny]), axis=1)
    idx = cell[ok, 0] * ny + cell[ok, 1]
    zs = p[ok, 2]
    band = np.abs(zs - z_plane[idx]) <= MESH_BAND_M
    idx, zs = idx[band], zs[band]
    z = z_plane.copy()
    if len(idx):
        order = np.lexsort((zs, idx))                      # by cell, then height
        idx, zs = idx[order], zs[order]
        starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
        counts = np.diff(np.r_[starts, len(idx)])
        ok = counts >= MESH_MIN_HITS
        pick = starts[ok] + (MESH_QUANTILE * (counts[ok] - 1)).astype(np.int64)
        z[idx[starts[ok]]] = zs[pick]
        # a 3 x 3 median over the cells that had Gaussians: one cell's outlier (a low wall's foot) does not dent it
        grid_z = np.full((nx, ny), np.nan)
        grid_z.ravel()[idx[starts[ok]]] = zs[pick]
        pad = np.pad(grid_z, 1, constant_values=np.nan)
        stack = np.stack([pad[i:i + nx, j:j + ny] for i in range(3) for j in range(3)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)          # all-NaN windows: cells without Gaussians
            smooth = np.nanmedian(stack, axis=0).ravel()
        has = np.isfinite(grid_z.ravel())
        z[has] = smooth[has]
    # vertices inside, faces: two triangles per grid square whose four corners are inside (counter-clockwise
    # seen from above: normals up)
    vid = np.full(len(xy), -1, np.int64)
    vid[inside] = np.arange(int(inside.sum()))
    v = np.stack([xy[inside, 0], xy[inside, 1], z[inside]], axis=1)
    grid = vid.reshape(nx, ny)
    a, b, c, d = grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]
    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.stack([a[full], b[full], c[full]], 1), np.stack([a[full], c[full], d[full]], 1)])
    world = v @ E[:3, :3].T + E[:3, 3]
    return world.astype(np.float32), faces.astype(np.int32), notes


def mesh_ply(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary little-endian PLY of a triangle mesh (vertex x, y, z float; face vertex_indices uchar/int)."""
    from plyfile import PlyData, PlyElement

    vert = np.empty(len(vertices), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    vert["x"], vert["y"], vert["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    face = np.empty(len(faces), [("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")], byte_order="<",
            comments=["xyzcyl ground mesh: metres, the world frame of the artifact's trajectory, z up"]).write(buf)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------- the NuRec volume

def nurec_state(g: Gaussians) -> dict[str, Any]:
    """The NuRec template (module docstring) of ``g`` (scene frame): the layout's tensors as float16 bytes with
    their shapes; pre-activation values (logit opacity, log scale, unnormalised wxyz rotation) as in a 3DGS PLY,
    with the activations named in the config."""
    n = len(g)
    f16 = np.float16
    sh = np.asarray(g.sh, np.float32)
    spec = np.zeros((n, NUREC_SH_COLUMNS, 3), np.float32)         # [N, coefficient, colour], degree 3 layout
    spec[:, :sh.shape[1] - 1] = sh[:, 1:]
    tensors = {
        "positions": np.asarray(g.means, np.float32),
        "rotations": np.asarray(g.quats, np.float32),
        "scales": np.asarray(g.log_scales, np.float32),
        "densities": np.asarray(g.opacity_logits, np.float32)[:, None],
        "features_albedo": sh[:, 0, :],
        "features_specular": spec.reshape(n, NUREC_SH_COLUMNS * 3),
        "extra_signal": np.zeros((n, 0), np.float32),
    }
    state: dict[str, Any] = {"._extra_state": {"obj_track_ids": {"gaussians": []}}}
    for name, arr in tensors.items():
        key = f".gaussians_nodes.gaussians.{name}"
        state[key] = np.ascontiguousarray(arr.astype(f16)).tobytes()
        state[key + ".shape"] = list(arr.shape)
    state[".gaussians_nodes.gaussians.n_active_features"] = np.array([g.sh_degree], np.int64).tobytes()
    state[".gaussians_nodes.gaussians.n_active_features.shape"] = []
    return {"nre_data": {
        "version": NUREC_VERSION,
        "model": "nre",
        "config": {"layers": {"gaussians": {
            "name": "sh-gaussians", "density_activation": "sigmoid", "scale_activation": "exp",
            "rotation_activation": "normalize", "precision": 16,
            "particle": {"radiance_sph_degree": 3}}},
            "name": "gaussians_primitive",
            "producer": f"xyzcyl ({FORMAT_VERSION})"},
        "state_dict": state,
    }}


def nurec_bytes(g: Gaussians) -> bytes:
    """The `.nurec` file: gzip of the msgpack of nurec_state (ISA-L's gzip at its fastest level: the specular
    zeros and the float16 bytes shrink the same at any level)."""
    import msgpack
    from isal import igzip

    return igzip.compress(msgpack.packb(nurec_state(g), use_bin_type=True), compresslevel=1)


def _usda_header() -> str:
    return '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Z"\n)\n\n'


def _tuple(v) -> str:
    return "(" + ", ".join(repr(float(x)) for x in v) + ")"


def gauss_usda(nurec_name: str, E: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> str:
    """gauss.usda: the NuRec volume prim /World/gauss, its transform E (the volume's scene frame -> world; USD
    multiplies row vectors, so the matrix written is E transposed), its extent [lo, hi] (volume frame, metres) and
    its two fields naming ``nurec_name``."""
    rows = ", ".join(_tuple(r) for r in np.asarray(E, np.float64).T)
    field = ('        def OmniNuRecFieldAsset "{name}_field"\n        {{\n'
             '            asset filePath = @./{file}@\n'
             '            token fieldName = "{field}"\n'
             '            token fieldDataType = "{dtype}"\n'
             '            token fieldRole = "{field}"\n{extra}        }}\n')
    ccm = "".join(f"            float4 omni:nurec:ccm{c} = {_tuple(v)}\n"
                  for c, v in zip("RGB", np.eye(4)[:3]))
    return (_usda_header()
            + 'def Xform "World"\n{\n'
            + '    def Volume "gauss"\n    {\n'
            + f"        float3[] extent = [{_tuple(lo)}, {_tuple(hi)}]\n"
            + "        rel field:density = </World/gauss/density_field>\n"
            + "        rel field:emissiveColor = </World/gauss/emissive_color_field>\n"
            + "        bool omni:nurec:isNuRecVolume = 1\n"
            + "        bool omni:nurec:useProxyTransform = 0\n"
            + "        float3 omni:nurec:offset = (0, 0, 0)\n"
            + f"        float3 omni:nurec:crop:minBounds = {_tuple(lo)}\n"
            + f"        float3 omni:nurec:crop:maxBounds = {_tuple(hi)}\n"
            + "        rel proxy\n"
            + f"        matrix4d xformOp:transform = ({rows})\n"
            + '        uniform token[] xformOpOrder = ["xformOp:transform"]\n\n'
            + field.format(name="density", file=nurec_name, field="density", dtype="float", extra="")
            + "\n"
            + field.format(name="emissive_color", file=nurec_name, field="emissiveColor", dtype="float3",
                           extra=ccm)
            + "    }\n}\n")


def default_usda() -> str:
    """default.usda: the root layer (first in the archive): /World/gauss references gauss.usda."""
    return (_usda_header() + 'def Xform "World"\n{\n'
            + '    over "gauss" (\n        prepend references = @./gauss.usda@\n    )\n    {\n    }\n}\n')


# ------------------------------------------------------------------------------------------- the archive

def write_zip(parts: list[tuple[str, bytes]], out: Path) -> int:
    """Write ``parts`` (name, bytes; the first is the root layer) uncompressed, each member's data at a multiple
    of ALIGN bytes (the USDZ rules), to ``out`` atomically (a temporary file beside it, then a rename). Bytes."""
    out = Path(out)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh, zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_STORED) as zf:
            for name, data in parts:
                info = zipfile.ZipInfo(name, date_time=(2000, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_STORED
                start = fh.tell() + 30 + len(name.encode("utf-8"))
                pad = -start % ALIGN
                if pad:
                    pad += ALIGN if pad < 4 else 0          # an extra field is at least its 4-byte header
                    info.extra = struct.pack("<HH", PAD_HEADER_ID, pad - 4) + bytes(pad - 4)
                zf.writestr(info, data)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out.stat().st_size


def export_usdz(folder: str | os.PathLike, out: str | os.PathLike, scene_id: str | None = None,
                progress: Callable[[str], None] | None = None) -> UsdzReport:
    """Write the scene folder ``folder`` as an AlpaSim scene artifact at ``out`` (module docstring). ``scene_id``:
    the id AlpaSim asks the renderer for (the gRPC front end lists a served scene's name, else its id); default
    the folder's name. SceneError for a folder that is not a scene; UsdzError for one that cannot be exported."""
    import time

    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    d = Path(folder)
    sid = scene_id if scene_id is not None else d.resolve().name
    if not sid or len(sid) > 256 or any(ord(ch) < 32 for ch in sid):
        raise UsdzError("scene_id", f"1-256 printable characters (got {sid[:80]!r})")
    say("reading the scene")
    scene = Scene.load(d)
    notes: list[str] = []
    if not scene.drive:
        notes.append("not a drive: the trajectory is the scene's one frame")
    sha = hashlib.sha256((d / "scene.json").read_bytes()).hexdigest()
    say("writing the trajectory, cameras and tracks")
    rig = rig_trajectories(scene, sid)
    tracks = sequence_tracks(scene, sid)
    meta = metadata(scene, sid, sha)
    say("fitting the ground mesh")
    verts, faces, mesh_notes = ground_mesh(scene)
    notes += mesh_notes
    mesh = mesh_ply(verts, faces)
    say(f"packing {len(scene.gaussians):,} Gaussians (float16, gzip)")
    nurec = nurec_bytes(scene.gaussians)
    means = np.asarray(scene.gaussians.means, np.float64)
    lo, hi = (means.min(axis=0), means.max(axis=0)) if len(means) else (np.zeros(3), np.zeros(3))
    parts = [
        ("default.usda", default_usda().encode()),
        ("gauss.usda", gauss_usda(NUREC_NAME, _ego_to_world(scene), lo, hi).encode()),
        (NUREC_NAME, nurec),
        ("metadata.yaml", (json.dumps(meta, indent=1) + "\n").encode()),
        ("rig_trajectories.json", json.dumps(rig).encode()),
        ("sequence_tracks.json", json.dumps(tracks).encode()),
        ("mesh_ground.ply", mesh),
        ("mesh.ply", mesh),
    ]
    say(f"writing {out}")
    size = write_zip(parts, Path(out))
    traj = rig["rig_trajectories"][0]
    return UsdzReport(path=Path(out), scene_id=sid, bytes=size, gaussians=len(scene.gaussians),
                      frames=len(traj["T_rig_world_timestamps_us"]), cameras=len(rig["camera_calibrations"]),
                      tracks=len(tracks[sid]["tracks_data"]["tracks_id"]), mesh_vertices=len(verts),
                      mesh_faces=len(faces), seconds=time.perf_counter() - t0, notes=tuple(notes))


__all__ = ["ALIGN", "CONTROLLABLE", "EXPOSURE_HALF_US", "FORMAT_VERSION", "NUREC_NAME", "UsdzError", "UsdzReport",
           "default_usda", "export_usdz", "gauss_usda", "ground_mesh", "mesh_ply", "metadata", "nurec_bytes",
           "nurec_state", "pose_row", "rig_trajectories", "sequence_tracks", "to_us", "window", "write_zip"]
