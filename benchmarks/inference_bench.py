"""Inference benchmark (issue 11): one JSON line per case.

Setup: a model folder (--model; default: the cpu preset with random weights, seed 0, exported once into --work,
its occupancy head biased so that --occupied of the voxels are selected on the bench input -- an untrained head
selects none or all of them); the example rig (examples/synth_nuscenes, 6 cameras) upscaled to 1600x900 and stored
as JPEG (quality 90), calibrations scaled with Camera.resized. onnxruntime, numba and torch limited to --threads.

Cases (medians of --repeats runs after a warm-up):
- ``reconstruct``: rig.json + 6 JPEGs -> Scene (decode, resize, lifting, encode, select, volume, Gaussians,
  background bake), stage breakdown; ``first`` = the cold call (lifting inputs computed), ``cached`` = later calls
  (lifting inputs from the cache); peak RSS of the process (a child process without torch) after model load and
  after the reconstructions.
- ``onnx_vs_torch``: the network part (encode + volume graphs vs XYZCylinder.forward in torch eager with the same
  voxels), same inputs and threads, in one run; ratio torch / onnxruntime.
- ``render``: the scene from CAM_FRONT at 1600x900 with its background (render_view), the background's share, and
  without a background.
- ``background``: the bake's cost, ZNet_bg run per view at 1600x900 (the alternative), and the PSNR between the
  baked panorama and the per-view network on the 6 input views at 800x450 for bake scales 2, 4, 8.

    .venv/bin/python benchmarks/inference_bench.py [--model DIR] [--threads 2] [--repeats 5] [--occupied 0.08]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from xyzcyl.testing.rigs import make_rig  # the example rig as 6 JPEGs at width x height

# torch's OpenMP threads busy-wait between operators by default; on cores shared with other work (this machine's two
# cores run training beside the benchmark) that made torch eager ~10x slower at 2 threads (8.2 s instead of 0.77 s
# per forward, measured). onnxruntime's sessions do not spin either (runtime.inference), so both sides are measured
# without busy-waiting. Set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def rss_mb() -> float:
    """Peak resident set of this process, MB: VmHWM (reset by exec, unlike getrusage's ru_maxrss, which a child
    inherits from the parent it was forked from)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def emit(d: dict) -> None:
    print(json.dumps(d), flush=True)


def export_random(work: Path, occupied: float, rig_json: Path, threads: int) -> Path:
    """cpu preset, seed 0, occupancy head biased to select ``occupied`` of the voxels; exported once."""
    out = work / f"cpu-random-{occupied:g}"
    if (out / "model.json").is_file():
        return out
    import torch
    from xyzcyl.model_export.config import preset
    from xyzcyl.model_export.export import write_model_folder
    from xyzcyl.model_export.lifting import rig_inputs
    from xyzcyl.model_export.model import XYZCylinder
    from xyzcyl.runtime.inference import resize_area
    from xyzcyl.runtime.rig import load_rig

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cfg = preset("cpu")
    model = XYZCylinder(cfg).eval()
    rig = load_rig(rig_json)
    H, W = cfg.backbone.input_height, cfg.backbone.input_width
    imgs = torch.from_numpy(np.stack([resize_area(i, H, W).transpose(2, 0, 1) for i in rig.load_images()]))
    with torch.no_grad():
        occ = model(imgs, rig_inputs(rig, cfg))["occ_logits"]
        model.occ_head[-1].bias[1] -= float(torch.quantile((occ[1] - occ[0]).flatten(), 1.0 - occupied))
    torch.save({"model": model.state_dict(), "model_cfg": cfg.to_dict(), "step": 0,
                "train_cfg": {"stage": "render"}}, work / "cpu-random.pt")
    t0 = time.perf_counter()
    write_model_folder(model, out, "cpu-random", "0.0.0", notes="Random weights (benchmark).")
    emit({"case": "export", "model": str(out), "seconds": round(time.perf_counter() - t0, 1)})
    return out


