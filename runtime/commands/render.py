"""`xyzcyl render PLY|SCENE_DIR ...`: render a 3DGS PLY (INRIA layout) or a scene folder (`xyzcyl reconstruct`:
Gaussians composited over the scene's background panorama) from one camera pose to PNG (RGB) or EXR (float32
channels R G B A Z; Z = expected depth in metres, 0 where A == 0). The pose: --K/--cam-to-world, or --camera NAME
(an input camera of the scene's rig), optionally moved (--forward/--left/--up metres along ego x/y/z, --yaw degrees
to the left; common/poses.py, shared with `xyzcyl client render`). See docs/renderer.md and
docs/inference.md."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from xyzcyl.common.poses import (
    PoseArgError,
    add_matrix_argument,
    add_move_arguments,
    move_from_args,
    parse_matrix,
)

from ..rig import RigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", metavar="PLY|SCENE_DIR",
                        help="Gaussians in the 3DGS PLY layout (world = ego frame), or a scene folder written by "
                             "`xyzcyl reconstruct` (its background is composited)")
    parser.add_argument("--width", type=int, default=None, help="image width, pixels (required unless --camera; "
                        "with --camera: resize that camera)")
    parser.add_argument("--height", type=int, default=None, help="image height, pixels (as --width)")
    parser.add_argument("--K", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="pinhole intrinsics in pixels, OpenCV (pixel u is centred at x = u); required "
                             "unless --equirect or --camera")
    add_matrix_argument(parser, "--cam-to-world",
                        help="4x4 camera-to-world matrix (OpenCV camera: x right, y down, z forward); required "
                             "unless --camera")
    parser.add_argument("--camera", default=None, metavar="NAME",
                        help="SCENE_DIR only: render from this input camera of the scene's rig (its K, size, pose)")
    parser.add_argument("--out", required=True, metavar="PATH", help="output .png (RGB, 8 bit) or .exr "
                        "(float32 R G B A Z)")
    parser.add_argument("--background", type=float, nargs=3, default=None, metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default: the scene's background panorama for a "
                             "SCENE_DIR, black for a PLY)")
    parser.add_argument("--equirect", action="store_true",
                        help="render a full 360x180 equirectangular panorama instead (K not used)")
    parser.add_argument("--antialiased", action="store_true", help="gsplat's antialiased opacity compensation")
    parser.add_argument("--max-points", type=int, default=None, help="refuse PLYs with more Gaussians")
    parser.add_argument("--threads", type=int, default=None, help="renderer threads (default: all cores)")
    add_move_arguments(parser)


def _fail(msg: str) -> int:
    print(f"xyzcyl render: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from xyzcyl.common.media import write_exr

    from ..imageio import write_png
    from ..render import CameraError, EquirectCamera, GaussianError, Gaussians, PinholeCamera, render
    from ..render.gaussians import DEFAULT_MAX_POINTS
    from ..scene import JSON_NAME, Scene, SceneError, rig_camera

    out = Path(args.out)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".exr"):
        return _fail(f"--out: extension must be .png or .exr, got {out.suffix or 'none'!r}")
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")
    if args.background is not None and not all(np.isfinite(args.background)):
        return _fail("--background: values must be finite")
    try:
        move = move_from_args(args)
        c2w = None if args.cam_to_world is None else parse_matrix(args.cam_to_world, "--cam-to-world")
    except PoseArgError as exc:
        return _fail(str(exc))
    for flag, v in (("--width", args.width), ("--height", args.height)):
        if v is not None and v < 1:          # 0 too: with --camera it would mean "the camera's own size"
            return _fail(f"{flag}: must be >= 1, got {v}")
    if args.threads is not None:
        if args.threads < 1:
            return _fail(f"--threads: must be >= 1, got {args.threads}")
        import numba

        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    src = Path(args.ply)
    is_scene = src.is_dir()
    what = "SCENE_DIR" if is_scene else "PLY"
    if not src.exists():
        return _fail(f"PLY|SCENE_DIR: {args.ply!r} does not exist")
    if args.camera is not None:
        if not is_scene:
            return _fail("--camera: needs a SCENE_DIR (a PLY has no rig); pass --K and --cam-to-world instead")
        if args.cam_to_world is not None or args.K is not None or args.equirect:
            return _fail("--camera: give either --camera or --K/--cam-to-world/--equirect, not both")
    else:
        if args.cam_to_world is None:
            return _fail("--cam-to-world: required (or --camera NAME with a SCENE_DIR)")
        if args.width is None or args.height is None:
            return _fail(f"--{'width' if args.width is None else 'height'}: required unless --camera")
        if not args.equirect and args.K is None:
            return _fail("--K: required for a pinhole camera (or pass --equirect)")
    if is_scene and not (src / JSON_NAME).is_file():
        return _fail(f"SCENE_DIR: {str(src)!r} has no {JSON_NAME} (not a scene folder)")
    if not is_scene and not src.is_file():
        return _fail(f"PLY: no such file {args.ply!r}")
    max_points = DEFAULT_MAX_POINTS if args.max_points is None else args.max_points
    scene = None
    try:
        if is_scene:
            scene = Scene.load(src, max_points=max_points)
            g = scene.gaussians
        else:
            g = Gaussians.load_ply(src, max_points=max_points)
    except (GaussianError, SceneError) as exc:
        return _fail(f"{what}: {exc}")
    try:
        if args.camera is not None:
            try:
                rc = scene.rig.camera(args.camera)
            except KeyError:
                return _fail(f"--camera: no camera {args.camera!r} in the scene's rig (cameras: "
                             f"{', '.join(scene.rig.names)})")
            if move:
                rc = replace(rc, cam_to_ego=move.apply(rc.cam_to_ego))
            cam = rig_camera(rc, width=args.width, height=args.height)
        else:
            c2w = move.apply(c2w)
            if args.equirect:
                cam = EquirectCamera(c2w, args.width, args.height)
            else:
                fx, fy, cx, cy = args.K
                cam = PinholeCamera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), c2w, args.width, args.height)
    except CameraError as exc:
        flag = {"cam_to_world": "--cam-to-world", "K": "--K"}.get(exc.field, f"--{exc.field}")
        return _fail(f"{flag}: {exc.message}")
    except RigError as exc:
        flag = "--camera" if args.camera is not None else "--width"
        return _fail(f"{flag}: {str(exc).split(': ', 1)[-1]}")
    if args.background is not None:
        bg = args.background
    elif scene is not None and scene.background is not None:
        bg = scene.background.render(cam)
    else:
        bg = None
    res = render(g, cam, background=bg, antialiased=args.antialiased)
    try:
        if suffix == ".png":
            write_png(out, res.rgb)
        else:
            write_exr(str(out), np.dstack([res.rgb, res.alpha, res.depth]), ("R", "G", "B", "A", "Z"))
    except OSError as exc:
        return _fail(f"--out: {exc}")
    print(f"rendered {len(g)} Gaussians -> {out} ({cam.width}x{cam.height}, "
          f"coverage {float((res.alpha > 0).mean()):.3f}{', with background' if bg is not None else ''})")
    return 0
