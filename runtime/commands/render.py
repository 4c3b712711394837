"""`xyzcyl render PLY|SCENE_DIR ...`: render a 3DGS PLY (INRIA layout) or a scene folder (`xyzcyl reconstruct`:
Gaussians composited over the scene's background panorama) from one camera pose. The view is stated as a
common.wire.ViewQuery (runtime.views.request) and encoded by runtime.views.encode_view, exactly as the HTTP service does: --out .png /
.jpg / .exr, --output rgb | depth | alpha (PNG depth: 16-bit millimetres; EXR: float32 metres), or for an .exr the
default "all" (float32 channels R G B A Z; Z = expected depth in metres, 0 where A == 0); --format png|jpeg|exr
must agree with --out's extension. The pose: --K or --fov with --cam-to-world (and a --distortion lens),
--equirect with --cam-to-world, or --camera NAME (an input camera of the scene's rig; with --distortion: its pose
and K through that lens), optionally moved (--forward/--left/--up metres along ego x/y/z, --yaw degrees to the
left; common.poses.CameraMove, applied by runtime.views.move_camera as the service applies the same query
parameters; the flags are shared with `xyzcyl client render`). --quiet: nothing on stdout or stderr but errors
(no summary line, no numba compile notice). See docs/renderer.md and docs/inference.md."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from xyzcyl.common.poses import (
    MOVE_NAMES,
    PoseArgError,
    add_format_argument,
    add_matrix_argument,
    add_move_arguments,
    move_from_args,
    out_format,
    parse_lens,
    parse_matrix,
)
from xyzcyl.common.wire import LOCAL_OUTPUTS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", metavar="PLY|SCENE_DIR",
                        help="Gaussians in the 3DGS PLY layout (world = ego frame), or a scene folder written by "
                             "`xyzcyl reconstruct` (its background is composited)")
    parser.add_argument("--width", type=int, default=None, help="image width, pixels (required unless --camera; "
                        "with --camera: resize that camera)")
    parser.add_argument("--height", type=int, default=None, help="image height, pixels (as --width)")
    parser.add_argument("--K", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="pinhole intrinsics in pixels, OpenCV (pixel u is centred at x = u); this or --fov is "
                             "required unless --equirect or --camera")
    parser.add_argument("--distortion", default=None, metavar="JSON|FILE",
                        help="the camera's lens, as rig.json writes it: an OpenCV coefficient list or {\"model\": "
                             "\"opencv\" | \"opencv_fisheye\" | \"ftheta\", ...} (docs/conventions.md, Lens models), "
                             "or a .json file holding it (or a rig camera entry); with --K or --fov, or with "
                             "--camera: that camera's pose and K through this lens")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help="horizontal field of view in degrees, instead of --K (square pixels, centred "
                             "principal point)")
    add_matrix_argument(parser, "--cam-to-world", "--cam-to-ego",
                        help="4x4 camera-to-ego matrix, the scene's frame (OpenCV camera: x right, y down, "
                             "z forward; --cam-to-ego is the same flag); required unless --camera")
    parser.add_argument("--camera", default=None, metavar="NAME",
                        help="SCENE_DIR only: render from this input camera of the scene's rig (its K, size, "
                             "lens, pose)")
    parser.add_argument("--out", required=True, metavar="PATH",
                        help="output file: .png, .jpg or .exr, encoded as the service encodes (docs/inference.md "
                             "'Encodings')")
    add_format_argument(parser)
    parser.add_argument("--output", choices=LOCAL_OUTPUTS, default=None,
                        help="what to write: rgb (default for .png/.jpg), depth (PNG: 16-bit millimetres; EXR: "
                             "float32 metres), alpha, or all (.exr only, the default there: R G B A Z)")
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality 1..100 (default 90)")
    parser.add_argument("--time", type=float, default=None, metavar="T",
                        help="seconds on the rigs' clock: a drive's scene draws its moving objects where they were "
                             "then (default: its first frame)")
    parser.add_argument("--actors", default=None, metavar="JSON|FILE.json",
                        help="a drive scene's actors edited for this view: a JSON list of {\"id\", and one of "
                             "\"pose\" (16 numbers, box -> scene frame), \"offset\" ([forward, left, up] metres), "
                             "\"hide\": true; \"insert\": a new id draws a copy}, or a .json file holding it "
                             "(docs/api.md 'Actors'; `xyzcyl actors SCENE_DIR` lists them)")
    parser.add_argument("--background", type=float, nargs=3, default=None, metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default: the scene's background panorama for a "
                             "SCENE_DIR, black for a PLY)")
    parser.add_argument("--equirect", action="store_true",
                        help="render a full 360x180 equirectangular panorama instead (K not used)")
    parser.add_argument("--antialiased", action="store_true", help="gsplat's antialiased opacity compensation")
    parser.add_argument("--max-points", type=int, default=None, help="refuse PLYs with more Gaussians")
    parser.add_argument("--threads", type=int, default=None, help="renderer threads (default: all cores)")
    parser.add_argument("--quiet", "-q", action="store_true",
                        help="print nothing but errors (no summary line, no numba compile notice)")
    add_move_arguments(parser)
    lidar = parser.add_argument_group("LiDAR (docs/simulators.md 'LiDAR')")
    lidar.add_argument("--lidar", nargs="?", const="pandar128", default=None, metavar="MODEL",
                       help="simulate one LiDAR sweep instead of an image: pandar128 (default), at128 or pandar64 "
                            "(nominal beam layouts); --out .ply (x y z intensity ring) or .npy (float32 N x 4: x y z "
                            "intensity), points in the end-of-spin LiDAR frame")
    add_matrix_argument(lidar, "--lidar-pose",
                        help="--lidar: the LiDAR's pose at the spin's start, lidar -> the scene's frame (LiDAR axes x "
                             "forward, y left, z up; default: the identity, the scene's origin)")
    add_matrix_argument(lidar, "--lidar-end-pose", help="--lidar: its pose at the spin's end (default: --lidar-pose)")
    lidar.add_argument("--lidar-beams", default=None, metavar="JSON|FILE.json",
                       help="--lidar: beam elevations of one's own, degrees (a JSON list, or a .json file holding one)")
    lidar.add_argument("--azimuth-step", type=float, default=None, metavar="DEG",
                       help="--lidar: degrees between columns (default: the model's)")
    lidar.add_argument("--max-range", type=float, default=None, metavar="M",
                       help="--lidar: metres (default: the model's)")


def _fail(msg: str) -> int:
    print(f"xyzcyl render: {msg}", file=sys.stderr)
    return 2


# where each ViewQuery field comes from on this command line (its errors name the flag)
FLAGS = {"camera": "--camera", "cam_to_ego": "--cam-to-world", "fx": "--K", "fy": "--K", "cx": "--K", "cy": "--K",
         "fov": "--fov", "distortion": "--distortion", "width": "--width", "height": "--height", "output": "--output",
         "format": "--out", "quality": "--quality", "time": "--time", "actors": "--actors",
         **{k: f"--{k}" for k in MOVE_NAMES}}


def run(args: argparse.Namespace) -> int:
    from xyzcyl.common.files import atomic_file
    from xyzcyl.common.wire import ViewError, actor_edits, validated

    from ..render import GaussianError, Gaussians, render
    from ..render.gaussians import DEFAULT_MAX_POINTS
    from ..scene import JSON_NAME, Scene, SceneError
    from ..views import ViewRequest, encode_view, equirect_camera, request

    if args.quiet:       # the numba compile notice (runtime.compile_notice) goes nowhere
        from ..compile_notice import install

        install(lambda line: None)
    if args.lidar is not None:
        return run_lidar(args)
    if any(v is not None for v in (args.lidar_pose, args.lidar_end_pose, args.lidar_beams, args.azimuth_step,
                                   args.max_range)):
        return _fail("--lidar-pose, --lidar-end-pose, --lidar-beams, --azimuth-step, --max-range: need --lidar")
    out = Path(args.out)
    try:
        fmt = out_format(out, args.format)
    except PoseArgError as exc:
        return _fail(str(exc))
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")
    if args.background is not None and not all(np.isfinite(args.background)):
        return _fail("--background: values must be finite")
    try:
        move = move_from_args(args)
        c2w = None if args.cam_to_world is None else parse_matrix(args.cam_to_world, "--cam-to-world")
        lens = None if args.distortion is None else parse_lens(args.distortion)
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
        if args.cam_to_world is not None or args.K is not None or args.fov is not None or args.equirect:
            return _fail("--camera: give either --camera or --K/--fov/--cam-to-world/--equirect, not both (an "
                         "input camera has its own K and pose; --distortion gives it another lens)")
    else:
        if args.cam_to_world is None:
            return _fail("--cam-to-world: required (or --camera NAME with a SCENE_DIR)")
        if args.width is None or args.height is None:
            return _fail(f"--{'width' if args.width is None else 'height'}: required unless --camera")
        if not args.equirect and args.K is None and args.fov is None:
            return _fail("--K: required for a pinhole camera (or --fov, or pass --equirect)")
    if is_scene and not (src / JSON_NAME).is_file():
        return _fail(f"SCENE_DIR: {str(src)!r} has no {JSON_NAME} (not a scene folder)")
    if not is_scene and not src.is_file():
        return _fail(f"PLY: no such file {args.ply!r}")
    max_points = DEFAULT_MAX_POINTS if args.max_points is None else args.max_points
    scene = None
    try:
        if is_scene:
            scene = Scene.load(src, max_points=max_points)
            g = None            # a drive's scene reads only the tiles the view sees (runtime.tiles)
        else:
            g = Gaussians.load_ply(src, max_points=max_points)
    except SceneError as exc:
        return _fail(f"{what}: {exc}")
    except GaussianError as exc:     # its where names the PLY file ("PLY 'g.ply'")
        return _fail(str(exc))
    fx, fy, cx, cy = args.K if args.K is not None else (None,) * 4
    output = args.output or ("all" if fmt == "exr" else "rgb")
    names = FLAGS if args.format is None else {**FLAGS, "format": "--format"}
    wire = {"output": "rgb"} if output == "all" else {"output": output}    # "all" (R G B A Z) is local: no wire value
    try:
        edits = () if args.actors is None else actor_edits(args.actors, "--actors")
        if edits and scene is None:
            raise ViewError("--actors", "a PLY has no actors: give a drive's SCENE_DIR")
        if args.equirect:        # a 360x180 panorama: a pose and a size, no intrinsics (not a wire view)
            given = [f for f, v in (("--K", args.K), ("--fov", args.fov), ("--distortion", lens)) if v is not None]
            if given:
                raise ViewError(given[0], "an equirectangular panorama takes no intrinsics")
            req = ViewRequest(equirect_camera(c2w, args.width, args.height, move, names), output, fmt, args.quality,
                              args.time, edits)
        else:
            query = validated({"camera": args.camera, "cam_to_ego": c2w, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
                               "fov": args.fov, "distortion": lens, **move.values(), "width": args.width,
                               "height": args.height, **wire, "format": fmt, "quality": args.quality,
                               "time": args.time, "actors": edits or None}, names)
            req = request(query, None if scene is None else scene.rig, names, output=output)
        if scene is not None:
            scene.check_actors(req.actors, req.time_s, "--actors")
    except ViewError as exc:
        return _fail(str(exc))
    cam = req.camera
    if args.background is not None:
        bg = args.background
    elif scene is not None and scene.background is not None:
        bg = scene.background.render(cam)
    else:
        bg = None
    if scene is not None:    # what the service renders for this camera (runtime.scene.render_view)
        rgb, depth, alpha = scene.render(cam, req.time_s, background=bg, actors=req.actors,
                                         antialiased=args.antialiased)
    else:
        res = render(g, cam, background=bg, antialiased=args.antialiased)
        rgb, depth, alpha = res.rgb, res.depth, res.alpha
    data = encode_view(rgb, depth, alpha, req)
    try:
        with atomic_file(out) as f:
            f.write(data)
    except OSError as exc:
        return _fail(f"--out: {exc}")
    if not args.quiet:
        chunks = " and the view's viewpoint chunks" if scene is not None and scene.viewpoints is not None else ""
        if scene is None:
            n = len(g)
        elif scene.tiles is not None:      # a drive's: the tiles the view sees (runtime.tiles)
            seen = scene.tiles.visible(cam, antialiased=args.antialiased)
            n = sum(scene.tiles.tiles[t].count for t in seen)
            chunks = f" (the {len(seen)} of {len(scene.tiles)} tiles the view sees)" + chunks
            k = scene.primary_keyframe(cam, req.time_s)
            layer = scene.camera_layer(cam, k) if k is not None else None
            if layer is not None:           # drawn first: the view stands at a keyframe's camera
                chunks += f", over them the camera layer of the camera it stands at ({len(layer)} Gaussians)"
        else:
            n = len(scene.gaussians)
        print(f"rendered {n} Gaussians{chunks} -> {out} ({cam.width}x{cam.height}, "
              f"coverage {float((alpha > 0).mean()):.3f}{', with background' if bg is not None else ''})")
    return 0


LIDAR_OUT = {".ply": "ply", ".npy": "npy"}
_LIDAR_IMAGE_FLAGS = ("K", "fov", "cam_to_world", "camera", "equirect", "distortion", "output", "background",
                      "width", "height", "format")


def _lidar_beams(value: str) -> list:
    import json

    text = Path(value).read_text() if value.strip().endswith(".json") and Path(value).is_file() else value
    try:
        beams = json.loads(text)
    except ValueError:
        raise PoseArgError("--lidar-beams", "a JSON list of elevations in degrees expected (or a .json file)") from None
    if not isinstance(beams, list):
        raise PoseArgError("--lidar-beams", f"a JSON list of elevations in degrees expected (got {type(beams).__name__})")
    return beams


def run_lidar(args: argparse.Namespace) -> int:
    """`xyzcyl render SCENE_DIR|PLY --lidar [MODEL] --out F.ply|F.npy`: one simulated sweep (runtime.lidarsim)."""
    from xyzcyl.common.files import atomic_file
    from xyzcyl.common.wire import ViewError, actor_edits

    from ..errors import FieldError
    from ..lidarsim import gaussians_drawer, lidar_model, render_lidar, scene_drawer, sweep_bytes
    from ..render import GaussianError, Gaussians
    from ..render.gaussians import DEFAULT_MAX_POINTS
    from ..scene import JSON_NAME, Scene, SceneError

    if args.quiet:
        from ..compile_notice import install

        install(lambda line: None)
    given = [f for f in _LIDAR_IMAGE_FLAGS if getattr(args, f) not in (None, False)]
    if given:
        return _fail(f"--{given[0].replace('_', '-')}: an image flag; --lidar renders a sweep (its pose: --lidar-pose)")
    if any(getattr(args, k) for k in MOVE_NAMES if getattr(args, k, None) is not None):
        return _fail("--forward/--left/--up/--yaw: image flags; move the LiDAR with --lidar-pose")
    out = Path(args.out)
    fmt = LIDAR_OUT.get(out.suffix.lower())
    if fmt is None:
        return _fail(f"--out: a LiDAR sweep is written as .ply or .npy (got {out.suffix or 'no extension'!r})")
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")
    if args.time is not None and not np.isfinite(args.time):
        return _fail("--time: must be finite")
    try:
        start = np.eye(4) if args.lidar_pose is None else parse_matrix(args.lidar_pose, "--lidar-pose")
        end = None if args.lidar_end_pose is None else parse_matrix(args.lidar_end_pose, "--lidar-end-pose")
        beams = None if args.lidar_beams is None else _lidar_beams(args.lidar_beams)
    except PoseArgError as exc:
        return _fail(str(exc))
    try:
        model = lidar_model(args.lidar, elevations_deg=beams, azimuth_step_deg=args.azimuth_step,
                            max_range_m=args.max_range,
                            fields={"model": "--lidar", "elevations_deg": "--lidar-beams",
                                    "azimuth_step_deg": "--azimuth-step", "max_range_m": "--max-range"})
    except ViewError as exc:
        return _fail(str(exc))
    src = Path(args.ply)
    if not src.exists():
        return _fail(f"PLY|SCENE_DIR: {args.ply!r} does not exist")
    max_points = DEFAULT_MAX_POINTS if args.max_points is None else args.max_points
    try:
        if src.is_dir():
            if not (src / JSON_NAME).is_file():
                return _fail(f"SCENE_DIR: {str(src)!r} has no {JSON_NAME} (not a scene folder)")
            scene = Scene.load(src, max_points=max_points)
            edits = () if args.actors is None else actor_edits(args.actors, "--actors")
            scene.check_actors(edits, args.time, "--actors")
            draw = scene_drawer(scene, args.time, edits)
        else:
            if args.actors is not None:
                return _fail("--actors: a PLY has no actors: give a drive's SCENE_DIR")
            draw = gaussians_drawer(Gaussians.load_ply(src, max_points=max_points))
    except SceneError as exc:
        return _fail(f"SCENE_DIR: {exc}")
    except (GaussianError, ViewError) as exc:
        return _fail(str(exc))
    try:
        sweep = render_lidar(draw, model, start, end)
    except FieldError as exc:       # a pose that is no rigid transform
        flag = "--lidar-end-pose" if end is not None and "end" in str(exc) else "--lidar-pose"
        return _fail(f"{flag}: {exc.message}")
    try:
        with atomic_file(out) as f:
            f.write(sweep_bytes(sweep, fmt))
    except OSError as exc:
        return _fail(f"--out: {exc}")
    if not args.quiet:
        st = sweep.stats
        print(f"LiDAR {model.name}: {st['returns']} points of {st['rays']} rays ({model.beams} beams x "
              f"{model.columns} columns, {st['sectors']} sectors) -> {out}")
    return 0
