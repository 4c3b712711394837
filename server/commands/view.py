"""`xyzcyl view SCENE_DIR [--port P] [--camera NAME] [--open]`: the web viewer of a scene folder (docs/viewer.md).

It runs the service (the same app as `xyzcyl serve`) on 127.0.0.1 only, without API keys, over a temporary store
that holds the folder as its one scene (a link to the folder, never a copy: the folder is only read), prints the
viewer's URL and serves until Ctrl-C; the temporary store is removed at exit. ``--open`` opens the URL in the
default browser. Exit status 2 for a folder that is not a scene."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HOST = "127.0.0.1"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE_DIR", help="a scene folder (of `xyzcyl reconstruct`)")
    parser.add_argument("--port", type=int, default=0, metavar="P",
                        help="TCP port on 127.0.0.1 (default 0: a free one; the URL printed names it)")
    parser.add_argument("--camera", default=None, metavar="NAME",
                        help="the input camera the viewer opens at (default: the rig's first)")
    parser.add_argument("--open", action="store_true", help="open the URL in the default web browser")


def _fail(message: str) -> int:
    print(f"xyzcyl view: {message}", file=sys.stderr)
    return 2


def _record_fields(doc: dict) -> tuple[list[dict], dict]:
    """(cameras, the ready record's fields) of a scene.json (what a reconstruction worker reports)."""
    cams = [{"name": c["name"], "width": int(c["width"]), "height": int(c["height"]),
             "model": c.get("model", "pinhole")} for c in doc["rig"]["cameras"]]
    gaussians = doc.get("gaussians") or {}
    fields = {"model": doc.get("model"), "counts": doc.get("counts"), "timings": doc.get("timings"),
              "bbox": doc.get("bbox"), "gaussians": gaussians.get("count"),
              "background": doc.get("background") is not None}
    return cams, fields


def store_with_scene(scene: Path, root: Path) -> str:
    """A folder store at ``root`` whose one ready scene is ``scene`` (linked, not copied); its scene id."""
    from ..store.folder import FolderStore
    from ..store.record import new_scene_id

    cams, fields = _record_fields(json.loads((scene / "scene.json").read_text()))
    store = FolderStore(root, max_bytes=1 << 60)
    store.open()
    sid = new_scene_id()
    store.create(sid, {"cameras": cams, "name": scene.absolute().name[:200] or None})
    link = store.work_dir() / "scene"
    link.symlink_to(scene.resolve(), target_is_directory=True)
    store.commit(sid, link, **fields)
    return sid


def run(args: argparse.Namespace) -> int:
    import shutil
    import socket
    import tempfile

    from xyzcyl.runtime.scene import JSON_NAME

    scene = Path(args.scene)
    if not (scene / JSON_NAME).is_file():
        return _fail(f"SCENE_DIR: {str(scene)!r} is not a scene folder (no {JSON_NAME} there)")
    if not 0 <= args.port <= 65535:
        return _fail(f"--port: {args.port} is not a TCP port (0..65535)")
    try:
        doc = json.loads((scene / JSON_NAME).read_text())
        names = [c["name"] for c in doc["rig"]["cameras"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        return _fail(f"SCENE_DIR: {scene / JSON_NAME}: not a scene's JSON ({type(e).__name__}: {e})")
    if args.camera is not None and args.camera not in names:
        return _fail(f"--camera: no camera {args.camera!r} in the scene's rig (cameras: {', '.join(names)})")
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((HOST, args.port))
    except OSError as e:
        return _fail(f"--port: cannot listen on {HOST}:{args.port} ({e.strerror or e})")
    root = Path(tempfile.mkdtemp(prefix="xyzcyl-view-"))
    try:
        return _serve(args, scene, root, sock)
    finally:
        sock.close()
        shutil.rmtree(root, ignore_errors=True)     # the store's link goes; the linked folder is never followed


def _serve(args: argparse.Namespace, scene: Path, root: Path, sock) -> int:
    from urllib.parse import quote

    import uvicorn
    from xyzcyl.runtime.inference import ModelError

    from ..app import create_app
    from ..settings import Settings
    from ..viewer import missing, modules_dir
    from .serve import _configure_logging, _server_class

    sid = store_with_scene(scene, root)
    # local and for one user: no API keys (docs/viewer.md), no warm-up (the first server render loads its kernels)
    settings = Settings(store=str(root), host=HOST, port=sock.getsockname()[1], api_keys=(), warm_up=False,
                        max_store_bytes=1 << 60)
    why = missing(modules_dir(settings))
    if why is not None:
        print(f"xyzcyl view: warning: {why}; the page says so until then", file=sys.stderr)
    _configure_logging("warning")
    try:
        app = create_app(settings)
    except ModelError as e:
        return _fail(f"the model (for the server's own renders): {e}")
    port = sock.getsockname()[1]
    query = f"?camera={quote(args.camera)}" if args.camera else ""
    url = f"http://{HOST}:{port}/v1/scenes/{sid}/viewer{query}"
    config = uvicorn.Config(app, log_level="warning", server_header=False, timeout_graceful_shutdown=5)

    class Server(_server_class()):
        async def startup(self, sockets=None):
            await super().startup(sockets=sockets)
            print(f"xyzcyl view: {scene} at {url} (Ctrl-C stops)", flush=True)
            if args.open:
                import webbrowser

                webbrowser.open(url)

    server = Server(config)
    server.service = app.state.service
    server.run(sockets=[sock])
    return 0
