"""Network benchmark (issue 5): one JSON line per case.

Setup: the given preset (default cpu), a synthetic 6-camera ring rig (xyzcyl.runtime.rig.ring_rig, 70 degree
horizontal FoV, images at the preset's input size, random pixels), ground-truth occupancy selection with a
random --occupied fraction of the voxels (an untrained occupancy head predicts almost nothing, so the
predicted selection would under-count volume Gaussians), torch and numba limited to --threads.

Cases:
- ``forward``: no-grad forward through the Gaussians + ZNet_bg + one render at 224x400 (+ blend);
- ``train_step``: forward, render of 4 target views, background, blend, L1 loss, backward and an AdamW step.
Median of --repeats timed runs after one warm-up run.

    .venv/bin/python benchmarks/model_bench.py [--preset cpu] [--threads 2] [--repeats 3] [--occupied 0.08]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np
import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--occupied", type=float, default=0.08, help="fraction of voxels selected as occupied")
    ap.add_argument("--views", type=int, default=4, help="target views per training step")
    ap.add_argument("--override", default="{}", help='JSON merged into the preset, e.g. \'{"background": {"k": 2}}\'')
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    import numba

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))

    from xyzcyl.model_export.config import ModelConfig, preset
    from xyzcyl.model_export.lifting import rig_inputs
    from xyzcyl.model_export.model import XYZCylinder, blend
    from xyzcyl.model_export.render_fn import render_views
    from xyzcyl.runtime.camera import Camera
    from xyzcyl.runtime.lifting import background_grid, spec_from_array
    from xyzcyl.runtime.rig import ring_rig

    torch.manual_seed(0)
    def merge(a, b):
        return {k: merge(a[k], v) if isinstance(v, dict) and isinstance(a.get(k), dict) else v
                for k, v in {**a, **b}.items()}

    cfg = ModelConfig.from_dict(merge(preset(args.preset).to_dict(), json.loads(args.override)))
    cfg = cfg.replace(volume_selection="ground_truth")
    H, W = cfg.backbone.input_height, cfg.backbone.input_width
    model = XYZCylinder(cfg)
    rig = ring_rig(6, hfov_deg=70.0, width=W, height=H)
    inp = rig_inputs(rig, cfg)
    images = torch.rand(6, 3, H, W)
    gt = torch.rand(cfg.grid.shape) < args.occupied
    cams = [Camera(K=c.K, cam_to_ego=c.cam_to_ego, width=c.width, height=c.height) for c in rig.cameras[: args.views]]
    spec = spec_from_array(inp["spec_vol"].numpy(), cfg.cylinder.height, cfg.cylinder.width)
    grids = torch.from_numpy(np.stack([background_grid(spec, c.K, c.cam_to_ego, c.width, c.height)
                                       for c in cams]))
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    target = torch.rand(len(cams), 3, H, W)

    def forward_once():
        model.eval()
        with torch.no_grad():
            out = model(images, inp, occ_gt=gt)
            rgb, alpha, _ = render_views(out["gaussians"], cams[:1])
            img = blend(rgb, alpha, model.background(out["app_plane"], grids[:1]))
        return out, img

    def train_once():
        model.train()
        out = model(images, inp, occ_gt=gt)
        rgb, alpha, _ = render_views(out["gaussians"], cams)
        img = blend(rgb, alpha, model.background(out["app_plane"], grids))
        loss = (img - target).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return out

    load = os.getloadavg()[0]
    for name, fn in (("forward", forward_once), ("train_step", train_once)):
        fn()  # warm-up (numba compile / caches, allocator)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = fn()
            times.append(time.perf_counter() - t0)
        out = res[0] if isinstance(res, tuple) else res
        print(json.dumps({
            "case": name, "preset": args.preset, "threads": args.threads, "cameras": 6, "input": [H, W],
            "target_views": 1 if name == "forward" else len(cams),
            "gaussians": int(out["n_volume"] + out["n_pixel"]), "volume": int(out["n_volume"]),
            "pixel": int(out["n_pixel"]), "median_s": round(statistics.median(times), 3),
            "min_s": round(min(times), 3), "target_s": 1.5 if name == "forward" else 4.0,
            "override": json.loads(args.override),
            "loadavg_1m_at_start": round(load, 2)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
