"""Synthetic data generator benchmark (issue 4): scenes per minute, one JSON line per case.

Case "full": scenes 0..N-1 of seed 0 with the nuScenes-like rig (6 inputs) + 8 ego-inward targets at 224x400,
2x2 supersampling, sun shadows, occupancy at 0.4 m and 0.8 m, written to a temporary folder exactly as
`xyzcyl data synth` does (PNG + EXR + npz, background writer thread). Case "render": the same without the
writing. Case "workers" (one line per worker count W): `synth(..., workers=W)` into a fresh folder, i.e.
`xyzcyl data synth --workers W` (W = 1: one process with --threads numba threads, as "full"; W > 1: W spawned
processes with max(1, cores // W) numba threads each), timed from the call to its return, so the pool's
start-up (process spawn, imports, numba cache loads) is included. One warm-up scene (numba compilation) is
rendered first and not timed. The CPU load average at the start of each case is printed: the machine is
shared, so figures taken under load are lower than on idle cores.

    .venv/bin/python benchmarks/synth_bench.py [--scenes 12] [--threads 2] [--workers 1,2,N] \
        [--cases render,full,workers]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numba


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--threads", type=int, default=2, help="numba threads of the single process (render, full, W=1)")
    ap.add_argument("--workers", default="1,2", help="comma list of worker counts for case workers")
    ap.add_argument("--cases", default="render,full,workers", help="comma list of render, full, workers")
    args = ap.parse_args()
    cases = {c.strip() for c in args.cases.split(",") if c.strip()}
    numba.set_num_threads(args.threads)
    from xyzcyl.model_export.data.synth import SynthConfig, cores, render_scene, synth

    cfg = SynthConfig(rig="nuscenes", height=224, width=400, targets=("ego-inward",), inward_views=8,
                      supersample=2, shadows=True, voxels=(0.4, 0.8), seed=0)
    render_scene(SynthConfig(height=16, width=24, inward_views=2), 0)  # compile / load the numba cache
    base = {"threads": args.threads, "scenes": args.scenes, "views_per_scene": 14, "size": "224x400", "ss": 2,
            "cores": cores()}

    def report(case: str, dt: float, dc: float, load: float, **extra) -> None:
        n = args.scenes
        print(json.dumps({"case": case, **base, **extra, "load_avg_1min": round(load, 2),
                          "scenes_per_s": round(n / dt, 3), "scenes_per_min": round(60 * n / dt, 2),
                          "s_per_scene": round(dt / n, 3), "cpu_s_per_scene": round(dc / n, 3)}), flush=True)

    if "render" in cases:
        load = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(args.scenes):
            render_scene(cfg, i)
        report("render", time.perf_counter() - t0, time.process_time() - c0, load)
    if "full" in cases:
        with tempfile.TemporaryDirectory() as tmp:
            load = os.getloadavg()[0]
            t0, c0 = time.perf_counter(), time.process_time()
            synth(Path(tmp) / "ds", args.scenes, cfg, progress=False)
            report("full", time.perf_counter() - t0, time.process_time() - c0, load)
    if "workers" in cases:
        for w in (int(x) for x in args.workers.split(",") if x.strip()):
            with tempfile.TemporaryDirectory() as tmp:
                load = os.getloadavg()[0]
                t0 = time.perf_counter()
                r0 = os.times()
                synth(Path(tmp) / "ds", args.scenes, cfg, progress=False, workers=w)
                r1 = os.times()
                dt = time.perf_counter() - t0
                # CPU time of this process and of its finished children (the pool's workers)
                dc = (r1.user + r1.system + r1.children_user + r1.children_system
                      - r0.user - r0.system - r0.children_user - r0.children_system)
                report("workers", dt, dc, load, workers=w,
                       threads_per_worker=args.threads if w == 1 else max(1, cores() // w))


if __name__ == "__main__":
    main()
