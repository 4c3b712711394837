"""`xyzcyl export SCENE_DIR --format usdz --out scene.usdz [--scene-id ID]`: a scene folder in a format other tools
open. ``usdz``: an AlpaSim scene artifact (runtime.usdz; docs/simulators.md "Scene artifacts (USDZ)"): the rig's
trajectory, cameras, tracks, a ground mesh and the Gaussians as a NuRec volume, for AlpaSim pointed at the artifact
and at `xyzcyl serve --grpc-port`. Prints the export's report as JSON; exit 2 for bad input.

The model's ONNX export, which `xyzcyl export --checkpoint` ran before, is `xyzcyl export-model` (the old spelling
still runs it, with a notice, until the next release: xyzcyl.cli)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

FORMATS = ("usdz",)
LATER = {"gltf": "glTF", "glb": "glTF", "spz": "SPZ"}     # the exchange formats of the web viewer's issue (not yet)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE_DIR", help="a scene folder (of `xyzcyl reconstruct`)")
    parser.add_argument("--format", default="usdz", metavar="FORMAT",
                        help="usdz: an AlpaSim scene artifact (the trajectory, cameras, tracks, a ground mesh and "
                             "the Gaussians as a NuRec volume) (default usdz)")
    parser.add_argument("--out", required=True, metavar="FILE", help="the file to write (replaced atomically)")
    parser.add_argument("--scene-id", default=None, metavar="ID",
                        help="the scene id written into the artifact: the id AlpaSim asks the renderer for (a "
                             "served scene's name, else its id: what `xyzcyl serve --grpc-port` lists); default "
                             "the folder's name")


def _fail(message: str) -> int:
    print(f"xyzcyl export: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from ..scene import JSON_NAME, SceneError
    from ..usdz import UsdzError, export_usdz

    fmt = str(args.format).lower()
    if fmt in LATER:
        return _fail(f"--format: {LATER[fmt]} export is not available yet; formats: {', '.join(FORMATS)}")
    if fmt not in FORMATS:
        return _fail(f"--format: {args.format!r} is not one of {', '.join(FORMATS)}")
    out = Path(args.out)
    if out.suffix.lower() != ".usdz":
        return _fail(f"--out: {str(out)!r}: a USDZ file's name ends in .usdz (AlpaSim finds artifacts by it)")
    if not out.parent.is_dir():
        return _fail(f"--out: the folder {str(out.parent)!r} does not exist")
    if not (Path(args.scene) / JSON_NAME).is_file():
        return _fail(f"SCENE_DIR: {str(args.scene)!r} is not a scene folder (no {JSON_NAME} there)")
    try:
        report = export_usdz(args.scene, out, args.scene_id,
                             progress=lambda msg: print(f"xyzcyl export: {msg}", file=sys.stderr))
    except SceneError as e:
        return _fail(f"SCENE_DIR: {e}")
    except UsdzError as e:
        return _fail(str(e))
    for note in report.notes:
        print(f"xyzcyl export: note: {note}", file=sys.stderr)
    print(json.dumps(report.to_json(), indent=1))
    return 0
