"""`xyzcyl client ACTION ...`: drive a running `xyzcyl serve` over HTTP (clients/client.py; docs/client.md).

    xyzcyl client reconstruct RIG_JSON|DRIVE_JSON [--wait [S]] [--detail-stride N | --no-detail]
                         [--keyframe-spacing M] [--keyframe-gap S] [--json]
    xyzcyl client render SCENE_ID (--camera NAME | --K FX FY CX CY --cam-to-world M*16 | --cam-to-world M*16 --fov F
                         | --carla X Y Z PITCH YAW ROLL --fov F) [--distortion JSON|FILE] [--width W --height H]
                         --out FILE [--format png|jpeg|exr] [--output rgb|depth|alpha] [--quality Q]
                         [--forward M] [--left M] [--up M] [--yaw DEG]
    xyzcyl client path SCENE_ID CAMERA_PATH_JSON --out DIR [--video OUT.mp4] [--fps N] [--output ...] [--format ...]
    xyzcyl client gaussians SCENE_ID --out scene.ply|scene.splat
    xyzcyl client scene SCENE_ID [--wait [S]]
    xyzcyl client scenes [--json]
    xyzcyl client delete SCENE_ID

Every action takes --server URL (default $XYZCYL_SERVER, else http://127.0.0.1:8000), --api-key KEY (default
$XYZCYL_API_KEY), --timeout S and --quiet (no progress bars or summaries on stderr). Errors exit with status 2 and
one line, ``xyzcyl client: <field>: <message> [<status> <code>]``, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from xyzcyl.common.wire import FORMATS, OUTPUTS, detail_stride_error, keyframe_error

_SCENE_HELP = "the scene's id (printed by `xyzcyl client reconstruct`)"


class _UsageError(Exception):
    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")


def _common() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("server")
    g.add_argument("--server", default=None, metavar="URL",
                   help="the service's base URL (default $XYZCYL_SERVER, else http://127.0.0.1:8000)")
    g.add_argument("--api-key", default=None, metavar="KEY", help="API key (default $XYZCYL_API_KEY)")
    g.add_argument("--timeout", type=float, default=60.0, metavar="S", help="seconds per request (default 60)")
    g.add_argument("--quiet", "-q", action="store_true", help="no progress bars or summaries on stderr")
    return p


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # the pose flags of `xyzcyl render` (one definition; a light module: argparse at import, numpy when run)
    from xyzcyl.common.poses import add_format_argument, add_matrix_argument, add_move_arguments

    parser.description = ("Talk to a running `xyzcyl serve` (docs/client.md): reconstruct a rig, render views and "
                          "camera paths, download Gaussians, list and delete scenes.")
    common = _common()
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    p = sub.add_parser("reconstruct", parents=[common], help="upload a rig.json and its images, or a recorded drive; "
                       "print the scene id",
                       description="Upload RIG_JSON with the images (and depth and ego mask files) it names, "
                                   "relative to its folder; or a drive file (DRIVE_JSON: frames of rigs with the "
                                   "ego's poses and times; docs/inference.md \"Drives\") with every frame's files, "
                                   "as one scene. Prints the scene id on stdout (the scene JSON with --json).")
    p.add_argument("rig", metavar="RIG_JSON|DRIVE_JSON",
                   help="the rig.json (the files it names are read relative to its folder), or a drive file (its "
                        "rigs relative to it, each rig's files relative to the rig)")
    p.add_argument("--wait", nargs="?", type=float, const=600.0, default=None, metavar="S",
                   help="wait until the scene is ready or failed, up to S seconds (default 600)")
    p.add_argument("--no-depth", action="store_true", help="do not upload the depth files the rig names")
    p.add_argument("--no-lidar", action="store_true", help="do not upload the LiDAR file the rig's lidar block names "
                   "(the server then uses the depth head alone)")
    p.add_argument("--detail-stride", type=int, default=None, metavar="N",
                   help="detail layer: one Gaussian per N x N block of each input camera's pixels, 1..16 (default: "
                        "the server's, 2)")
    p.add_argument("--no-detail", action="store_true", help="no detail layer (the model's Gaussians only)")
    p.add_argument("--keyframe-spacing", type=float, default=None, metavar="M",
                   help="a drive: a keyframe each M metres the ego moves (default: the server's, 1.5)")
    p.add_argument("--keyframe-gap", type=float, default=None, metavar="S",
                   help="a drive: a keyframe at least every S seconds, moving or not (default: the server's, 2)")
    p.add_argument("--stationary-actors", action="store_true",
                   help="a drive: its tracks marked stationary (parked cars) become actors too, which a render can "
                        "hide or move (default: they stay in the static scene)")
    p.add_argument("--json", action="store_true", help="print the scene JSON instead of its id")

    p = sub.add_parser("render", parents=[common], help="render one view to a file (png, jpg or exr)",
                       description="Render one view and write the server's bytes to --out as they are; the "
                                   "extension picks the format (.png, .jpg/.jpeg, .exr), or --format (which must "
                                   "agree with it). Poses are in the scene's ego frame (x forward, y left, z up, "
                                   "metres; docs/api.md); the moves apply to any pose, the input camera's too.")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)
    pose = p.add_argument_group("pose (exactly one of --camera, --cam-to-world, --carla)")
    pose.add_argument("--camera", metavar="NAME", help="an input camera of the scene's rig")
    add_matrix_argument(pose, "--cam-to-world", "--cam-to-ego",
                        help="4x4 camera-to-ego matrix, OpenCV camera axes (x right, y down, z forward; "
                             "--cam-to-ego is the same flag); with --K or --fov")
    pose.add_argument("--K", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                      help="pinhole intrinsics in pixels (OpenCV: pixel u is centred at x = u)")
    pose.add_argument("--carla", type=float, nargs=6, metavar=("X", "Y", "Z", "PITCH", "YAW", "ROLL"),
                      help="a CARLA camera sensor's transform relative to the vehicle (metres, degrees; CARLA's "
                           "left-handed axes); with --fov")
    pose.add_argument("--fov", type=float, metavar="DEG", help="horizontal field of view, degrees")
    pose.add_argument("--distortion", metavar="JSON|FILE",
                      help="the camera's lens as rig.json writes it (an OpenCV coefficient list or {\"model\": "
                           "\"opencv\" | \"opencv_fisheye\" | \"ftheta\", ...}), or a .json file holding it; with "
                           "--cam-to-world, or with --camera: that camera's pose and K through this lens")
    p.add_argument("--time", type=float, default=None, metavar="T",
                   help="seconds on the rigs' clock: a drive's scene draws its moving objects then (default the "
                        "drive's first frame)")
    p.add_argument("--actors", default=None, metavar="JSON|FILE.json",
                   help="a drive scene's actors edited for this view: a JSON list of {\"id\", and one of \"pose\" "
                        "(16 numbers, box -> scene frame), \"offset\" ([forward, left, up] metres), \"hide\": "
                        "true; \"insert\": a new id draws a copy}, or a .json file holding it (`xyzcyl client "
                        "actors SCENE_ID` lists them)")
    p.add_argument("--width", type=int, metavar="W", help="pixels (required unless --camera; with --camera: resize)")
    p.add_argument("--height", type=int, metavar="H", help="pixels (as --width)")
    p.add_argument("--output", choices=OUTPUTS, default="rgb",
                   help="rgb (default), depth (png: 16-bit millimetres; exr: float metres) or alpha")
    p.add_argument("--quality", type=int, metavar="Q", help="JPEG quality 1..100 (default 90)")
    p.add_argument("--out", required=True, metavar="FILE", help="output .png, .jpg or .exr")
    add_format_argument(p)
    add_move_arguments(p)

    p = sub.add_parser("path", parents=[common], help="render a camera path (nerfstudio camera_path.json or "
                       "{\"cameras\": [...]}) to frames and a video",
                       description="Render every camera of CAMERA_PATH_JSON in one batch request and write the frames "
                                   "(frame_00000.png ...) and index.json into --out; --video also writes an mp4.")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)
    p.add_argument("camera_path", metavar="CAMERA_PATH_JSON",
                   help="{\"cameras\": [...]} (the items of POST /render; docs/api.md) or a nerfstudio camera_path.json")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the frames (created)")
    p.add_argument("--video", metavar="OUT.mp4", help="also write the frames as an mp4 video (OpenCV, mp4v)")
    p.add_argument("--fps", type=float, default=None, help="video frame rate (default: the camera path's fps, else 24)")
    p.add_argument("--output", choices=OUTPUTS, default=None, help="default: the file's, else rgb")
    p.add_argument("--format", choices=FORMATS, default=None, help="default: the file's, else png")
    p.add_argument("--quality", type=int, metavar="Q", help="JPEG quality 1..100")

    p = sub.add_parser("gaussians", parents=[common], help="download the Gaussians (.ply or .splat)")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)
    p.add_argument("--out", required=True, metavar="FILE",
                   help="scene.ply (3DGS binary PLY) or scene.splat (antimatter15)")
    p.add_argument("--format", choices=("ply", "splat"), default=None, help="default: from the extension")

    p = sub.add_parser("actors", parents=[common], help="list a drive scene's actors (JSON)",
                       description="Print GET /v1/scenes/{id}/actors: each moving object's id, label, box size, "
                                   "time span and Gaussians; with --time, its pose then (box -> scene frame).")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)
    p.add_argument("--time", type=float, default=None, metavar="T", help="seconds on the rigs' clock: poses then")

    p = sub.add_parser("scene", parents=[common], help="print a scene's JSON")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)
    p.add_argument("--wait", nargs="?", type=float, const=600.0, default=None, metavar="S",
                   help="first wait until it is ready or failed, up to S seconds")

    p = sub.add_parser("scenes", parents=[common], help="list the scenes, newest first")
    p.add_argument("--json", action="store_true", help="one JSON object per line")

    p = sub.add_parser("delete", parents=[common], help="delete a scene")
    p.add_argument("scene", metavar="SCENE_ID", help=_SCENE_HELP)


# ----------------------------------------------------------------------------------------------- helpers

def _bar(args, total, unit: str, desc: str):
    """A tqdm progress callback (done, total) -> None and its closer; nothing when --quiet or when stderr is not a
    terminal (common.progress: a redirected bar wrote `upload: 0.00B [00:00, ?B/s]` lines into logs)."""
    from xyzcyl.common.progress import is_terminal, progress_bar

    if args.quiet or not is_terminal(sys.stderr):
        return None, lambda: None
    bar = progress_bar(total=total, unit=unit, unit_scale=unit == "B", unit_divisor=1024 if unit == "B" else 1000,
                       desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True)

    def update(done: int, tot: int | None) -> None:
        if tot is not None and bar.total != tot:
            bar.total = tot
        bar.update(done - bar.n)

    return update, bar.close


def _say(args, text: str) -> None:
    if not args.quiet:
        print(text, file=sys.stderr)


def _write_atomic(path: Path, data: bytes) -> None:
    from xyzcyl.common.files import atomic_file

    with atomic_file(path) as f:
        f.write(data)


def _out_file(value: str, what: str = "--out") -> Path:
    path = Path(value)
    if not path.parent.is_dir():
        raise _UsageError(what, f"folder {str(path.parent)!r} does not exist")
    return path


def _summary(info) -> str:
    total = (info.timings or {}).get("total")
    took = f" in {total:.1f} s" if total is not None else ""
    n_detail = (info.counts or {}).get("detail")
    stride = None if info.detail is None else info.detail.stride
    detail = "" if n_detail is None else f" ({n_detail} detail" + (f", stride {stride})" if stride else ")")
    drive = "" if info.drive is None else f", {info.drive.frames} frames ({len(info.drive.keyframes)} keyframes)"
    return (f"scene {info.id} {info.state}: {info.gaussians or 0} Gaussians{detail}, {len(info.cameras)} "
            f"cameras{drive}{took}")


# ----------------------------------------------------------------------------------------------- actions

def _reconstruct(c, args) -> int:
    from xyzcyl.clients.client import is_drive_file, read_drive

    if args.no_detail and args.detail_stride is not None:
        raise _UsageError("--no-detail", "cannot be combined with --detail-stride")
    if (why := detail_stride_error(args.detail_stride)) is not None:
        raise _UsageError("--detail-stride", why)
    knobs = {"--keyframe-spacing": args.keyframe_spacing, "--keyframe-gap": args.keyframe_gap}
    drive = is_drive_file(args.rig)
    if args.stationary_actors and not drive:
        raise _UsageError("--stationary-actors", f"goes with a drive file ({args.rig} is a rig.json: one timestamp)")
    for flag, v in knobs.items():
        if v is not None and not drive:
            raise _UsageError(flag, f"goes with a drive file ({args.rig} is a rig.json: one timestamp)")
        if (why := keyframe_error(v)) is not None:
            raise _UsageError(flag, why)
    if drive:                   # the drive read first: a missing file is refused before anything is sent
        drive = read_drive(args.rig, depths=not args.no_depth, lidar=not args.no_lidar)
        with_lidar = f", LiDAR in {drive.lidar_frames}" if drive.lidar_frames else ""
        _say(args, f"drive {args.rig}: {drive.frames} frames of {len(drive.cameras)} cameras{with_lidar}, "
                   f"{drive.size / 1e6:.1f} MB to upload")
    depths = {} if args.no_depth else None
    update, close = _bar(args, None, "B", "upload")
    try:
        wait = args.wait is not None
        if wait and not args.quiet:
            def progress(done, total):
                if update is not None:          # no bar when stderr is not a terminal
                    update(done, total)
                if done == total:
                    close()
                    print(f"uploaded {total / 1e6:.1f} MB; waiting for the reconstruction ...", file=sys.stderr)
        else:
            progress = update
        if drive:
            info = c.reconstruct_drive(drive, wait=wait, timeout=args.wait or 600.0, progress=progress,
                                       detail_stride=args.detail_stride, detail=not args.no_detail,
                                       keyframe_spacing=args.keyframe_spacing, keyframe_gap=args.keyframe_gap,
                                       stationary_actors=args.stationary_actors)
        else:
            info = c.reconstruct(args.rig, depths=depths, wait=wait, timeout=args.wait or 600.0, progress=progress,
                                 lidar=False if args.no_lidar else None, detail_stride=args.detail_stride,
                                 detail=not args.no_detail)
    finally:
        close()
    _say(args, _summary(info) if info.ready else f"scene {info.id} {info.state}; `xyzcyl client scene {info.id} "
                                                  "--wait` waits for it")
    print(json.dumps(info.raw, indent=1) if args.json else info.id)
    return 0


def _pose(args) -> tuple[object, object]:
    """The camera (as Client.render takes it) and the move of the pose flags; the move goes to the server, which
    applies it (runtime.views.move_camera) to the input camera's or the given pose (on a --carla pose the client
    folds it into the transform: view_params)."""
    from xyzcyl.common.poses import CARLA_POSE, PoseArgError, move_from_args, parse_lens, parse_matrix

    try:
        move = move_from_args(args)
        c2w = None if args.cam_to_world is None else parse_matrix(args.cam_to_world, "--cam-to-world")
        lens = None if args.distortion is None else parse_lens(args.distortion)
    except PoseArgError as e:
        raise _UsageError(e.field, e.message) from None
    modes = [m for m, on in (("--camera", args.camera), ("--cam-to-world", args.cam_to_world),
                             ("--carla", args.carla)) if on is not None]
    if len(modes) != 1:
        raise _UsageError(modes[1] if len(modes) > 1 else "--camera",
                          "give exactly one pose: --camera NAME, --cam-to-world M*16 (with --K or --fov), or "
                          "--carla X Y Z PITCH YAW ROLL (with --fov)")
    if lens is not None and args.carla is not None:
        raise _UsageError("--distortion", "goes with --cam-to-world or --camera (a CARLA camera has none)")
    if args.camera is not None:
        for flag, v in (("--K", args.K), ("--fov", args.fov)):
            if v is not None:
                raise _UsageError(flag, "cannot be combined with --camera (the camera has its intrinsics)")
        return (args.camera if lens is None else {"camera": args.camera, "distortion": lens}), move
    if args.width is None or args.height is None:
        raise _UsageError("--width" if args.width is None else "--height", "required unless --camera")
    if args.carla is not None:
        if args.K is not None:
            raise _UsageError("--K", "a CARLA camera takes --fov (square pixels, centred principal point)")
        if args.fov is None:
            raise _UsageError("--fov", "required with --carla")
        return dict(zip(CARLA_POSE, args.carla, strict=True), fov=args.fov), move
    if (args.K is None) == (args.fov is None):
        raise _UsageError("--K", "give exactly one of --K FX FY CX CY and --fov DEG with --cam-to-world")
    cam = {"cam_to_ego": c2w.reshape(-1).tolist()} if lens is None else {"cam_to_ego": c2w.reshape(-1).tolist(),
                                                                          "distortion": lens}
    if args.K is not None:
        fx, fy, cx, cy = args.K
        return {"K": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], **cam}, move
    return {"fov": args.fov, **cam}, move


def _render(c, args) -> int:
    from xyzcyl.common.poses import PoseArgError, out_format

    out = _out_file(args.out)
    try:
        fmt = out_format(out, args.format)
    except PoseArgError as e:
        raise _UsageError(e.field, e.message) from None
    camera, move = _pose(args)
    data = c.render_bytes(args.scene, camera, output=args.output, format=fmt, width=args.width,
                          height=args.height, quality=args.quality, move=move, time=args.time,
                          actors=_actors_arg(args.actors))
    _write_atomic(out, data)
    _say(args, f"wrote {out} ({len(data)} bytes, {args.output} {fmt})")
    return 0


def _actors_arg(value: str | None):
    """--actors: the edits (common.wire.actor_edits reads JSON text or a .json file), a _UsageError naming the flag."""
    from xyzcyl.common.wire import ViewError, actor_edits

    if value is None:
        return None
    try:
        return actor_edits(value, "--actors")
    except ViewError as e:
        raise _UsageError(e.field, e.message) from None


def _actors(c, args) -> int:
    print(json.dumps(c.actors(args.scene, args.time).model_dump(), indent=1))
    return 0


def _path(c, args) -> int:
    out = Path(args.out)
    if args.video is not None:
        video = _out_file(args.video, "--video")
        if video.suffix.lower() != ".mp4":
            raise _UsageError("--video", f"must be an .mp4 file (got {video.suffix or 'none'!r})")
    try:
        doc = json.loads(Path(args.camera_path).read_text())
    except OSError as e:
        raise _UsageError("camera_path", f"cannot read {args.camera_path!r}: {e.strerror or e}") from None
    except ValueError as e:
        raise _UsageError("camera_path", f"{args.camera_path!r} is not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise _UsageError("camera_path", "must be a JSON object ({\"cameras\": [...]} or a nerfstudio camera path)")
    output = args.output or doc.get("output") or "rgb"
    if args.video is not None and output == "depth":
        raise _UsageError("--video", "a video shows rgb or alpha frames, not depth")
    out.mkdir(parents=True, exist_ok=True)
    frames = doc.get("cameras", doc.get("camera_path"))
    update, close = _bar(args, len(frames) if isinstance(frames, list) else None, "frame", "render")
    try:
        batch = c.render_path(args.scene, doc, output=args.output, format=args.format, quality=args.quality,
                              decode=False, progress=update)
    finally:
        close()
    with batch:
        names = batch.save(out)
    _say(args, f"wrote {len(names)} frames ({batch.output} {batch.format}) and index.json to {out}")
    if args.video is not None:
        fps = args.fps or doc.get("fps") or 24.0
        if not (isinstance(fps, (int, float)) and fps > 0):
            raise _UsageError("--fps", f"must be > 0 (got {fps!r})")
        from xyzcyl.clients.client import write_video

        err = write_video(out, names, batch.output, video, float(fps))
        if err is not None:
            raise _UsageError("--video", err)
        _say(args, f"wrote {video} ({len(names)} frames at {float(fps):g} fps)")
    return 0


def _gaussians(c, args) -> int:
    out = _out_file(args.out)
    update, close = _bar(args, None, "B", "download")
    try:
        path = c.gaussians(args.scene, out, format=args.format, progress=update)
    finally:
        close()
    _say(args, f"wrote {path} ({path.stat().st_size} bytes)")
    return 0


def _scene(c, args) -> int:
    info = c.wait(args.scene, timeout=args.wait) if args.wait is not None else c.scene(args.scene)
    print(json.dumps(info.raw, indent=1))
    return 0


def _scenes(c, args) -> int:
    n = 0
    for info in c.scenes():
        n += 1
        if args.json:
            print(json.dumps(info.raw))
        else:
            print(f"{info.id}  {info.state:<7}  {info.created or '-':<25}  {info.gaussians or 0:>9} Gaussians  "
                  f"{len(info.cameras)} cameras")
    _say(args, f"{n} scene{'' if n == 1 else 's'}")
    return 0


def _delete(c, args) -> int:
    c.delete(args.scene)
    _say(args, f"deleted {args.scene}")
    return 0


_ACTIONS = {"reconstruct": _reconstruct, "render": _render, "path": _path, "gaussians": _gaussians,
            "scene": _scene, "scenes": _scenes, "delete": _delete, "actors": _actors}


def run(args: argparse.Namespace) -> int:
    try:
        from xyzcyl.clients.client import Client, XyzcylError
    except ModuleNotFoundError as e:
        print(f"xyzcyl client: missing dependency {e.name!r} (pip install 'xyzcyl[client]')", file=sys.stderr)
        return 2
    try:
        with Client(args.server, api_key=args.api_key, timeout=args.timeout) as c:
            return _ACTIONS[args.action](c, args)
    except (XyzcylError, _UsageError) as e:
        print(f"xyzcyl client: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:      # stdout closed early (`... | head`): stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"xyzcyl client: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("xyzcyl client: interrupted", file=sys.stderr)
        return 130
