"""`xyzcyl import-model MODEL_DIR --out CKPT.pt`: a model folder (`xyzcyl export-model`) back to a training checkpoint
with the exact weights of every module its graphs use, for `xyzcyl train --init CKPT.pt` when the original
checkpoint is gone (model_export/recover.py, docs/inference.md)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, metavar="MODEL_DIR", help="model folder written by `xyzcyl export-model`")
    parser.add_argument("--out", required=True, type=Path, metavar="CKPT", help="checkpoint file to write (.pt)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")
    parser.add_argument("--no-verify", action="store_true",
                        help="skip the check that the recovered weights export to the same graphs (saves one "
                             "export, about a minute)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def _fail(msg: str) -> int:
    print(f"xyzcyl import-model: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from xyzcyl.model_export.commands.common import set_threads
    from xyzcyl.model_export.config import ConfigError
    from xyzcyl.model_export.recover import RecoverError, import_model

    if not (args.model / "model.json").is_file():
        return _fail(f"MODEL_DIR: no model.json in {str(args.model)!r}")
    if args.out.suffix != ".pt":
        return _fail(f"--out: the checkpoint must end in .pt, got {args.out.name!r}")
    if args.out.exists() and not args.force:
        return _fail(f"--out: {str(args.out)!r} exists (pass --force to replace it)")
    if not args.out.parent.is_dir():
        return _fail(f"--out: folder {str(args.out.parent)!r} does not exist")
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    try:
        set_threads(args.threads)
        t0 = time.perf_counter()
        r = import_model(args.model, args.out, verify=not args.no_verify, progress=say)
    except (RecoverError, ConfigError, ValueError) as exc:
        return _fail(str(exc))
    meta = r["meta"]
    modules = sorted({".".join(k.split(".")[:2]) for k in r["not_in_graphs"]})
    verified = "" if args.no_verify else " (verified: the same graphs)"
    print(f"{args.out}: {meta.get('name')} {meta.get('version')}, {len(r['state'])} tensors{verified}; "
          f"{len(r['not_in_graphs'])} found in no graph keep their initialisation ({', '.join(modules) or 'none'}); "
          f"{time.perf_counter() - t0:.0f} s")
    return 0
