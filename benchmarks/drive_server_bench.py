"""The service's GET of a drive's scene over HTTP (issue 37's target: the service's GET 1600x900 <= 0.3 s), against a
real `xyzcyl serve` on 127.0.0.1 and a free port (xyzcyl.testing.serve). One JSON line per case:

- ``reconstruct``: `xyzcyl client reconstruct DRIVE --keyframe-gap G --wait` (the drive uploaded whole, its frames'
  images, LiDAR and tracks; G 0.15 s: a keyframe every 2nd frame of the shared PandaSet drive, 20 of them, as
  benchmarks/drive_bench.py reconstructs it): upload to ready, seconds, and the scene's keyframes and Gaussians.
- ``render``: GET /v1/scenes/{id}/render at the places of drive_bench's render case (each input camera of 10
  keyframes, at the time halfway to the next keyframe's), the camera's pose in the scene's frame (``cam_to_ego``)
  and its intrinsics scaled to --size, --format (default PNG); after --warmup GETs, --passes passes over the 60
  views (each pass: median, p90, max of the client's wall time per answer, the server's own render-and-encode
  time per request from its Prometheus histogram). The first pass reads each place's chunks and camera layers; the
  later ones find them kept (a running service's state), unless the scene's caches let them go.

    .venv/bin/python benchmarks/drive_server_bench.py [--drive D] [--every 2] [--size 1600x900] [--format png]
        [--passes 2] [--warmup 1] [--work DIR] [--serve-args "--render-threads 1"]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DRIVE = HERE.parent.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"


def places(drive_json: Path, every: int, width: int, height: int) -> list[dict]:
    """The render case's views as GET query parameters: each input camera of every (keys // 10)-th keyframe (every
    ``every``-th frame), its pose in the scene's frame (the first frame's ego frame), its intrinsics at width x
    height, at the time halfway to the next keyframe's."""
    from xyzcyl.runtime.drive import load_drive

    d = load_drive(drive_json)
    keys = list(range(0, len(d), every))
    out = []
    for k in keys[:: max(1, len(keys) // 10)]:
        t = 0.5 * (d.frames[k].timestamp_s + d.frames[min(k + every, len(d) - 1)].timestamp_s)
        T = d.relative(k)
        for cam in d.frames[k].rig.cameras:
            c = dataclasses.replace(cam, cam_to_ego=T @ np.asarray(cam.cam_to_ego))
            c = c if (c.width, c.height) == (width, height) else c.resized(width, height)
            K = np.asarray(c.K, np.float64)
            out.append({"cam_to_ego": ",".join(f"{v:.9g}" for v in np.asarray(c.cam_to_ego).reshape(-1)),
                        "width": width, "height": height, "fx": f"{K[0, 0]:.9g}", "fy": f"{K[1, 1]:.9g}",
                        "cx": f"{K[0, 2]:.9g}", "cy": f"{K[1, 2]:.9g}", "time": f"{t:.6f}"})
    return out


def server_render(c) -> tuple[float, float]:
    """(sum, count) of the server's render-and-encode histogram."""
    from server_bench import metric  # benchmarks/: the script's own folder, first on sys.path

    text = c.get("/metrics").text
    return metric(text, "xyzcyl_render_duration_seconds_sum"), metric(text, "xyzcyl_render_duration_seconds_count")


def stats(xs: list[float]) -> dict:
    if not xs:
        return {"n": 0}
    q = np.quantile(np.asarray(xs), [0.5, 0.9])
    return {"n": len(xs), "median_s": round(float(q[0]), 4), "p90_s": round(float(q[1]), 4),
            "max_s": round(max(xs), 4), "mean_s": round(statistics.fmean(xs), 4)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drive", type=Path, default=DEFAULT_DRIVE)
    ap.add_argument("--every", type=int, default=2, help="a keyframe every this many frames (default 2: 20)")
    ap.add_argument("--size", default="1600x900", help="WIDTHxHEIGHT of the views (default 1600x900)")
    ap.add_argument("--format", default="png", choices=("png", "jpeg", "exr"))
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--work", type=Path, default=None, help="store and log folder (default: a temporary one)")
    ap.add_argument("--serve-args", default="", help="more arguments for xyzcyl serve (shell-quoted)")
    args = ap.parse_args()
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size: WIDTHxHEIGHT, got {args.size!r}")
    if not args.drive.is_file():
        ap.error(f"--drive: {args.drive} is not a file")
    import httpx
    from xyzcyl.testing.serve import XYZCYL, serve

    work = args.work or Path(tempfile.mkdtemp(prefix="xyzcyl-drive-server-"))
    work.mkdir(parents=True, exist_ok=True)
    # the shared drive's frames are ~0.1 s apart (their clocks jitter by a millisecond): a gap of every - 0.5 frames
    # picks every `every`-th frame (runtime.drive.pick_keyframes: a keyframe once the gap is reached)
    gap = 0.1 * (args.every - 0.5)
    with serve(work / "store", work / "serve.log", ["--log-level", "warning", *shlex.split(args.serve_args)],
               ready_s=180.0, stop_s=30.0) as server:
        t0 = time.perf_counter()
        run = subprocess.run([str(XYZCYL), "client", "reconstruct", str(args.drive), "--server", server.url,
                              "--keyframe-gap", f"{gap:g}", "--wait", "1800", "--quiet"], capture_output=True,
                             text=True, timeout=2000)
        dt = time.perf_counter() - t0
        if run.returncode != 0:
            print(json.dumps({"case": "reconstruct", "error": run.stderr[-2000:]}))
            return 1
        sid = run.stdout.strip().split()[-1]
        with httpx.Client(base_url=server.url, timeout=120.0) as c:
            info = c.get(f"/v1/scenes/{sid}").json()
            print(json.dumps({"case": "reconstruct", "upload_to_ready_s": round(dt, 2), "scene": sid,
                              "keyframes": len((info.get("drive") or {}).get("keyframes", []) or []),
                              "gaussians": info.get("gaussians")}), flush=True)
            views = places(args.drive, args.every, width, height)
            for p in views[: args.warmup]:
                c.get(f"/v1/scenes/{sid}/render", params={**p, "format": args.format})
            for n in range(args.passes):
                s0, n0 = server_render(c)
                times, errors = [], {}
                for i, p in enumerate(views):
                    # a distinct request each time (the render cache would answer a repeat): a pass moves the
                    # camera by n + 1 micrometres, far below anything the picture shows
                    q = {**p, "format": args.format, "forward": f"{(n + 1) * 1e-6:g}"}
                    t = time.perf_counter()
                    r = c.get(f"/v1/scenes/{sid}/render", params=q)
                    times.append(time.perf_counter() - t)
                    if r.status_code != 200:
                        errors[str(r.status_code)] = r.text[:300]
                s1, n1 = server_render(c)
                print(json.dumps({"case": "render", "pass": n + 1, "size": f"{width}x{height}",
                                  "format": args.format, **stats(times),
                                  "server_render_mean_s": round((s1 - s0) / max(1.0, n1 - n0), 4),
                                  "errors": errors}), flush=True)
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
