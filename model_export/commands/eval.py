"""`xyzcyl eval`: novel-view metrics of a trained model or of the pixel-unprojection baseline on synthetic
data sets (docs/training.md, "Evaluation").

    xyzcyl eval --checkpoint RUN/render.pt --data data/val --setting ego-forward --out eval/
    xyzcyl eval --baseline unproject --checkpoint RUN/render.pt --data data/val --setting ego-inward
    xyzcyl eval --baseline unproject-gt-depth --data data/val --setting ego-forward,ego-inward
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from xyzcyl.model_export.commands.common import add_runtime_arguments, set_threads


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="training checkpoint: stage-2 render.pt / last.pt or stage-depth depth.pt for the "
                             "model; any checkpoint (its depth head) for --baseline unproject")
    parser.add_argument("--data", required=True, type=Path, action="append",
                        help="data set folder (xyzcyl data synth output); repeat for several rigs")
    parser.add_argument("--setting", required=True,
                        help="ego-forward, ego-inward, or both comma-separated")
    parser.add_argument("--rig", default=None, help="rig name; the data sets must have been generated with it "
                                                    "(label when a data set has no index.json)")
    parser.add_argument("--baseline", default=None, choices=("unproject", "unproject-gt-depth"),
                        help="evaluate the pixel-unprojection baseline instead of the model")
    parser.add_argument("--gt-occupancy", action="store_true",
                        help="select the model's voxels from the ground-truth occupancy (oracle, labelled)")
    parser.add_argument("--out", type=Path, default=Path("eval"), help="report folder (default: ./eval)")
    parser.add_argument("--max-scenes", type=int, default=None, help="first N scenes of each data set")
    parser.add_argument("--sheet", type=int, default=4, metavar="N",
                        help="picture <tag>_sheet.png of the first view of the first N scenes per data set and "
                             "setting: ground truth, render, depths (default 4; 0: none)")
    add_runtime_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from xyzcyl.model_export.config import ConfigError
    from xyzcyl.model_export.dataset import DataError
    from xyzcyl.model_export.evaluate import EvalConfig, EvalError, evaluate, write_reports, write_sheet
    from xyzcyl.runtime.rig import RigError

    try:
        set_threads(args.threads)
        if args.baseline == "unproject-gt-depth" and args.checkpoint is not None:
            raise ValueError("checkpoint: --baseline unproject-gt-depth uses ground-truth depth, not a checkpoint")
        if args.baseline is not None and args.gt_occupancy:
            raise ValueError("gt_occupancy: applies to the model only, not to --baseline")
        if args.max_scenes is not None and args.max_scenes < 1:
            raise ValueError(f"max_scenes: must be >= 1, got {args.max_scenes}")
        if args.sheet < 0:
            raise ValueError(f"sheet: must be >= 0, got {args.sheet}")
        cfg = EvalConfig(settings=tuple(s.strip() for s in args.setting.split(",") if s.strip()),
                         method=args.baseline or "model",
                         occupancy="ground-truth" if args.gt_occupancy else "predicted", rig=args.rig,
                         max_scenes=args.max_scenes, lpips_backbone_path=args.lpips_backbone,
                         lpips_lin_path=args.lpips_lin, lpips_net=args.lpips_net, sheet_scenes=args.sheet)
        tiles: list = []
        result = evaluate(args.data, cfg, args.checkpoint, progress=not args.quiet, sheet=tiles)
    except (ValueError, ConfigError, DataError, EvalError, RigError, FileNotFoundError) as exc:
        print(f"xyzcyl eval: {exc}", file=sys.stderr)
        return 2
    json_path, md_path = write_reports(result, args.out)
    print(md_path.read_text(), end="")
    print(f"wrote {json_path} and {md_path}")
    if tiles:
        sheet = write_sheet(tiles, json_path.with_name(json_path.stem + "_sheet.png"))
        print(f"wrote {sheet}")
    return 0
