"""The ground under the ego in a drive's scene (issue 37 item 3: "the ground below the cameras a flat grey disc ...
must come from the frames that drove over it"): one JSON document on stdout with the alpha a camera looking straight
down from above the ego sees at one frame of the drive, drawn from the drive's scene and from that frame's rig
reconstructed alone, and a picture (left the drive, right the frame alone; one row per height).

    .venv/bin/python benchmarks/drive_under_ego.py /work/synth_drive/drive.json --frame 20 --every 4 \\
        --picture docs/pictures/drive_synth_ground_under_ego.jpg

The camera: 960x720 pixels, f = 300 px, at the ego's origin raised by each --heights value (metres), ego x forward
pointing up in the image. The drive's LiDAR is used where its frames have it (--no-lidar: camera only).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def down_camera(T: np.ndarray, height_m: float, width: int = 960, rows: int = 720, f: float = 300.0):
    """A pinhole runtime.camera.Camera looking straight down from ``height_m`` metres above the origin of the ego
    pose T ([4, 4] ego -> the scene's frame): camera x = -ego y, camera y = -ego x (forward is up in the image),
    camera z = -ego z."""
    from xyzcyl.runtime.camera import Camera, pinhole_K

    c2e = np.eye(4)
    c2e[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    c2e[:3, 3] = (0.0, 0.0, height_m)
    return Camera(K=pinhole_K(f, f, (width - 1) / 2, (rows - 1) / 2), cam_to_ego=T @ c2e, width=width, height=rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drive", help="drive.json")
    ap.add_argument("--frame", type=int, default=20, help="the frame the ego stands at (default 20)")
    ap.add_argument("--every", type=int, default=4, help="a keyframe every N frames (default 4)")
    ap.add_argument("--heights", default="1.8,6", help="metres above the ego's origin, comma separated")
    ap.add_argument("--no-lidar", action="store_true", help="camera only")
    ap.add_argument("--picture", default=None, help="write the picture (.jpg / .png)")
    args = ap.parse_args(argv)

    import cv2
    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.inference import Reconstructor, default_model_dir
    from xyzcyl.runtime.lidar import has_lidar, load_lidar

    drive = load_drive(args.drive)
    if not 0 <= args.frame < len(drive):
        print(f"--frame: the drive has frames 0..{len(drive) - 1}", file=sys.stderr)
        return 2
    heights = [float(h) for h in args.heights.split(",")]
    rec = Reconstructor.load(default_model_dir())
    keys = list(range(0, len(drive), max(1, args.every)))
    scene = reconstruct_drive(rec, drive, keys, lidar=not args.no_lidar)
    rig = drive.frames[args.frame].rig
    lidar = load_lidar(rig).points if has_lidar(rig) and not args.no_lidar else None
    alone = rec.reconstruct(rig, lidar=lidar)
    t = drive.frames[args.frame].timestamp_s
    rows, out = [], {"drive": args.drive, "frame": args.frame, "keyframes": keys, "lidar": not args.no_lidar,
                     "views": []}
    for h in heights:
        a = scene.render(down_camera(drive.relative(args.frame), h), time_s=t)
        b = alone.render(down_camera(np.eye(4), h))
        out["views"].append({"height_m": h,
                             "drive": {"alpha_mean": round(float(a[2].mean()), 4),
                                       "alpha_under_half": round(float((a[2] < 0.5).mean()), 4)},
                             "frame_alone": {"alpha_mean": round(float(b[2].mean()), 4),
                                             "alpha_under_half": round(float((b[2] < 0.5).mean()), 4)}})
        rows.append(np.concatenate([np.clip(a[0], 0, 1), np.clip(b[0], 0, 1)], axis=1))
    if args.picture:
        img = (np.concatenate(rows, axis=0)[::2, ::2] * 255).astype(np.uint8)
        cv2.imwrite(args.picture, cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
        out["picture"] = args.picture
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
