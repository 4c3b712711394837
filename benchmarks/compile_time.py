"""Cold numba compile per camera model: one JSON line per model, then the total, on stdout.

Renders the warm-up's tiny scene (xyzcyl.runtime.warmup.tiny_scene, Gaussians only, 64x48) through each camera
model in turn (pinhole, equirect, opencv, fisheye, ftheta, or those named) and prints the render's wall time and
the seconds numba spent compiling each function (its ``numba:compile`` events, over 0.3 s; nested: a kernel's
figure includes the functions it compiled on the way). The projection is compiled per camera model, so each model
pays its own compile once per machine (docs/renderer.md "numba compile cache" quotes these figures). Run it with
an empty cache; with a filled one it measures loading the kernels instead (well under a second per model):

    NUMBA_CACHE_DIR=$(mktemp -d) .venv/bin/python benchmarks/compile_time.py [MODEL ...]
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time

import numpy as np

MODELS = ("pinhole", "equirect", "opencv", "fisheye", "ftheta")


def cameras() -> dict:
    """{model name: a 64x48 camera of that model looking along ego x} (equirect: 128x64)."""
    from xyzcyl.runtime.camera import Camera
    from xyzcyl.runtime.lenses import Lens

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="*", metavar="MODEL",
                    help=f"camera models, in this order (default: all, {' '.join(MODELS)})")
    args = ap.parse_args(argv)
    if bad := [m for m in args.models if m not in MODELS]:
        ap.error(f"unknown camera model(s) {bad}: choose from {', '.join(MODELS)}")

    from numba.core import event as ev
    from xyzcyl.runtime.render import render
    from xyzcyl.runtime.warmup import tiny_scene

    compile_s: dict[str, float] = collections.defaultdict(float)   # function qualname -> seconds compiling

    class Timer(ev.Listener):
        def __init__(self):
            self.started = {}

        def on_start(self, event):
            self.started[id(event.data["dispatcher"]), str(event.data["args"])] = time.perf_counter()

        def on_end(self, event):
            key = (id(event.data["dispatcher"]), str(event.data["args"]))
            compile_s[event.data["dispatcher"].py_func.__qualname__] += time.perf_counter() - self.started.pop(key)

    ev.register("numba:compile", Timer())
    g = tiny_scene().gaussians
    cams = cameras()
    total = 0.0
    for name in args.models or MODELS:
        compile_s.clear()
        t0 = time.perf_counter()
        r = render(g, cams[name])
        wall = time.perf_counter() - t0
        total += wall
        top = {k: round(v, 2) for k, v in sorted(compile_s.items(), key=lambda kv: -kv[1]) if v > 0.3}
        print(json.dumps({name: {"wall_s": round(wall, 2), "compile_s": top, "rgb_sum": float(r.rgb.sum())}}),
              flush=True)
    print(json.dumps({"total_wall_s": round(total, 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
