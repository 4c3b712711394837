"""`xyzcyl export-model`: a training checkpoint -> a model folder (ONNX graphs, model.json, MODEL_CARD.md) that
`xyzcyl reconstruct` and the server run with onnxruntime (docs/inference.md). (`xyzcyl export` is the export of
scenes; its old spelling with --checkpoint runs this command, with a notice, until the next release: xyzcyl.cli.)

    xyzcyl export-model --checkpoint RUN/render.pt --out models/xyzcyl-cpu-v1 --version 1.0.0 \\
        --eval-report eval/model_ego-forward.json --eval-report eval/model_ego-inward.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", required=True, type=Path,
                        help="stage-2 training checkpoint (render.pt, or a stage-depth depth.pt)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="model folder to write (models/NAME)")
    parser.add_argument("--name", default=None, help="model name (default: the --out folder's name)")
    parser.add_argument("--version", default="0.1.0", help="model version recorded in model.json (default 0.1.0)")
    parser.add_argument("--eval-report", type=Path, action="append", default=[], metavar="JSON",
                        help="`xyzcyl eval` JSON report quoted in MODEL_CARD.md and model.json (repeatable)")
    parser.add_argument("--notes", default=None, metavar="TEXT_OR_FILE",
                        help="extra Markdown for the model card's Notes section (text, or a file path)")
    parser.add_argument("--allow-stage", action="store_true",
                        help="export a checkpoint that is not a stage-2 (render) checkpoint (tests, debugging)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out folder")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def _fail(msg: str) -> int:
    print(f"xyzcyl export-model: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from xyzcyl.model_export.commands.common import set_threads
    from xyzcyl.model_export.config import ConfigError
    from xyzcyl.model_export.export import ExportError, export_checkpoint

    name = args.name or args.out.name
    notes = args.notes
    if notes is not None and Path(notes).is_file():
        notes = Path(notes).read_text()
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    try:
        set_threads(args.threads)
        t0 = time.perf_counter()
        out = export_checkpoint(args.checkpoint, args.out, name=name, version=args.version,
                                eval_reports=args.eval_report, notes=notes, overwrite=args.force,
                                require_render_stage=not args.allow_stage, progress=say)
    except (ExportError, ConfigError, ValueError) as exc:
        return _fail(str(exc))
    import json

    meta = json.loads((out / "model.json").read_text())
    size = sum(f["bytes"] for f in meta["files"].values())
    print(f"exported {name} {args.version} -> {out} ({', '.join(meta['files'])}; {size / 1e6:.1f} MB) in "
          f"{time.perf_counter() - t0:.0f} s")
    return 0