def child(args) -> int:
    """The torch-free part, in its own process (peak RSS without torch)."""
    import numba
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import render_view, rig_camera

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    base = rss_mb()
    t0 = time.perf_counter()
    rec = Reconstructor.load(args.model, threads=args.threads)
    t_load = time.perf_counter() - t0
    rss_loaded = rss_mb()
    rig = load_rig(args.rig)
    first = rec.reconstruct(rig)
    runs = [rec.reconstruct(rig) for _ in range(args.repeats)]
    stages = {k: round(statistics.median(r.timings[k] for r in runs), 4) for k in runs[0].timings}
    emit({"case": "reconstruct", "threads": args.threads, "cameras": len(rig.cameras),
          "input": f"{rig.cameras[0].width}x{rig.cameras[0].height} JPEG", "model_load_s": round(t_load, 3),
          "first_s": round(first.timings["total"], 4), "first_lifting_s": round(first.timings["lifting"], 4),
          "cached_median_s": stages["total"], "cached_min_s": round(min(r.timings["total"] for r in runs), 4),
          "stages_median_s": stages, "counts": first.counts, "lifting_cached": runs[-1].lifting_cached,
          "rss_start_mb": round(base), "rss_after_load_mb": round(rss_loaded),
          "peak_rss_mb": round(rss_mb()), "load_avg": os.getloadavg()[0]})
    scene = runs[-1]
    scene.save(args.work / "scene")

    cam = rig_camera(rig.camera("CAM_FRONT"), width=1600, height=900)
    render_view(scene, cam)   # warm-up (numba compile / cache load)
    tot, bgt, plain = [], [], []
    from xyzcyl.runtime.render import render

    for _ in range(args.repeats):
        t0 = time.perf_counter()
        render_view(scene, cam)
        tot.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        scene.background.render(cam)
        bgt.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        render(scene.gaussians, cam)
        plain.append(time.perf_counter() - t0)
    emit({"case": "render", "size": "1600x900", "gaussians": len(scene.gaussians),
          "with_background_median_s": round(statistics.median(tot), 4),
          "background_median_s": round(statistics.median(bgt), 4),
          "background_share": round(statistics.median(bgt) / statistics.median(tot), 3),
          "without_background_median_s": round(statistics.median(plain), 4), "load_avg": os.getloadavg()[0]})

    # background: bake vs per-view network
    net_t = []
    for _ in range(max(1, args.repeats // 2)):
        t0 = time.perf_counter()
        rec.background_network(scene, cam)
        net_t.append(time.perf_counter() - t0)
    row = {"case": "background", "bake_s": scene.timings.get("background"),
           "per_view_network_1600x900_s": round(statistics.median(net_t), 4),
           "baked_lookup_1600x900_s": round(statistics.median(bgt), 4)}
    views = [rig_camera(c, width=800, height=450) for c in rig.cameras]
    nets = [rec.background_network(scene, v) for v in views]
    for scale in (2, 4, 8):
        t0 = time.perf_counter()
        bg = rec.bake_background(rig, scene.app_plane, scale=scale)
        dt = time.perf_counter() - t0
        ps = [float(-10 * np.log10(np.mean((bg.render(v).astype(np.float64) - n) ** 2) + 1e-30))
              for v, n in zip(views, nets)]
        row[f"scale{scale}"] = {"bake_s": round(dt, 4), "panorama": list(bg.image.shape[:2]),
                                "psnr_mean_db": round(float(np.mean(ps)), 2), "psnr_min_db": round(min(ps), 2)}
    emit(row)
    return 0


def torch_vs_onnx(args, model_dir: Path, rig_json: Path, ck: Path | None) -> None:
    import torch
    from xyzcyl.model_export.config import ModelConfig
    from xyzcyl.model_export.lifting import to_torch
    from xyzcyl.model_export.model import XYZCylinder
    from xyzcyl.runtime.inference import Reconstructor, select_voxels
    from xyzcyl.runtime.rig import load_rig

    if ck is None:
        emit({"case": "onnx_vs_torch", "skipped": "needs the checkpoint (--checkpoint) of --model"})
        return
    torch.set_num_threads(args.threads)
    state = torch.load(ck, map_location="cpu", weights_only=False)
    model = XYZCylinder(ModelConfig.from_dict(state["model_cfg"])).eval()
    model.load_state_dict(state["model"])
    rec = Reconstructor.load(model_dir, threads=args.threads)
    rig = load_rig(rig_json)
    imgs, depth, mask = rec.prepare(rig, rig.load_images())
    lift, _ = rec.lifting(rig)
    feed = {"images": imgs, "depth": depth, "depth_mask": mask, **lift}

    def onnx():
        enc = rec._run("encode", feed)
        if "volume" not in rec.sessions:       # a model without the volume branch (e.g. the shipped 1.1.0)
            return np.zeros(0, np.int64)
        idx = select_voxels(enc["occ_logits"], rec.info.max_voxels)
        rec._run("volume", {"geo_cpfg": enc["geo_cpfg"], "app_cpfg": enc["app_cpfg"], "voxel_idx": idx,
                            "vol_coords": lift["vol_coords"], "voxel_centres": lift["voxel_centres"]})
        return idx

    idx = onnx()
    ti, tl, ti_idx = torch.from_numpy(imgs), to_torch(lift), torch.from_numpy(idx)

    def eager():
        with torch.no_grad():
            model(ti, tl, voxel_idx=ti_idx)

    eager()
    t_onnx, t_torch = [], []
    for _ in range(args.repeats):   # interleaved, so that load changes hit both alike
        t0 = time.perf_counter()
        onnx()
        t_onnx.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        eager()
        t_torch.append(time.perf_counter() - t0)
    mo, mt = statistics.median(t_onnx), statistics.median(t_torch)
    what = "encode + selection + volume" if "volume" in rec.sessions else "encode (no volume branch)"
    emit({"case": "onnx_vs_torch", "threads": args.threads, "what": f"{what} vs forward",
          "onnxruntime_median_s": round(mo, 4), "torch_eager_median_s": round(mt, 4),
          "torch_over_onnx": round(mt / mo, 2), "voxels": int(idx.size), "load_avg": os.getloadavg()[0]})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=None, help="model folder (default: cpu preset, random weights)")
    ap.add_argument("--checkpoint", type=Path, default=None, help="the --model's checkpoint (onnx_vs_torch case)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--occupied", type=float, default=0.08)
    ap.add_argument("--work", type=Path, default=Path("/tmp/xyzcyl_inference_bench"))
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--rig", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.child:
        return child(args)
    rig_json = make_rig(args.work)
    ck = args.checkpoint
    if args.model is None:
        args.model = export_random(args.work, args.occupied, rig_json, args.threads)
        ck = args.work / "cpu-random.pt"
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    r = subprocess.run([sys.executable, __file__, "--child", "--model", str(args.model), "--rig", str(rig_json),
                        "--threads", str(args.threads), "--repeats", str(args.repeats), "--work", str(args.work)],
                       env=env, check=False)
    if r.returncode:
        return r.returncode
    torch_vs_onnx(args, args.model, rig_json, ck)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
