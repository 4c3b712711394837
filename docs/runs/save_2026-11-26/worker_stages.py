"""The reconstruction worker's stages outside the runtime (docs/results.md "Service"): what `xyzcyl serve`'s worker
does per job (server/jobs.py `_worker_reconstruct`: load the rig, reconstruct, save the scene folder, its JSON),
timed one by one on the example rig upscaled to 6 x 1600x900 JPEG as benchmarks/server_bench.py posts it.

    .venv/bin/python docs/runs/save_2026-11-26/worker_stages.py [--runs 3] [--work /tmp/xyzcyl-worker-stages]

Prints one dict per run (seconds): load_rig, reconstruct, save, to_json; then the runtime's own stage timings.
The first run includes one-time costs (kernel loading, first-touch page faults).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from xyzcyl.runtime.inference import DEFAULT_DETAIL, Reconstructor, default_model_dir
from xyzcyl.runtime.rig import load_rig
from xyzcyl.testing.rigs import make_rig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/xyzcyl-worker-stages"))
    args = ap.parse_args()
    rig_json = make_rig(args.work / "rig")
    rec = Reconstructor.load(default_model_dir(), threads=2, verify=False)
    for k in range(args.runs):
        t = {}
        t0 = time.perf_counter()
        rig = load_rig(rig_json)
        t["load_rig"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene = rec.reconstruct(rig, lidar=None, detail=DEFAULT_DETAIL)
        t["reconstruct"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene.save(args.work / f"scene{k}")
        t["save"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene.to_json()
        t["to_json"] = time.perf_counter() - t0
        print({n: round(v, 3) for n, v in t.items()}, {n: round(v, 3) for n, v in scene.timings.items()})


if __name__ == "__main__":
    main()
