"""The web viewer (docs/viewer.md): ``GET /v1/scenes/{id}/viewer``'s page, the files it loads and the scene data
it is given.

- The page (``web/index.html``, ``web/viewer.js``) draws the scene's Gaussians with Spark (``@sparkjsdev/spark``)
  over three.js, both pinned npm packages (package.json, package-lock.json; ``npm ci`` installs them into
  node_modules, which is not in git). The server serves them itself (``install``: ``/viewer/modules/three/``,
  ``/viewer/modules/spark/``; the page's importmap names them), so a page needs no CDN; the page's own files are at
  ``/viewer/web/``. Those are public library and page files: they need no API key (the page route does).
- ``modules_dir(settings)``: where the npm packages are (``viewer_modules``, else node_modules in the working
  folder, else in the source checkout); ``missing(folder)`` says what is absent and how to install it (the page
  route answers 503 ``viewer_not_installed`` with it, never a 500).
- ``scene_data(scene)``: what the page draws besides the Gaussians (its JSON, embedded in the page): the input
  cameras (K, cam_to_ego), the drive's trajectory in the scene's frame, the time span and whether there are actors.
- ``page(...)``: the page's HTML; ``error_page(...)``: the same error body as the API's, as a page a browser shows.

Frames: the data is in the scene's frame (ego: x forward, y left, z up; cameras' cam_to_ego with OpenCV axes);
viewer.js converts to three.js's y-up frame in one place (docs/conventions.md "Viewer")."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

WEB_DIR = Path(__file__).resolve().parent / "web"
# the npm packages the page imports: (URL name under /viewer/modules/, folder under node_modules, the files the page
# needs in it, relative to that folder)
PACKAGES = (
    ("three", "three", ("build/three.module.js", "build/three.core.js",
                        "examples/jsm/controls/OrbitControls.js", "examples/jsm/postprocessing/Pass.js")),
    ("spark", "@sparkjsdev/spark/dist", ("spark.module.js",)),
)
INSTALL = "npm ci (in the repository, next to package.json; docs/viewer.md)"


def modules_dir(settings) -> Path:
    """The node_modules folder the viewer's packages are served from: the ``viewer_modules`` setting, else
    ./node_modules when it exists, else the source checkout's node_modules (next to package.json)."""
    configured = getattr(settings, "viewer_modules", None)
    if configured is not None:
        return Path(configured)
    local = Path("node_modules")
    if local.is_dir():
        return local.resolve()
    return Path(__file__).resolve().parents[2] / "node_modules"


def missing(folder: Path) -> str | None:
    """None when every file the page imports is in ``folder``, else what is missing and how to install it."""
    absent = [f"{pkg.split('/dist')[0]}/{f}" for _, pkg, files in PACKAGES for f in files
              if not (folder / pkg / f).is_file()]
    if not absent:
        return None
    return (f"the viewer's browser modules are not installed ({len(absent)} files missing under {folder}, e.g. "
            f"{absent[0]}): run {INSTALL}, or point the viewer_modules setting (XYZCYL_VIEWER_MODULES) at a "
            "node_modules folder that has three and @sparkjsdev/spark")


def install(app, settings) -> None:
    """Mount the page's files and the npm packages (read-only static files, outside /v1). A folder that does not exist
    (yet) answers 404 per file: the page route says what to install."""
    from starlette.staticfiles import StaticFiles

    class Files(StaticFiles):
        async def check_config(self) -> None:
            """No error for a folder that is not there (yet): each file then answers 404."""
            if self.directory is None or Path(self.directory).is_dir():
                await super().check_config()

    folder = modules_dir(settings)
    app.mount("/viewer/web", Files(directory=WEB_DIR, check_dir=False), name="viewer-web")
    for name, pkg, _ in PACKAGES:
        app.mount(f"/viewer/modules/{name}", Files(directory=folder / pkg, check_dir=False), name=f"viewer-{name}")


def _rows(m) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(m, np.float64)]


