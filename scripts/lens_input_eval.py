"""Fisheye inputs against pinhole inputs (issue 28's input-side target): the same synthetic scenes seen by the same
6-camera rig through pinhole lenses and through fisheye / f-theta lenses of the same resolution and field of view,
each reconstructed with the shipped model, both rendered at the same held-out pinhole target cameras.

Per scene (model_export.data.scene.sample_scene(SEED, i), as `xyzcyl data synth` draws its scenes): the nuScenes
preset rig at 400x224 (jittered as the generator does) and its ego-forward targets (the rig moved back and forward
along the lane by U(1, 3) m, the paper's ego-forward setting: 12 pinhole views), all ray traced
(model_export.data.trace.render_view). Input rigs, every camera at the same mount, size and principal point:
- ``pinhole``: the preset's pinhole cameras;
- ``fisheye``: OpenCV fisheye (Kannala-Brandt, k1..k4 = FISHEYE_K, mild), its focal chosen so the image spans the
  pinhole's horizontal and vertical field of view (the edge midpoints see the same angles);
- ``ftheta``: NVIDIA f-theta, r(theta) = a1 theta + a3 theta^3 with a3 = FTHETA_CUBIC a1, a1 (and linear_cde's c
  for x) chosen likewise;
- ``fisheye_samef``: the fisheye lens on the pinhole's own K (the same paraxial focal, so the same resolution at
  the image centre; the image then spans a wider field than the pinhole's);
- ``fisheye_z`` (ablation): the fisheye rig with the network's depth rays in camera z instead of the distance
  (runtime.lifting.depth_rays patched), to check the convention the runtime chose.
The input images of the lens rigs are traced through each pixel's true ray (no undistortion anywhere).

Each rig is reconstructed with runtime.inference.Reconstructor (the shipped model, 2 threads; detail layer on, the
default, and off), rendered with runtime.scene.render_view at the 12 targets and compared with the traced ground
truth: PSNR, PSNR over non-sky pixels, SSIM (skimage.metrics.structural_similarity, channel_axis 2, data range 1),
sharpness = variance of the Laplacian of the luminance, render / ground truth, and sharpness_grad = the mean
luminance gradient, render / ground truth (runtime.realeval.sharpness_ratio). Differences lens - pinhole are
paired per view; the summary gives their mean over scenes with a 95 % t interval over the scene means.

    .venv/bin/python scripts/lens_input_eval.py --scenes 4 --out benchmarks/records/lens_inputs_2026-11-26.json \
        --picture docs/pictures/lens_inputs.png

Deterministic: fixed seeds; the tracer traces each pixel alone and the runtime's results do not depend on its
thread count (docs/inference.md).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import cv2
import numpy as np
from skimage.metrics import structural_similarity
from xyzcyl.model_export.data.rigs import base_rig, ego_forward_targets, jitter
from xyzcyl.model_export.data.scene import SceneConfig, sample_scene
from xyzcyl.model_export.data.trace import build_grid, render_view
from xyzcyl.runtime import lifting
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.detail import DetailOptions
from xyzcyl.runtime.inference import Reconstructor, default_model_dir
from xyzcyl.runtime.lenses import fisheye_theta_d
from xyzcyl.runtime.realeval import sharpness_ratio
from xyzcyl.runtime.rig import Rig
from xyzcyl.runtime.scene import render_view as render_scene_view

SEED = 7                                  # scenes of this seed (the training set is seed 0, validation seed 1)
WIDTH, HEIGHT = 400, 224
FISHEYE_K = (0.02, -0.005, 0.001, 0.0)
FTHETA_CUBIC = -0.05
MAX_ANGLE_DEG = 100.0
RIGS = ("pinhole", "fisheye", "ftheta", "fisheye_samef", "fisheye_z")
METRICS = ("psnr", "psnr_fg", "ssim", "sharpness", "sharpness_grad")
PICTURE_SCALE = 0.75                      # the sheet's tiles at 300 x 168 (the PNG stays under 400 kB)
LUMA = np.array([0.299, 0.587, 0.114], np.float32)


# ------------------------------------------------------------------------------------------- rigs


def _edge_angles(cam: Camera) -> tuple[float, float]:
    """Angles from the axis of the pinhole's left-edge midpoint (u = -0.5) and top-edge midpoint (v = -0.5)."""
    K = cam.K
    return math.atan((K[0, 2] + 0.5) / K[0, 0]), math.atan((K[1, 2] + 0.5) / K[1, 1])


def fisheye_camera(cam: Camera) -> Camera:
    """``cam`` with an OpenCV fisheye lens (FISHEYE_K) whose image edges see the pinhole's edge angles."""
    ax, ay = _edge_angles(cam)
    K = cam.K.copy()
    K[0, 0] = (K[0, 2] + 0.5) / float(fisheye_theta_d(ax, FISHEYE_K))
    K[1, 1] = (K[1, 2] + 0.5) / float(fisheye_theta_d(ay, FISHEYE_K))
    lens = {"model": "opencv_fisheye", **dict(zip(("k1", "k2", "k3", "k4"), FISHEYE_K)),
            "max_angle_deg": MAX_ANGLE_DEG}
    return cam.replace(K=K, distortion=lens)


