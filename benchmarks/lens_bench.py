"""Renders through real lenses (issue 28 step 3): the example detail scene seen from its front camera's pose at
1920x1080 by a 120-degree pinhole, a 120-degree f-theta and a 190-degree fisheye; one JSON line per camera and a
ratio line (f-theta / pinhole, fisheye / pinhole), all measured in one process.

Each view is what the service renders (runtime.scene.render_view: the baked background through the same camera,
then the Gaussians over it). The cameras are timed in turn, round after round (--repeats rounds after one
warm-up round), so load from other work on the machine falls on all of them alike; medians and minima per camera.

    .venv/bin/python benchmarks/lens_bench.py [--work /tmp/xyzcyl-render-bench] [--repeats 5] [--threads 2]
        [--pictures DIR]

--work: the folder where benchmarks/render_scenes_bench.py keeps its reconstructed scenes (the "example" scene at
the default detail stride is reconstructed there once when missing). --pictures DIR: also write the fisheye and
f-theta views as small PNGs (640x360) into DIR.

Cameras (all at the front camera's pose, 1920x1080, principal point at the centre):
- pinhole: fx = fy = 960 / tan(60 deg) = 554.3 (120 degrees across);
- ftheta: NVIDIA f-theta, pixeldist_to_angle_poly [0, 1/900, 0, -2.2e-11] (theta(960 px) = 60.0 deg: 120 degrees
  across, 68 degrees down), max_angle 80 deg (the corners lie at 68.5 deg, inside the circle), K's f = 900;
- fisheye: OpenCV fisheye k = (0.02, -0.01, 0.002, -0.0003), max_angle 95 deg (190 degrees), f = 318.5: its image
  circle (radius 530 px) fits the height.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numba
import numpy as np

W, H = 1920, 1080
FTHETA_POLY = (0.0, 1.0 / 900.0, 0.0, -2.2e-11)
FISHEYE_K = (0.02, -0.01, 0.002, -0.0003)


def cameras(cam_to_ego: np.ndarray) -> dict:
    from xyzcyl.runtime.camera import Camera
    from xyzcyl.runtime.lenses import Lens

    cx, cy = (W - 1) / 2, (H - 1) / 2
    f_pin = (W / 2) / math.tan(math.radians(60.0))
    ft = Lens("ftheta", max_angle_deg=80.0, pixeldist_to_angle_poly=FTHETA_POLY)
    fe = Lens("opencv_fisheye", FISHEYE_K, max_angle_deg=95.0)
    f_fe = 530.0 / float(fe.circle_limit)

    def K(f):
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])

    return {"pinhole": Camera(K=K(f_pin), cam_to_ego=cam_to_ego, width=W, height=H),
            "ftheta": Camera(K=K(900.0), cam_to_ego=cam_to_ego, width=W, height=H, distortion=ft),
            "fisheye": Camera(K=K(f_fe), cam_to_ego=cam_to_ego, width=W, height=H, distortion=fe)}


def view(scene, cam):
    from xyzcyl.runtime.render import render

    t0 = time.perf_counter()
    bg = scene.background.render(cam) if scene.background is not None else None
    t1 = time.perf_counter()
    res = render(scene.gaussians, cam, background=bg)
    return time.perf_counter() - t0, t1 - t0, res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/xyzcyl-render-bench"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--pictures", type=Path, default=None)
    args = ap.parse_args()
    if args.repeats < 1 or args.threads < 1:
        print("lens_bench: --repeats and --threads must be >= 1", file=sys.stderr)
        return 2
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    # render_scenes_bench: a sibling script, importable as its folder is on the path (run as a script)
    from render_scenes_bench import build_scene
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.testing.rigs import make_rig

    args.work.mkdir(parents=True, exist_ok=True)
    rig_json = make_rig(args.work, 1600, 900)
    scene, stride = build_scene(args.work, "example", rig_json, None, args.threads)
    front = load_rig(rig_json).cameras[0]
    cams = cameras(front.cam_to_ego)
    runs: dict[str, list] = {k: [] for k in cams}
    for rnd in range(args.repeats + 1):
        for name, cam in cams.items():
            res = None        # dropped before the next render, as the service does: its buffers are reused
            wall, bg_s, res = view(scene, cam)
            st = res.state
            if rnd:
                runs[name].append((wall, bg_s, dict(st.timings), int(np.unique(st.ids).size), int(st.ids.shape[0]),
                                   int(st.row_evals.sum()) * 16))
            if rnd == args.repeats and args.pictures is not None and name != "pinhole":
                import cv2
                from xyzcyl.runtime.imageio import write_png

                args.pictures.mkdir(parents=True, exist_ok=True)
                small = cv2.resize(np.clip(res.rgb, 0, 1), (640, 360), interpolation=cv2.INTER_AREA)
                write_png(args.pictures / f"lens_{name}.png", small)
    med = {}
    for name, rows in runs.items():
        walls = [r[0] for r in rows]
        m = sorted(rows, key=lambda r: r[0])[len(rows) // 2]
        med[name] = statistics.median(walls)
        cam = cams[name]
        print(json.dumps({"case": "lens", "camera": name, "lens": cam.lens_model, "width": W, "height": H,
                          "hfov_deg": round(math.degrees(cam.horizontal_fov), 1),
                          "vfov_deg": round(math.degrees(cam.vertical_fov), 1), "stride": stride,
                          "median_s": round(med[name], 4), "min_s": round(min(walls), 4),
                          "background_s": round(m[1], 4), "stages_s": {k: round(v, 4) for k, v in m[2].items()},
                          "gaussians": len(scene.gaussians), "visible": m[3], "tile_instances": m[4],
                          "gaussian_pixel_evals": m[5], "repeats": args.repeats, "threads": args.threads,
                          "load_avg_1m": round(os.getloadavg()[0], 2)}), flush=True)
    print(json.dumps({"case": "ratio", "ftheta_over_pinhole": round(med["ftheta"] / med["pinhole"], 3),
                      "fisheye_over_pinhole": round(med["fisheye"] / med["pinhole"], 3),
                      "target": "ftheta_over_pinhole <= 2"}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
