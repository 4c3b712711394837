"""The web viewer on a real scene (docs/viewer.md): screenshots for the docs and the viewer-against-our-render figure.

`xyzcyl view SCENE_DIR` serves the scene; headless Chromium (tests/server/viewer_browser.mjs: Debian's chromium,
npm's playwright-core, software WebGL) opens the viewer (1) at input camera CAMERA at exactly W x H pixels (panel and
frustums hidden: H, F), and
(2) in a 1280 x 720 window seen from behind and above the ego (every input camera's frustum, the panel). The first
is compared with our render of the same view (GET .../render?camera=CAMERA&width=W&height=H, and its alpha): PSNR and
mean absolute difference over the pixels our render covers (alpha >= 0.99; the viewer draws no sky). Writes
OUT/viewer_<name>.jpg (the window), OUT/viewer_<name>_vs_ours.jpg (the WebGL view above our render) and prints
the figures as JSON.

    .venv/bin/python scripts/viewer_screenshots.py /tmp/pd_one --camera front_camera --width 960 \\
        --name pandaset --out docs/pictures

Needs `npm ci` and Chromium (docs/viewer.md "Set up"). A real scene of millions of Gaussians takes SwiftShader (the
CPU) tens of seconds to draw: the timeout is generous.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from xyzcyl.testing.viewer import ViewServer, browse, chromium, compare, fetch_image


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a scene folder")
    ap.add_argument("--camera", default="front_camera", help="the input camera compared (default front_camera)")
    ap.add_argument("--width", type=int, default=960, help="the compared view's width, pixels (height: the camera's "
                                                           "aspect ratio)")
    ap.add_argument("--name", default="scene", help="the pictures' name: viewer_<name>.jpg (default scene)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the pictures (default: none written)")
    ap.add_argument("--timeout", type=float, default=480, help="seconds the browser may take per page")
    args = ap.parse_args(argv)
    if chromium() is None or shutil.which("node") is None:
        raise SystemExit("needs chromium and node (docs/viewer.md \"Set up\")")
    from PIL import Image

    scene_json = json.loads((args.scene / "scene.json").read_text())
    cam = next(c for c in scene_json["rig"]["cameras"] if c["name"] == args.camera)
    W = args.width
    H = max(1, round(W * cam["height"] / cam["width"]))
    tmp = Path(tempfile.mkdtemp(prefix="viewer-shots-"))
    try:
        with ViewServer(args.scene, args.camera, timeout=120) as server:
            # the overview: behind and above the ego, looking ahead over it (scene frame: x forward, z up)
            overview = "window.xyzcylViewer.lookAt([-9, 2, 5], [14, 0, 0])"
            report = browse([
                {"url": f"{server.url}?camera={args.camera}&width={W}&height={H}", "viewport": [W + 40, H + 40],
                 "keys": ["h", "f"], "screenshot": str(tmp / "view.png")},
                {"url": f"{server.url}?camera={args.camera}", "viewport": [1280, 720], "script": overview,
                 "screenshot": str(tmp / "window.png"), "selector": "body"}], tmp, args.timeout)
            for p in report["pages"]:
                if p.get("failure") or p.get("state") != "ready":
                    raise SystemExit(f"the page did not get ready: {json.dumps(p)[:2000]}")
            query = f"{server.scene_url}/render?camera={args.camera}&width={W}&height={H}"
            t1 = time.monotonic()
            ours = fetch_image(query)
            ours_s = time.monotonic() - t1
            alpha = fetch_image(f"{query}&output=alpha")[..., 0]
        webgl = np.asarray(Image.open(tmp / "view.png").convert("RGB"), np.float32) / 255.0
        state = report["pages"][0]["viewer"]["state"]
        figures = {"scene": str(args.scene), "gaussians": state["splats"], "format": state["format"], "view": [W, H],
                   "camera": args.camera, **{k: round(v, 2) for k, v in compare(webgl, ours, alpha).items()},
                   "page_ready_s": [round(p["ready_s"], 1) for p in report["pages"]],
                   "browser_s": round(report["browser_s"], 1), "our_render_s": round(ours_s, 2),
                   "chromium": subprocess.run([chromium(), "--version"], capture_output=True, text=True).stdout.strip()}
        print(json.dumps(figures, indent=1))
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            Image.open(tmp / "window.png").convert("RGB").save(args.out / f"viewer_{args.name}.jpg", quality=85)
            both = (np.concatenate([webgl, ours], 0).clip(0, 1) * 255).astype(np.uint8)
            Image.fromarray(both).save(args.out / f"viewer_{args.name}_vs_ours.jpg", quality=85)
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
