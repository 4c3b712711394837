"""Renderer benchmark on the scenes users render (issue 26): one JSON line per case, all in one process.

Scenes (reconstructed once with the shipped model and kept in --work, outside git; delete the folder to rebuild):
- ``example``: the example rig (examples/synth_nuscenes) upscaled to 6 x 1600x900 JPEGs, as benchmarks/server_bench.py
  posts it, no LiDAR; the detail layer at the default stride and at stride 1;
- ``pandaset``: the real PandaSet frame (../shared/data/real/pandaset_002_seq/frame_20, 6 x 1920x1080 + LiDAR) at
  the default stride and at stride 1 (skipped when the data is absent).

Cases:
- ``scene``: each scene seen from its first camera at 1920x1080, 1600x900 and 800x450 (runtime.scene.render_view:
  the Gaussians over the baked background, what the service renders), median and min of --repeats after one
  warm-up; the renderer's stage times of the median run; Gaussians, visible Gaussians, tile instances and the
  Gaussian-pixel evaluations the raster made (16 per evaluated tile row; `evals_per_s` = those over the raster's
  time, the figure to compare with the CPU's limit in docs/renderer.md).
- ``peer``: the 500k-Gaussian random scene of benchmarks/render_bench.py at 1600x900 and 800x450, ours against the
  plain numba port of 3DGS's forward pass in benchmarks/peer_renderer.py (same process, same threads).
- ``server`` (with --server): the GET figures of benchmarks/server_bench.py (its render series at full length, the
  other cases shortened), run as a child (it starts its own `xyzcyl serve` on the example rig's detail scene).

    .venv/bin/python benchmarks/render_scenes_bench.py [--work /tmp/xyzcyl-render-bench] [--repeats 5]
        [--threads 2] [--strides default,1] [--server] [--baseline DIR]

With --baseline DIR (DIR/xyzcyl: an older tree, e.g. `git archive <commit> | tar -x -C DIR/xyzcyl`), every scene
case runs again with that renderer in a child process right after, and a ``ratio`` line gives baseline / now.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
PANDASET = REPO.parent / "shared" / "data" / "real" / "pandaset_002_seq" / "frame_20" / "rig.json"
SIZES = ((1920, 1080), (1600, 900), (800, 450))


def build_scene(work: Path, name: str, rig_json: Path, stride: int | None, threads: int):
    """The scene `name` at `stride` (None: the default DetailOptions), reconstructed once and cached in work."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.inference import DEFAULT_DETAIL
    from xyzcyl.runtime.scene import Scene

    stride = DEFAULT_DETAIL.stride if stride is None else stride
    folder = work / f"{name}_s{stride}"
    if (folder / "scene.json").is_file():
        return Scene.load(folder), stride
    from xyzcyl.runtime.inference import Reconstructor, default_model_dir
    from xyzcyl.runtime.lidar import load_lidar
    from xyzcyl.runtime.rig import load_rig

    rig = load_rig(rig_json)
    lidar = load_lidar(rig).points if rig.extra.get("lidar") else None
    rec = Reconstructor.load(default_model_dir(), threads=threads)
    scene = rec.reconstruct(rig, lidar=lidar, detail=DetailOptions(stride=stride))
    scene.save(folder)
    return scene, stride


def time_calls(fn, repeats: int) -> tuple[list[float], object]:
    fn()                                          # warm-up (numba loads or compiles here)
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def scene_cases(name: str, scene, stride: int, rig_json: Path, repeats: int):
    from xyzcyl.runtime.render import render
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import rig_camera

    cam = load_rig(rig_json).cameras[0]
    for w, h in SIZES:
        c = rig_camera(cam, width=w, height=h)
        runs = []
        for _ in range(repeats + 1):
            res = st = None   # dropped before the next render, as the service does: its buffers are reused
            t0 = time.perf_counter()
            b = scene.background.render(c) if scene.background is not None else None
            res = render(scene.gaussians, c, background=b)
            wall = time.perf_counter() - t0
            st = res.state
            evals = getattr(st, "row_evals", None)      # None: a --baseline renderer from before it was counted
            runs.append((wall, st.timings, int(np.unique(st.ids).size), int(st.ids.shape[0]),
                         None if evals is None else int(evals.sum()) * 16))
        res = st = None
        runs = runs[1:]
        walls = [r[0] for r in runs]
        med = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
        evals = med[4]
        yield {"case": "scene", "scene": name, "stride": stride, "camera": cam.name, "width": w, "height": h,
               "median_s": round(statistics.median(walls), 4), "min_s": round(min(walls), 4),
               "stages_s": {k: round(v, 4) for k, v in med[1].items()},
               "background_s": round(med[0] - sum(med[1].values()), 4),
               "gaussians": len(scene.gaussians), "visible": med[2], "tile_instances": med[3],
               "gaussian_pixel_evals": evals,
               "evals_per_s": None if evals is None else round(evals / max(med[1]["raster"], 1e-9)),
               "load_avg_1m": round(os.getloadavg()[0], 2)}


