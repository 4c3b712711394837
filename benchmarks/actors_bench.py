"""What a view's actor edits cost, and what they look like (issue 38 item 5: "a render with 30 moved actors costs at
most 15 % more than without edits"): one JSON document on stdout with the median render time of views along a drive
with no edits and with 30 actors moved 1.5 m to their left (copies inserted when fewer are drawn at that time), and
their ratio; with --picture, one actor seen by an input camera as recorded, moved 1.5 m to its left and hidden.

    .venv/bin/python benchmarks/actors_bench.py /work/shared/data/real/pandaset_002_drive/drive.json --every 4 \\
        --picture docs/pictures/actors_pandaset_moved_hidden.jpg

The scene is the drive reconstructed with keyframes every --every frames (LiDAR where its frames have it;
--scene DIR reads a scene folder written before, or writes one there when it has none). Views: every camera of
the drive's rig at 1920x1080 (their own size) placed at the frames --frames, at those frames' times; each timed
--repeats times alternately with and without edits (the median of each). The picture's actor: the tracked actor
drawn at one of those frames whose box centre one camera sees nearest (5-25 m, inside the image).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

N_MOVED = 30
SIDEWAYS_M = 1.5


def moved_edits(actors, time_s: float, slack_s: float, n: int = N_MOVED, left_m: float = SIDEWAYS_M):
    """``n`` edits (common.wire.ActorEdit): every actor drawn at ``time_s`` moved ``left_m`` metres to its left,
    then copies of them inserted (new ids "<id>+k") further to the left until there are ``n``."""
    from xyzcyl.common.wire import actor_edits

    drawn = [a for a, _ in actors.placements(time_s, slack_s)]
    if not drawn:
        return ()
    out = [{"id": actors.track_id[a], "offset": [0.0, left_m, 0.0]} for a in drawn[:n]]
    k = 0
    while len(out) < n:
        a = drawn[k % len(drawn)]
        out.append({"id": actors.track_id[a], "insert": f"{actors.track_id[a]}+{k}",
                    "offset": [0.0, left_m + 3.0 * (1 + k // len(drawn)), 0.0]})
        k += 1
    return actor_edits(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drive", help="drive.json (with tracks)")
    ap.add_argument("--every", type=int, default=4, help="a keyframe every N frames (default 4)")
    ap.add_argument("--scene", default=None, help="a scene folder of the drive to read (written when absent)")
    ap.add_argument("--frames", default="2,18,34", help="frames whose cameras and times are rendered")
    ap.add_argument("--repeats", type=int, default=3, help="timed renders per view and case (default 3)")
    ap.add_argument("--picture", default=None, help="write the picture (.jpg / .png)")
    args = ap.parse_args(argv)

    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.drive_eval import camera_at
    from xyzcyl.runtime.scene import Scene

    drive = load_drive(args.drive)
    frames = [int(f) for f in args.frames.split(",")]
    if not drive.tracks:
        print("drive: has no tracks (its moving objects become actors only with tracks)", file=sys.stderr)
        return 2
    if any(not 0 <= f < len(drive) for f in frames):
        print(f"--frames: the drive has frames 0..{len(drive) - 1}", file=sys.stderr)
        return 2
    if args.scene and (Path(args.scene) / "scene.json").is_file():
        scene = Scene.load(args.scene)
    else:
        from xyzcyl.runtime.inference import Reconstructor, default_model_dir

        keys = list(range(0, len(drive), max(1, args.every)))
        scene = reconstruct_drive(Reconstructor.load(default_model_dir()), drive, keys)
        if args.scene:
            scene.save(args.scene)
            scene = Scene.load(args.scene)
    if scene.actors is None:
        print("the scene has no actors", file=sys.stderr)
        return 2
    slack = 0.5 * scene.frame_interval()
    plain, edited, moved_counts = [], [], []
    for f in frames:
        t = drive.frames[f].timestamp_s
        edits = moved_edits(scene.actors, t, slack)
        moved_counts.append(len(edits))
        for cam in drive.frames[f].rig.cameras:
            c = camera_at(drive, 0, f, cam)
            scene.render(c, t)                        # warm: chunks read, kernels compiled
            scene.render(c, t, actors=edits)
            for _ in range(max(1, args.repeats)):
                t0 = time.perf_counter()
                scene.render(c, t)
                plain.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                scene.render(c, t, actors=edits)
                edited.append(time.perf_counter() - t0)
    a, b = statistics.median(plain), statistics.median(edited)
    doc = {"views": len(plain) // max(1, args.repeats), "size": [c.width, c.height], "moved_actors": moved_counts,
           "seconds_no_edits": round(a, 4), "seconds_30_moved": round(b, 4), "ratio": round(b / a, 3),
           "actors": len(scene.actors), "actor_gaussians": len(scene.actors.gaussians)}
    if args.picture:
        doc["picture"] = {"path": args.picture, "rows": picture(scene, drive, frames, slack, args.picture)}
    print(json.dumps(doc))
    return 0


def picture(scene, drive, frames, slack: float, path: str, rows: int = 2) -> list[dict]:
    """Write the sheet (recorded | moved 1.5 m left | hidden) of the ``rows`` tracked actors the input cameras see
    largest (the whole box in the image, 6-25 m away; one row each, different cameras); their descriptions."""
    import cv2
    from xyzcyl.common.wire import actor_edits
    from xyzcyl.runtime.actors import MOVED_LABEL
    from xyzcyl.runtime.drive_eval import camera_at
    from xyzcyl.runtime.realeval import sheet

    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    found = []
    for f in frames:
        t = drive.frames[f].timestamp_s
        for a, T in scene.actors.placements(t, slack):
            if scene.actors.track_label[a] == MOVED_LABEL:      # untracked cells that moved away: no car
                continue
            corners = (signs * 0.5 * scene.actors.track_size[a]) @ T[:3, :3].T + T[:3, 3]
            for cam in drive.frames[f].rig.cameras:
                c = camera_at(drive, 0, f, cam)
                uv, z, front = c.project(corners)
                inside = front.all() and np.all((uv >= 0) & (uv < (c.width, c.height)))
                if inside and 6.0 <= z.min() and z.max() <= 25.0:
                    area = cv2.contourArea(cv2.convexHull(uv.astype(np.float32)))
                    found.append((area, f, a, cam.name, c, t, float(z.min())))
    if not found:
        raise SystemExit("no tracked actor is seen whole 6-25 m from a camera at --frames")
    found.sort(key=lambda r: -r[0])
    chosen, used = [], set()
    for r in found:
        if r[3] not in used and r[2] not in {c[2] for c in chosen}:
            chosen.append(r)
            used.add(r[3])
        if len(chosen) == rows:
            break
    out, described = [], []
    for _, f, a, name, c, t, z in chosen:
        aid = scene.actors.track_id[a]
        imgs = [np.clip(scene.render(c, t, actors=actor_edits(e))[0], 0, 1)
                for e in ((), [{"id": aid, "offset": [0, SIDEWAYS_M, 0]}], [{"id": aid, "hide": True}])]
        out.append((f"frame {f} {name}: {scene.actors.track_label[a]} {z:.0f} m", imgs))
        described.append({"frame": f, "camera": name, "actor": aid, "label": scene.actors.track_label[a],
                          "nearest_m": round(z, 2)})
    img = sheet(out, ("as recorded", f"moved {SIDEWAYS_M} m to its left", "hidden"), 640)
    if not cv2.imwrite(path, img[..., ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 88]):
        raise OSError(f"could not write {path!r}")
    return described


if __name__ == "__main__":
    sys.exit(main())