def ftheta_camera(cam: Camera) -> Camera:
    """``cam`` with an f-theta lens r = a1 theta + a3 theta^3 (a3 = FTHETA_CUBIC a1) whose top edge sees the
    pinhole's top-edge angle and, with linear_cde's c, whose left edge its left-edge angle; K's fx, fy set to the
    paraxial focal."""
    ax, ay = _edge_angles(cam)
    a1 = (cam.K[1, 2] + 0.5) / (ay + FTHETA_CUBIC * ay ** 3)
    c = (cam.K[0, 2] + 0.5) / (a1 * (ax + FTHETA_CUBIC * ax ** 3))
    K = cam.K.copy()
    K[0, 0], K[1, 1] = c * a1, a1
    lens = {"model": "ftheta", "reference_poly": "angle_to_pixeldist",
            "angle_to_pixeldist_poly": [0.0, a1, 0.0, FTHETA_CUBIC * a1], "max_angle_deg": MAX_ANGLE_DEG,
            "linear_cde": [c, 0.0, 0.0]}
    return cam.replace(K=K, distortion=lens)


def z_depth_rays(rig: Rig, spec):
    """runtime.lifting.depth_rays with camera z for every camera (the ablation's convention)."""
    P = spec.points()
    rays, offs = [], []
    for cam in rig.cameras:
        _, z, front = cam.project(P)
        ok = front & (z > 1e-6)
        rays.append(np.where(ok[..., None], (P - cam.position) / np.where(ok, z, 1.0)[..., None], 0.0))
        offs.append(cam.position - spec.centre)
    return np.stack(rays).astype(np.float32), np.stack(offs).astype(np.float32)


# ------------------------------------------------------------------------------------------- metrics


def metrics(pred: np.ndarray, gt: np.ndarray, sky: np.ndarray) -> dict[str, float]:
    pred = np.clip(pred, 0.0, 1.0).astype(np.float32)
    mse = float(np.mean((pred - gt) ** 2))
    fg = ~sky
    mse_fg = float(np.mean((pred[fg] - gt[fg]) ** 2)) if fg.any() else float("nan")
    lap = lambda img: float(cv2.Laplacian(img @ LUMA, cv2.CV_32F).var())  # noqa: E731
    return {"psnr": -10 * math.log10(max(mse, 1e-12)), "psnr_fg": -10 * math.log10(max(mse_fg, 1e-12)),
            "ssim": float(structural_similarity(pred, gt, channel_axis=2, data_range=1.0)),
            "sharpness": lap(pred) / max(lap(gt), 1e-12), "sharpness_grad": sharpness_ratio(pred, gt)}


def t_interval(x: list[float]) -> list[float]:
    """95 % two-sided t interval of the mean (scipy-free: the t quantiles for n - 1 <= 10)."""
    t95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228}
    a = np.asarray(x, np.float64)
    if len(a) < 2:
        return [float("nan"), float("nan")]
    h = t95.get(len(a) - 1, 1.96) * a.std(ddof=1) / math.sqrt(len(a))
    return [float(a.mean() - h), float(a.mean() + h)]


