"""The layers of issue 27, house 3 (docs/design.md): the HTTP client imports no xyzcyl.runtime and no xyzcyl.server,
xyzcyl.common imports nothing else of xyzcyl, and the server's routes never import server/app.py (they take the
service and their dependencies from deps.py). Each rule is checked twice: by importing in a fresh interpreter
(and running the code paths that used to import lazily), and by reading every import statement of the files,
those inside functions included."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FOLDERS = {"xyzcyl.common": "common", "xyzcyl.runtime": "runtime", "xyzcyl.server": "server",
           "xyzcyl.clients": "clients", "xyzcyl.model_export": "model_export"}


def _module_of(path: Path) -> str:
    for dotted, folder in FOLDERS.items():
        root = REPO / folder
        if path.is_relative_to(root):
            parts = path.relative_to(root).with_suffix("").parts
            return ".".join((dotted, *(parts[:-1] if parts[-1] == "__init__" else parts)))
    raise ValueError(path)


def imports_of(path: Path) -> set[str]:
    """The absolute names of every module a file imports (relative imports resolved; `from a import b` counts as
    a.b too, b may be a module), at any depth of the file."""
    module = _module_of(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.add(name)
            out |= {f"{name}.{a.name}" for a in node.names}
    return out


def _run(code: str) -> None:
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120, cwd=REPO)


def test_the_client_imports_no_runtime_and_no_server():
    # the modules, then the paths that imported runtime helpers lazily: a float depth map as EXR, the pose flags,
    # the progress bar
    _run("import argparse, sys\n"
         "import numpy as np\n"
         "from xyzcyl.clients import client\n"
         "from xyzcyl.clients.commands import client as command\n"
         "assert client._encode_depth(np.ones((4, 4), np.float32))[1] == '.exr'\n"
         "parser = argparse.ArgumentParser()\n"
         "command.add_arguments(parser)\n"
         "args = parser.parse_args(['render', 'S', '--carla', '1', '0', '2', '0', '0', '0', '--fov', '90',\n"
         "                          '--width', '8', '--height', '8', '--out', 'x.png', '--forward', '1'])\n"
         "pose, move = command._pose(args)\n"
         "assert pose['x'] == 1.0 and move.forward == 1.0\n"
         "args.quiet = False\n"
         "command._bar(args, 10, 'B', 'upload')[1]()\n"
         "bad = sorted(m for m in sys.modules if m.startswith(('xyzcyl.runtime', 'xyzcyl.server')))\n"
         "assert not bad, bad\n")
    for path in (REPO / "clients" / "client.py", REPO / "clients" / "commands" / "client.py"):
        bad = sorted(m for m in imports_of(path) if m.startswith(("xyzcyl.runtime", "xyzcyl.server")))
        assert bad == [], f"{path.relative_to(REPO)} imports {bad}"


def test_common_imports_nothing_else_of_xyzcyl():
    modules = sorted(_module_of(p) for p in (REPO / "common").glob("*.py"))
    _run("import sys\n"
         f"for m in {modules!r}: __import__(m)\n"
         "bad = sorted(m for m in sys.modules if m.startswith('xyzcyl.') and not m.startswith('xyzcyl.common'))\n"
         "assert not bad, bad\n")
    for path in (REPO / "common").rglob("*.py"):
        bad = sorted(m for m in imports_of(path) if m.startswith("xyzcyl") and m != "xyzcyl"
                     and not m.startswith("xyzcyl.common"))
        assert bad == [], f"{path.relative_to(REPO)} imports {bad}"


def test_the_clients_scene_is_the_wire_type():
    """The client's SceneInfo (its public type) is the wire model the server answers with, not a copy to keep in
    step, and a scene answer round-trips through it."""
    from xyzcyl.clients.client import SceneInfo
    from xyzcyl.common import wire

    assert SceneInfo is wire.SceneInfo
    doc = {"id": "s" * 22, "name": None, "state": "failed", "created": "2026-01-01T00:00:00+00:00",
           "updated": "2026-01-01T00:00:01+00:00", "error": {"code": "timeout", "message": "took too long"},
           "cameras": [{"name": "CAM_FRONT", "width": 800, "height": 450, "model": "pinhole"}],
           "detail": {"enabled": True, "stride": 2}, "links": {"self": "/v1/scenes/" + "s" * 22}}
    info = SceneInfo.from_json(doc)
    assert info.raw == doc and info.failed and not info.ready and info.camera_names == ["CAM_FRONT"]
    assert info.detail.stride == 2 and info.error.code == "timeout"


def test_common_is_packaged():
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "xyzcyl.common" in tool["packages"] and tool["package-dir"]["xyzcyl.common"] == "common"
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert [d.split(">")[0].split("=")[0] for d in extras["client"]] == ["httpx"]     # the client extra stays small


def test_routes_never_import_the_app():
    """Nothing the routes import, directly or through other server modules, is server/app.py (the cycle app ->
    routes -> app is gone), and importing the routes loads no app."""
    server = {_module_of(p): p for p in (REPO / "server").rglob("*.py")}
    for start in sorted(m for m in server if m.startswith("xyzcyl.server.routes.")):
        seen, todo = set(), [start]
        while todo:
            m = todo.pop()
            if m in seen:
                continue
            seen.add(m)
            todo += [n for n in imports_of(server[m]) if n in server and n != "xyzcyl.server"]
        assert "xyzcyl.server.app" not in seen, f"{start} reaches xyzcyl.server.app"
    _run("import sys\n"
         "from xyzcyl.server.routes import health, render, scenes\n"
         "assert 'xyzcyl.server.app' not in sys.modules\n")


def test_no_layer_imports_the_console_script():
    """xyzcyl.cli (cli.py at the top) gathers the commands the layers declare; no layer imports it, and a layer's
    ``commands`` package loads only its own modules (the server's no HTTP client, the runtime's no torch)."""
    for dotted, folder in FOLDERS.items():
        for path in (REPO / folder).rglob("*.py"):
            bad = sorted(m for m in imports_of(path) if m in ("xyzcyl.cli", "xyzcyl.__main__")
                         or m.startswith("xyzcyl.cli."))
            assert bad == [], f"{path.relative_to(REPO)} imports {bad}"
        init = REPO / folder / "commands" / "__init__.py"
        if init.is_file():
            others = sorted(m for m in imports_of(init) if m.startswith("xyzcyl.")
                            and not m.startswith((f"{dotted}.commands", "xyzcyl.common")))
            assert others == [], f"{init.relative_to(REPO)} imports {others}"
