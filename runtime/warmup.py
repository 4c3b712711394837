"""Warm-up: a tiny rig and a tiny scene pushed through the same code as real requests, so that every numba kernel
those paths call is compiled (cold cache) or loaded from numba's cache (warm), and the image codecs are loaded,
before the first real request. ``xyzcyl serve`` runs it before /v2/health/ready answers 200 (docs/api.md).

    folder = write_rig(tmp)                 # rig.json + 2 small pinhole images + a LiDAR sweep (.npy)
    # a reconstruction worker: server.jobs._worker_reconstruct(str(folder / "rig.json"), out, stride)
    seconds = warm_render(tmp)              # the server process: tiny renders through runtime.views

Why through the real entry points and not by calling the kernels: numba compiles one specialisation per argument
type signature (dtype, dimensions, layout, read-only or not), and only the real path gives the real types.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

RIG_NAME = "rig.json"
LIDAR_NAME = "sweep.npy"
WIDTH, HEIGHT = 192, 108          # input images (the model resizes them; the detail layer works at this size)
VIEW_W, VIEW_H = 64, 48           # rendered views (>= 16 px a side: the background's reduced-resolution trace runs)


def _pose(R, t) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(R, np.float64), t
    return T.tolist()


# OpenCV camera (x right, y down, z forward) -> ego (x forward, y left, z up): the columns are the camera axes
_FRONT = _pose([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], [1.5, 0.0, 1.5])
_LEFT = _pose([[1, 0, 0], [0, 0, 1], [0, -1, 0]], [1.0, 0.5, 1.5])


def _image(seed: int) -> np.ndarray:
    """[HEIGHT, WIDTH, 3] float32: a sky-to-ground gradient with texture (the detail layer keeps textured cells)."""
    rng = np.random.default_rng(seed)
    y = np.linspace(0.0, 1.0, HEIGHT, dtype=np.float32)[:, None, None]
    base = np.concatenate([0.6 - 0.3 * y, 0.7 - 0.3 * y, 0.9 - 0.5 * y], axis=2)
    img = base + 0.15 * rng.random((HEIGHT, WIDTH, 3), dtype=np.float32)
    return np.clip(np.broadcast_to(img, (HEIGHT, WIDTH, 3)), 0.0, 1.0).astype(np.float32)


def lidar_sweep(seed: int = 0) -> np.ndarray:
    """[P, 3] float32 ego-frame LiDAR points: the ground (z = 0, enough points for the detail layer's ground fit)
    and a wall 12 m ahead and one 6 m to the left."""
    rng = np.random.default_rng(seed)
    g = np.stack([rng.uniform(-20, 30, 3000), rng.uniform(-20, 20, 3000), rng.normal(0, 0.01, 3000)], axis=1)
    wf = np.stack([np.full(800, 12.0), rng.uniform(-8, 8, 800), rng.uniform(0, 4, 800)], axis=1)
    wl = np.stack([rng.uniform(-2, 15, 800), np.full(800, 6.0), rng.uniform(0, 4, 800)], axis=1)
    return np.concatenate([g, wf, wl]).astype(np.float32)


def rig_doc() -> dict:
    """The warm-up rig.json (two 192x108 pinhole cameras, front and left, and the LiDAR block)."""
    fx = 0.8 * WIDTH
    K = [[fx, 0.0, (WIDTH - 1) / 2], [0.0, fx, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]]
    cams = [{"name": name, "image": f"{name}.png", "width": WIDTH, "height": HEIGHT, "K": K, "cam_to_ego": pose,
             "distortion": None, "model": "pinhole"} for name, pose in (("WARM_FRONT", _FRONT), ("WARM_LEFT", _LEFT))]
    return {"source": "xyzcyl warm-up (runtime/warmup.py)", "cameras": cams, "lidar": {"file": LIDAR_NAME}}


def write_rig(folder: str | Path) -> Path:
    """Write the warm-up rig into ``folder`` (created): rig.json, one PNG per camera, the LiDAR sweep. Returns
    the folder; its rig.json is what a POST /v1/scenes leaves for a reconstruction worker."""
    from .imageio import write_png

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    doc = rig_doc()
    for i, cam in enumerate(doc["cameras"]):
        write_png(out / cam["image"], _image(i))
    np.save(out / LIDAR_NAME, lidar_sweep())
    (out / RIG_NAME).write_text(json.dumps(doc, indent=1) + "\n")
    return out


def tiny_scene():
    """A small runtime Scene: 3000 Gaussians in front of the rig, a background panorama, the warm-up rig."""
    from .cylinder import CylinderSpec
    from .render import Gaussians
    from .rig import Rig
    from .scene import Background, Scene

    rng = np.random.default_rng(1)
    n = 3000
    means = np.stack([rng.uniform(3, 20, n), rng.uniform(-8, 8, n), rng.uniform(0, 4, n)], axis=1)
    q = rng.normal(size=(n, 4))
    g = Gaussians(means=means.astype(np.float32), quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(
                  np.float32), log_scales=np.full((n, 3), np.log(0.15), np.float32),
                  opacity_logits=rng.normal(0, 1, n).astype(np.float32),
                  sh=rng.normal(0, 0.5, (n, 1, 3)).astype(np.float32))
    spec = CylinderSpec(centre=[0.0, 0.0, 1.0], radius=30.0, z_min=-2.0, z_max=8.0, height=16, width=64)
    bg = Background(image=rng.random((20, 64, 3), dtype=np.float32), cylinder=spec, v_range=(-1.25, 1.25))
    return Scene(gaussians=g, background=bg, rig=Rig.from_dict(rig_doc(), check_images=False))


LENS_MODELS = ("equirectangular", "opencv", "opencv_fisheye", "ftheta")   # view_requests(scene, models=...)


def view_requests(scene, models: str = "all") -> list:
    """The warm-up views (runtime.views.ViewRequest). models="pinhole": a pinhole pose in every output and format
    and an input camera of the rig (what most requests use: ``xyzcyl serve`` renders these before it reports
    ready); "lenses": an equirectangular view and one view through each lens model (opencv, opencv_fisheye,
    ftheta; LENS_MODELS), each compiling its own projection kernel (runtime.render.kernels.project_kernel), which
    ``xyzcyl serve`` renders after it is ready; "all": both."""
    from .camera import Camera
    from .lenses import Lens
    from .views import ViewRequest, camera_from_opencv, camera_from_rig

    if models not in ("pinhole", "lenses", "all"):
        raise ValueError(f"models: one of pinhole, lenses, all (got {models!r})")
    pin = camera_from_opencv(_FRONT, VIEW_W, VIEW_H, fov=70.0)
    reqs = []
    if models in ("pinhole", "all"):
        reqs += [ViewRequest(pin, out, fmt) for out, fmt in (("rgb", "png"), ("rgb", "jpeg"), ("rgb", "exr"),
                                                             ("depth", "png"), ("depth", "exr"), ("alpha", "png"))]
        reqs.append(ViewRequest(camera_from_rig(scene.rig, "WARM_LEFT", width=VIEW_W)))
    if models in ("lenses", "all"):
        T = np.eye(4)
        T[2, 3] = 1.5
        reqs.append(ViewRequest(Camera(model="equirectangular", cam_to_ego=T, width=2 * VIEW_W, height=VIEW_W)))
        for lens in (Lens("opencv", (-0.28, 0.07, 0.001, -0.001, 0.0)),
                     Lens("opencv_fisheye", (0.02, -0.01, 0.002, -0.0003), max_angle_deg=95.0),
                     Lens("ftheta", max_angle_deg=80.0, angle_to_pixeldist_poly=(0.0, 40.0, 0.0, -1.0))):
            reqs.append(ViewRequest(pin.replace(distortion=lens)))
    return reqs


def warm_render(folder: str | Path, models: str = "all") -> float:
    """Save the tiny scene into ``folder`` / "scene", load it back (Scene.load, as the server's scene cache does)
    and render and encode every view_requests(scene, models) view with runtime.views.render_request. Returns the
    seconds. A failing render raises (the caller must not report ready over a renderer that fails)."""
    from .render import Gaussians, render
    from .render.gaussians import TAKE_ROWS_MIN, take_rows
    from .scene import Scene
    from .views import render_request

    t0 = time.perf_counter()
    path = tiny_scene().save(Path(folder) / "scene")
    scene = Scene.load(path)
    # a drive scene's readers (its tiles' and camera layers' runs, its chunks' rows) and the gather of large
    # subsets: numba kernels the tiny one-rig scene does not reach
    n = len(scene.gaussians)
    Gaussians.load_ply_rows(Path(path) / "scene.ply", 0, n)
    Gaussians.load_ply_take(Path(path) / "scene.ply", np.arange(n - 1, -1, -1))
    take_rows([np.zeros((TAKE_ROWS_MIN, 3), np.float32)], np.ones(TAKE_ROWS_MIN, bool))
    # a drive's layered view (Scene._layers): several sets drawn as one, a layer behind another over the tiles it
    # left open, and the moving objects moved to the view's time (Gaussians.transformed)
    g, cam = scene.gaussians, scene.rig.cameras[0].resized(VIEW_W, VIEW_H)
    front = render([g.slice(0, len(g) // 2), g.slice(len(g) // 2, len(g))], cam)
    # a cover of 0.99: tiles the tiny scene barely fills count as covered, so the open-tile path runs (a drive view
    # uses scene.LAYER_COVER; the kernels' types are the same)
    render([g], cam, behind=front, behind_inplace=True, cover=0.99)
    g.transformed(np.eye(4))
    for req in view_requests(scene, models):
        data = render_request(scene, req)
        if not data:
            raise RuntimeError(f"warm-up: an empty {req.output} {req.format} view")
    return time.perf_counter() - t0


def warm_reconstruct(reconstructor, folder: str | Path) -> float:
    """Reconstruct the warm-up rig (written into ``folder`` / "rig") with a runtime.inference.Reconstructor as
    ``xyzcyl reconstruct`` does (its LiDAR sweep, the detail layer at its default stride) and save the scene into
    ``folder`` / "scene". Returns the seconds."""
    from .lidar import load_lidar
    from .rig import load_rig

    t0 = time.perf_counter()
    rig = load_rig(write_rig(Path(folder) / "rig") / RIG_NAME)
    reconstructor.reconstruct(rig, lidar=load_lidar(rig).points).save(Path(folder) / "scene")
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    """``python -m xyzcyl.runtime.warmup [--model DIR]``: compile (or load) every kernel of the render and
    reconstruction paths into numba's cache ahead of time, e.g. right after ``pip install`` or in an image build
    (with NUMBA_CACHE_DIR set as the service will run)."""
    import argparse
    import tempfile

    from .compile_notice import cache_dir

    ap = argparse.ArgumentParser(prog="python -m xyzcyl.runtime.warmup", description=main.__doc__)
    ap.add_argument("--model", default=None, help="model folder (default: $XYZCYL_MODEL or the shipped one)")
    ap.add_argument("--render-only", action="store_true", help="the render path only (no model needed)")
    ap.add_argument("--models", choices=("pinhole", "lenses", "all"), default="all",
                    help="the render views: pinhole, the equirectangular and lens models, or all (default)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="xyzcyl-warmup-") as tmp:
        r = warm_render(Path(tmp) / "render", args.models)
        line = f"render path {r:.1f} s"
        if not args.render_only:
            from .inference import Reconstructor, default_model_dir

            rec = Reconstructor.load(args.model or default_model_dir(), verify=False)
            line += f", reconstruction path {warm_reconstruct(rec, Path(tmp) / 'reconstruct'):.1f} s"
    print(f"xyzcyl warm-up: {line}; numba cache: {cache_dir()}")
    return 0


__all__ = ["LENS_MODELS", "lidar_sweep", "main", "rig_doc", "tiny_scene", "view_requests", "warm_reconstruct", "warm_render",
           "write_rig"]

if __name__ == "__main__":
    raise SystemExit(main())
