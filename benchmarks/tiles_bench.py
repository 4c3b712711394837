"""Tiles benchmark (issue 37 item 6: a long drive served within a server's memory): a long drive's scene, and views
along it drawn from its folder read tile by tile (runtime.tiles) against the same scene read whole. One JSON line
per case, each case in a child process of its own (peak RSS from its getrusage):

- ``build``: a long drive made from a real drive's scene folder (SCENE, e.g. `xyzcyl reconstruct` of the shared
  PandaSet drive): its shared Gaussians and keyframes repeated ``--copies`` times ``--spacing`` metres apart along
  x (the scene's forward axis), as if the car had driven on through ``--copies`` such streets; its viewpoint chunks
  and actors left out (they are read per view already). Not a reconstruction: a scene of a long drive's size and
  density, built in seconds. Its Gaussians, tiles and folder size.
- ``tiles``: Scene.load of that folder (tiles read as views need them), then the six input cameras of the first
  keyframe seen from each copy's place along the drive (1920x1080, the input cameras' own size): per view seconds
  (median, max: the views that read new tiles), the tiles and bytes held, the process's peak RSS (VmHWM, Linux).
- ``whole``: the same views of the same folder after reading the whole set (Scene.gaussians), what the service did
  before the tiles.

    .venv/bin/python benchmarks/tiles_bench.py SCENE [--copies 8] [--spacing 60] [--work /tmp/xyzcyl-tiles-bench]
        [--horizon M] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import dataclasses, json, statistics, sys, time
import numpy as np
from xyzcyl.runtime.scene import Scene

case, folder, copies, spacing = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
if sys.argv[5] != "-":              # --horizon: another than the runtime's (runtime.tiles.HORIZON_M)
    import xyzcyl.runtime.scene as S
    S.HORIZON_M = float(sys.argv[5])
t0 = time.perf_counter()
scene = Scene.load(folder)
load_s = time.perf_counter() - t0
if case == "whole":
    t0 = time.perf_counter()
    len(scene.gaussians)
    load_s += time.perf_counter() - t0
keys = scene.drive["keyframes"]
per_copy = len(keys) // copies
poses = np.asarray(scene.drive["trajectory"], np.float64).reshape(-1, 4, 4)
ts = []
for i in range(copies):
    k = keys[i * per_copy]
    for cam in scene.rig.cameras:
        c = dataclasses.replace(cam, cam_to_ego=poses[k] @ np.asarray(cam.cam_to_ego))
        t0 = time.perf_counter()
        scene.render(c, time_s=scene.drive["timestamp_s"] + scene.drive["times_s"][k])
        ts.append(time.perf_counter() - t0)
tiles = scene.tiles
r = {"case": case, "horizon_m": __import__("xyzcyl.runtime.scene").runtime.scene.HORIZON_M, "views": len(ts), "load_s": round(load_s, 3), "median_s": round(statistics.median(ts), 4),
     "max_s": round(max(ts), 4), "first_s": round(ts[0], 4),
     "tiles_held": len(tiles._cache) if tiles.lazy else len(tiles), "tiles": len(tiles),
     "held_gb": round((tiles.held_bytes if tiles.lazy else 56 * tiles.count) / 1e9, 3),
     # VmHWM: this process's own peak (getrusage's ru_maxrss keeps the parent's across fork and exec, and the
     # parent held the whole long drive while it built it)
     "peak_rss_gb": round(int(next(l.split()[1] for l in open("/proc/self/status") if l.startswith("VmHWM"))) / 1e6,
                          2)}
print(json.dumps(r))
"""


def build(scene_dir: Path, out: Path, copies: int, spacing: float) -> dict:
    """The long drive's folder (module docstring): SCENE's shared Gaussians and keyframes, ``copies`` times along x."""
    import numpy as np
    from xyzcyl.runtime.detail import concat_gaussians
    from xyzcyl.runtime.scene import Scene

    s = Scene.load(scene_dir)
    if s.keyframe_of is None or not s.drive:
        raise SystemExit(f"{scene_dir}: not a drive's scene of several keyframes")
    g, kf, d = s.gaussians, np.asarray(s.keyframe_of, np.int64), s.drive
    n_frames, n_keys = int(d["frames"]), len(d["keyframes"])
    traj = np.asarray(d["trajectory"], np.float64).reshape(-1, 4, 4)
    period = float(d["times_s"][-1]) + 0.1
    parts, kfs, trajs, times, keys = [], [], [], [], []
    for i in range(copies):
        shift = np.array([i * spacing, 0.0, 0.0], np.float32)
        parts.append(type(g)(g.means + shift, g.quats, g.log_scales, g.opacity_logits, g.sh))
        kfs.append(kf + i * n_keys)
        t = traj.copy()
        t[:, 0, 3] += i * spacing
        trajs.append(t)
        times += [float(x) + i * period for x in d["times_s"]]
        keys += [int(k) + i * n_frames for k in d["keyframes"]]
    drive = {**{k: v for k, v in d.items() if k != "exposure"}, "frames": n_frames * copies, "keyframes": keys,
             "times_s": times, "trajectory": np.concatenate(trajs).tolist(), "tracks": 0}
    long = Scene(gaussians=concat_gaussians(parts), background=s.background, rig=s.rig, model=s.model,
                 counts={"total": len(g) * copies}, drive=drive, keyframe_of=np.concatenate(kfs).astype(np.int16))
    long.save(out)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return {"case": "build", "copies": copies, "spacing_m": spacing, "road_m": round(copies * spacing, 1),
            "gaussians": len(long.gaussians), "keyframes": len(keys), "tiles": len(long.tiles),
            "folder_gb": round(size / 1e9, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a drive's scene folder (xyzcyl reconstruct DRIVE --out SCENE)")
    ap.add_argument("--copies", type=int, default=8)
    ap.add_argument("--spacing", type=float, default=60.0, help="metres between the copies along x")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "xyzcyl-tiles-bench")
    ap.add_argument("--horizon", type=float, default=None,
                    help="metres: draw other keyframes only this near (default the runtime's HORIZON_M; 1e9: none)")
    ap.add_argument("--reuse", action="store_true", help="keep WORK/long when it was built before (same options)")
    args = ap.parse_args()
    if args.copies < 1 or args.spacing <= 0:
        raise SystemExit("--copies must be >= 1 and --spacing > 0")
    if not (args.scene / "scene.json").is_file():
        raise SystemExit(f"no scene folder at {args.scene}")
    out = args.work / "long"
    if not args.reuse or not (out / "scene.json").is_file():
        print(json.dumps(build(args.scene, out, args.copies, args.spacing)), flush=True)
    for case in ("tiles", "whole"):
        p = subprocess.run([sys.executable, "-c", CHILD, case, str(out), str(args.copies), str(args.spacing),
                            "-" if args.horizon is None else str(args.horizon)],
                           capture_output=True, text=True)
        if p.returncode:
            sys.stderr.write(p.stderr[-4000:])
            raise SystemExit(f"{case} failed")
        print(p.stdout.strip().splitlines()[-1], flush=True)


if __name__ == "__main__":
    main()
