"""Compare `xyzcyl eval` reports on the same views: one JSON line per result on stdout.

Two comparisons, each reading the one report JSON in a folder that `xyzcyl eval --out FOLDER` wrote (or a report
file itself):

- ``paired A B``: is model A better than model B, or is the difference within what the choice of validation scenes
  alone moves? Per setting: the mean over the views both reports hold of A - B (the difference of the two table
  rows), its 95 % interval from a bootstrap over scenes (the views of one scene share a layout, so scenes, not
  views, are the independent draws; --resamples resamples, fixed seed) and the number of scenes where A beats B.
  A view whose metric is undefined (null) in either report is left out and counted. docs/results.md quotes these
  intervals ("above unprojection ... 95 % CI").
- ``rig-gap LABEL=SIX_CAMERA_DIR,RIG_DIR[,RIG_DIR ...]``: a model on other rigs against its own 6-camera figure
  on the same scenes. The rig data sets hold the first scenes of the validation seed, so the 6-camera figure is
  the mean PSNR over the 6-camera report's views of exactly those scenes (not the 50-scene table row).
  docs/results.md quotes these gaps ("the held-out rigs against the 6-camera figure").

    .venv/bin/python benchmarks/eval_compare.py paired eval/val eval/unproject [--metric psnr] [--resamples 10000]
    .venv/bin/python benchmarks/eval_compare.py rig-gap "1.4.0=eval/val,eval/waymo,eval/argoverse,eval/ring8"

How the reports are made: docs/results.md "The model alone (1.4.0): its own Gaussians at 400x224".
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def load_report(path: Path) -> dict:
    """The report JSON ``path`` names, or the one report JSON in the folder ``path``."""
    if path.is_dir():
        found = sorted(path.glob("*.json"))
        if len(found) != 1:
            raise SystemExit(f"eval_compare.py: {path} holds {len(found)} report JSONs, expected 1")
        path = found[0]
    return json.loads(path.read_text())


def keyed_views(report: dict) -> dict[tuple[str, str, str, str], dict]:
    """A report's per-view rows keyed by (data, setting, scene, view)."""
    return {(r["data"], r["setting"], r["scene"], r["view"]): r for r in report["views"]}


def paired(a: dict, b: dict, metric: str, resamples: int = 10_000, seed: int = 0) -> list[dict]:
    """Per setting: mean of A - B over shared views, bootstrap 95 % interval over scenes, scenes A wins."""
    out = []
    for setting in sorted({k[1] for k in a} & {k[1] for k in b}):
        keys = [k for k in a if k[1] == setting and k in b]
        ok = [k for k in keys if a[k][metric] is not None and b[k][metric] is not None]
        scenes = sorted({(k[0], k[2]) for k in ok})
        if not scenes:
            continue
        # per scene: sum and count of the view differences, so a resample's mean is the mean over its views
        idx = {s: i for i, s in enumerate(scenes)}
        sums = np.zeros(len(scenes))
        counts = np.zeros(len(scenes))
        for k in ok:
            i = idx[(k[0], k[2])]
            sums[i] += a[k][metric] - b[k][metric]
            counts[i] += 1
        rng = np.random.default_rng(seed)
        draw = rng.integers(0, len(scenes), size=(resamples, len(scenes)))
        boot = sums[draw].sum(1) / counts[draw].sum(1)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        out.append({"case": "paired", "setting": setting, "metric": metric, "views": len(ok),
                    "undefined": len(keys) - len(ok), "scenes": len(scenes),
                    "mean_diff": round(float(sums.sum() / counts.sum()), 4),
                    "ci95": [round(float(lo), 4), round(float(hi), 4)], "scenes_a_better": int((sums > 0).sum())})
    return out


def mean_psnr(rows: list[dict], setting: str, scenes: set[str] | None = None) -> float:
    vals = [r["psnr"] for r in rows if r["setting"] == setting and r["psnr"] is not None
            and (scenes is None or r["scene"] in scenes)]
    return float(np.mean(vals)) if vals else float("nan")


def rig_gap(label: str, six: dict, rigs: list[dict]) -> list[dict]:
    """Per rig report: its ego-forward / ego-inward PSNR against the 6-camera report's on the same scenes."""
    out = []
    six_rows = six["views"]
    for report in rigs:
        rows = report["views"]
        scenes = {r["scene"] for r in rows}
        row = {"case": "rig_gap", "model": label, "rig": rows[0]["rig"], "data": rows[0]["data"],
               "scenes": len(scenes)}
        for s in ("ego-forward", "ego-inward"):
            base, rig = mean_psnr(six_rows, s, scenes), mean_psnr(rows, s)
            row[s] = {"six_cameras": round(base, 2), "rig": round(rig, 2), "difference": round(rig - base, 2)}
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("paired", help="A - B on the same views, with a scene-bootstrap interval")
    p.add_argument("a", type=Path, help="report JSON of model A, or the folder holding it")
    p.add_argument("b", type=Path, help="report JSON of model B, or the folder holding it")
    p.add_argument("--metric", default="psnr", help="a per-view metric of the reports (default psnr)")
    p.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples (default 10000)")
    g = sub.add_parser("rig-gap", help="other rigs against the same model's 6-camera figure on the same scenes")
    g.add_argument("models", nargs="+", metavar="LABEL=SIX_CAMERA_DIR,RIG_DIR[,...]")
    args = ap.parse_args(argv)
    if args.what == "paired":
        if args.resamples < 1:
            ap.error("--resamples: must be >= 1")
        rows = paired(keyed_views(load_report(args.a)), keyed_views(load_report(args.b)), args.metric,
                      args.resamples)
        rows = [{"a": str(args.a), "b": str(args.b), **r} for r in rows]
    else:
        rows = []
        for spec in args.models:
            label, _, dirs = spec.partition("=")
            six, *rigs = dirs.split(",")
            if not label or not rigs:
                ap.error(f"rig-gap: expected LABEL=SIX_CAMERA_DIR,RIG_DIR[,...], got {spec!r}")
            rows += rig_gap(label, load_report(Path(six)), [load_report(Path(r)) for r in rigs])
    for row in rows:
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