# ------------------------------------------------------------------------------------------- run


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--out", type=Path, required=True, help="JSON report")
    ap.add_argument("--picture", type=Path, default=None,
                    help="PNG: scene 0's front target t2: ground truth | from pinhole inputs | from fisheye inputs; "
                         "below, its front input through the pinhole, the fisheye and the f-theta lens")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    t_start = time.perf_counter()
    rec = Reconstructor.load(default_model_dir(), threads=args.threads)
    detail_modes = {"detail": DetailOptions(), "no_detail": None}
    rows: list[dict] = []
    tiles: list[list[np.ndarray]] = []
    inputs_info: dict[str, list] = {}
    original_depth_rays = lifting.depth_rays
    for i in range(args.scenes):
        scene = sample_scene(SEED, i, SceneConfig(with_ego=False))
        grid = build_grid(scene)
        rng = np.random.default_rng([SEED, i, 0xCA3])
        pins = jitter(base_rig("nuscenes", WIDTH, HEIGHT), rng)
        targets = ego_forward_targets(pins, scene.lane_dir, rng)
        gts = [render_view(scene, grid, c, 2) for c in targets]
        rigs = {"pinhole": pins, "fisheye": [fisheye_camera(c) for c in pins],
                "ftheta": [ftheta_camera(c) for c in pins]}
        rigs["fisheye_samef"] = [c.replace(distortion=rigs["fisheye"][0].distortion) for c in pins]
        rigs["fisheye_z"] = rigs["fisheye"]
        images = {}
        for name in ("pinhole", "fisheye", "ftheta", "fisheye_samef"):
            views = [render_view(scene, grid, c, 2) for c in rigs[name]]
            images[name] = [v.rgb for v in views]
            if i == 0:
                inputs_info[name] = [{"camera": c.name, "K": np.round(c.K, 4).tolist(),
                                      "distortion": None if c.distortion is None else c.distortion.to_json(),
                                      "hfov_deg": round(math.degrees(c.horizontal_fov), 3),
                                      "vfov_deg": round(math.degrees(c.vertical_fov), 3),
                                      "focal_n": float(lifting.focal_n(Rig(cameras=(c,)))[0])}
                                     for c in rigs[name]]
        images["fisheye_z"] = images["fisheye"]
        renders = {}
        for name in RIGS:
            rig = Rig(cameras=tuple(rigs[name]))
            for mode, opts in detail_modes.items():
                lifting.depth_rays = z_depth_rays if name == "fisheye_z" else original_depth_rays
                rec._cache.clear()
                try:
                    sc = rec.reconstruct(rig, images[name], detail=opts)
                finally:
                    lifting.depth_rays = original_depth_rays
                for k, (cam, gt) in enumerate(zip(targets, gts)):
                    rgb, _, _ = render_scene_view(sc, Camera(K=cam.K, cam_to_ego=cam.cam_to_ego, width=cam.width,
                                                             height=cam.height))
                    m = metrics(rgb, gt.rgb.astype(np.float32) / 255.0, gt.sky)
                    rows.append({"scene": i, "view": cam.name, "rig": name, "mode": mode,
                                 **{k: round(v, 5) for k, v in m.items()}})
                    if mode == "detail":
                        renders[(name, k)] = rgb
            print(f"scene {i} {name}: {time.perf_counter() - t_start:.0f} s", flush=True)
        if args.picture is not None and i == 0:
            k = [c.name for c in targets].index("CAM_FRONT_t2")
            tiles.append([gts[k].rgb.astype(np.float32) / 255.0, renders[("pinhole", k)], renders[("fisheye", k)]])
            tiles.append([images[n][0].astype(np.float32) / 255.0 for n in ("pinhole", "fisheye", "ftheta")])
    summary = summarise(rows)
    doc = {"what": "fisheye / f-theta inputs against pinhole inputs, same scenes, same pinhole targets "
                   "(scripts/lens_input_eval.py)",
           "model": rec.info.name + " " + rec.info.version, "seed": SEED, "scenes": args.scenes,
           "size": [WIDTH, HEIGHT], "targets": "ego-forward (rig moved -U(1,3) and +U(1,3) m along the lane), 12 per "
                                               "scene, pinhole",
           "fisheye_k": list(FISHEYE_K), "ftheta_cubic": FTHETA_CUBIC, "rigs_scene0": inputs_info,
           "metrics": {"psnr": "dB, whole image", "psnr_fg": "dB, non-sky pixels", "ssim": "skimage, data range 1",
                       "sharpness": "Laplacian variance of the luminance, render / ground truth"},
           "summary": summary, "rows": rows,
           "machine": {"python": platform.python_version(), "cpu_threads": args.threads},
           "seconds": round(time.perf_counter() - t_start, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    if args.picture is not None:
        sheet = np.concatenate([np.concatenate(t, axis=1) for t in tiles], axis=0)
        sheet = cv2.resize(sheet, None, fx=PICTURE_SCALE, fy=PICTURE_SCALE, interpolation=cv2.INTER_AREA)
        u8 = (np.clip(sheet, 0, 1) * 255 + 0.5).astype(np.uint8)
        args.picture.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.picture), u8[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(json.dumps(summary, indent=1))
    return 0


def summarise(rows: list[dict]) -> dict:
    """Per rig and detail mode: the mean of each metric over all views; per lens rig: the paired difference lens -
    pinhole (per view, then the mean per scene) with a 95 % t interval over the scene means."""
    out: dict = {}
    keys = METRICS
    for mode in ("detail", "no_detail"):
        sel = [r for r in rows if r["mode"] == mode]
        out[mode] = {}
        base = {(r["scene"], r["view"]): r for r in sel if r["rig"] == "pinhole"}
        for rig in RIGS:
            rr = [r for r in sel if r["rig"] == rig]
            entry = {k: float(np.mean([r[k] for r in rr])) for k in keys}
            refs = {"pinhole": base}
            if rig == "fisheye_z":     # the ablation against the runtime's convention on the same images
                refs["fisheye"] = {(r["scene"], r["view"]): r for r in sel if r["rig"] == "fisheye"}
            for ref_name, ref in refs.items():
                if rig == ref_name:
                    continue
                scenes = sorted({r["scene"] for r in rr})
                for k in keys:
                    per_scene = [float(np.mean([r[k] - ref[(r["scene"], r["view"])][k] for r in rr
                                                if r["scene"] == s])) for s in scenes]
                    entry[f"{k}_minus_{ref_name}"] = float(np.mean(per_scene))
                    entry[f"{k}_minus_{ref_name}_ci95"] = t_interval(per_scene)
            out[mode][rig] = entry
    return out


if __name__ == "__main__":
    raise SystemExit(main())