def baseline_cases(args: argparse.Namespace, name: str, stride: int, rig_json: Path) -> list[dict]:
    """scene_cases of the same cached scene with the package under args.baseline (a child process)."""
    env = dict(os.environ, PYTHONPATH=str(args.baseline.resolve()))
    out = subprocess.run([sys.executable, __file__, "--work", str(args.work), "--repeats", str(args.repeats),
                          "--threads", str(args.threads), "--child", name, str(stride), str(rig_json)],
                         env=env, capture_output=True, text=True, check=True)
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def peer_cases(repeats: int):
    from peer_renderer import render_peer
    from render_bench import camera, scene
    from xyzcyl.runtime.render import render

    g = scene(500_000)
    for w, h in ((1600, 900), (800, 450)):
        cam = camera(w, h)
        ours, res = time_calls(lambda cam=cam: render(g, cam), repeats)
        peer, out = time_calls(lambda cam=cam: render_peer(g, cam), repeats)
        mse = float(np.mean((np.clip(out[0], 0, 1) - np.clip(res.rgb, 0, 1)) ** 2))
        yield {"case": "peer", "gaussians": len(g), "width": w, "height": h,
               "ours_s": round(statistics.median(ours), 4), "peer_s": round(statistics.median(peer), 4),
               "speedup": round(statistics.median(peer) / statistics.median(ours), 2),
               "psnr_peer_vs_ours": round(10 * np.log10(1.0 / max(mse, 1e-20)), 1),
               "load_avg_1m": round(os.getloadavg()[0], 2)}


def server_case() -> dict:
    # server_bench's render series at full length, the other cases short (they are not this figures)
    args = ["--recon-runs", "2", "--render-runs", "60", "--jpeg-runs", "120", "--warmup", "20",
            "--concurrent-requests", "4", "--cache-runs", "5", "--renders", "30"]
    out = subprocess.run([sys.executable, str(Path(__file__).parent / "server_bench.py"), *args],
                         capture_output=True, text=True, check=False)
    if out.returncode:
        return {"case": "server", "error": out.stderr[-2000:]}
    doc = json.loads(out.stdout)
    keep = {k: v for k, v in doc.items() if k.startswith("render") or k in ("targets", "pass")}
    return {"case": "server", **keep}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/xyzcyl-render-bench"),
                    help="folder for the reconstructed scenes (kept between runs; outside git)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--strides", default="default,1", help="comma-separated detail strides ('default' or N)")
    ap.add_argument("--no-peer", action="store_true", help="skip the peer comparison")
    ap.add_argument("--server", action="store_true", help="also run server_bench.py (GET figures)")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="a folder holding an older xyzcyl package (e.g. `git archive` of a commit into DIR/xyzcyl): "
                         "each scene case is also run with it, in a child process, and the ratio printed")
    ap.add_argument("--child", nargs=3, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.repeats < 1 or args.threads < 1:
        print("render_scenes_bench: --repeats and --threads must be >= 1", file=sys.stderr)
        return 2
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    if args.child is not None:                  # one scene with whatever xyzcyl PYTHONPATH gives (--baseline)
        from xyzcyl.runtime.scene import Scene

        name, stride, rig_json = args.child
        for row in scene_cases(name, Scene.load(args.work / f"{name}_s{stride}"), int(stride), Path(rig_json),
                               args.repeats):
            print(json.dumps(row), flush=True)
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    from xyzcyl.testing.rigs import make_rig

    rigs = [("example", make_rig(args.work, 1600, 900))]
    if PANDASET.is_file():
        rigs.append(("pandaset", PANDASET))
    strides = [None if s.strip() == "default" else int(s) for s in args.strides.split(",")]
    for name, rig_json in rigs:
        for stride in strides:
            scene, s = build_scene(args.work, name, rig_json, stride, args.threads)
            rows = list(scene_cases(name, scene, s, rig_json, args.repeats))
            del scene
            for row in rows:
                print(json.dumps(row), flush=True)
            if args.baseline is not None:
                for row, base in zip(rows, baseline_cases(args, name, s, rig_json), strict=True):
                    print(json.dumps(base | {"code": "baseline"}), flush=True)
                    print(json.dumps({"case": "ratio", "scene": name, "stride": s, "width": row["width"],
                                      "height": row["height"], "baseline_s": base["median_s"],
                                      "now_s": row["median_s"],
                                      "speedup": round(base["median_s"] / row["median_s"], 2)}), flush=True)
    if not args.no_peer:
        for row in peer_cases(args.repeats):
            print(json.dumps(row), flush=True)
    if args.server:
        print(json.dumps(server_case()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
