"""`xyzcyl export` of a scene folder to the exchange formats, measured (runtime.exports): the scene's load once,
then per format the seconds to write it (best of --repeat) and the file's size. Prints one JSON line.

    NUMBA_CACHE_DIR=/tmp/nc .venv/bin/python benchmarks/export_bench.py SCENE_DIR --out-dir /tmp/exports \\
        --formats ply,spz,glb [--time T] [--repeat 1]

A drive's actors are placed at --time (default its first frame): glTF nodes, baked into the single clouds."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

FORMATS = ("gltf", "glb", "spz", "ply", "splat")        # runtime.exports.FORMATS without usdz (usdz_bench.py)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", metavar="SCENE_DIR")
    p.add_argument("--out-dir", required=True, metavar="DIR", help="the files are written here (scene.<format>)")
    p.add_argument("--formats", default="ply,spz,glb", help=f"comma-separated, of {', '.join(FORMATS)}")
    p.add_argument("--time", type=float, default=None, metavar="T", help="a drive: when its actors are placed")
    p.add_argument("--repeat", type=int, default=1, help="writes per format; the best is reported (default 1)")
    a = p.parse_args(argv)
    a.formats = [f.strip().lower() for f in a.formats.split(",") if f.strip()]
    bad = [f for f in a.formats if f not in FORMATS]
    if bad or not a.formats:
        p.error(f"--formats: {', '.join(bad) or 'none given'}: not of {', '.join(FORMATS)}")
    if a.repeat < 1:
        p.error(f"--repeat: must be >= 1 (got {a.repeat})")
    if not Path(a.out_dir).is_dir():
        p.error(f"--out-dir: {a.out_dir!r} is not a folder")
    return a


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    from xyzcyl.runtime.exports import write_scene
    from xyzcyl.runtime.scene import Scene

    t0 = time.perf_counter()
    scene = Scene.load(a.scene)
    load_s = time.perf_counter() - t0
    rows = []
    for fmt in a.formats:
        out = Path(a.out_dir) / f"scene.{fmt}"
        best = None
        for _ in range(a.repeat):
            report = write_scene(scene, out, fmt, a.time, Path(a.scene).resolve().name)
            best = report if best is None or report.seconds < best.seconds else best
        rows.append({"format": fmt, "seconds": round(best.seconds, 3), "bytes": best.bytes,
                     "megabytes": round(best.bytes / 1e6, 2), "gaussians": best.gaussians,
                     "bytes_per_gaussian": round(best.bytes / max(best.gaussians, 1), 2),
                     "actors": len(best.actors), "time_s": best.time_s})
    print(json.dumps({"scene": str(a.scene), "gaussians": len(scene.gaussians),
                      "actors": 0 if scene.actors is None else len(scene.actors),
                      "load_seconds": round(load_s, 3), "repeat": a.repeat, "formats": rows}))


if __name__ == "__main__":
    main()
