"""`xyzcyl actors SCENE_DIR [--time T]`: a drive scene's actors as JSON (what GET /v1/scenes/{id}/actors answers:
runtime.scene.Scene.actor_list): each moving object's id (the id a render's actor edits name), label, box size,
time span, copies and Gaussians; with --time, its pose then (box -> the scene's frame, 16 numbers row-major)."""

from __future__ import annotations

import argparse
import json
import math
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE_DIR", help="a scene folder (of `xyzcyl reconstruct DRIVE.json`)")
    parser.add_argument("--time", type=float, default=None, metavar="T",
                        help="seconds on the rigs' clock: each actor's pose then (null when it is not drawn then)")


def run(args: argparse.Namespace) -> int:
    from ..scene import JSON_NAME, Scene, SceneError

    if args.time is not None and not math.isfinite(args.time):
        print(f"xyzcyl actors: --time: must be a finite number of seconds (got {args.time})", file=sys.stderr)
        return 2
    try:
        scene = Scene.load(args.scene)
    except (SceneError, FileNotFoundError, NotADirectoryError) as e:
        hint = "" if not isinstance(e, (FileNotFoundError, NotADirectoryError)) else f" (no {JSON_NAME} there)"
        print(f"xyzcyl actors: SCENE_DIR: {e}{hint}", file=sys.stderr)
        return 2
    print(json.dumps(scene.actor_list(args.time), indent=1))
    return 0
