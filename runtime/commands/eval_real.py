"""`xyzcyl eval-real PATH --out DIR`: how a reconstruction of real camera images looks at full resolution
(runtime/realeval.py has the metrics and the pair geometry).

- PATH a folder of frames of one drive (sub-folders each with a rig.json carrying ``ego_to_world``): novel views.
  Each pair (A, B): frame A reconstructed, rendered at the cameras of frame B, compared with B's images next to
  "not moving" (A's own image of that camera). Pairs: ``--pairs A:B,...`` or every ordered pair whose ego origins
  are --min-distance..--max-distance metres apart; ``--max-pairs K`` keeps K of them, evenly spread.
- PATH a rig.json: input views (each camera rendered at its own pose against its image).
- ``--drive DRIVE.json`` (a drive file, runtime.drive): the drive reconstructed whole against one frame alone and
  against not moving on the frames between its keyframes (runtime/drive_eval.py: keyframes every ``--every``th frame
  of ``--frames A:B``, ``--max-views K`` scored frames, ``--width W``, ``--stride S`` the detail stride, ``--lidar
  on|off``). Writes report.json and a picture sheet per scored frame, draws a progress bar over the scored frames
  (on a terminal) and prints one JSON line per method (drive, one, still) and one with the sizes and times.

Each frame A is reconstructed once per LiDAR mode (``--lidar off``: the depth head; ``on``: the rig's LiDAR sweep
as the depth input) with all of its cameras; ``--cameras`` only picks the cameras that are rendered and compared.
Writes report.json and a picture per pair and mode into --out, and prints one line per mode."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import FieldError
from .detail_flags import add_detail_arguments, detail_options

MODES = {"off": ("off",), "on": ("on",), "both": ("off", "on")}
PICTURE_WIDTH = 480
REPORT_FORMAT = "xyzcyl-eval-real"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", metavar="PATH", nargs="?", default=None,
                        help="a folder of frames of one drive (sub-folders with a rig.json carrying ego_to_world): "
                             "novel views; or one rig.json: input views (or --drive instead)")
    parser.add_argument("--drive", default=None, metavar="DRIVE_JSON",
                        help="a drive file: the drive reconstructed whole against one frame alone and not moving, "
                             "scored on the frames between its keyframes (docs/cli.md)")
    parser.add_argument("--every", type=int, default=None, metavar="N",
                        help="--drive: a keyframe every N frames (default 8)")
    parser.add_argument("--frames", default=None, metavar="A:B",
                        help="--drive: use frames A..B-1 of the drive (default all)")
    parser.add_argument("--width", type=int, default=None, metavar="W",
                        help="--drive: score at W pixels wide, aspect kept (default the cameras' own)")
    parser.add_argument("--max-views", type=int, default=None, metavar="K",
                        help="--drive: score K of the frames between keyframes, evenly spread (a quick run)")
    parser.add_argument("--stereo", choices=("on", "off"), default=None,
                        help="--drive: keyframes without a LiDAR sweep take depth from the motion between frames "
                             "(runtime.stereo; default on)")
    parser.add_argument("--ego-body", choices=("on", "off"), default=None,
                        help="--drive: the drive's reconstruction leaves out the ego's own body found over the "
                             "frames (runtime.egobody; default on). On or off, the body found is left out of the "
                             "scores of all three methods")
    parser.add_argument("--exposure", choices=("on", "off"), default=None,
                        help="--drive: harmonise the drive's cameras' exposure and white balance "
                             "(runtime.exposure; default on)")
    parser.add_argument("--stride", type=int, default=None, metavar="S",
                        help="the detail stride: --detail-stride's short form")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="folder for report.json and the pictures (created; files in it are replaced)")
    parser.add_argument("--pairs", default=None, metavar="A:B,...",
                        help="frame pairs to evaluate (frame folder names: reconstruct A, render at B's cameras), "
                             "e.g. frame_20:frame_34 (default: every ordered pair --min-distance..--max-distance "
                             "apart)")
    parser.add_argument("--min-distance", type=float, default=None, metavar="M",
                        help="default pairs: ego origins at least M metres apart (default 0.8)")
    parser.add_argument("--max-distance", type=float, default=None, metavar="M",
                        help="default pairs: ego origins at most M metres apart (default 2.1)")
    parser.add_argument("--max-pairs", type=int, default=None, metavar="K",
                        help="keep K of the pairs, evenly spread over their sorted list (a quick run)")
    parser.add_argument("--lidar", choices=tuple(MODES), default=None,
                        help="reconstruct without LiDAR (off), with the rig's LiDAR sweep as the depth input (on), "
                             "or both, side by side (default both; --drive: on or off, default on)")
    parser.add_argument("--cameras", default=None, metavar="A,B",
                        help="evaluate these cameras only (names; default: all). Reconstruction uses every camera")
    parser.add_argument("--model", default=None, metavar="DIR",
                        help="model folder (default: $XYZCYL_MODEL, else the shipped models/xyzcyl-cpu-v1)")
    add_detail_arguments(parser)
    parser.add_argument("--threads", type=int, default=None,
                        help="onnxruntime and renderer threads (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def _fail(msg: str) -> int:
    print(f"xyzcyl eval-real: {msg}", file=sys.stderr)
    return 2


class _Usage(FieldError):
    """A user error found while planning: ``field`` the flag or argument ("--pairs", "PATH")."""


def _start(out: Path, threads: int | None) -> None:
    """Make --out and set numba's threads (--threads), once the arguments are checked (both modes)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _Usage("--out", str(exc)) from None
    if threads is not None:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def _outputs(args: argparse.Namespace) -> tuple[Path, Path, Callable[[str], None]]:
    """--out (a folder or nothing yet), the model folder (--model or the default) and the progress printer
    (--quiet: none), both modes'."""
    from ..inference import default_model_dir

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise _Usage("--out", f"{str(out)!r} exists and is not a folder")
    model_dir = Path(args.model) if args.model else default_model_dir()
    if not model_dir.exists():
        raise _Usage("--model", f"no model folder at {str(model_dir)!r}")
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    return out, model_dir, say


