"""How far a pixel Gaussian's anchor lies from the point whose colour it carries, for the two placements of the
pixel branch (`pixel.placement`), measured with ground-truth depth on synthetic scenes: one JSON line on stdout.

For each fine-lattice pixel (the cpu preset, k_o = --k-out) that camera n sees, X is the point camera n sees there
(the scene's true depth). The colour path samples X's colour; ``camera_ray`` (the default) anchors the Gaussian at
X, ``cylinder_ray`` at X's horizontal radius on the cylinder ray. Printed: how far the cylinder_ray anchor
reprojects from where the colour was sampled (pixels at 400 px wide) and its distance from X (metres), median,
p90 and p99. docs/architecture.md quotes these figures (5.4 px median, p90 16 px, p99 46 px; 0.21 m) for the
first five training scenes of `xyzcyl data synth --seed 0` (the nuScenes-like rig at 224x400):

    .venv/bin/python benchmarks/anchor_parallax.py --data data/train --scenes 5

A scene is a folder of `xyzcyl data synth` (docs/data.md): rig.json whose cameras name a depth file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def scene_errors(folder: Path, k_out: int) -> np.ndarray:
    """[M, 2]: per seen fine-lattice pixel, the cylinder_ray anchor's reprojection error (px at 400 wide) and its
    distance from the camera's point (m)."""
    from xyzcyl.model_export.config import preset
    from xyzcyl.runtime.lifting import LiftingParams, build_lifting_inputs
    from xyzcyl.runtime.rig import load_rig, read_image

    cfg = preset("cpu")
    cfg = cfg.replace(pixel=cfg.pixel.replace(k_out=k_out))
    rig = load_rig(folder / "rig.json")
    doc = json.loads((folder / "rig.json").read_text())
    p = LiftingParams.from_config_dict(cfg.to_dict())
    inp = build_lifting_inputs(rig, p)
    centre = p.spec(rig, "pixel").centre
    g, sel, dirs = inp["grid_pixc"], inp["sel_pixc"], inp["pix_dirs"]
    out = []
    for n, cam in enumerate(rig.cameras):
        d = read_image(folder / doc["cameras"][n]["depth"], "depth", channels=1, scale=False)[..., 0]
        u = (g[n][..., 0] + 1) * cam.width / 2 - 0.5
        v = (g[n][..., 1] + 1) * cam.height / 2 - 0.5
        ui = np.clip(np.round(u).astype(int), 0, cam.width - 1)
        vi = np.clip(np.round(v).astype(int), 0, cam.height - 1)
        z = d[vi, ui]
        ok = (sel[n] > 0) & (z > 0) & (z < 80)
        uu, vv, zz = u[ok], v[ok], z[ok]
        K = cam.K
        cam_pts = np.stack([zz * (uu - K[0, 2]) / K[0, 0], zz * (vv - K[1, 2]) / K[1, 1], zz, np.ones_like(zz)])
        X = (cam.cam_to_ego @ cam_pts)[:3].T
        r = np.hypot(X[:, 0] - centre[0], X[:, 1] - centre[1])
        A = centre + r[:, None] * dirs[ok]
        uv, _, _ = cam.project(A)
        err = np.hypot(uv[:, 0] - uu, uv[:, 1] - vv) * 400 / cam.width
        out.append(np.stack([err, np.linalg.norm(A - X, axis=1)], 1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a data set of `xyzcyl data synth` (scene_* folders)")
    ap.add_argument("--scenes", type=int, default=5, help="its first N scenes (default 5)")
    ap.add_argument("--k-out", type=int, default=4, help="the pixel lattice's upsampling k_o (default 4)")
    args = ap.parse_args(argv)
    if args.scenes < 1:
        ap.error("--scenes: must be >= 1")
    folders = sorted(p for p in args.data.glob("scene_*") if p.is_dir())[:args.scenes]
    if not folders:
        ap.error(f"--data: no scene_* folder in {args.data}")
    e = np.concatenate([scene_errors(f, args.k_out) for f in folders])
    if not len(e):
        raise SystemExit("anchor_parallax.py: no pixel with a depth in (0, 80) m")
    px, m = e[:, 0], e[:, 1]
    print(json.dumps({"case": "cylinder_ray_anchor", "data": str(args.data), "scenes": len(folders),
                      "k_out": args.k_out, "pixels": len(e),
                      "reprojection_px_at_400": {"median": round(float(np.median(px)), 2),
                                                 "p90": round(float(np.percentile(px, 90)), 2),
                                                 "p99": round(float(np.percentile(px, 99)), 2)},
                      "distance_m": {"median": round(float(np.median(m)), 3),
                                     "p90": round(float(np.percentile(m, 90)), 3)}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
