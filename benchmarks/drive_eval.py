"""A drive reconstructed whole against one frame alone and against not moving (runtime.drive), on real frames:

    .venv/bin/python benchmarks/drive_eval.py DRIVE.json --every 8 --out out/drive_eval [--lidar on|off]
        [--frames 0:40] [--width 1920] [--stride 2] [--max-views N]

Keyframes every ``--every``th frame of ``--frames``; the drive of those keyframes is reconstructed once
(runtime.drive.reconstruct_drive) and each keyframe alone once (Reconstructor.reconstruct). Every frame between
keyframes is scored, with all its cameras at ``--width`` pixels (aspect kept), three ways against its own images:
- drive: the drive's scene rendered at the frame's cameras (placed in the first frame's ego frame) and time (its
  moving objects where the tracks put them then);
- one: the nearest keyframe reconstructed alone, rendered at the frame's cameras (in that keyframe's frame);
- still: "not moving", the nearest keyframe's own image of that camera.
Prints one JSON line per method (PSNR, SSIM, sharpness ratio means, per camera too) plus the scene sizes and times,
writes report.json and a picture sheet per scored frame (ground truth, drive, one frame alone, not moving) into
--out. With --max-views the scored frames are spread evenly over the drive (a quick run)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drive", type=Path)
    ap.add_argument("--every", type=int, default=8, help="a keyframe every N frames (default 8)")
    ap.add_argument("--frames", default=None, metavar="A:B", help="use frames A..B-1 of the drive (default all)")
    ap.add_argument("--lidar", choices=("on", "off"), default="on")
    ap.add_argument("--width", type=int, default=None, help="score at this width (default the cameras' own)")
    ap.add_argument("--stride", type=int, default=2, help="detail stride (default 2)")
    ap.add_argument("--max-views", type=int, default=None, help="score at most N frames, evenly spread")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--model", type=Path, default=None)
    args = ap.parse_args(argv)

    import cv2
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import Drive, load_drive, reconstruct_drive
    from xyzcyl.runtime.inference import Reconstructor, default_model_dir
    from xyzcyl.runtime.lidar import has_lidar, load_lidar
    from xyzcyl.runtime.realeval import image_metrics, sheet
    from xyzcyl.runtime.scene import render_view, rig_camera

    drive = load_drive(args.drive)
    if args.frames:
        a, b = (int(x) for x in args.frames.split(":"))
        drive = Drive(drive.path, drive.frames[a:b], drive.tracks)
        drive = Drive(drive.path, tuple(f.__class__(i, f.rig_path, f.rig, f.timestamp_s, f.ego_to_world)
                                        for i, f in enumerate(drive.frames)), ())
    keys = list(range(0, len(drive), args.every))
    scored = [k for k in range(len(drive)) if k not in keys]
    if args.max_views:
        scored = [scored[round(i * (len(scored) - 1) / max(1, args.max_views - 1))]
                  for i in range(min(args.max_views, len(scored)))]
        scored = sorted(set(scored))
    args.out.mkdir(parents=True, exist_ok=True)
    rec = Reconstructor.load(args.model or default_model_dir())
    opts = DetailOptions(stride=args.stride)
    lidar = args.lidar == "on"

    t0 = time.perf_counter()
    whole = reconstruct_drive(rec, drive, keyframes=keys, lidar=lidar, detail=opts)
    t_drive = time.perf_counter() - t0
    singles, t_single = {}, []
    for k in keys:
        t1 = time.perf_counter()
        rig = drive.frames[k].rig
        pts = load_lidar(rig).points if lidar and has_lidar(rig) else None
        singles[k] = rec.reconstruct(rig, lidar=pts, detail=opts)
        t_single.append(time.perf_counter() - t1)

    def cam_at(k_from: int, k_to: int, cam, width: int | None):
        """Camera ``cam`` of frame k_to in frame k_from's ego frame, at ``width`` pixels."""
        T = np.linalg.inv(drive.frames[k_from].ego_to_world) @ drive.frames[k_to].ego_to_world @ cam.cam_to_ego
        T[3] = (0, 0, 0, 1)
        c = rig_camera(cam.replace(cam_to_ego=T))
        if width and width != c.width:
            c = c.resized(width, round(c.height * width / c.width))
        return c

    def shot(scene, cam, time_s=None) -> np.ndarray:
        rgb, _, _ = render_view(scene, cam, time_s=time_s)
        return np.clip(rgb, 0, 1)

    rows = []
    for b in scored:
        near = min(keys, key=lambda k: (abs(k - b), k))
        fb, fk = drive.frames[b], drive.frames[near]
        imgs_b, imgs_k = fb.rig.load_images(), fk.rig.load_images()
        pics = []
        for cam, gt, still in zip(fb.rig.cameras, imgs_b, imgs_k):
            c_drive = cam_at(0, b, cam, args.width)
            c_one = cam_at(near, b, cam, args.width)
            size = (c_drive.width, c_drive.height)
            gt_s = cv2.resize(gt, size, interpolation=cv2.INTER_AREA) if gt.shape[1] != size[0] else gt
            st_s = cv2.resize(still, size, interpolation=cv2.INTER_AREA) if still.shape[1] != size[0] else still
            r_drive, r_one = shot(whole, c_drive, fb.timestamp_s), shot(singles[near], c_one)
            row = {"frame": b, "keyframe": near, "camera": cam.name}
            for name, img in (("drive", r_drive), ("one", r_one), ("still", st_s)):
                row.update({f"{name}_{k}": v for k, v in image_metrics(img, gt_s).items()})
            rows.append(row)
            pics.append((cam.name, [gt_s, r_drive, r_one, st_s]))
        pic = sheet(pics, ["ground truth", "drive", "one frame alone", "not moving"], width=480)
        cv2.imwrite(str(args.out / f"frame_{b:02d}.jpg"), pic[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 88])

    def mean(key: str, sel=lambda r: True) -> float:
        v = [r[key] for r in rows if sel(r) and np.isfinite(r[key])]
        return float(np.mean(v)) if v else float("nan")

    cams = sorted({r["camera"] for r in rows})
    report = {"drive": str(args.drive), "frames": len(drive), "keyframes": keys, "scored_frames": scored,
              "lidar": args.lidar, "width": args.width, "stride": args.stride,
              "gaussians": {"drive": len(whole.gaussians),
                            "one_frame": {str(k): int((s.gaussians.opacity_logits > -20).sum())
                                          for k, s in singles.items()}},
              "seconds": {"drive": round(t_drive, 2), "one_frame_each": [round(t, 2) for t in t_single],
                          "drive_stages": whole.timings},
              "drive_counts": whole.counts, "methods": {}}
    for m in ("drive", "one", "still"):
        report["methods"][m] = {k: mean(f"{m}_{k}") for k in ("psnr", "ssim", "sharpness")}
        report["methods"][m]["per_camera"] = {c: mean(f"{m}_psnr", lambda r, c=c: r["camera"] == c) for c in cams}
        print(json.dumps({"method": m, **report["methods"][m]}))
    report["rows"] = rows
    (args.out / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({"gaussians": report["gaussians"], "seconds": report["seconds"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
