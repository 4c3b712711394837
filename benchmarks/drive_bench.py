"""Drive speed benchmark (issue 37's speed targets): a recorded drive reconstructed from N keyframes, and 1920x1080
views rendered along it, each in a child process of its own (peak RSS from the child's getrusage). One JSON line
per case:

- ``reconstruct``: `xyzcyl reconstruct DRIVE --keyframes ...` (default: every 2nd frame of the shared PandaSet drive,
  20 keyframes of six 1920x1080 cameras + LiDAR): seconds in all and per keyframe, the scene's stage times
  (scene.json timings), Gaussians, peak RSS.
- ``render``: the scene seen by each input camera of the keyframes at 10 places along the drive, at 1920x1080, at the
  keyframe's time and halfway to the next (Scene.render, what `xyzcyl render` and the service draw): median, max;
  after the file system's dirty pages are written (os.sync: the scene was written just before).
- ``sequence``: what a simulator replaying the drive asks: the six input cameras at every frame, in time order, at
  the frame's time (1920x1080): median, p90, p99, max, views over 0.6 s and the loop's seconds. A view whose primary
  keyframe changed reads that keyframe's viewpoint chunk (runtime.viewpoints): the spikes are those reads.

With ``--cases render,sequence`` a scene already in WORK/now (and WORK/baseline) is drawn again without rebuilding it.

    .venv/bin/python benchmarks/drive_bench.py [--drive D] [--every 2] [--work /tmp/xyzcyl-drive-bench]
        [--threads 2] [--workers N] [--baseline DIR] [--rounds 1] [--cases reconstruct,render,sequence]

With --baseline DIR (DIR/xyzcyl: an older tree, e.g. `git archive <commit> | tar -x -C DIR/xyzcyl`), the cases run
again with that tree, and a ``ratio`` line gives baseline / now. ``--rounds N`` reconstructs N times a tree in ABBA
order (now, baseline, baseline, now, ...; the ratio from the medians): on a machine whose speed drifts, the tree run
second in every pair looked 8-21 % faster than in the other order (docs/results.md "Speed, session of 2026-12-03
(night)"). Every case starts after os.sync().
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CASES = ("reconstruct", "render", "sequence")
DEFAULT_DRIVE = HERE.parent.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"

CHILD = r"""
import dataclasses, json, resource, statistics, sys, time
try:                        # the C heap as the `xyzcyl` command sets it, before numpy starts threads (runtime.heap)
    from xyzcyl.runtime.heap import keep_freed_memory
    keep_freed_memory()
except ImportError:         # an older tree: glibc's defaults
    pass
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
    if case == "sequence":          # every frame's six cameras in time order, at the frame's time
        places = [(f, d.frames[f].timestamp_s) for f in range(len(d))]
    else:                           # 10 keyframes, halfway to the next keyframe's time
        places = [(k, 0.5 * (d.frames[k].timestamp_s + d.frames[min(k + every, len(d) - 1)].timestamp_s))
                  for k in keys[:: max(1, len(keys) // 10)]]
    cams, times = [], []
    for f, t in places:
        T = d.relative(f)
        for cam in d.frames[f].rig.cameras:
            c = dataclasses.replace(cam, cam_to_ego=T @ np.asarray(cam.cam_to_ego))
            cams.append(c if (c.width, c.height) == (1920, 1080) else c.resized(1920, 1080))
            times.append(t)
    scene.render(cams[0], time_s=times[0])          # warm-up: kernels loaded, chunks read
    t_all = time.perf_counter()
    ts = []
    for c, t in zip(cams, times):
        t0 = time.perf_counter()
        scene.render(c, time_s=t)
        ts.append(time.perf_counter() - t0)
    r = {"case": case, "views": len(ts), "width": 1920, "height": 1080,
         "median_s": round(statistics.median(ts), 4), "max_s": round(max(ts), 4), "min_s": round(min(ts), 4)}
    if case == "sequence":
        q = np.percentile(ts, [90, 99])
        r |= {"p90_s": round(float(q[0]), 4), "p99_s": round(float(q[1]), 4),
              "over_0_6_s": sum(t > 0.6 for t in ts), "loop_s": round(time.perf_counter() - t_all, 2)}
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
    ap.add_argument("--cases", default="reconstruct,render,sequence",
                    help="comma-separated, in this order: reconstruct (writes WORK/now, WORK/baseline), render, "
                         "sequence (default: all three)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="reconstructs of each tree, in ABBA order with --baseline (the ratio from the medians)")
    args = ap.parse_args()
    if args.rounds < 1:
        raise SystemExit(f"--rounds: at least 1, got {args.rounds}")
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = sorted(set(cases) - set(CASES))
    if unknown or not cases:
        raise SystemExit(f"--cases: {', '.join(unknown) or 'none given'}; choose from {', '.join(CASES)}")
    cases = [c for c in CASES if c in cases]
    if not args.drive.exists():
        raise SystemExit(f"no drive at {args.drive} (--drive)")
    trees: list[tuple[str, Path | None]] = [("now", None)]
    if args.baseline is not None:
        trees.append(("baseline", args.baseline.resolve()))
    for name, _ in trees:
        if "reconstruct" not in cases and not (args.work / name / "scene.json").is_file():
            raise SystemExit(f"--cases without reconstruct: no scene in {args.work / name}")

    def one(name: str, tree: Path | None, case: str) -> dict:
        # the scene just written (~5-9 GB for 20 keyframes) flushed to disk first: the kernel's writeback of it made
        # the views 0.61 s instead of 0.48-0.50 (docs/results.md "Drives: camera layers"); a reconstruct is not timed
        # against the other tree's writeback either
        os.sync()
        r = run(tree, case, args, args.work / name)
        r["tree"] = name
        print(json.dumps(r), flush=True)
        return r

    results = {}
    if "reconstruct" in cases:      # ABBA: each round the other tree first
        made: dict[str, list[dict]] = {}
        for k in range(args.rounds):
            for name, tree in (trees if k % 2 == 0 else trees[::-1]):
                made.setdefault(name, []).append(one(name, tree, "reconstruct"))
        for name, rs in made.items():
            results[(name, "reconstruct")] = {"seconds": statistics.median(r["seconds"] for r in rs)}
    for name, tree in trees:
        for case in cases:
            if case != "reconstruct":
                results[(name, case)] = one(name, tree, case)
    if args.baseline is not None:
        ratio = {"case": "ratio", "what": "baseline / now"}
        for case, key in (("reconstruct", "seconds"), ("render", "median_s"), ("sequence", "median_s"),
                          ("sequence", "p99_s"), ("sequence", "max_s"), ("sequence", "loop_s")):
            if case in cases:
                ratio[f"{case}_{key}"] = round(results[("baseline", case)][key] / results[("now", case)][key], 2)
        print(json.dumps(ratio), flush=True)


if __name__ == "__main__":
    main()