def scene_data(scene) -> dict[str, Any]:
    """What the page draws besides the Gaussians, from a loaded runtime.scene.Scene: the input cameras (name, model,
    width, height, K (null for an equirectangular one), cam_to_ego at the scene's first frame), the trajectory (each
    frame's ego origin in the scene's frame, metres) with its times (seconds on the rigs' clock), the time span and
    whether the scene has actors (a drive's moving objects: the page's time slider), and its bbox."""
    cameras = []
    for cam in scene.rig.cameras:
        K = None if cam.model == "equirectangular" or cam.K is None else _rows(cam.K)
        cameras.append({"name": cam.name, "model": cam.lens_model, "width": int(cam.width),
                        "height": int(cam.height), "K": K, "cam_to_ego": _rows(cam.cam_to_ego)})
    times, poses = scene.timeline()
    # the scene's frame: a drive's recorded ego_to_world of it (its first frame's), else the one frame's ego
    to_scene = np.linalg.inv(np.asarray(scene.drive["ego_to_world"], np.float64) if scene.drive else poses[0])
    path = np.einsum("ij,fjk->fik", to_scene, poses)[:, :3, 3]
    actors = scene.actors is not None and bool(scene.actor_list(None)["actors"])
    return {"cameras": cameras,
            "trajectory": [[float(v) for v in p] for p in path], "times": [float(t) for t in times],
            "time": {"start": float(times[0]), "end": float(times[-1]),
                     "step": float(scene.frame_interval())},
            "actors": actors, "bbox": scene.bbox()}


def _affine(R) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3] = R
    return _rows(T)


def frames() -> dict[str, Any]:
    """The page's frames, from the exports' (runtime.exports, the one place each is defined): ``ego_to_three``, the
    scene's ego frame -> three.js's (glTF's axes: +X left, +Y up, +Z forward), and each splat file's frame -> ego
    (``to_ego``: the PLY is in ego, the SPZ in RUB)."""
    from xyzcyl.runtime.exports import EGO_TO_GLTF, EGO_TO_SPZ

    return {"ego_to_three": _affine(EGO_TO_GLTF), "to_ego": {"ply": _rows(np.eye(4)), "spz": _affine(EGO_TO_SPZ.T)}}


def splat_sources(url: str) -> list[dict[str, Any]]:
    """The page's splat files of the scene at ``url`` (/v1/scenes/{id}), best first: SPZ (about a tenth of the PLY's
    bytes; the drive's actors baked in at its first frame) from GET .../export, else the PLY of GET .../gaussians
    (the static scene), each with its frame -> ego."""
    to_ego = frames()["to_ego"]
    return [{"format": "spz", "url": f"{url}/export?format=spz", "to_ego": to_ego["spz"]},
            {"format": "ply", "url": f"{url}/gaussians?format=ply", "to_ego": to_ego["ply"]}]


def _script_json(doc: Any) -> str:
    """JSON that is safe inside a <script> element (no "</", no "<!--")."""
    return json.dumps(doc, separators=(",", ":")).replace("<", "\\u003c").replace(">", "\\u003e")


def page(base: str, scene_id: str, name: str | None, data: dict[str, Any]) -> str:
    """The viewer page of a scene: ``base`` the app's root path ("" unless behind a path prefix), ``data`` the page's
    JSON (scene_data plus the route's: id, splats, view)."""
    text = (WEB_DIR / "index.html").read_text(encoding="utf-8")
    title = html.escape(f"{name or scene_id} - xyzcyl viewer")
    return (text.replace("{{BASE}}", html.escape(base)).replace("{{TITLE}}", title)
            .replace("{{DATA}}", _script_json(data)))


def error_page(status: int, body: dict[str, Any]) -> str:
    """The API's error body as a page (a browser that opened a viewer URL shows the error, not a blank canvas)."""
    err = body.get("error", {})
    field = f" (field: {err['field']})" if err.get("field") else ""
    return ("<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>xyzcyl viewer: error</title>"
            "<style>body{font:15px system-ui,sans-serif;margin:2em;color:#222}"
            "#error{border-left:4px solid #c33;padding:.6em 1em;background:#fdecec}</style></head><body>"
            f"<div id=\"error\" role=\"alert\" data-status=\"{int(status)}\" data-code=\"{html.escape(str(err.get('code', '')))}\">"
            f"<b>{int(status)} {html.escape(str(err.get('code', 'error')))}</b>: "
            f"{html.escape(str(err.get('message', '')))}{html.escape(field)}</div>"
            f"<pre hidden id=\"body\">{html.escape(json.dumps(body))}</pre></body></html>")


__all__ = ["INSTALL", "PACKAGES", "WEB_DIR", "error_page", "frames", "install", "missing", "modules_dir", "page",
           "scene_data", "splat_sources"]
