"""`xyzcyl data`: synthetic training data.

    xyzcyl data synth --out DIR --scenes N --rig nuscenes --height H --width W \
        --targets ego-forward,ego-inward --seed S [--inward-views V] [--supersample 2] [--voxels 0.4,0.8] \
        [--near-cars P] [--workers N]
    xyzcyl data gallery DIR --out sheet.png [--scenes 8]
    xyzcyl data synth-drive OUT [--seed S] [--frames 40] [--hz 10] [--speed 5] [--rig pandaset] [--width 1920] \
        [--movers 3] [--workers N]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    s = sub.add_parser("synth", help="render a synthetic data set (resumable)")
    s.add_argument("--out", required=True, type=Path, help="data set folder (created; finished scenes are kept)")
    s.add_argument("--scenes", required=True, type=int, help="number of scenes (indices 0..N-1)")
    s.add_argument("--rig", default="nuscenes",
                   help="nuscenes, carla-centric, pandaset, waymo, once, argoverse, or a rig.json path")
    s.add_argument("--height", type=int, default=224, help="image height, pixels")
    s.add_argument("--width", type=int, default=400, help="image width, pixels")
    s.add_argument("--targets", default="ego-forward,ego-inward",
                   help="comma list of target settings: ego-forward, ego-inward (empty for none)")
    s.add_argument("--inward-views", type=int, default=16, help="V, ego-inward target cameras per scene")
    s.add_argument("--supersample", type=int, default=2, help="ss: ss x ss RGB samples per pixel")
    s.add_argument("--no-shadows", action="store_true", help="no sun shadows (faster)")
    s.add_argument("--voxels", default="0.4,0.8", help="comma list of occupancy voxel sizes, metres")
    s.add_argument("--seed", type=int, default=0,
                   help="data set seed: scene i is the same for the same (seed, i) (default 0)")
    s.add_argument("--near-cars", type=float, default=0.0, metavar="P",
                   help="probability of a scene with traffic beside the ego: cars in the neighbouring lanes and "
                        "parking lane 1-3 m from the ego, as real rigs see them (default 0: none within 8 m)")
    s.add_argument("--photo-textures", type=float, default=0.0, metavar="P",
                   help="probability of a scene whose facades, road and sidewalks show real photo tiles (CC0 street "
                        "panoramas; docs/data.md) instead of procedural textures (default 0: none)")
    s.add_argument("--workers", type=int, default=1,
                   help="scenes rendered at once, each in its own process with cores/N numba threads (default 1: "
                        "one process, all cores per scene); the files are identical for any N")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    d = sub.add_parser("synth-drive", help="render a synthetic drive at speed with exact ground truth (resumable)")
    d.add_argument("out", type=Path, help="drive folder (created; finished frames are kept)")
    d.add_argument("--seed", type=int, default=7, help="the street: scene --scene of this seed (default 7)")
    d.add_argument("--scene", type=int, default=None,
                   help="scene index of the seed (default: its first scene with parking on both sides)")
    d.add_argument("--frames", type=int, default=40, help="frames (default 40)")
    d.add_argument("--hz", type=float, default=10.0, help="frames per second (default 10)")
    d.add_argument("--speed", type=float, default=5.0, help="the ego's speed, m/s (default 5)")
    d.add_argument("--rig", default="pandaset",
                   help="nuscenes, carla-centric, pandaset, waymo, once, argoverse, or a rig.json path "
                        "(default pandaset)")
    d.add_argument("--width", type=int, default=1920,
                   help="image width, pixels; the height keeps the rig's real aspect (default 1920: 1920x1080)")
    d.add_argument("--movers", type=int, default=3, help="cars driving along the road, both ways (default 3)")
    d.add_argument("--supersample", type=int, default=2, help="ss: ss x ss RGB samples per pixel")
    d.add_argument("--no-shadows", action="store_true", help="no sun shadows (faster)")
    d.add_argument("--workers", type=int, default=1,
                   help="frames rendered at once, each in its own process with cores/N numba threads (default 1)")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    g = sub.add_parser("gallery", help="contact sheet of a data set")
    g.add_argument("dataset", type=Path, help="data set folder (`xyzcyl data synth` output)")
    g.add_argument("--out", required=True, type=Path, help="output PNG")
    g.add_argument("--scenes", type=int, default=8, help="the first N scenes, one row each (default 8)")
    g.add_argument("--tile-width", type=int, default=200, help="pixels per tile")


def _floats(text: str, field: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"{field}: expected a comma list of numbers, got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    try:
        if args.action == "synth":
            from xyzcyl.model_export.data.synth import SynthConfig, synth

            if args.scenes < 0:
                raise ValueError(f"scenes: must be >= 0, got {args.scenes}")
            cfg = SynthConfig(rig=args.rig, height=args.height, width=args.width,
                              targets=tuple(t.strip() for t in args.targets.split(",") if t.strip()),
                              inward_views=args.inward_views, supersample=args.supersample,
                              shadows=not args.no_shadows, voxels=_floats(args.voxels, "voxels"), seed=args.seed,
                              near_cars=args.near_cars, photo_textures=args.photo_textures)
            n = synth(args.out, args.scenes, cfg, progress=not args.quiet, workers=args.workers)
            print(f"{n} scenes rendered into {args.out}")
            return 0
        if args.action == "synth-drive":
            from xyzcyl.model_export.data.drive import DriveConfig, synth_drive

            cfg = DriveConfig(seed=args.seed, frames=args.frames, hz=args.hz, speed=args.speed, rig=args.rig,
                              width=args.width, movers=args.movers, supersample=args.supersample,
                              shadows=not args.no_shadows, scene_index=args.scene)
            n = synth_drive(args.out, cfg, progress=not args.quiet, workers=args.workers)
            print(f"{n} frames rendered into {args.out} ({cfg.width}x{cfg.height}); drive: {args.out / 'drive.json'}")
            return 0
        import cv2
        from xyzcyl.model_export.data.gallery import contact_sheet

        if args.scenes < 1:
            raise ValueError(f"scenes: must be >= 1, got {args.scenes}")
        if not args.dataset.is_dir():
            raise ValueError(f"dataset: {args.dataset} is not a folder")
        sheet = contact_sheet(args.dataset, args.scenes, args.tile_width)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(args.out), sheet[..., ::-1]):
            raise ValueError(f"out: cannot write {args.out}")
        print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
        return 0
    except ValueError as exc:
        print(f"xyzcyl data {args.action}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. --out is a file or not writable
        print(f"xyzcyl data {args.action}: out: {exc}", file=sys.stderr)
        return 2
