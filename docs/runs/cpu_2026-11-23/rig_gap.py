"""The issue-10 rig check: a model on other rigs against its own 6-camera figure on the same scenes.

The rig data sets hold scenes 0-9 of the validation seed, so the 6-camera figure is the mean PSNR over the views
of scenes 0-9 of the 6-camera report (not the 50-scene table row). Prints markdown and writes --json.

    .venv/bin/python docs/runs/cpu_2026-11-23/rig_gap.py --json OUT.json \
        "v1.1.0=runs/cpu2b/eval/no-volume,runs/cpu2b/eval/rig_waymo,runs/cpu2b/eval/rig_argoverse,..."
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def views(folder: str) -> list[dict]:
    (path,) = sorted(Path(folder).glob("*.json"))
    return json.loads(path.read_text())["views"]


def mean_psnr(rows: list[dict], setting: str, scenes: set[str] | None = None) -> float:
    vals = [r["psnr"] for r in rows if r["setting"] == setting and r["psnr"] is not None
            and (scenes is None or r["scene"] in scenes)]
    return float(np.mean(vals))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="+", help="LABEL=SIX_CAMERA_DIR,RIG_DIR,...")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args()
    out = []
    print("| model | rig | ego-forward (rig - 6 cams, dB) | ego-inward (rig - 6 cams, dB) |")
    print("| --- | --- | ---: | ---: |")
    for spec in args.models:
        label, _, dirs = spec.partition("=")
        six, *rigs = dirs.split(",")
        six_rows = views(six)
        for rig_dir in rigs:
            rows = views(rig_dir)
            scenes = {r["scene"] for r in rows}
            row = {"model": label, "rig": rows[0]["rig"], "data": rows[0]["data"], "scenes": len(scenes)}
            for s in ("ego-forward", "ego-inward"):
                base, rig = mean_psnr(six_rows, s, scenes), mean_psnr(rows, s)
                row[s] = {"six_cameras": round(base, 2), "rig": round(rig, 2), "difference": round(rig - base, 2)}
            out.append(row)
            f, i = row["ego-forward"], row["ego-inward"]
            print(f"| {label} | {row['data']} | {f['rig']:.2f} - {f['six_cameras']:.2f} = {f['difference']:+.2f} "
                  f"| {i['rig']:.2f} - {i['six_cameras']:.2f} = {i['difference']:+.2f} |")
    args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
