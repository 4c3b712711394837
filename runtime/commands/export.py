"""`xyzcyl export SCENE_DIR --format usdz|gltf|glb|spz|ply|splat --out FILE [--time T] [--scene-id ID]`: a scene
folder in a format other tools open (runtime.exports; docs/cli.md). ``usdz``: an AlpaSim scene artifact
(runtime.usdz; docs/simulators.md "Scene artifacts (USDZ)"): the rig's trajectory, cameras, tracks, a ground mesh
and the Gaussians as a NuRec volume, for AlpaSim pointed at the artifact and at `xyzcyl serve --grpc-port`.
``gltf`` / ``glb``: glTF 2.0 with KHR_gaussian_splatting, the static scene as one node and a drive's actors each
as its own node at --time. ``spz`` (Niantic's compressed splats), ``ply`` (3DGS), ``splat`` (antimatter15): one
cloud, a drive's actors at --time baked in. --time: seconds on the rigs' clock (default the drive's first frame).
Prints the export's report as JSON; exit 2 for bad input.

The model's ONNX export, which `xyzcyl export --checkpoint` ran before, is `xyzcyl export-model` (the old spelling
still runs it, with a notice, until the next release: xyzcyl.cli)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

FLAGS = {"format": "--format", "time": "--time", "scene_id": "--scene-id", "out": "--out"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE_DIR", help="a scene folder (of `xyzcyl reconstruct`)")
    parser.add_argument("--format", default="usdz", metavar="FORMAT",
                        help="usdz: an AlpaSim scene artifact (the trajectory, cameras, tracks, a ground mesh and "
                             "the Gaussians as a NuRec volume); gltf / glb: glTF 2.0 with KHR_gaussian_splatting "
                             "(+Y up; a drive's actors as nodes at --time); spz: Niantic's compressed splats; ply: "
                             "3DGS PLY; splat: antimatter15 .splat (spz, ply, splat: one cloud, a drive's actors at "
                             "--time baked in) (default usdz)")
    parser.add_argument("--out", required=True, metavar="FILE",
                        help="the file to write, named FILE.<format> (replaced atomically)")
    parser.add_argument("--time", type=float, default=None, metavar="T",
                        help="a drive: seconds on the rigs' clock, the time its actors are placed at (default the "
                             "drive's first frame; not for usdz, which holds every frame)")
    parser.add_argument("--scene-id", default=None, metavar="ID",
                        help="usdz: the scene id written into the artifact: the id AlpaSim asks the renderer for (a "
                             "served scene's name, else its id: what `xyzcyl serve --grpc-port` lists); gltf/glb: "
                             "the root node's name; default the folder's name")


def _fail(message: str) -> int:
    print(f"xyzcyl export: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from ..exports import ExportError, check_request, export_scene
    from ..scene import JSON_NAME, SceneError
    from ..usdz import UsdzError

    try:
        fmt = check_request(args.format, args.time, args.scene_id)
    except ExportError as e:
        return _fail(f"{FLAGS.get(e.field, e.field)}: {e.message}")
    out = Path(args.out)
    if out.suffix.lower() != f".{fmt}":
        why = " (AlpaSim finds artifacts by it)" if fmt == "usdz" else ""
        return _fail(f"--out: {str(out)!r}: a {fmt} file's name ends in .{fmt}{why}")
    if not out.parent.is_dir():
        return _fail(f"--out: the folder {str(out.parent)!r} does not exist")
    if not (Path(args.scene) / JSON_NAME).is_file():
        return _fail(f"SCENE_DIR: {str(args.scene)!r} is not a scene folder (no {JSON_NAME} there)")
    try:
        report = export_scene(args.scene, out, fmt, args.time, args.scene_id,
                              progress=lambda msg: print(f"xyzcyl export: {msg}", file=sys.stderr))
    except SceneError as e:
        return _fail(f"SCENE_DIR: {e}")
    except ExportError as e:
        return _fail(f"{FLAGS.get(e.field, e.field)}: {e.message}")
    except UsdzError as e:
        return _fail(str(e))
    for note in report.notes:
        print(f"xyzcyl export: note: {note}", file=sys.stderr)
    print(json.dumps(report.to_json(), indent=1))
    return 0
