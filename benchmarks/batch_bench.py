"""`xyzcyl batch` against `xyzcyl reconstruct` on one machine (issue 41's benchmark): the same drive and keyframes
through both commands, each run in a child process of its own, the batch with 1 and 2 keyframe workers of one CPU
and with one of two. One
JSON line per run and a summary line:

- ``reconstruct``: `xyzcyl reconstruct DRIVE --keyframes K --out DIR` (keyframes made one ahead in a thread while
  the last one fuses: the command's default): wall seconds, its peak PSS and RSS;
- ``batch``: `xyzcyl batch MANIFEST --out STORE --workers N --worker-cpus C` into an empty store (the drive with the same keyframes
  as a JSON line): wall seconds, the drive's own seconds inside Ray (the results table's ``seconds``: from its record
  begun to its scene committed) and its plan stage's, Ray's overhead (wall - both: Ray's start, the workers'
  model loads, shutting down), the peak memory of the whole process tree (Ray's processes included; the sum of
  their PSS, which splits the object store's shared pages among the processes mapping them) and each kind of
  process's peak RSS (the keyframe workers, the fusion task, the driver, Ray's own);
- ``summary``: batch / reconstruct wall ratios, the scaling from 1 to 2 workers.

    .venv/bin/python benchmarks/batch_bench.py [--drive D] [--every 4] [--workers 1:1,2:1,1:2]
        [--work /tmp/xyzcyl-batch-bench]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_DRIVE = HERE.parent.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"


def _role(pid: int) -> str:
    """A process's role: Ray's process title ("ray::KeyframeWorker", "ray::Map(reconstruct_item)", "raylet", ...)
    or the command's program name."""
    try:
        argv = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    first = argv[0].decode(errors="replace").strip()
    if first.startswith("ray::"):
        return first.split()[0]
    name = Path(first).name
    if name.startswith("python") and len(argv) > 1:
        script = next((Path(a.decode()).name for a in argv[1:] if a and not a.startswith(b"-")), "")
        return f"python {script}" if script else name
    return name


