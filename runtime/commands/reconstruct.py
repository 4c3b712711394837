"""`xyzcyl reconstruct RIG_JSON|DRIVE_JSON --out SCENE_DIR`: one timestamp of a rig (rig.json + its images, optional
depth maps), or a recorded drive (a drive file: frames of rigs with their ego poses; runtime.drive) -> a scene
folder (scene.ply, background.exr/png, scene.json) with the onnxruntime model (no torch). See docs/inference.md."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..errors import FieldError
from .detail_flags import add_detail_arguments, detail_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("rig", metavar="RIG_JSON|DRIVE_JSON",
                        help="rig.json (cameras, calibrations, image files relative to it), or a drive file "
                             "({\"frames\": [{\"rig\": \"frame_00/rig.json\"}, ...]}: a recorded drive, one scene)")
    parser.add_argument("--out", required=True, metavar="SCENE_DIR", help="scene folder to write (replaced if it "
                        "exists and --force is given)")
    parser.add_argument("--model", default=None, metavar="DIR",
                        help="model folder (default: $XYZCYL_MODEL, else the shipped models/xyzcyl-cpu-v1)")
    parser.add_argument("--threads", type=int, default=None,
                        help="onnxruntime and renderer threads (default: all cores)")
    parser.add_argument("--no-depth", action="store_true", help="ignore the rig's depth files (use the depth head)")
    parser.add_argument("--lidar-file", default=None, metavar="FILE",
                        help="a LiDAR sweep of the same timestamp (.npy [N, >=3] or float32 .bin; ego frame unless "
                             "the rig's lidar block has lidar_to_ego). Default: the rig's lidar.file, if any. Cameras "
                             "without a depth file get a depth map made from it (two encode passes; "
                             "docs/inference.md)")
    parser.add_argument("--no-lidar", action="store_true", help="ignore the rig's LiDAR sweep (use the depth head)")
    parser.add_argument("--lidar-columns", type=int, default=None, metavar="C",
                        help="columns of a .bin LiDAR file (default: the rig's lidar.columns, else 5 for *.pcd.bin, "
                             "4 otherwise)")
    parser.add_argument("--no-exposure", action="store_true",
                        help="do not harmonise the cameras' exposure and white balance (by default a per-channel gain "
                             "per camera, and per keyframe of a drive, is solved on what two of them both saw, with "
                             "the detail layer; docs/inference.md \"Exposure\")")
    add_detail_arguments(parser)
    g = parser.add_argument_group("drives (a DRIVE_JSON)")
    g.add_argument("--keyframe-spacing", type=float, default=None, metavar="M",
                   help="a keyframe each M metres the ego moves (default 1.5: a drive posted at ~2 m spacing is "
                        "used whole)")
    g.add_argument("--keyframe-gap", type=float, default=None, metavar="S",
                   help="a keyframe at least every S seconds, moving or not (default 2)")
    g.add_argument("--keyframes", default=None, metavar="I,J,...",
                   help="these frames (indices into the drive's frames) as the keyframes instead")
    st = g.add_mutually_exclusive_group()
    st.add_argument("--stereo", action="store_true",
                    help="keyframes without a LiDAR sweep take depth from the motion between frames: points "
                         "triangulated with the frames ~1 m before and after each (the default; docs/inference.md, "
                         "\"Stereo between frames\"; ~2-5 s a keyframe)")
    st.add_argument("--no-stereo", action="store_true",
                    help="keyframes without a LiDAR sweep take depth from the model alone")
    g.add_argument("--no-ego-body", action="store_true",
                   help="do not look for the ego's own body over the frames (by default the pixels that stay put "
                        "while the world moves, e.g. a hood or trunk, get no Gaussians; a camera's ego_mask wins)")
    g.add_argument("--stationary-actors", action="store_true",
                   help="the tracks marked stationary (parked cars) become actors too, which a render can hide or "
                        "move (by default they stay in the static scene; docs/api.md \"Actors\")")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="reconstruct the next keyframes in N worker processes while this one fuses (default 0: "
                        "in this process, the next keyframe in a thread; on 2 cores a worker was slower, "
                        "docs/inference.md \"Workers\")")
    parser.add_argument("--force", action="store_true", help="replace an existing SCENE_DIR")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def _fail(msg: str) -> int:
    print(f"xyzcyl reconstruct: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from ..inference import InferenceError, ModelError, Reconstructor, default_model_dir
    from ..lidar import LidarError, has_lidar, load_lidar
    from ..rig import RigError, load_rig
    from ..scene import SceneError

    if args.threads is not None and args.threads < 1:
        return _fail(f"--threads: must be >= 1, got {args.threads}")
    if args.no_lidar and (args.lidar_file is not None or args.lidar_columns is not None):
        return _fail("--no-lidar: cannot be combined with --lidar-file / --lidar-columns")
    try:
        detail = detail_options(args)
    except FieldError as exc:
        return _fail(str(exc))
    out = Path(args.out)
    if out.exists() and not args.force:
        return _fail(f"--out: {str(out)!r} exists (pass --force to replace it)")
    model_dir = Path(args.model) if args.model else default_model_dir()
    if not model_dir.exists():
        if args.model:
            return _fail(f"--model: no model folder at {str(model_dir)!r}")
        return _fail(f"no shipped model is present yet at {str(model_dir)!r} (the trained model has not been "
                     "exported into models/ yet); pass --model DIR (a folder written by `xyzcyl export-model`)")
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    if args.threads is not None:
        import numba

        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    from ..drive import is_drive_file

    if is_drive_file(args.rig):
        if args.workers is not None and args.workers < 0:
            return _fail(f"--workers: must be >= 0 (got {args.workers})")
        return _drive(args, detail, out, model_dir, say)
    drive_flags = [f for f, v in (("--keyframe-spacing", args.keyframe_spacing), ("--keyframe-gap", args.keyframe_gap),
                                  ("--keyframes", args.keyframes), ("--stereo", args.stereo or None),
                                  ("--no-stereo", args.no_stereo or None),
                                  ("--no-ego-body", args.no_ego_body or None), ("--workers", args.workers),
                                  ("--stationary-actors", args.stationary_actors or None))
                   if v is not None]
    if drive_flags:
        return _fail(f"{drive_flags[0]}: goes with a drive file (a rig.json is one timestamp)")
    try:
        # the inputs first (the rig, its files' presence and sizes, the LiDAR sweep): a bad rig is refused at
        # once, not after the model's load (~1 s)
        say(f"read rig {args.rig}")
        rig = load_rig(args.rig)
        depths = [None] * len(rig.cameras) if args.no_depth else None
        lidar, pts = None, None
        if not args.no_lidar and (args.lidar_file is not None or has_lidar(rig)):
            pts = load_lidar(rig, args.lidar_file, args.lidar_columns)
            say(f"{len(pts.points)} LiDAR points from {pts.source}"
                + (f" ({pts.nonfinite} with a non-finite coordinate left out)" if pts.nonfinite else ""))
            lidar = pts.points
        t0 = time.perf_counter()
        say(f"load model {model_dir}")
        rec = Reconstructor.load(model_dir, threads=args.threads)
        t_load = time.perf_counter() - t0
        scene = rec.reconstruct(rig, depths=depths, progress=say, lidar=lidar, detail=detail,
                                exposure=not args.no_exposure)
        if pts is not None:
            scene.counts.update(pts.counts())
        say(f"write {out}")
        t1 = time.perf_counter()
        scene.save(out, overwrite=True)
        t_save = time.perf_counter() - t1
    except (ModelError, RigError, InferenceError, SceneError, LidarError) as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"--out: {exc}")
    c, t = scene.counts, scene.timings
    layers = f"{c['volume']} volume from {c['voxels']} voxels, {c['pixel']} pixel, {c['pruned']} invisible pruned"
    if detail is not None and "detail" in c:
        layers += (f", {c['detail']} detail (stride {detail.stride}), {c.get('culled', 0)} model Gaussians culled "
                   "under detail")
    print(f"{out}: {c['total']} Gaussians ({layers}), model {rec.info.name} {rec.info.version}")
    stages = ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in t.items() if k != "total")
    print(f"reconstruct {t['total']:.2f} s ({stages}); model load {t_load:.2f} s, save {t_save:.2f} s")
    return 0


def _drive(args: argparse.Namespace, detail, out: Path, model_dir: Path, say) -> int:
    """A drive file: its keyframes reconstructed and fused into one scene (runtime.drive.reconstruct_drive)."""
    from xyzcyl.common.wire import keyframe_error

    from ..drive import DriveError, load_drive, pick_keyframes, save_drive_scene
    from ..inference import InferenceError, ModelError, Reconstructor
    from ..lidar import LidarError
    from ..rig import RigError
    from ..scene import SceneError

    if args.lidar_file is not None or args.lidar_columns is not None or args.no_depth:
        flag = "--lidar-file" if args.lidar_file is not None else "--lidar-columns" if args.lidar_columns else \
            "--no-depth"
        return _fail(f"{flag}: goes with a rig.json (a drive's frames name their own sweeps)")
    for flag, v in (("--keyframe-spacing", args.keyframe_spacing), ("--keyframe-gap", args.keyframe_gap)):
        if (why := keyframe_error(v)) is not None:
            return _fail(f"{flag}: {why}")
    try:
        say(f"read drive {args.rig}")
        drive = load_drive(args.rig)
        if args.keyframes is not None:
            try:
                keys = [int(x) for x in args.keyframes.split(",") if x.strip()]
            except ValueError:
                return _fail(f"--keyframes: frame indices separated by commas (got {args.keyframes!r})")
            if not keys or keys != sorted(set(keys)) or not all(0 <= k < len(drive) for k in keys):
                return _fail(f"--keyframes: increasing frame indices in 0..{len(drive) - 1} (got {args.keyframes!r})")
        else:
            keys = pick_keyframes(drive, args.keyframe_spacing, args.keyframe_gap)
        say(f"{len(drive)} frames, {len(keys)} keyframes: {', '.join(map(str, keys))}")
        t0 = time.perf_counter()
        say(f"load model {model_dir}")
        rec = Reconstructor.load(model_dir, threads=args.threads)
        t_load = time.perf_counter() - t0
        scene, t_save = save_drive_scene(rec, drive, keys, out, lidar=not args.no_lidar, detail=detail, say=say,
                                          stereo=not args.no_stereo, ego_body=not args.no_ego_body,
                                          exposure=not args.no_exposure, workers=args.workers,
                                          stationary_actors=args.stationary_actors)
    except (DriveError, ModelError, RigError, InferenceError, SceneError, LidarError) as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"--out: {exc}")
    c, t = scene.counts, scene.timings
    chunks = f" (+ {c['viewpoint_gaussians']} in {c['viewpoints']} viewpoint chunks" if c.get("viewpoints") else ""
    if c.get("camera_layer_gaussians"):     # runtime.cameralayers
        chunks += f"{', ' if chunks else ' ('}+ {c['camera_layer_gaussians']} in its keyframes' camera layers"
    chunks += ")" if chunks else ""
    print(f"{out}: {c['total']} Gaussians{chunks} from {len(keys)} keyframes of {len(drive)} frames, model "
          f"{rec.info.name} {rec.info.version}")
    if scene.ego_body is not None and scene.ego_body.masks:
        print("ego body found: " + ", ".join(f"{n} {scene.ego_body.fractions[n]:.0%}" for n in scene.ego_body.masks)
              + f" of the image (masks in {out / 'ego_body'})")
    print(f"reconstruct {t['total']:.2f} s; model load {t_load:.2f} s, save {t_save:.2f} s")
    return 0
