"""`xyzcyl export --format usdz` of a scene folder, measured (runtime.usdz; docs/simulators.md "Scene artifacts"): the
export's time and size, and with --drive the ground mesh against the drive's LiDAR; --picture draws the artifact read
back from the .usdz alone (the ground mesh coloured by height, the rig's trajectory, the tracks' boxes and paths).
Prints one JSON line.

    NUMBA_CACHE_DIR=/tmp/nc .venv/bin/python benchmarks/usdz_bench.py SCENE_DIR --out /tmp/scene.usdz \\
        --drive ../shared/data/real/pandaset_002_drive --picture docs/pictures/usdz_pandaset_topdown.jpg

The mesh check: the LiDAR returns of every --every-th frame (each frame's rig.json `lidar` file, taken to the world
frame by its `ego_to_world`), binned in 1 m cells centred on the mesh's vertices; a cell counts where it holds at
least MIN_RETURNS returns and looks flat (its median return at most FLAT_M above its 20 % one: road, not a kerb, a
car or a wall); the error is the vertex's height minus that 20 % height."""

from __future__ import annotations

import argparse
import io
import json
import sys
import zipfile
from pathlib import Path

import numpy as np

MIN_RETURNS = 10
FLAT_M = 0.1


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", metavar="SCENE_DIR")
    p.add_argument("--out", required=True, metavar="FILE.usdz")
    p.add_argument("--scene-id", default=None)
    p.add_argument("--drive", default=None, metavar="DIR", help="a drive folder whose frames name LiDAR sweeps")
    p.add_argument("--every", type=int, default=4, help="with --drive: every N-th frame's sweep (default 4)")
    p.add_argument("--picture", default=None, metavar="FILE.jpg")
    a = p.parse_args(argv)
    if a.every < 1:
        p.error(f"--every: must be >= 1 (got {a.every})")
    return a


def mesh_of(z: zipfile.ZipFile) -> tuple[np.ndarray, np.ndarray]:
    from plyfile import PlyData

    ply = PlyData.read(io.BytesIO(z.read("mesh_ground.ply")))
    v = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(np.float64)
    return v, np.stack(ply["face"]["vertex_indices"]).astype(np.int64)


def _cell(xy: np.ndarray) -> np.ndarray:
    """[N] int64 key of the 1 m cell centred on the nearest whole metre."""
    k = np.floor(xy + 0.5).astype(np.int64)
    return k[:, 0] * (1 << 32) + (k[:, 1] & 0xFFFFFFFF)


def mesh_against_lidar(v: np.ndarray, drive: Path, every: int) -> dict:
    doc = json.loads((drive / "drive.json").read_text())
    pts = []
    for entry in doc["frames"][::every]:
        rig_path = drive / entry["rig"]
        rig = json.loads(rig_path.read_text())
        if not rig.get("lidar"):
            continue
        E = np.asarray(rig["ego_to_world"], np.float64)
        p = np.load(rig_path.parent / rig["lidar"]["file"])[:, :3].astype(np.float64)
        p = p[np.all(np.isfinite(p), axis=1)]
        pts.append(p @ E[:3, :3].T + E[:3, 3])
    if not pts:
        raise SystemExit("--drive: no frame with a LiDAR sweep")
    p = np.concatenate(pts)
    key = _cell(p[:, :2])
    order = np.lexsort((p[:, 2], key))
    key, z = key[order], p[order, 2]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    count = np.diff(np.r_[start, len(key)])
    low, mid = z[start + (0.2 * (count - 1)).astype(int)], z[start + (0.5 * (count - 1)).astype(int)]
    ok = (count >= MIN_RETURNS) & (mid - low <= FLAT_M)
    ref = dict(zip(key[start][ok].tolist(), low[ok].tolist()))
    kv = _cell(v[:, :2]).tolist()
    d = np.array([v[i, 2] - ref[k] for i, k in enumerate(kv) if k in ref])
    if not len(d):
        return {"vertices_compared": 0}
    return {"vertices_compared": int(len(d)), "median_error_m": round(float(np.median(d)), 3),
            "median_abs_error_m": round(float(np.median(np.abs(d))), 3),
            "p90_abs_error_m": round(float(np.percentile(np.abs(d), 90)), 3),
            "share_within_0.1m": round(float((np.abs(d) <= 0.1).mean()), 3)}


def picture(z: zipfile.ZipFile, v: np.ndarray, f: np.ndarray, path: Path, px_per_m: float = 10.0) -> None:
    import cv2

    (traj,) = json.loads(z.read("rig_trajectories.json"))["rig_trajectories"]
    P = np.asarray(traj["T_rig_worlds"], np.float64)
    tracks = json.loads(z.read("sequence_tracks.json"))
    sid = next(iter(tracks))
    data, dims = tracks[sid]["tracks_data"], tracks[sid]["cuboidtracks_data"]["cuboids_dims"]
    lo, hi = v[:, :2].min(0) - 2, v[:, :2].max(0) + 2
    W, H = int((hi[0] - lo[0]) * px_per_m), int((hi[1] - lo[1]) * px_per_m)

    def px(xy):
        return np.stack([(xy[:, 0] - lo[0]) * px_per_m, (hi[1] - xy[:, 1]) * px_per_m], 1).astype(np.int32)

    img = np.zeros((H, W, 3), np.uint8)
    z0, z1 = np.percentile(v[:, 2], [2, 98])
    shade = np.clip((v[:, 2] - z0) / max(z1 - z0, 1e-3), 0, 1)
    for tri in f:
        c = cv2.applyColorMap(np.uint8([[shade[tri].mean() * 255]]), cv2.COLORMAP_VIRIDIS)[0, 0]
        cv2.fillConvexPoly(img, px(v[tri, :2]), (0.6 * c).astype(int).tolist())
    for rows, dim, label in zip(data["tracks_poses"], dims, data["tracks_label_class"]):
        rows = np.asarray(rows, np.float64)
        cv2.polylines(img, [px(rows[:, :2])], False, (0, 200, 255), 1)
        x, y, _, qx, qy, qz, qw = rows[0]
        yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        c, s, L, Wd = np.cos(yaw), np.sin(yaw), dim[0] / 2, dim[1] / 2
        box = np.array([[x + c * a - s * b, y + s * a + c * b] for a, b in ((L, Wd), (L, -Wd), (-L, -Wd), (-L, Wd))])
        cv2.polylines(img, [px(box)], True, (0, 140, 255) if label != "moved" else (180, 180, 180), 2)
    cv2.polylines(img, [px(P[:, :2, 3])], False, (255, 255, 255), 3)
    cv2.circle(img, tuple(int(t) for t in px(P[:1, :2, 3])[0]), 6, (255, 255, 255), -1)
    for i, text in enumerate((f"{sid}: the ground mesh ({len(v)} vertices; height {z0:.2f}..{z1:.2f} m, dark to light)",
                              f"the rig trajectory (white, {len(P)} poses), {len(data['tracks_id'])} tracks (orange: "
                              "box at the first pose, path; grey: untracked 'moved')")):
        cv2.putText(img, text, (10, 22 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 85])


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    from xyzcyl.runtime.usdz import export_usdz

    report = export_usdz(a.scene, a.out, a.scene_id)
    doc = report.to_json()
    z = zipfile.ZipFile(a.out)
    doc["members"] = {i.filename: i.file_size for i in z.infolist()}
    v, f = mesh_of(z)
    if a.drive:
        doc["mesh_against_lidar"] = mesh_against_lidar(v, Path(a.drive), a.every)
    if a.picture:
        picture(z, v, f, Path(a.picture))
        doc["picture"] = a.picture
    json.dump(doc, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
