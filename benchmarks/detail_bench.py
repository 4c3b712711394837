"""Detail-layer benchmark (issue 25): one JSON line per case, each case in its own child process (its peak RSS is
its own).

Input: a real rig with LiDAR (default: the PandaSet frame ../shared/data/real/pandaset_002_seq/frame_20, six
1920x1080 JPEGs + a Pandar64 sweep), the shipped model (models/xyzcyl-cpu-v1), --threads for onnxruntime and numba.

Cases, for each --strides value (an integer stride, or "off" for the model's Gaussians alone):
- ``reconstruct``: rig.json + JPEGs + LiDAR -> Scene (`Reconstructor.reconstruct` with the images decoded from the
  files, so decode is timed), median and min of --repeats runs after one warm-up (numba compiles and the lifting
  cache fills there), the stage breakdown of the median run, the Gaussian counts per layer, the PLY's bytes, and the
  child's peak RSS (VmHWM) after the runs and after the save too.
- ``render``: the scene seen from --camera at 1920x1080, 1600x900 and 800x450 (runtime.scene.render_view: Gaussians
  over the baked background), median of --repeats, with the renderer's own stage times of the median run.
- ``input_view``: PSNR / SSIM / sharpness ratio of the render at --camera's own pose against its image (full size).

    .venv/bin/python benchmarks/detail_bench.py [--rig RIG_JSON] [--strides off,4,2,1] [--repeats 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RIG = REPO.parent / "shared" / "data" / "real" / "pandaset_002_seq" / "frame_20" / "rig.json"
SIZES = ((1920, 1080), (1600, 900), (800, 450))


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def child(args: argparse.Namespace) -> None:
    import numba
    import numpy as np
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.inference import Reconstructor, as_rgb, default_model_dir
    from xyzcyl.runtime.lidar import load_lidar
    from xyzcyl.runtime.realeval import image_metrics
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import render_view, rig_camera

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    detail = None if args.child == "off" else DetailOptions(stride=int(args.child))
    rec = Reconstructor.load(args.model or default_model_dir(), threads=args.threads)
    rig = load_rig(args.rig)
    lidar = load_lidar(rig).points
    runs = []
    scene = None
    for i in range(args.repeats + 1):
        scene = None                            # the previous scene is not held while the next one is built
        t0 = time.perf_counter()
        scene = rec.reconstruct(rig, lidar=lidar, detail=detail)
        wall = time.perf_counter() - t0
        if i:                                   # run 0 warms numba, onnxruntime and the lifting cache up
            runs.append((wall, scene.timings))
    walls = [w for w, _ in runs]
    med = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    rss_reconstruct = peak_rss_mb()                 # before the save (its PLY buffer) and the renders
    with tempfile.TemporaryDirectory() as tmp:
        scene.save(Path(tmp) / "s")
        ply = (Path(tmp) / "s" / "scene.ply").stat().st_size
    case = {"stride": args.child, "rig": str(args.rig), "threads": args.threads}
    print(json.dumps({"case": "reconstruct", **case, "median_s": statistics.median(walls), "min_s": min(walls),
                      "runs": len(walls), "stages_s": med[1], "counts": scene.counts, "ply_bytes": ply,
                      "peak_rss_mb": round(rss_reconstruct, 1), "peak_rss_with_save_mb": round(peak_rss_mb(), 1)}),
          flush=True)
    cam = rig.camera(args.camera)
    for w, h in SIZES:
        c = rig_camera(cam, width=w, height=h)
        times = []
        for _ in range(args.repeats + 1):
            t0 = time.perf_counter()
            render_view(scene, c)
            times.append(time.perf_counter() - t0)
        times = times[1:]
        print(json.dumps({"case": "render", **case, "camera": args.camera, "width": w, "height": h,
                          "gaussians": len(scene.gaussians), "median_s": statistics.median(times),
                          "min_s": min(times)}), flush=True)
    gt = as_rgb(rig.load_images()[rig.names.index(args.camera)], cam)
    rgb, _, _ = render_view(scene, rig_camera(cam))
    m = image_metrics(np.clip(rgb, 0, 1), gt)
    print(json.dumps({"case": "input_view", **case, "camera": args.camera, **m}), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rig", type=Path, default=RIG, help="a rig.json with LiDAR (default: the PandaSet frame 20)")
    ap.add_argument("--model", default=None, help="model folder (default: the shipped one)")
    ap.add_argument("--strides", default="off,4,2,1", help="comma-separated strides; 'off' = no detail layer")
    ap.add_argument("--camera", default=None, help="camera for the render and input-view cases (default: the first)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not args.rig.is_file():
        print(f"detail_bench: --rig: {str(args.rig)!r} does not exist", file=sys.stderr)
        return 2
    if args.camera is None:
        args.camera = json.loads(args.rig.read_text())["cameras"][0]["name"]
    if args.child is not None:
        child(args)
        return 0
    for s in args.strides.split(","):
        cmd = [sys.executable, __file__, "--rig", str(args.rig), "--strides", s, "--child", s.strip(),
               "--camera", args.camera, "--repeats", str(args.repeats), "--threads", str(args.threads)]
        if args.model:
            cmd += ["--model", args.model]
        rc = subprocess.run(cmd, check=False).returncode
        if rc:
            print(json.dumps({"case": "error", "stride": s, "returncode": rc}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
