"""A drive reconstructed whole against one frame alone and against not moving, on real frames: a thin wrapper of
`xyzcyl eval-real --drive` (runtime/drive_eval.py holds the evaluation; docs/cli.md the command):

    .venv/bin/python benchmarks/drive_eval.py DRIVE.json --every 8 --out out/drive_eval [--lidar on|off]
        [--frames 0:40] [--width 1920] [--stride 2] [--max-views N] [--model DIR]

is `xyzcyl eval-real --drive DRIVE.json --every 8 --out out/drive_eval ...` with the same flags. Prints one JSON line
per method (drive, one, still: PSNR, SSIM, sharpness ratio means, PSNR per camera) plus the scene sizes and times,
writes report.json and a picture sheet per scored frame (ground truth, drive, one frame alone, not moving) into
--out."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drive")
    ap.add_argument("--every", default="8", help="a keyframe every N frames (default 8)")
    ap.add_argument("--frames", default=None, metavar="A:B", help="use frames A..B-1 of the drive (default all)")
    ap.add_argument("--lidar", choices=("on", "off"), default="on")
    ap.add_argument("--width", default=None, help="score at this width (default the cameras' own)")
    ap.add_argument("--stride", default="2", help="detail stride (default 2)")
    ap.add_argument("--max-views", default=None, help="score at most N frames, evenly spread")
    ap.add_argument("--out", required=True)
    ap.add_argument("--model", default=None)
    args = ap.parse_args(argv)
    from xyzcyl import cli

    cmd = ["eval-real", "--drive", args.drive, "--every", args.every, "--out", args.out, "--lidar", args.lidar,
           "--stride", args.stride]
    for flag, value in (("--frames", args.frames), ("--width", args.width), ("--max-views", args.max_views),
                        ("--model", args.model)):
        if value is not None:
            cmd += [flag, value]
    return cli.main(cmd)


if __name__ == "__main__":
    sys.exit(main())
