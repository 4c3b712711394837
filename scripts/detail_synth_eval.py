"""The detail layer (runtime/detail.py) on synthetic validation scenes, through the runtime path: detail on vs off.

For each scene folder of a synthetic data set (`xyzcyl data synth`, docs/data.md): the input rig (K, cam_to_ego,
size; camera only: no depth, no LiDAR) is reconstructed twice with the shipped model, ``detail=None`` (off) and
``detail=DetailOptions(stride=S)`` (on), and each scene is rendered with ``runtime.scene.render_view`` at

- every target view of the ego-forward and ego-inward settings (targets.json; views the generator marked
  ``occluded`` are skipped, as model_export/evaluate.py does by default), and
- every input camera ("input").

Scores (runtime.realeval.image_metrics, render clipped to 0..1): PSNR, SSIM, sharpness ratio (mean luminance
gradient of the render / that of the ground truth); plus PSNR over the non-sky pixels (the view's sky mask < 128)
and PSNR without the ego car's pixels (semantic class 10: only ego-inward views show the ego, which no input
camera sees). Ego-inward rows carry the camera's elevation above the hemisphere centre; the summary splits the
ego-inward differences into elevation bands.

Torch-free: only xyzcyl.runtime, numpy, cv2 and the data set's files (read directly, not through
model_export.dataset, which imports torch).

    .venv/bin/python scripts/detail_synth_eval.py --data /work/runs/synth_val_detail --out /work/runs/detail_eval \
        [--max-scenes 20] [--stride 2] [--sheet docs/detail_synth.jpg]

Writes OUT/detail_synth_eval.json (per-view rows, per-scene means, means per setting for off and on, paired
differences on - off over scenes with a 95 % t interval and a 95 % bootstrap interval), the contact sheet (ground
truth | detail off | detail on for a few target views) as JPEG at --sheet (< 400 kB) and as PNG in OUT.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.detail import DetailOptions
from xyzcyl.runtime.inference import Reconstructor, default_model_dir
from xyzcyl.runtime.realeval import image_metrics, psnr
from xyzcyl.runtime.rig import Rig, read_image
from xyzcyl.runtime.scene import render_view, rig_camera
from xyzcyl.runtime.views import camera_from_opencv

SETTINGS = ("ego-forward", "ego-inward", "input")
METRICS = ("psnr", "psnr_fg", "psnr_noego", "ssim", "sharpness")
EGO_CLASS = 10                      # docs/data.md: ego_vehicle (only ego-inward views show it)
INWARD_CENTRE = np.array([1.3, 0.0, 0.8])   # docs/data.md: the ego-inward hemisphere's centre
MODES = ("off", "on")


# ------------------------------------------------------------------------------------------- data set files


def scene_dirs(root: Path, max_scenes: int | None) -> list[Path]:
    dirs = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("scene_"))
    return dirs if max_scenes is None else dirs[:max_scenes]


def input_rig(scene: Path) -> tuple[Rig, list[np.ndarray]]:
    """The scene's input rig as a runtime Rig (calibration only: image and depth file names dropped, so
    reconstruct reads no depth) and its images [H, W, 3] float32 0..1 in rig order."""
    doc = json.loads((scene / "rig.json").read_text())
    cams, images = [], []
    for i, d in enumerate(doc["cameras"]):
        c = Camera.from_dict(d, i)
        img = read_image(scene / d["image"], f"{scene.name} {c.name}")
        assert img.shape[:2] == (c.height, c.width), (scene, c.name, img.shape)
        cams.append(c.replace(image=None, depth=None))
        images.append(img)
    return Rig(cameras=tuple(cams)), images


def target_views(scene: Path, setting: str) -> list[dict[str, Any]]:
    """Target camera entries of a setting (targets.json), occluded ones skipped."""
    doc = json.loads((scene / "targets.json").read_text())
    s = doc["settings"].get(setting)
    if s is None:
        return []
    return [c for c in s["cameras"] if not c.get("occluded", False)]


def view_camera(entry: dict[str, Any]):
    K = np.asarray(entry["K"], np.float64)
    return camera_from_opencv(entry["cam_to_ego"], entry["width"], entry["height"], fx=K[0, 0], fy=K[1, 1],
                              cx=K[0, 2], cy=K[1, 2])


def sky_mask(scene: Path, entry: dict[str, Any]) -> np.ndarray | None:
    name = entry.get("sky")
    if not name:
        return None
    return read_image(scene / name, f"{scene.name} {entry['name']} sky", channels=1, scale=False)[..., 0] >= 128


def ego_mask(scene: Path, entry: dict[str, Any]) -> np.ndarray | None:
    """True where the view sees the ego car (semantic class 10): no input camera sees it (docs/data.md)."""
    name = entry.get("semantic")
    if not name:
        return None
    return read_image(scene / name, f"{scene.name} {entry['name']} sem", channels=1, scale=False)[..., 0] == EGO_CLASS


def elevation_deg(entry: dict[str, Any]) -> float:
    """Elevation of the camera above the ego-inward centre, degrees."""
    d = np.asarray(entry["cam_to_ego"], np.float64)[:3, 3] - INWARD_CENTRE
    return float(np.degrees(np.arctan2(d[2], np.hypot(d[0], d[1]))))


# ------------------------------------------------------------------------------------------- scoring


def score(pred: np.ndarray, gt: np.ndarray, sky: np.ndarray | None, ego: np.ndarray | None) -> dict[str, float]:
    m = image_metrics(pred, gt)
    fg = None if sky is None else ~sky
    m["psnr_fg"] = psnr(pred[fg], gt[fg]) if fg is not None and fg.any() else float("nan")
    m["psnr_noego"] = m["psnr"] if ego is None or not ego.any() else psnr(pred[~ego], gt[~ego])
    return m


def finite_mean(v) -> float:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def paired(diffs: np.ndarray, rng: np.random.Generator, n_boot: int = 10000) -> dict[str, Any]:
    """Mean of paired differences, its 95 % t interval and 95 % percentile bootstrap interval (over scenes)."""
    from scipy import stats

    d = np.asarray([x for x in diffs if math.isfinite(x)], np.float64)
    n = len(d)
    out: dict[str, Any] = {"n": n, "mean": float(d.mean()) if n else float("nan")}
    if n >= 2:
        se = d.std(ddof=1) / math.sqrt(n)
        q = stats.t.ppf(0.975, n - 1)
        out["sd"] = float(d.std(ddof=1))
        out["t95"] = [float(d.mean() - q * se), float(d.mean() + q * se)]
        bm = d[rng.integers(0, n, (n_boot, n))].mean(axis=1)
        out["boot95"] = [float(np.percentile(bm, 2.5)), float(np.percentile(bm, 97.5))]
        out["frac_positive"] = float((d > 0).mean())
    return out


# ------------------------------------------------------------------------------------------- contact sheet


def write_sheet(tiles: list[dict[str, Any]], jpg: Path | None, png: Path, width: int = 400) -> None:
    import cv2

    def thumb(img: np.ndarray) -> np.ndarray:
        h = round(img.shape[0] * width / img.shape[1])
        t = cv2.resize(np.clip(img, 0, 1).astype(np.float32), (width, h), interpolation=cv2.INTER_AREA)
        return np.rint(t * 255).astype(np.uint8)

    def label(img: np.ndarray, text: str) -> None:
        (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)
        img[:h + base + 6, :w + 8] //= 3                     # darkened box behind the text
        cv2.putText(img, text, (4, h + 3), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 0), 1, cv2.LINE_AA)

    head = np.zeros((22, 3 * width, 3), np.uint8)
    for i, t in enumerate(("ground truth", "detail off", "detail on")):
        cv2.putText(head, t, (6 + i * width, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.48, (255, 255, 255), 1, cv2.LINE_AA)
    rows = [head]
    for t in tiles:
        a, b, c = thumb(t["gt"]), thumb(t["off"]), thumb(t["on"])
        label(a, t["title"])
        label(b, f"PSNR {t['m_off']['psnr']:.2f} SSIM {t['m_off']['ssim']:.3f} sharp {t['m_off']['sharpness']:.2f}")
        label(c, f"PSNR {t['m_on']['psnr']:.2f} SSIM {t['m_on']['ssim']:.3f} sharp {t['m_on']['sharpness']:.2f}")
        rows.append(np.concatenate([a, b, c], axis=1))
    sheet = np.concatenate(rows, axis=0)
    bgr = sheet[..., ::-1]
    png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(png), bgr)
    if jpg is not None:
        jpg.parent.mkdir(parents=True, exist_ok=True)
        for q in (88, 82, 76, 70, 64, 58, 50, 40):
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, q, cv2.IMWRITE_JPEG_OPTIMIZE, 1])
            if ok and len(buf) < 400_000:
                break
        jpg.write_bytes(buf.tobytes())
        print(f"sheet: {jpg} ({len(buf) / 1000:.0f} kB, JPEG quality {q}), {png}", flush=True)


# ------------------------------------------------------------------------------------------- driver


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, type=Path, help="synthetic data set folder (xyzcyl data synth)")
    ap.add_argument("--out", required=True, type=Path, help="output folder (JSON, PNG contact sheet)")
    ap.add_argument("--max-scenes", type=int, default=None, help="first N scenes (default: all)")
    ap.add_argument("--set", action="append", metavar="FIELD=VALUE",
                    help="another DetailOptions field for the 'on' run (repeatable), e.g. surface_stretch=4")
    ap.add_argument("--stride", type=int, default=DetailOptions().stride, help="detail stride (default: the "
                    "runtime default)")
    ap.add_argument("--max-views", type=int, default=None,
                    help="at most this many target views per setting and scene, evenly spread (default: all)")
    ap.add_argument("--sheet", type=Path, default=Path("docs/detail_synth.jpg"), help="contact sheet JPEG")
    ap.add_argument("--sheet-scenes", type=int, default=3, help="scenes on the sheet (one view per setting each)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    ap.add_argument("--model", type=Path, default=None, help="model folder (default: the shipped model)")
    args = ap.parse_args(argv)

    import dataclasses

    extra = {}
    for kv in args.set or []:
        key, _, value = kv.partition("=")
        field = {f.name: f for f in dataclasses.fields(DetailOptions)}.get(key)
        if field is None:
            ap.error(f"--set: {key!r} is not a DetailOptions field")
        default = getattr(DetailOptions(), key)
        extra[key] = (value.lower() in ("1", "true", "yes")) if isinstance(default, bool) else type(default)(value)
    opts = DetailOptions(stride=args.stride, **extra)
    model_dir = args.model or default_model_dir()
    rec = Reconstructor.load(model_dir, threads=args.threads)
    scenes = scene_dirs(args.data, args.max_scenes)
    if not scenes:
        print(f"no scene_* folders in {args.data}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    scene_info: list[dict[str, Any]] = []
    tiles: list[dict[str, Any]] = []
    for si, scene in enumerate(scenes):
        t_scene = time.perf_counter()
        rig, images = input_rig(scene)
        recon, t_rec, counts = {}, {}, {}
        for mode in MODES:
            t0 = time.perf_counter()
            recon[mode] = rec.reconstruct(rig, images=images, depths=[None] * len(images), lidar=None,
                                          detail=None if mode == "off" else opts)
            t_rec[mode] = time.perf_counter() - t0
            counts[mode] = dict(recon[mode].counts)
        t_render = {m: 0.0 for m in MODES}
        views: list[tuple[str, str, Any, np.ndarray, np.ndarray | None, np.ndarray | None, dict]] = []
        for setting in SETTINGS[:2]:
            entries = target_views(scene, setting)
            if args.max_views is not None and len(entries) > args.max_views:
                idx = np.linspace(0, len(entries) - 1, args.max_views).round().astype(int)
                entries = [entries[k] for k in sorted(set(idx))]
            for e in entries:
                extra = {"elevation_deg": elevation_deg(e)} if setting == "ego-inward" else {}
                ego = ego_mask(scene, e)
                if ego is not None:
                    extra["ego_frac"] = float(ego.mean())
                views.append((setting, e["name"], view_camera(e), read_image(scene / e["image"], e["name"]),
                              sky_mask(scene, e), ego, extra))
        doc = json.loads((scene / "rig.json").read_text())
        for cam, img, d in zip(rig.cameras, images, doc["cameras"]):
            views.append(("input", cam.name, rig_camera(cam), img, sky_mask(scene, d), None, {}))
        sheet_pick = set()
        if si < args.sheet_scenes:
            for setting in SETTINGS[:2]:
                names = [v[1] for v in views if v[0] == setting]
                if names:
                    # ego-forward: a front-camera view moved forward (t2) if any; ego-inward: the middle view
                    pref = [n for n in names if n.startswith("CAM_FRONT_t2")] if setting == "ego-forward" else []
                    sheet_pick.add((setting, pref[0] if pref else names[len(names) // 2]))
        for setting, name, cam, gt, sky, ego, extra in views:
            row: dict[str, Any] = {"scene": scene.name, "setting": setting, "view": name, **extra}
            preds = {}
            for mode in MODES:
                t0 = time.perf_counter()
                rgb, _, _ = render_view(recon[mode], cam)
                t_render[mode] += time.perf_counter() - t0
                pred = np.clip(rgb, 0.0, 1.0)
                preds[mode] = pred
                for k, v in score(pred, gt, sky, ego).items():
                    row[f"{mode}_{k}"] = v
            rows.append(row)
            if (setting, name) in sheet_pick:
                tiles.append({"title": f"{scene.name} {setting} {name}", "gt": gt, "off": preds["off"],
                              "on": preds["on"], "m_off": {k: row[f"off_{k}"] for k in METRICS},
                              "m_on": {k: row[f"on_{k}"] for k in METRICS}})
        info = {"scene": scene.name, "seconds": time.perf_counter() - t_scene,
                "reconstruct_s": t_rec, "render_s": t_render,
                "gaussians": {m: len(recon[m].gaussians) for m in MODES}, "counts_on": counts["on"],
                "views": {s: sum(r["scene"] == scene.name and r["setting"] == s for r in rows) for s in SETTINGS}}
        scene_info.append(info)
        mine = [r for r in rows if r["scene"] == scene.name]
        msg = "  ".join(f"{s}: {finite_mean(r['off_psnr'] for r in mine if r['setting'] == s):.2f}->"
                        f"{finite_mean(r['on_psnr'] for r in mine if r['setting'] == s):.2f}" for s in SETTINGS)
        print(f"[{si + 1}/{len(scenes)}] {scene.name} {info['seconds']:.1f}s (recon off {t_rec['off']:.1f}s, "
              f"on {t_rec['on']:.1f}s; render off {t_render['off']:.1f}s, on {t_render['on']:.1f}s) PSNR {msg}",
              flush=True)
        del recon

    # ---- aggregate
    rng = np.random.default_rng(0)
    summary: dict[str, Any] = {}
    for s in SETTINGS:
        rs = [r for r in rows if r["setting"] == s]
        if not rs:
            continue
        per_scene = {}
        for sc in dict.fromkeys(r["scene"] for r in rs):
            mine = [r for r in rs if r["scene"] == sc]
            per_scene[sc] = {f"{m}_{k}": finite_mean(r[f"{m}_{k}"] for r in mine) for m in MODES for k in METRICS}
        entry: dict[str, Any] = {"views": len(rs), "scenes": len(per_scene)}
        for k in METRICS:
            entry[k] = {
                "off": finite_mean(r[f"off_{k}"] for r in rs),
                "on": finite_mean(r[f"on_{k}"] for r in rs),
                # paired over scenes (the independent unit): per-scene mean(on) - mean(off)
                "diff_scenes": paired(np.array([v[f"on_{k}"] - v[f"off_{k}"] for v in per_scene.values()]), rng),
                # over views (not independent within a scene; for reference)
                "diff_views_mean": finite_mean(r[f"on_{k}"] - r[f"off_{k}"] for r in rs),
                "views_on_better": float(np.mean([r[f"on_{k}"] > r[f"off_{k}"] for r in rs])),
            }
        if s == "ego-inward":
            bands = {}
            for lo, hi in ((0, 25), (25, 45), (45, 90)):
                b = [r for r in rs if lo <= r.get("elevation_deg", -1) < hi]
                if b:
                    bands[f"{lo}-{hi}deg"] = {"views": len(b), **{
                        k: {"off": finite_mean(r[f"off_{k}"] for r in b), "on": finite_mean(r[f"on_{k}"] for r in b)}
                        for k in ("psnr", "psnr_noego", "ssim", "sharpness")}}
            entry["elevation_bands"] = bands
        entry["per_scene"] = per_scene
        summary[s] = entry
    total = time.perf_counter() - t_start
    result = {
        "data": str(args.data), "model": str(model_dir), "detail": opts.__dict__, "scenes": len(scenes),
        "inputs": "camera only (no depth, no LiDAR), full-resolution images as arrays",
        "targets": "ego-forward and ego-inward views of targets.json, occluded skipped"
                   + ("" if args.max_views is None else f", at most {args.max_views} per setting and scene"),
        "metrics": "runtime.realeval.image_metrics on the render clipped to 0..1; psnr_fg: non-sky pixels",
        "seconds_total": total, "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "summary": summary, "scenes_info": scene_info, "rows": rows,
    }

    def clean(o):
        if isinstance(o, float):
            return o if math.isfinite(o) else None
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [clean(v) for v in o]
        if isinstance(o, (np.floating, np.integer)):
            return clean(o.item())
        return o

    out_json = args.out / "detail_synth_eval.json"
    out_json.write_text(json.dumps(clean(result), indent=1))
    if tiles:
        write_sheet(tiles, args.sheet, args.out / "detail_synth.png")

    print(f"\n{len(scenes)} scenes, {total:.0f} s; detail stride {opts.stride}; {out_json}")
    print(f"{'setting':<12}{'metric':<10}{'off':>9}{'on':>9}{'on-off':>9}  {'95% t CI':<20}{'95% bootstrap CI':<20}"
          f"{'scenes+':>8}")
    for s, e in summary.items():
        for k in METRICS:
            m = e[k]
            d = m["diff_scenes"]
            t95 = d.get("t95", [math.nan, math.nan])
            b95 = d.get("boot95", [math.nan, math.nan])
            print(f"{s:<12}{k:<10}{m['off']:9.4f}{m['on']:9.4f}{d['mean']:+9.4f}  "
                  f"[{t95[0]:+.4f}, {t95[1]:+.4f}]  [{b95[0]:+.4f}, {b95[1]:+.4f}]  "
                  f"{d.get('frac_positive', math.nan):7.2f}")
    for band, b in summary.get("ego-inward", {}).get("elevation_bands", {}).items():
        print(f"ego-inward elevation {band} ({b['views']} views): " + "  ".join(
            f"{k} {b[k]['off']:.3f}->{b[k]['on']:.3f}" for k in ("psnr", "psnr_noego", "ssim", "sharpness")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
