"""`xyzcyl batch` against `xyzcyl reconstruct` on one machine (issue 41's benchmark): the same drive and keyframes
through both commands, each run in a child process of its own, then the batch with 1 and 2 keyframe workers. One
JSON line per run and a summary line:

- ``reconstruct``: `xyzcyl reconstruct DRIVE --keyframes K --out DIR` (keyframes made one ahead in a thread while
  the last one fuses: the command's default): wall seconds, the largest process's peak RSS;
- ``batch``: `xyzcyl batch MANIFEST --out STORE --workers N` into an empty store (the drive with the same keyframes
  as a JSON line): wall seconds, the drive's own seconds inside Ray (the results table's ``seconds``: from its record
  begun to its scene committed) and its plan stage's, Ray's overhead (wall - both: Ray's start, the workers'
  model loads, shutting down), the largest process's peak RSS (a Ray worker's or the driver's);
- ``summary``: batch / reconstruct wall ratios, the scaling from 1 to 2 workers.

    .venv/bin/python benchmarks/batch_bench.py [--drive D] [--every 4] [--workers 1,2] [--work /tmp/xyzcyl-batch-bench]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_DRIVE = HERE.parent.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"


def _timed(argv: list[str], log: Path) -> tuple[float, int, float]:
    """(wall seconds, exit status, the largest finished descendant's peak RSS in GiB) of a command."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT, check=False).returncode
    wall = time.perf_counter() - t0
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss      # kiB on Linux, the max so far
    return wall, rc, peak_kib / 2**20


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drive", default=str(DEFAULT_DRIVE))
    ap.add_argument("--every", type=int, default=4, help="a keyframe every N frames (default 4)")
    ap.add_argument("--workers", default="1,2", help="the batch's keyframe workers, one run each (default 1,2)")
    ap.add_argument("--work", default="/tmp/xyzcyl-batch-bench")
    args = ap.parse_args()
    drive = Path(args.drive)
    if not drive.is_file():
        print(json.dumps({"error": f"no drive file {str(drive)!r}"}))
        return 2
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    frames = len(json.loads(drive.read_text())["frames"])
    keys = list(range(0, frames, args.every))
    exe = [sys.executable, "-m", "xyzcyl"]
    out = []
    # the peak RSS of RUSAGE_CHILDREN is a running maximum: each case runs in a fresh interpreter of this script
    if os.environ.get("_BATCH_BENCH_CASE"):
        return _case(os.environ["_BATCH_BENCH_CASE"], drive, keys, work, exe)
    for case in ["reconstruct"] + [f"batch:{w}" for w in args.workers.split(",")]:
        r = subprocess.run([sys.executable, __file__, "--drive", str(drive), "--every", str(args.every),
                            "--work", str(work)], env={**os.environ, "_BATCH_BENCH_CASE": case},
                           capture_output=True, text=True, check=False)
        line = json.loads(r.stdout.strip().splitlines()[-1]) if r.stdout.strip() else {"case": case,
                                                                                       "error": r.stderr[-2000:]}
        print(json.dumps(line), flush=True)
        out.append(line)
    base = next((o for o in out if o["case"] == "reconstruct" and "wall_s" in o), None)
    batches = {o["workers"]: o for o in out if o["case"] == "batch" and "wall_s" in o}
    summary = {"case": "summary", "keyframes": len(keys), "frames": frames, "cpus": os.cpu_count()}
    if base:
        summary.update({f"batch_{w}_over_reconstruct": round(o["wall_s"] / base["wall_s"], 3)
                        for w, o in batches.items()})
    if 1 in batches and 2 in batches:
        summary["scaling_1_to_2_workers"] = round(batches[1]["wall_s"] / batches[2]["wall_s"], 3)
        summary["drive_scaling_1_to_2_workers"] = round(batches[1]["drive_s"] / batches[2]["drive_s"], 3)
    print(json.dumps(summary))
    return 0


def _case(case: str, drive: Path, keys: list[int], work: Path, exe: list[str]) -> int:
    if case == "reconstruct":
        wall, rc, peak = _timed(exe + ["reconstruct", str(drive), "--keyframes", ",".join(map(str, keys)), "--out",
                                       str(work / "scene"), "--force"], work / "reconstruct.log")
        scene = json.loads((work / "scene" / "scene.json").read_text()) if rc == 0 else {}
        print(json.dumps({"case": "reconstruct", "rc": rc, "keyframes": len(keys), "wall_s": round(wall, 2),
                          "gaussians": scene.get("gaussians", {}).get("count"), "peak_rss_gib": round(peak, 2)}))
        return 0
    workers = int(case.split(":")[1])
    manifest = work / f"drives-{workers}.jsonl"
    manifest.write_text(json.dumps({"input": str(drive.resolve()), "keyframes": keys, "name": "bench"}) + "\n")
    store, results = work / f"store-{workers}", work / f"results-{workers}.jsonl"
    wall, rc, peak = _timed(exe + ["batch", str(manifest), "--out", str(store), "--results", str(results),
                                   "--workers", str(workers), "--quiet"], work / f"batch-{workers}.log")
    rows = [json.loads(x) for x in results.read_text().splitlines()] if results.is_file() else []
    row = rows[0] if rows else {}
    drive_s, plan_s = row.get("seconds") or 0.0, row.get("plan_s") or 0.0
    print(json.dumps({"case": "batch", "workers": workers, "rc": rc, "status": row.get("status"),
                      "keyframes": len(keys), "wall_s": round(wall, 2), "drive_s": drive_s, "plan_s": plan_s,
                      "ray_overhead_s": round(wall - drive_s - plan_s, 2), "gaussians": row.get("gaussians"),
                      "peak_rss_gib": round(peak, 2)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
