"""`xyzcyl batch MANIFEST --out STORE`: every drive (or rig) a manifest lists reconstructed on Ray into the service's
scene store (server.batch; docs/batch.md). Exit status: 0 every item ready or skipped, 3 some failed (the others
done; the results table says which and why), 2 bad arguments or manifest (nothing run), 1 Ray or the store failed."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ("exit status: 0 every item ready or skipped, 3 some failed (the results table says which and "
                     "why), 2 bad arguments or manifest (nothing ran), 1 Ray or the store failed, 130 interrupted")
    parser.add_argument("manifest", metavar="MANIFEST",
                        help="a file (or s3://bucket/key) listing the inputs: one drive file or rig.json per line "
                             "(relative to the manifest, or s3:// URIs), or JSON lines {\"input\": ..., \"name\": "
                             "..., options} (docs/batch.md)")
    parser.add_argument("--out", required=True, metavar="STORE",
                        help="the scene store: a folder or s3://bucket/prefix, as `xyzcyl serve --store` takes it")
    parser.add_argument("--address", default=None, metavar="ADDR",
                        help="a Ray cluster (ray://host:10001, or auto); default $RAY_ADDRESS, else a local Ray "
                             "on this machine's cores")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="keyframe workers (each loads the model once; default: the cluster's CPUs / "
                             "--worker-cpus, fewer when Ray's memory cannot hold their peaks, ~3.7 GiB each, beside "
                             "the drives' fusions)")
    parser.add_argument("--worker-cpus", type=int, default=1, metavar="C",
                        help="CPUs (and threads) of each keyframe worker (default 1)")
    parser.add_argument("--drives", type=int, default=None, metavar="D",
                        help="drives fused at once (default: workers / 4, at least 1; a 40-frame drive's fusion "
                             "peaks at ~3.5 GiB)")
    parser.add_argument("--results", default=None, metavar="FILE",
                        help="the results table, JSON lines (a path or s3:// URI; default MANIFEST's name with "
                             ".results.jsonl beside it, or STORE/batch-results.jsonl for an s3:// manifest)")
    parser.add_argument("--usdz", action="store_true",
                        help="also write each scene's AlpaSim artifact (scene.usdz) into its scene folder")
    parser.add_argument("--model", default=None, metavar="DIR",
                        help="model folder, at this path on every node (default: $XYZCYL_MODEL, else the shipped "
                             "models/xyzcyl-cpu-v1)")
    parser.add_argument("--dry-run", action="store_true",
                        help="plan only, without Ray: check every input, pick its keyframes, derive its scene id and "
                             "say whether the store has it (to make / skipped / FAILED); nothing is reconstructed or "
                             "written (exit 3 when an input is bad)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or Ray logs; the lines per item stay")


def _fail(msg: str) -> int:
    print(f"xyzcyl batch: {msg}", file=sys.stderr)
    return 2


def default_results(manifest: str, store: str) -> str:
    if manifest.startswith("s3://"):
        return (store.rstrip("/") + "/" if store.startswith("s3://") else str(Path(store)) + os.sep) + \
            "batch-results.jsonl"
    p = Path(manifest)
    return str(p.with_name(p.stem + ".results.jsonl"))


def run(args: argparse.Namespace) -> int:
    from xyzcyl.runtime.inference import default_model_dir

    from ..batch import (
        EXIT_OK,
        EXIT_PARTIAL,
        BatchOptions,
        ManifestError,
        plan_batch,
        read_manifest,
        run_batch,
    )

    for flag, v in (("--workers", args.workers), ("--worker-cpus", args.worker_cpus), ("--drives", args.drives)):
        if v is not None and v < 1:
            return _fail(f"{flag}: must be >= 1 (got {v})")
    if not args.dry_run:
        try:
            import ray  # noqa: F401
        except ImportError:
            return _fail("needs Ray: pip install 'xyzcyl[batch]'")
    model_dir = Path(args.model) if args.model else default_model_dir()
    if not (model_dir / "model.json").is_file():
        return _fail(f"--model: no model folder at {str(model_dir)!r}")
    say = lambda msg: print(msg, file=sys.stderr, flush=True)       # noqa: E731
    try:
        items = read_manifest(args.manifest)
    except ManifestError as e:
        return _fail(str(e))
    results = args.results or default_results(args.manifest, args.out)
    say(f"{len(items)} input(s) from {args.manifest} -> store {args.out}" +
        ("" if args.dry_run else f"; results table {results}"))
    # a folder store by its absolute path: a cluster's workers do not run in this folder
    store = args.out if args.out.startswith("s3://") else str(Path(args.out).resolve())
    opts = BatchOptions(store=store, model_dir=str(model_dir.resolve()), results=results, address=args.address,
                        workers=args.workers, worker_cpus=args.worker_cpus, drives=args.drives, usdz=args.usdz,
                        quiet=args.quiet)
    if args.dry_run:
        try:
            rows = plan_batch(items, opts, say)
        except OSError as e:
            print(f"xyzcyl batch: {e}", file=sys.stderr)
            return 1
        counts = {s: sum(r["status"] == s for r in rows) for s in ("todo", "skipped", "failed")}
        say(f"dry run: {counts['todo']} to make, {counts['skipped']} in the store, {counts['failed']} failed")
        return EXIT_PARTIAL if counts["failed"] else EXIT_OK
    try:
        rows = run_batch(items, opts, say)
    except KeyboardInterrupt:
        say("xyzcyl batch: interrupted; run it again to finish (ready scenes are skipped)")
        return 130
    except OSError as e:
        print(f"xyzcyl batch: {e}", file=sys.stderr)
        return 1
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ready", "skipped", "failed")}
    say(f"done: {counts['ready']} ready, {counts['skipped']} skipped, {counts['failed']} failed "
        f"(results: {results})")
    return EXIT_PARTIAL if counts["failed"] else EXIT_OK