def _tree(root: int) -> dict[int, tuple[str, int, int]]:
    """pid -> (role, RSS bytes, PSS bytes) of ``root`` and every process below it (/proc; PSS from smaps_rollup:
    shared pages, Ray's object store among them, split between the processes that map them)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            parent[int(d.name)] = int(stat[stat.rindex(")") + 2:].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    tree, todo = {root}, [root]
    while todo:
        p = todo.pop()
        for c, pp in parent.items():
            if pp == p and c not in tree:
                tree.add(c)
                todo.append(c)
    out = {}
    for p in tree:
        try:
            rollup = (Path("/proc") / str(p) / "smaps_rollup").read_text().splitlines()
        except OSError:
            continue
        kib = {line.split()[0].rstrip(":"): int(line.split()[1]) for line in rollup[1:] if len(line.split()) >= 2}
        out[p] = (_role(p), kib.get("Rss", 0) * 1024, kib.get("Pss", 0) * 1024)
    return out


def _timed(argv: list[str], log: Path) -> tuple[float, int, float, dict[str, float]]:
    """(wall seconds, exit status, the peak of the process tree's summed PSS in GiB, the peak RSS in GiB of each
    role) of a command; the tree sampled every 0.5 s (Ray's workers are the raylet's children, not this one's:
    getrusage does not see them)."""
    t0 = time.perf_counter()
    peak_sum, roles = 0, {}
    with open(log, "w") as f:
        proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT)
        while proc.poll() is None:
            tree = _tree(proc.pid)
            peak_sum = max(peak_sum, sum(pss for _, _, pss in tree.values()))
            for role, rss, _ in tree.values():
                roles[role] = max(roles.get(role, 0), rss)
            time.sleep(0.5)
    wall = time.perf_counter() - t0
    big = {k: round(v / 2**30, 2) for k, v in sorted(roles.items(), key=lambda kv: -kv[1]) if v > 200 * 2**20}
    return wall, proc.returncode, peak_sum / 2**30, big


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drive", default=str(DEFAULT_DRIVE))
    ap.add_argument("--every", type=int, default=4, help="a keyframe every N frames (default 4)")
    ap.add_argument("--workers", default="1:1,2:1,1:2",
                    help="the batch's runs, WORKERS:WORKER_CPUS each (default 1:1,2:1,1:2: one worker of one CPU, "
                         "two of one, one of two)")
    ap.add_argument("--work", default="/tmp/xyzcyl-batch-bench")
    args = ap.parse_args()
    drive = Path(args.drive)
    if not drive.is_file():
        print(json.dumps({"error": f"no drive file {str(drive)!r}"}))
        return 2
    work = Path(args.work)
    frames = len(json.loads(drive.read_text())["frames"])
    keys = list(range(0, frames, args.every))
    exe = [sys.executable, "-m", "xyzcyl"]
    out = []
    # the peak RSS of RUSAGE_CHILDREN is a running maximum: each case runs in a fresh interpreter of this script
    if os.environ.get("_BATCH_BENCH_CASE"):
        return _case(os.environ["_BATCH_BENCH_CASE"], drive, keys, work, exe)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    for case in ["reconstruct"] + [f"batch:{w}" for w in args.workers.split(",")]:
        r = subprocess.run([sys.executable, __file__, "--drive", str(drive), "--every", str(args.every),
                            "--work", str(work)], env={**os.environ, "_BATCH_BENCH_CASE": case},
                           capture_output=True, text=True, check=False)
        line = json.loads(r.stdout.strip().splitlines()[-1]) if r.stdout.strip() else {"case": case,
                                                                                       "error": r.stderr[-2000:]}
        print(json.dumps(line), flush=True)
        out.append(line)
    base = next((o for o in out if o["case"] == "reconstruct" and "wall_s" in o), None)
    batches = {(o["workers"], o["worker_cpus"]): o for o in out if o["case"] == "batch" and "wall_s" in o}
    summary = {"case": "summary", "keyframes": len(keys), "frames": frames, "cpus": os.cpu_count()}
    if base:
        summary.update({f"batch_{w}x{c}_over_reconstruct": round(o["wall_s"] / base["wall_s"], 3)
                        for (w, c), o in batches.items()})
    if (1, 1) in batches and (2, 1) in batches:
        one, two = batches[(1, 1)], batches[(2, 1)]
        summary["scaling_1_to_2_workers"] = round(one["wall_s"] / two["wall_s"], 3)
        summary["drive_scaling_1_to_2_workers"] = round(one["drive_s"] / two["drive_s"], 3)
    print(json.dumps(summary))
    return 0


def _case(case: str, drive: Path, keys: list[int], work: Path, exe: list[str]) -> int:
    if case == "reconstruct":
        wall, rc, peak, roles = _timed(exe + ["reconstruct", str(drive), "--keyframes", ",".join(map(str, keys)), "--out",
                                       str(work / "scene"), "--force"], work / "reconstruct.log")
        scene = json.loads((work / "scene" / "scene.json").read_text()) if rc == 0 else {}
        print(json.dumps({"case": "reconstruct", "rc": rc, "keyframes": len(keys), "wall_s": round(wall, 2),
                          "gaussians": scene.get("gaussians", {}).get("count"), "peak_pss_gib": round(peak, 2),
                          "peak_rss_gib_by_process": roles}))
        return 0
    workers, cpus = (int(x) for x in case.split(":")[1:])
    manifest = work / f"drives-{workers}.jsonl"
    manifest.write_text(json.dumps({"input": str(drive.resolve()), "keyframes": keys, "name": "bench"}) + "\n")
    store, results = work / f"store-{workers}-{cpus}", work / f"results-{workers}-{cpus}.jsonl"
    wall, rc, peak, roles = _timed(exe + ["batch", str(manifest), "--out", str(store), "--results", str(results),
                                        "--workers", str(workers), "--worker-cpus", str(cpus), "--quiet"],
                                 work / f"batch-{case}.log")
    rows = [json.loads(x) for x in results.read_text().splitlines()] if results.is_file() else []
    row = rows[0] if rows else {}
    drive_s, plan_s = row.get("seconds") or 0.0, row.get("plan_s") or 0.0
    print(json.dumps({"case": "batch", "workers": workers, "worker_cpus": cpus, "rc": rc, "status": row.get("status"),
                      "keyframes": len(keys), "wall_s": round(wall, 2), "drive_s": drive_s, "plan_s": plan_s,
                      "ray_overhead_s": round(wall - drive_s - plan_s, 2), "gaussians": row.get("gaussians"),
                      "peak_pss_gib": round(peak, 2), "peak_rss_gib_by_process": roles}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
