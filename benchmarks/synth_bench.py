"""Synthetic data generator benchmark (issue 4): scenes per minute, one JSON line per case.

Case "full": scenes 0..N-1 of seed 0 with the nuScenes-like rig (6 inputs) + 8 ego-inward targets at 224x400,
2x2 supersampling, sun shadows, occupancy at 0.4 m and 0.8 m, written to a temporary folder exactly as
`xyzcyl data synth` does (PNG + EXR + npz, background writer thread). Case "render": the same without the
writing. One warm-up scene (numba compilation) is rendered first and not timed. The CPU load average at the
start is printed: the machine is shared, so figures taken under load are lower than on idle cores.

    .venv/bin/python benchmarks/synth_bench.py [--scenes 12] [--threads 2]
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
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    from xyzcyl.model_export.data.synth import SynthConfig, render_scene, synth

    cfg = SynthConfig(rig="nuscenes", height=224, width=400, targets=("ego-inward",), inward_views=8,
                      supersample=2, shadows=True, voxels=(0.4, 0.8), seed=0)
    render_scene(SynthConfig(height=16, width=24, inward_views=2), 0)  # compile / load the numba cache
    load = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(args.scenes):
        render_scene(cfg, i)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    base = {"threads": args.threads, "scenes": args.scenes, "views_per_scene": 14, "size": "224x400", "ss": 2,
            "load_avg_1min": round(load, 2)}
    print(json.dumps({"case": "render", **base, "scenes_per_min": round(60 * args.scenes / dt, 2),
                      "s_per_scene": round(dt / args.scenes, 3), "cpu_s_per_scene": round(dc / args.scenes, 3)}))
    with tempfile.TemporaryDirectory() as tmp:
        load = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        synth(Path(tmp) / "ds", args.scenes, cfg, progress=False)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
    base["load_avg_1min"] = round(load, 2)
    print(json.dumps({"case": "full", **base, "scenes_per_min": round(60 * args.scenes / dt, 2),
                      "s_per_scene": round(dt / args.scenes, 3), "cpu_s_per_scene": round(dc / args.scenes, 3)}))


if __name__ == "__main__":
    main()
