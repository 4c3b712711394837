"""Cold numba compile per camera model (docs/renderer.md "numba compile cache").

Run from the tree to measure, with an empty NUMBA_CACHE_DIR and no compiled kernels in its __pycache__:

    NUMBA_CACHE_DIR=$(mktemp -d) .venv/bin/python docs/runs/compile_spec_2026-11-26/compile_time.py [MODEL ...]

Renders the warm-up's tiny scene (Gaussians only, 64x48) through each camera model in turn (pinhole, equirect,
opencv, fisheye, ftheta, or those named) and prints one JSON line per model: the render's wall time (s) and the
seconds numba spent compiling each function (its numba:compile events; nested: a kernel's figure includes the
functions it compiled on the way), then the total.
"""

from __future__ import annotations

import collections
import json
import sys
import time

import numpy as np
from numba.core import event as ev
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.lenses import Lens
from xyzcyl.runtime.render import render
from xyzcyl.runtime.warmup import tiny_scene

COMPILE = collections.defaultdict(float)   # function qualname -> seconds compiling


class _Timer(ev.Listener):
    def __init__(self):
        self.started = {}

    def on_start(self, event):
        self.started[id(event.data["dispatcher"]), str(event.data["args"])] = time.perf_counter()

    def on_end(self, event):
        key = (id(event.data["dispatcher"]), str(event.data["args"]))
        COMPILE[event.data["dispatcher"].py_func.__qualname__] += time.perf_counter() - self.started.pop(key)


def cameras() -> dict[str, Camera]:
    W, H = 64, 48
    K = np.array([[40.0, 0, 31.7], [0, 40.0, 24.2], [0, 0, 1.0]])
    Kf = np.array([[20.0, 0, 31.85], [0, 20.0, 24.1], [0, 0, 1.0]])
    T = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1.0]], float)   # looking along ego x
    opencv = Lens("opencv", (-0.28, 0.07, 0.0008, -0.0012, -0.006, 0.02, 0.003, 0.0, 0.002, -0.0005, -0.001, 0.0003))
    fisheye = Lens("opencv_fisheye", (0.02, -0.01, 0.002, -0.0003), max_angle_deg=95.0)
    ftheta = Lens("ftheta", max_angle_deg=100.0, angle_to_pixeldist_poly=(0.0, 52.0, 0.0, -1.5, 0.1))
    return {"pinhole": Camera(K=K, cam_to_ego=T, width=W, height=H),
            "equirect": Camera(model="equirectangular", cam_to_ego=np.eye(4), width=128, height=64),
            "opencv": Camera(K=K, cam_to_ego=T, width=W, height=H, distortion=opencv),
            "fisheye": Camera(K=Kf, cam_to_ego=T, width=W, height=H, distortion=fisheye),
            "ftheta": Camera(K=K, cam_to_ego=T, width=W, height=H, distortion=ftheta)}


def main(names: list[str]) -> None:
    ev.register("numba:compile", _Timer())
    g = tiny_scene().gaussians
    cams = cameras()
    total = 0.0
    for name in names or list(cams):
        COMPILE.clear()
        t0 = time.perf_counter()
        r = render(g, cams[name])
        wall = time.perf_counter() - t0
        total += wall
        top = {k: round(v, 2) for k, v in sorted(COMPILE.items(), key=lambda kv: -kv[1]) if v > 0.3}
        print(json.dumps({name: {"wall_s": round(wall, 2), "compile_s": top, "rgb_sum": float(r.rgb.sum())}}),
              flush=True)
    print(json.dumps({"total_wall_s": round(total, 1)}))


if __name__ == "__main__":
    main(sys.argv[1:])
