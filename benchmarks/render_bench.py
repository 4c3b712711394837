"""Renderer benchmark: one JSON line per case (issue 3).

Random Gaussians in a 40 m box in front of the camera (x, y in [-20, 20] m, z in [0.5, 40.5] m), scales
log-uniform 3-15 cm, opacity uniform 0.2-0.95, random rotations, SH degree 0; pinhole camera at the origin
looking down +z with a 90 degree horizontal field of view (fx = fy = W / 2, principal point at the centre).
Median of --repeats timed calls after one warm-up call, per stage (project incl. SH colours; sort_bin:
depth radix sort, tile duplication and per-tile feature packing; raster) and in total. `cpu_s` is the
process CPU time per call (median): on a shared machine it is steadier than wall time for 1 thread (for 2
threads it includes OpenMP spin-waiting). The 1-minute load average is recorded with each line.

    .venv/bin/python benchmarks/render_bench.py [--sizes 100000 500000] [--threads 1 2] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numba
import numpy as np
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, render

RESOLUTIONS = ((400, 224), (1600, 900))


def scene(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    means = np.stack([rng.uniform(-20, 20, n), rng.uniform(-20, 20, n), rng.uniform(0.5, 40.5, n)], 1)
    scales = np.exp(rng.uniform(np.log(0.03), np.log(0.15), size=(n, 3)))
    opa = rng.uniform(0.2, 0.95, n)
    return Gaussians(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                     np.log(scales).astype(np.float32), np.log(opa / (1 - opa)).astype(np.float32),
                     rng.normal(scale=0.6, size=(n, 1, 3)).astype(np.float32))


def camera(width: int, height: int) -> Camera:
    f = width / 2.0
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(K=K, cam_to_ego=np.eye(4), width=width, height=height)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 500_000])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    for n in args.sizes:
        g = scene(n)
        for width, height in RESOLUTIONS:
            cam = camera(width, height)
            for threads in args.threads:
                numba.set_num_threads(threads)
                res = render(g, cam)  # warm-up (and compile on a cold cache)
                totals, cpus, stages = [], [], []
                for _ in range(args.repeats):
                    c0, t0 = time.process_time(), time.perf_counter()
                    res = render(g, cam)
                    totals.append(time.perf_counter() - t0)
                    cpus.append(time.process_time() - c0)
                    stages.append(res.state.timings)
                st = res.state
                n_inst = int(st.ids.shape[0])
                row = {
                    "case": f"{n}@{width}x{height}/t{threads}", "gaussians": n, "width": width,
                    "height": height, "threads": threads, "seconds": round(float(np.median(totals)), 4),
                    "cpu_s": round(float(np.median(cpus)), 4),
                    "stages_s": {k: round(float(np.median([s[k] for s in stages])), 4) for k in stages[0]},
                    "visible": int(np.unique(st.ids).size), "tile_instances": n_inst,
                    "evals_per_pixel": round(n_inst * 256 / (width * height), 1),
                    "mean_alpha": round(float(res.alpha.mean()), 3),
                    "load_avg_1m": round(os.getloadavg()[0], 2),
                }
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
