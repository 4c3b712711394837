"""Drive speed benchmark (issue 37's speed targets): a recorded drive reconstructed from N keyframes, and 1920x1080
views rendered along it, each in a child process of its own (peak RSS from the child's getrusage). One JSON line
per case:

- ``reconstruct``: `xyzcyl reconstruct DRIVE --keyframes ...` (default: every 2nd frame of the shared PandaSet drive,
  20 keyframes of six 1920x1080 cameras + LiDAR): seconds in all and per keyframe, the scene's stage times
  (scene.json timings), Gaussians, peak RSS.
- ``render``: the scene seen by each input camera of the keyframes at 10 places along the drive, at 1920x1080, at the
  keyframe's time and halfway to the next (Scene.render, what `xyzcyl render` and the service draw): median, max;
  after the file system's dirty pages are written (os.sync: the scene was written just before).

    .venv/bin/python benchmarks/drive_bench.py [--drive D] [--every 2] [--work /tmp/xyzcyl-drive-bench]
        [--threads 2] [--workers N] [--baseline DIR]

With --baseline DIR (DIR/xyzcyl: an older tree, e.g. `git archive <commit> | tar -x -C DIR/xyzcyl`), both cases run
again with that tree right after, and a ``ratio`` line gives baseline / now.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_DRIVE = HERE.parent.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"

CHILD = r"""
import dataclasses, json, resource, statistics, sys, time
import numba
import numpy as np
case, drive, out, every, threads, workers = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
numba.set_num_threads(threads)
from xyzcyl.runtime.drive import load_drive, reconstruct_drive
from xyzcyl.runtime.scene import Scene
d = load_drive(drive)
keys = list(range(0, len(d), every))
if case == "reconstruct":
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.model_folder import default_model_dir
    rec = Reconstructor.load(default_model_dir(), threads=threads)
    extra = {} if workers == "-" else {"workers": int(workers)}
    t0 = time.perf_counter()
    scene = reconstruct_drive(rec, d, keys, **extra)
    t1 = time.perf_counter()
    scene.save(out)
    r = {"case": "reconstruct", "keyframes": len(keys), "seconds": round(t1 - t0, 2),
         "per_keyframe_s": round((t1 - t0) / len(keys), 3), "save_s": round(time.perf_counter() - t1, 2),
         "gaussians": len(scene.gaussians), "chunk_gaussians": scene.viewpoints.count if scene.viewpoints else 0,
         "timings": scene.timings}
else:
    scene = Scene.load(out)
    cams, times = [], []
    for k in keys[:: max(1, len(keys) // 10)]:
        T = d.relative(k)
        t_next = d.frames[min(k + every, len(d) - 1)].timestamp_s
        for cam in d.frames[k].rig.cameras:
            c = dataclasses.replace(cam, cam_to_ego=T @ np.asarray(cam.cam_to_ego))
            cams.append(c if (c.width, c.height) == (1920, 1080) else c.resized(1920, 1080))
            times.append(0.5 * (d.frames[k].timestamp_s + t_next))
    scene.render(cams[0], time_s=times[0])          # warm-up: kernels loaded, chunks read
    ts = []
    for c, t in zip(cams, times):
        t0 = time.perf_counter()
        scene.render(c, time_s=t)
        ts.append(time.perf_counter() - t0)
    r = {"case": "render", "views": len(ts), "width": 1920, "height": 1080,
         "median_s": round(statistics.median(ts), 4), "max_s": round(max(ts), 4), "min_s": round(min(ts), 4)}
r["peak_rss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 2)
print(json.dumps(r))
"""


def run(tree: Path | None, case: str, args, out: Path) -> dict:
    """One case in a child process: the installed xyzcyl (tree None) or the one in tree/xyzcyl (PYTHONPATH)."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    workers = "-" if args.workers is None or tree is not None else str(args.workers)
    p = subprocess.run([sys.executable, "-c", CHILD, case, str(args.drive), str(out), str(args.every),
                        str(args.threads), workers], capture_output=True, text=True, env=env)
    if p.returncode:
        sys.stderr.write(p.stderr[-4000:])
        raise SystemExit(f"{case} failed ({'installed' if tree is None else tree})")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drive", type=Path, default=DEFAULT_DRIVE)
    ap.add_argument("--every", type=int, default=2, help="keyframes: every Nth frame (default 2: 20 of 40)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "xyzcyl-drive-bench")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--workers", type=int, default=None,
                    help="keyframe worker processes (default: the runtime's; not passed to --baseline)")
    ap.add_argument("--baseline", type=Path, default=None, help="DIR with an older tree in DIR/xyzcyl")
    args = ap.parse_args()
    if not args.drive.exists():
        raise SystemExit(f"no drive at {args.drive} (--drive)")
    trees: list[tuple[str, Path | None]] = [("now", None)]
    if args.baseline is not None:
        trees.append(("baseline", args.baseline.resolve()))
    results = {}
    for name, tree in trees:
        out = args.work / name
        for case in ("reconstruct", "render"):
            if case == "render":
                # the scene just written (~9 GB for 20 keyframes) flushed to disk first: the kernel's writeback of
                # it made the views 0.61 s instead of 0.48-0.50 (docs/results.md "Drives: camera layers")
                os.sync()
            r = run(tree, case, args, out)
            r["tree"] = name
            results[(name, case)] = r
            print(json.dumps(r), flush=True)
    if args.baseline is not None:
        ratio = {"case": "ratio", "what": "baseline / now",
                 "reconstruct_s": round(results[("baseline", "reconstruct")]["seconds"]
                                        / results[("now", "reconstruct")]["seconds"], 2),
                 "render_median_s": round(results[("baseline", "render")]["median_s"]
                                          / results[("now", "render")]["median_s"], 2)}
        print(json.dumps(ratio), flush=True)


if __name__ == "__main__":
    main()
