"""A drive's moving objects scored where they are (issue 38's target: "scored inside the moving objects' boxes
(projected) at the frames between keyframes: PSNR inside the boxes >= 2 dB above the same scene built without
tracks, and the whole image not worse"): one JSON document on stdout.

    .venv/bin/python benchmarks/actors_boxes.py /work/shared/data/real/pandaset_002_drive/drive.json --every 4 \\
        --work /tmp/actors-boxes [--no-lidar]

The drive is reconstructed twice with keyframes every --every frames (runtime.drive.reconstruct_drive, LiDAR where
its frames have it unless --no-lidar): with its tracks, and with its tracks left out (the same frames, no tracks
file). Scene folders are written into --work and read back when there (delete them after a code change). Scored:
--max-views frames between the keyframes, evenly spread (runtime.drive_eval.plan), every camera at its own size,
at the frame's time; PSNR of the RGB (0..1) against the frame's own image over the pixels inside the moving objects'
boxes at that frame (the tracks' boxes grown by TRACK_GROW, projected: runtime.stereo.box_mask, no growth in
pixels; a camera whose boxes cover fewer than 500 pixels is left out of "inside"), outside them, and over the whole
image, each the mean of the per-camera PSNRs; "still" is the nearest keyframe's image of that camera (not moving).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

MIN_PIXELS = 500      # a camera's boxes cover at least this many pixels to be scored inside them


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drive", help="drive.json with tracks")
    ap.add_argument("--every", type=int, default=4, help="a keyframe every N frames (default 4)")
    ap.add_argument("--max-views", type=int, default=8, help="frames scored between keyframes (default 8)")
    ap.add_argument("--no-lidar", action="store_true", help="camera only")
    ap.add_argument("--work", required=True, help="folder for the two scenes (reused when there)")
    args = ap.parse_args(argv)

    from dataclasses import replace

    from xyzcyl.runtime.drive import load_drive, moving_boxes, reconstruct_drive
    from xyzcyl.runtime.drive_eval import camera_at, nearest_keyframe, plan
    from xyzcyl.runtime.inference import Reconstructor, rgb_images
    from xyzcyl.runtime.model_folder import default_model_dir
    from xyzcyl.runtime.scene import Scene
    from xyzcyl.runtime.stereo import box_mask

    drive = load_drive(args.drive)
    if not drive.tracks:
        print("drive: has no tracks (nothing to score inside)", file=sys.stderr)
        return 2
    keys, scored = plan(len(drive), args.every, args.max_views)
    work = Path(args.work)
    rec = None
    scenes = {}
    for name, d in (("tracks", drive), ("untracked", replace(drive, tracks=()))):
        folder = work / name
        if not (folder / "scene.json").is_file():
            rec = rec or Reconstructor.load(default_model_dir())
            reconstruct_drive(rec, d, keys, lidar=not args.no_lidar).save(folder)
        scenes[name] = Scene.load(folder)
    acc = {k: {"inside": [], "outside": [], "all": []} for k in (*scenes, "still")}
    for b in scored:
        near = nearest_keyframe(keys, b)
        truth, still = rgb_images(drive.frames[b].rig), rgb_images(drive.frames[near].rig)
        boxes = [(inv, half) for _, inv, half in moving_boxes(drive, b)]
        for ci, cam in enumerate(drive.frames[b].rig.cameras):
            c = camera_at(drive, 0, b, cam)
            inside = (box_mask(cam, drive.relative(b), boxes, (c.width, c.height), grow_px=0) if boxes
                      else np.zeros((c.height, c.width), bool))
            images = {n: np.clip(s.render(c, drive.frames[b].timestamp_s)[0], 0, 1) for n, s in scenes.items()}
            images["still"] = still[ci]
            for n, img in images.items():
                err = ((img - truth[ci]) ** 2).mean(axis=2)
                acc[n]["all"].append(err.mean())
                acc[n]["outside"].append(err[~inside].mean())
                if inside.sum() >= MIN_PIXELS:
                    acc[n]["inside"].append(err[inside].mean())
    psnr = {n: {k: round(float(np.mean([-10 * np.log10(max(e, 1e-10)) for e in v])), 3) if v else None
                for k, v in a.items()} for n, a in acc.items()}
    print(json.dumps({"keyframes": keys, "scored_frames": scored, "lidar": not args.no_lidar,
                      "cameras_inside": len(acc["tracks"]["inside"]), "psnr": psnr,
                      "inside_over_untracked": round(psnr["tracks"]["inside"] - psnr["untracked"]["inside"], 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