def _finite(x: Any) -> Any:
    """JSON-safe: non-finite floats -> None (inf PSNR of identical images, NaN of a flat ground truth)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def spread(items: list, k: int | None) -> list:
    """``k`` items evenly spread over ``items`` (the centre of each of k equal runs; all when k is None or >=
    len)."""
    n = len(items)
    if k is None or k >= n:
        return list(items)
    return [items[(2 * i + 1) * n // (2 * k)] for i in range(k)]


def parse_pairs(text: str, names: list[str]) -> list[tuple[str, str]]:
    """``A:B,C:D`` -> [(A, B), (C, D)]; _Usage naming --pairs for a malformed item or an unknown frame."""
    out, unknown = [], []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        a, sep, b = item.partition(":")
        a, b = a.strip(), b.strip()
        if not sep or not a or not b:
            raise _Usage("--pairs", f"{item!r} is not A:B (two frame folder names)")
        if a == b:
            raise _Usage("--pairs", f"{item!r} pairs a frame with itself")
        unknown += [n for n in (a, b) if n not in names and n not in unknown]
        out.append((a, b))
    if unknown:
        raise _Usage("--pairs", f"unknown frame(s) {', '.join(map(repr, unknown))} (frames: {', '.join(names)})")
    if not out:
        raise _Usage("--pairs", "no pair given")
    return list(dict.fromkeys(out))


def _camera_names(text: str | None, known: list[str]) -> list[str] | None:
    if text is None:
        return None
    names = list(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise _Usage("--cameras", "no camera name given")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise _Usage("--cameras", f"unknown camera(s) {', '.join(map(repr, unknown))} (cameras: {', '.join(known)})")
    return names


def _subset(rig, names: list[str] | None):
    """The rig with only the cameras ``names`` (all when None), in rig order."""
    if names is None:
        return rig
    return dataclasses.replace(rig, cameras=tuple(c for c in rig.cameras if c.name in names))


def _fmt(v: Any, digits: int) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return "inf" if isinstance(v, float) and math.isinf(v) else f"{v:.{digits}f}"


def format_table(summaries: dict[str, dict[str, Any]]) -> str:
    """One line per LiDAR mode: views, PSNR render / not moving, SSIM both, sharpness both, PSNR gain."""
    head = (f"{'lidar':<6} {'views':>5} {'PSNR render':>11} {'still':>6} {'SSIM render':>11} {'still':>6} "
            f"{'sharp render':>12} {'still':>6} {'gain dB':>7}")
    lines = [head, "-" * len(head)]
    for mode, s in summaries.items():
        lines.append(f"{mode:<6} {s['views']:>5} {_fmt(s.get('render_psnr'), 2):>11} {_fmt(s.get('still_psnr'), 2):>6} "
                     f"{_fmt(s.get('render_ssim'), 3):>11} {_fmt(s.get('still_ssim'), 3):>6} "
                     f"{_fmt(s.get('render_sharpness'), 3):>12} {_fmt(s.get('still_sharpness'), 3):>6} "
                     f"{_fmt(s.get('gain_psnr'), 2):>7}")
    return "\n".join(lines)


def _write_jpeg(path: Path, rgb) -> None:
    import cv2

    if not cv2.imwrite(str(path), rgb[..., ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 90]):
        raise OSError(f"could not write {str(path)!r}")


def run(args: argparse.Namespace) -> int:
    try:
        if args.stride is not None:
            if args.detail_stride is not None or args.no_detail:
                raise _Usage("--stride", "is --detail-stride's short form: give one of --stride, --detail-stride, "
                                         "--no-detail")
            args.detail_stride = args.stride
        if args.drive is not None:
            return _run_drive(args)
        drive_only = [f for f, v in (("--every", args.every), ("--frames", args.frames), ("--width", args.width),
                                     ("--max-views", args.max_views), ("--stereo", args.stereo),
                                     ("--ego-body", args.ego_body), ("--exposure", args.exposure))
                      if v is not None]
        if drive_only:
            raise _Usage(drive_only[0], "goes with --drive DRIVE_JSON")
        if args.path is None:
            raise _Usage("PATH", "is missing: a folder of frames, a rig.json, or --drive DRIVE_JSON")
        if args.lidar is None:
            args.lidar = "both"
        return _run(args)
    except _Usage as exc:
        return _fail(str(exc))


def parse_frames(text: str, n: int) -> tuple[int, int]:
    """``A:B`` -> (A, B), frames A..B-1 of a drive of ``n`` frames (A empty: 0, B empty: n); _Usage naming
    --frames when it is not that or not within the drive."""
    a, sep, b = text.partition(":")
    try:
        start = int(a) if a.strip() else 0
        stop = int(b) if b.strip() else n
    except ValueError:
        start = stop = None
    if not sep or start is None:
        raise _Usage("--frames", f"{text!r} is not A:B (frames A..B-1, e.g. 0:17)")
    if not 0 <= start < stop <= n:
        raise _Usage("--frames", f"{text} is out of range: the drive has {n} frames (A:B with 0 <= A < B <= {n})")
    return start, stop


def _run_drive(args: argparse.Namespace) -> int:
    """`eval-real --drive DRIVE.json` (runtime/drive_eval.py does the work)."""
    from xyzcyl.common.progress import progress_bar

    from .. import drive_eval
    from ..drive import DriveError, load_drive
    from ..inference import InferenceError, ModelError, Reconstructor
    from ..lidar import LidarError
    from ..rig import RigError
    from ..scene import SceneError

    t_start = time.perf_counter()
    if args.path is not None:
        raise _Usage("PATH", f"{args.path!r} and --drive: give one of them")
    for flag, v in (("--pairs", args.pairs), ("--min-distance", args.min_distance),
                    ("--max-distance", args.max_distance), ("--max-pairs", args.max_pairs)):
        if v is not None:
            raise _Usage(flag, "is for a folder of frames (novel-view pairs), not --drive")
    every = 8 if args.every is None else args.every
    if every < 1:
        raise _Usage("--every", f"must be >= 1 (got {every})")
    if args.max_views is not None and args.max_views < 1:
        raise _Usage("--max-views", f"must be >= 1 (got {args.max_views})")
    if args.width is not None and args.width < 1:
        raise _Usage("--width", f"must be >= 1 (got {args.width})")
    if args.threads is not None and args.threads < 1:
        raise _Usage("--threads", f"must be >= 1, got {args.threads}")
    lidar = args.lidar or "on"
    if lidar == "both":
        raise _Usage("--lidar", "on or off with --drive (both: run it twice)")
    try:
        detail = detail_options(args)
    except FieldError as exc:
        raise _Usage("--stride" if args.stride is not None else exc.field, exc.message) from None
    out, model_dir, say = _outputs(args)

    path = Path(args.drive)
    if not path.is_file():
        raise _Usage("--drive", f"{str(path)!r} is not a file")
    try:
        whole = load_drive(path)
    except DriveError as exc:
        raise _Usage("--drive", str(exc)) from None
    start, stop = (0, len(whole)) if args.frames is None else parse_frames(args.frames, len(whole))
    drive = drive_eval.sub_drive(whole, start, stop)
    keys, scored = drive_eval.plan(len(drive), every, args.max_views)
    if not scored:
        raise _Usage("--every", f"every frame of {start}:{stop} is a keyframe at --every {every}: no frame between "
                                "keyframes to score")
    cameras = _camera_names(args.cameras, list(drive.frames[0].rig.names))
    if lidar == "on" and not any(drive_eval.frame_has_lidar(drive, k) for k in keys):
        raise _Usage("--lidar", "no keyframe's rig has a LiDAR sweep (a lidar block with a file); use --lidar off")
    _start(out, args.threads)

    bar = progress_bar(total=len(scored), desc="eval-real: frames scored", unit="frame", enabled=not args.quiet)
    if not args.quiet and not bar.disable:       # progress lines above the bar, not through it
        say = lambda msg: bar.write(f"  {msg}", file=sys.stderr)     # noqa: E731
    try:
        say(f"load model {model_dir}")
        rec = Reconstructor.load(model_dir, threads=args.threads)
        report = drive_eval.evaluate_drive(rec, drive, keys, scored, out, lidar=lidar == "on", detail=detail,
                                           width=args.width, cameras=cameras, first=start, say=say, bar=bar,
                                           stereo=args.stereo != "off", ego_body=args.ego_body != "off",
                                           exposure=args.exposure != "off")
    except (ModelError, RigError, InferenceError, SceneError, LidarError, DriveError) as exc:
        bar.close()
        return _fail(str(exc))
    except OSError as exc:
        bar.close()
        return _fail(f"--out: {exc}")
    report = {"format": REPORT_FORMAT, "format_version": 1, "kind": "drive", "drive": str(path),
              "frames_range": [start, stop], "every": every, "max_views": args.max_views, "lidar": lidar,
              "stereo": args.stereo or "on", "ego_body": args.ego_body or "on",
              "exposure": args.exposure or "on",
              "stride": None if detail is None else detail.stride,
              "settings": {"model": {"name": rec.info.name, "version": rec.info.version, "dir": str(model_dir)},
                           "detail": None if detail is None else dataclasses.asdict(detail),
                           "threads": args.threads},
              **report, "elapsed_s": round(time.perf_counter() - t_start, 3)}
    try:
        (out / "report.json").write_text(json.dumps(_finite(report), indent=1, allow_nan=False) + "\n")
    except OSError as exc:
        return _fail(f"--out: {exc}")
    say(f"wrote {out / 'report.json'} and {len(report['pictures'])} pictures")
    for line in drive_eval.method_lines(report):
        print(json.dumps(_finite(line)))
    return 0


def _run(args: argparse.Namespace) -> int:
    from .. import realeval
    from ..inference import InferenceError, ModelError, Reconstructor, rgb_images
    from ..lidar import LidarError, has_lidar, load_lidar
    from ..rig import RigError, load_rig
    from ..scene import SceneError

    t_start = time.perf_counter()
    # ------------------------------------------------------------------ flags
    if args.threads is not None and args.threads < 1:
        raise _Usage("--threads", f"must be >= 1, got {args.threads}")
    if args.max_pairs is not None and args.max_pairs < 1:
        raise _Usage("--max-pairs", f"must be >= 1, got {args.max_pairs}")
    lo = 0.8 if args.min_distance is None else args.min_distance
    hi = 2.1 if args.max_distance is None else args.max_distance
    if not (math.isfinite(lo) and lo >= 0):
        raise _Usage("--min-distance", f"must be a finite number >= 0, got {lo}")
    if not math.isfinite(hi):
        raise _Usage("--max-distance", f"must be finite, got {hi}")
    if hi < lo:
        raise _Usage("--max-distance", f"{hi:g} is less than --min-distance {lo:g}")
    if args.pairs is not None and (args.min_distance is not None or args.max_distance is not None):
        raise _Usage("--pairs", "names the pairs, so it takes no --min-distance / --max-distance")
    try:
        detail = detail_options(args)
    except FieldError as exc:
        raise _Usage(exc.field, exc.message) from None
    modes = MODES[args.lidar]
    out, model_dir, say = _outputs(args)

    # ------------------------------------------------------------------ what to evaluate
    path = Path(args.path)
    if not path.exists():
        raise _Usage("PATH", f"{str(path)!r} does not exist")
    novel = path.is_dir()
    try:
        if novel:
            if not any((p / "rig.json").is_file() for p in path.iterdir() if p.is_dir()) \
                    and (path / "rig.json").is_file():
                raise _Usage("PATH", f"{str(path)!r} holds one rig, not frame sub-folders; pass its rig.json for "
                                     "the input views")
            try:
                frames = realeval.load_frames(path)
            except RigError as exc:
                raise _Usage("PATH", str(exc)) from None
            by_name = {f.name: f for f in frames}
            if args.pairs is not None:
                pairs = [(by_name[a], by_name[b]) for a, b in parse_pairs(args.pairs, list(by_name))]
            else:
                pairs = realeval.pairs_within(frames, lo, hi)
                if not pairs:
                    d = [realeval.frame_distance(a, b) for a in frames for b in frames if a is not b]
                    raise _Usage("--min-distance / --max-distance",
                                 f"no pair of frames is {lo:g}..{hi:g} m apart (the frames are "
                                 f"{min(d):.2f}..{max(d):.2f} m apart)")
            pairs = spread(pairs, args.max_pairs)
            recon = list(dict.fromkeys(a.name for a, _ in pairs))           # frames to reconstruct, in order
            known = list(dict.fromkeys(n for a, b in pairs for n in b.rig.names if n in a.rig.names))
        else:
            if args.pairs is not None or args.min_distance is not None or args.max_distance is not None \
                    or args.max_pairs is not None:
                raise _Usage("--pairs / --min-distance / --max-distance / --max-pairs",
                             "for a folder of frames (novel views); PATH is one rig")
            rig = load_rig(path)
            frames, pairs, recon = [], [], [path.parent.name or "rig"]
            known = rig.names
        cameras = _camera_names(args.cameras, known)
        rigs = {f.name: f.rig for f in frames} if novel else {recon[0]: rig}
        if "on" in modes:
            missing = [n for n in recon if not has_lidar(rigs[n])]
            if missing:
                raise _Usage("--lidar", f"rig of {', '.join(map(repr, missing))} has no LiDAR sweep (a lidar block "
                                        f"with a file), needed by --lidar {args.lidar}; use --lidar off")
    except RigError as exc:
        raise _Usage("PATH", str(exc)) from None
    _start(out, args.threads)

    # ------------------------------------------------------------------ reconstruct and evaluate
    rows: list[dict[str, Any]] = []
    pair_summaries: list[dict[str, Any]] = []
    scenes: list[dict[str, Any]] = []
    pictures: list[str] = []
    try:
        say(f"load model {model_dir}")
        rec = Reconstructor.load(model_dir, threads=args.threads)

        for k, name in enumerate(recon, 1):
            r = rigs[name]
            say(f"[{k}/{len(recon)}] {name}: read {len(r)} images")
            images = rgb_images(r)
            mine = [(a, b) for a, b in pairs if a.name == name]
            targets: dict[str, list] = {}    # frame B -> its images of the evaluated cameras (read once per A)
            for mode in modes:
                lidar, n_points = None, 0
                if mode == "on":
                    pts = load_lidar(r)
                    lidar, n_points = pts.points, len(pts.points)
                    say(f"{name}: {n_points} LiDAR points from {pts.source}")
                say(f"{name}: reconstruct (lidar {mode})")
                scene = rec.reconstruct(r, images=images, lidar=lidar, detail=detail, progress=say)
                t0 = time.perf_counter()
                if novel:
                    for a, b in mine:
                        sub = _subset(b.rig, cameras)
                        if b.name not in targets:
                            targets[b.name] = rgb_images(sub)
                        bb = realeval.Frame(b.name, sub, b.pose)
                        t1 = time.perf_counter()
                        got, pics = realeval.evaluate_pair(scene, a, bb, images, targets[b.name], say=say)
                        dist = realeval.frame_distance(a, b)
                        rows += [{"lidar": mode, "a": a.name, "b": b.name, **g} for g in got]
                        pair_summaries.append({"a": a.name, "b": b.name, "lidar": mode, "distance_m": dist,
                                               "seconds": time.perf_counter() - t1, **realeval.summary(got)})
                        if pics:
                            pic = out / f"{a.name}_{b.name}_{mode}.jpg"
                            _write_jpeg(pic, realeval.sheet(pics, ("ground truth", "render", "not moving"),
                                                            PICTURE_WIDTH))
                            pictures.append(pic.name)
                            say(f"wrote {pic}")
                else:
                    idx = [i for i, c in enumerate(r.cameras) if cameras is None or c.name in cameras]
                    view = dataclasses.replace(scene, rig=_subset(r, cameras))
                    got, pics = realeval.evaluate_inputs(view, [images[i] for i in idx], say=say)
                    rows += [{"lidar": mode, "frame": name, **g} for g in got]
                    pic = out / f"inputs_{mode}.jpg"
                    _write_jpeg(pic, realeval.sheet(pics, ("ground truth", "render"), PICTURE_WIDTH))
                    pictures.append(pic.name)
                    say(f"wrote {pic}")
                scenes.append({"frame": name, "lidar": mode, "lidar_points": n_points, "counts": dict(scene.counts),
                               "timings": dict(scene.timings), "evaluate_s": round(time.perf_counter() - t0, 3)})
                del scene
    except (ModelError, RigError, InferenceError, SceneError, LidarError) as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"--out: {exc}")

    summaries = {mode: realeval.summary([x for x in rows if x["lidar"] == mode]) for mode in modes}
    report = {
        "format": REPORT_FORMAT, "format_version": 1,
        "kind": "novel_views" if novel else "input_views",
        "path": str(path),
        "settings": {
            "model": {"name": rec.info.name, "version": rec.info.version, "dir": str(model_dir)},
            "detail": None if detail is None else dataclasses.asdict(detail),
            "lidar": args.lidar, "modes": list(modes), "cameras": cameras,
            "min_distance": lo if novel and args.pairs is None else None,
            "max_distance": hi if novel and args.pairs is None else None,
            "max_pairs": args.max_pairs, "threads": args.threads,
        },
        "pairs": [{"a": a.name, "b": b.name, "distance_m": round(realeval.frame_distance(a, b), 4)}
                  for a, b in pairs],
        "summary": summaries,
        "pair_summaries": pair_summaries,
        "rows": rows,
        "scenes": scenes,
        "pictures": pictures,
        "elapsed_s": round(time.perf_counter() - t_start, 3),
    }
    try:
        (out / "report.json").write_text(json.dumps(_finite(report), indent=1, allow_nan=False) + "\n")
    except OSError as exc:
        return _fail(f"--out: {exc}")
    say(f"wrote {out / 'report.json'}")
    print(format_table(summaries))
    rec_s = sum(s["timings"].get("total", 0.0) for s in scenes)
    print(f"{len(scenes)} reconstruction(s) {rec_s:.1f} s, evaluation {sum(s['evaluate_s'] for s in scenes):.1f} s, "
          f"total {report['elapsed_s']:.1f} s; model {rec.info.name} {rec.info.version}, "
          f"detail {'off' if detail is None else f'stride {detail.stride}'}")
    return 0
