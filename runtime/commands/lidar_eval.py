"""`xyzcyl lidar-eval RIG_JSON`: how far off a reconstruction's depth is, against a LiDAR sweep of the same
timestamp (the rig's `lidar` block or --lidar-file FILE). Reconstructs the rig with the onnxruntime model (or reads a
scene folder of it), renders each input camera's depth, and prints AbsRel, RMSE, δ < 1.25 and the median
ratio rendered / LiDAR per camera, for all cameras and per range. See docs/inference.md and runtime/lidar.py."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from ..errors import FieldError
from .detail_flags import add_detail_arguments, detail_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..lidar import ALPHA_MIN, MAX_DEPTH, MIN_DEPTH, OCCLUSION_RADIUS

    parser.add_argument("rig", metavar="RIG_JSON", help="rig.json (cameras, images, and a lidar block unless --lidar-file)")
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--model", default=None, metavar="DIR",
                     help="model folder to reconstruct with (default: $XYZCYL_MODEL, else the shipped "
                          "models/xyzcyl-cpu-v1)")
    src.add_argument("--scene", default=None, metavar="SCENE_DIR",
                     help="check this scene folder (`xyzcyl reconstruct` of the same rig) instead of reconstructing")
    parser.add_argument("--lidar-file", default=None, metavar="FILE",
                        help="LiDAR points (.npy [N, >=3] or float32 .bin), ego frame unless the rig's lidar block "
                             "has lidar_to_ego (default: the rig's lidar.file)")
    parser.add_argument("--lidar-columns", type=int, default=None, metavar="C",
                        help="columns of a .bin file (default: the rig's lidar.columns, else 5 for *.pcd.bin, 4 "
                             "otherwise)")
    parser.add_argument("--holdout", type=float, default=None, metavar="F",
                        help="LiDAR-guided reconstruction, checked fairly: a random fraction F of the sweep's points "
                             "(seed 0) is the depth input (`xyzcyl reconstruct --lidar-file`), the rest is checked")
    parser.add_argument("--use-depth", action="store_true",
                        help="reconstruct with the rig's depth files (default: ignore them, use the depth head: a "
                             "depth file made from the same LiDAR would make the check circular)")
    parser.add_argument("--width", type=int, default=400, help="evaluation width in pixels (default 400)")
    parser.add_argument("--min-depth", type=float, default=MIN_DEPTH, metavar="M",
                        help=f"LiDAR points nearer than this camera z are left out (default {MIN_DEPTH:g})")
    parser.add_argument("--max-depth", type=float, default=MAX_DEPTH, metavar="M",
                        help=f"LiDAR points further than this are left out (default {MAX_DEPTH:g})")
    parser.add_argument("--occlusion-radius", type=int, default=OCCLUSION_RADIUS, metavar="PX",
                        help="drop a point when a point within PX pixels is nearer by more than 1.25x (0: keep all; "
                             f"default {OCCLUSION_RADIUS})")
    parser.add_argument("--alpha-min", type=float, default=ALPHA_MIN,
                        help=f"rendered alpha below which a pixel is not covered (default {ALPHA_MIN:g})")
    parser.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    parser.add_argument("--picture", default=None, metavar="PATH",
                        help="write a contact sheet (.png or .jpg): input + LiDAR, rendered depth, error per point")
    add_detail_arguments(parser)
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime and renderer threads (default: all)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def _fail(msg: str) -> int:
    print(f"xyzcyl lidar-eval: {msg}", file=sys.stderr)
    return 2


def _fmt(v: float, digits: int) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def format_table(result: dict) -> str:
    """The figures of `summarise` as a plain-text table (one row per camera, then all, then the range bins)."""
    head = f"{'camera':<22} {'LiDAR px':>9} {'covered':>8} {'AbsRel':>7} {'RMSE m':>7} {'d<1.25':>7} {'median r':>8}"
    lines = [head, "-" * len(head)]
    for r in [*result["cameras"], result["all"]]:
        lines.append(f"{r['camera']:<22} {r['lidar_pixels']:>9} {_fmt(r['covered'], 3):>8} {_fmt(r['abs_rel'], 3):>7} "
                     f"{_fmt(r['rmse'], 2):>7} {_fmt(r['delta1'], 3):>7} {_fmt(r['median_ratio'], 3):>8}")
    lines.append("")
    for r in result["ranges"]:
        name = f"LiDAR {r['from']:g}-{r['to']:g} m"
        lines.append(f"{name:<22} {r['points']:>9} {'':>8} {_fmt(r['abs_rel'], 3):>7} {_fmt(r['rmse'], 2):>7} "
                     f"{_fmt(r['delta1'], 3):>7} {_fmt(r['median_ratio'], 3):>8}")
    return "\n".join(lines)


def _nan_to_none(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def run(args: argparse.Namespace) -> int:
    from ..inference import InferenceError, ModelError, Reconstructor, default_model_dir
    from ..lidar import LidarError, camera_depths, depth_sheet, load_lidar, summarise
    from ..rig import RigError, load_rig
    from ..scene import Scene, SceneError

    if args.threads is not None and args.threads < 1:
        return _fail(f"--threads: must be >= 1, got {args.threads}")
    try:
        detail = detail_options(args)
    except FieldError as exc:
        return _fail(str(exc))
    if args.scene is not None and (args.no_detail or args.detail_stride is not None):
        return _fail("--detail-stride / --no-detail: apply to a reconstruction, not to --scene")
    if args.width < 8 or args.width > 4096:
        return _fail(f"--width: must be in 8..4096, got {args.width}")
    if not (math.isfinite(args.min_depth) and math.isfinite(args.max_depth) and 0 < args.min_depth < args.max_depth):
        return _fail(f"--min-depth / --max-depth: need 0 < min < max, both finite (got {args.min_depth}, "
                     f"{args.max_depth})")
    if not 0 <= args.occlusion_radius <= 32:
        return _fail(f"--occlusion-radius: must be in 0..32, got {args.occlusion_radius}")
    if not (math.isfinite(args.alpha_min) and 0 < args.alpha_min <= 1):
        return _fail(f"--alpha-min: must be in (0, 1], got {args.alpha_min}")
    if args.holdout is not None and not (0 < args.holdout < 1):
        return _fail(f"--holdout: must be in (0, 1), got {args.holdout}")
    if args.holdout is not None and args.scene is not None:
        return _fail("--holdout: reconstructs with part of the sweep, so it does not take --scene")
    if args.lidar_columns is not None and args.lidar_columns < 3:
        return _fail(f"--lidar-columns: must be >= 3, got {args.lidar_columns}")
    for opt, exts in (("json", (".json",)), ("picture", (".png", ".jpg", ".jpeg"))):
        path = getattr(args, opt)
        if path is not None:
            p = Path(path)
            if p.suffix.lower() not in exts:
                return _fail(f"--{opt}: extension must be one of {', '.join(exts)}, got {p.suffix or 'none'!r}")
            if not p.parent.is_dir():
                return _fail(f"--{opt}: folder {str(p.parent)!r} does not exist")
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    if args.threads is not None:
        import numba

        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    try:
        say(f"read rig {args.rig}")
        rig = load_rig(args.rig)
        pts = load_lidar(rig, args.lidar_file, args.lidar_columns)
        say(f"{len(pts.points)} LiDAR points from {pts.source}"
            + (f" ({pts.nonfinite} with a non-finite coordinate left out)" if pts.nonfinite else ""))
        if args.scene is not None:
            say(f"read scene {args.scene}")
            scene = Scene.load(args.scene)
            if scene.rig.names != rig.names:
                return _fail(f"--scene: its cameras {scene.rig.names} are not the rig's {rig.names}")
            model = scene.model
        else:
            model_dir = Path(args.model) if args.model else default_model_dir()
            if not model_dir.exists():
                return _fail(f"--model: no model folder at {str(model_dir)!r}")
            say(f"load model {model_dir}")
            rec = Reconstructor.load(model_dir, threads=args.threads)
            depths = None if args.use_depth else [None] * len(rig)
            check = pts.points
            lidar_in = None
            if args.holdout is not None:
                pick = np.random.default_rng(0).random(len(pts.points)) < args.holdout
                lidar_in, check = pts.points[pick], pts.points[~pick]
                say(f"{len(lidar_in)} points are the depth input, {len(check)} are checked")
            scene = rec.reconstruct(rig, depths=depths, progress=say, lidar=lidar_in, detail=detail)
            model = {"name": rec.info.name, "version": rec.info.version}
        say(f"render {len(rig)} cameras at {args.width} px wide")
        views = camera_depths(scene, pts.points if args.scene is not None else check, args.width, args.min_depth, args.max_depth, args.occlusion_radius)
        result = summarise(views, args.alpha_min, bins=_bins(args.max_depth))
        images = rig.load_images() if args.picture else None
    except (ModelError, RigError, InferenceError, SceneError, LidarError) as exc:
        return _fail(str(exc))
    result = {"rig": str(args.rig), "lidar": pts.source, "lidar_points": len(pts.points),
              "lidar_nonfinite": pts.nonfinite, "model": model, "width": args.width,
              "min_depth": args.min_depth, "max_depth": args.max_depth, "occlusion_radius": args.occlusion_radius,
              "alpha_min": args.alpha_min, "used_depth_files": bool(args.use_depth and args.scene is None),
              "holdout": args.holdout, **result}
    print(format_table(result))
    try:
        if args.json:
            Path(args.json).write_text(json.dumps(_nan_to_none(result), indent=1, allow_nan=False) + "\n")
            say(f"wrote {args.json}")
        if args.picture:
            import cv2

            sheet = depth_sheet(views, images, args.alpha_min, args.max_depth)
            jpeg = Path(args.picture).suffix.lower() in (".jpg", ".jpeg")  # a PNG takes no quality (cv2 warns)
            params = [cv2.IMWRITE_JPEG_QUALITY, 88] if jpeg else []
            if not cv2.imwrite(str(args.picture), sheet[..., ::-1].copy(), params):
                return _fail(f"--picture: could not write {args.picture!r}")
            say(f"wrote {args.picture}")
    except OSError as exc:
        return _fail(f"cannot write output: {exc}")
    return 0


def _bins(max_depth: float) -> tuple[float, ...]:
    """The range bins of runtime.lidar.RANGE_BINS up to max_depth (the last bin ends at max_depth)."""
    from ..lidar import RANGE_BINS

    edges = [b for b in RANGE_BINS if b < max_depth]
    return (*edges, max_depth)
