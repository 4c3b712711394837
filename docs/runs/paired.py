"""Paired comparison of two `xyzcyl eval` reports on the same views (docs/results.md): is A better than B, or is
the difference within what the choice of validation scenes alone moves?

    .venv/bin/python docs/runs/paired.py runs/cpu2b/eval/full runs/cpu2b/eval/no-volume [--metric psnr] [--json]

For each setting: the mean over views of A - B (the difference of the two table rows), its 95 % interval from a
bootstrap over scenes (views of one scene share a layout, so scenes, not views, are the independent draws;
10,000 resamples, fixed seed), and the scenes where A beats B. Only views present in both reports count; a view
whose metric is undefined (None) in either report is left out and counted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def load_views(path: Path) -> dict[tuple[str, str, str, str], dict]:
    """The per-view rows of the one report JSON in ``path`` (a folder) or ``path`` itself, keyed by
    (data, setting, scene, view)."""
    if path.is_dir():
        found = sorted(path.glob("*.json"))
        if len(found) != 1:
            raise SystemExit(f"paired.py: {path} holds {len(found)} report JSONs, expected 1")
        path = found[0]
    rep = json.loads(path.read_text())
    return {(r["data"], r["setting"], r["scene"], r["view"]): r for r in rep["views"]}


def paired(a: dict, b: dict, metric: str, resamples: int = 10_000, seed: int = 0) -> list[dict]:
    """Per setting: mean of A - B over shared views, bootstrap 95 % interval over scenes, scenes A wins."""
    out = []
    for setting in sorted({k[1] for k in a} & {k[1] for k in b}):
        keys = [k for k in a if k[1] == setting and k in b]
        ok = [k for k in keys if a[k][metric] is not None and b[k][metric] is not None]
        scenes = sorted({(k[0], k[2]) for k in ok})
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
        out.append({"setting": setting, "metric": metric, "views": len(ok), "undefined": len(keys) - len(ok),
                    "scenes": len(scenes), "mean_diff": float(sums.sum() / counts.sum()),
                    "ci95": [float(lo), float(hi)], "scenes_a_better": int((sums > 0).sum())})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--metric", default="psnr")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a line per setting")
    args = ap.parse_args()
    res = paired(load_views(args.a), load_views(args.b), args.metric)
    if args.json:
        print(json.dumps({"a": str(args.a), "b": str(args.b), "rows": res}, indent=1))
        return 0
    for r in res:
        print(f"{r['setting']}: {args.a} - {args.b} = {r['mean_diff']:+.2f} {r['metric']} "
              f"(95 % CI {r['ci95'][0]:+.2f} .. {r['ci95'][1]:+.2f} over {r['scenes']} scenes; "
              f"A better in {r['scenes_a_better']}/{r['scenes']}; {r['views']} views, {r['undefined']} undefined)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
