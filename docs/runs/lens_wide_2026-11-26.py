"""The picture of issue 28's fast-path fix for strong OpenCV lenses on wide images (docs/pictures/lens_wide_opencv.jpg).

Renders the wide test scenes of tests/runtime/render/test_render_lens.py (the ring rig's first camera, the issue's
lens k1 -0.2, k2 0.05, p1 0.001, p2 -0.002, here at 192x128 and f = 48 px: 127 degrees across as a pinhole) with
the fast renderer of the tree it runs in, and (with --reference) the float64 ray reference; saves the arrays.
Run once in a tree before the fix (main at 42ec4e5) with --tag before, once after with --tag after --reference,
then --compose. From the repository root:
    python docs/runs/lens_wide_2026-11-26.py --out DIR --tag after --reference
    (in the old tree) python docs/runs/lens_wide_2026-11-26.py --out DIR --tag before
    python docs/runs/lens_wide_2026-11-26.py --out DIR --compose docs/pictures/lens_wide_opencv.jpg
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "runtime" / "render"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "runtime"))


def _render(out: Path, tag: str, reference: bool) -> None:
    from test_render_lens import WIDE_OPENCV, _wide_camera, _wide_scene
    from xyzcyl.runtime.lenses import Lens
    from xyzcyl.runtime.render import render, render_reference

    cam = _wide_camera(Lens("opencv", WIDE_OPENCV["issue"]), 192, 128, 48.0)
    for scene in ("sphere", "random"):
        g = _wide_scene(cam, scene)
        r = render(g, cam, (0.1, 0.2, 0.3))
        np.savez(out / f"{tag}_{scene}.npz", rgb=r.rgb, depth=r.depth, alpha=r.alpha)
        if reference:
            r = render_reference(g, cam, (0.1, 0.2, 0.3))
            np.savez(out / f"reference_{scene}.npz", rgb=r.rgb, depth=r.depth, alpha=r.alpha)


def _compose(out: Path, path: Path) -> None:
    import cv2

    rows = []
    for scene in ("sphere", "random"):
        ref = np.load(out / f"reference_{scene}.npz")
        tiles = []
        for tag in ("before", "after", "reference"):
            r = np.load(out / f"{tag}_{scene}.npz")
            psnr = 10 * np.log10(1.0 / max(np.mean((r["rgb"] - ref["rgb"]) ** 2), 1e-20))
            rgb = (np.clip(r["rgb"], 0, 1) * 255).astype(np.uint8)[..., ::-1]
            d = np.clip(r["depth"] / 12.0, 0, 1)
            depth = cv2.applyColorMap((d * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
            t = np.concatenate([rgb, depth], 0)
            t = cv2.resize(t, (t.shape[1] * 2, t.shape[0] * 2), interpolation=cv2.INTER_NEAREST)
            label = {"before": "fast, before", "after": "fast, now", "reference": "ray reference"}[tag]
            if tag != "reference":
                label += f" ({psnr:.1f} dB)"
            cv2.putText(t, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
            tiles.append(t)
        rows.append(np.concatenate(tiles, 1))
    cv2.imwrite(str(path), np.concatenate(rows, 0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--tag", default="after")
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--compose", type=Path)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    if a.compose:
        _compose(a.out, a.compose)
    else:
        _render(a.out, a.tag, a.reference)


if __name__ == "__main__":
    main()
