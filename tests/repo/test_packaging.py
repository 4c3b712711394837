"""The distribution maps every package folder, the layering rules hold, the wheel holds the package and nothing
else of the repository (xyzcyl.testing works from it: it finds the checkout, not a path next to itself), and the
package has one version."""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from xyzcyl.testing import REPO

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
# top folder -> package, from [tool.setuptools.package-dir] (a hand-kept copy here missed `common`); "xyzcyl" maps
# the top of the repository itself (its modules only: ROOT_MODULES)
TOP = {folder: dotted for dotted, folder in SETUPTOOLS["package-dir"].items() if folder != "."}
ROOT_MODULES = ("__main__.py", "cli.py")
LAYERS = ("common", "runtime", "model_export", "server", "clients")


def test_the_top_packages_are_the_repository_folders():
    assert set(TOP) == {*LAYERS, "testing"}
    assert SETUPTOOLS["package-dir"]["xyzcyl"] == "." and "xyzcyl" in SETUPTOOLS["packages"]
    # the "xyzcyl" package is every module at the top of the repository: only the console script's
    assert sorted(p.name for p in REPO.glob("*.py")) == sorted(ROOT_MODULES)
    assert not (REPO / "__init__.py").exists()      # a namespace package: the layers' folders are its subpackages


def test_every_package_folder_is_listed_in_pyproject():
    listed = set(SETUPTOOLS["packages"])
    found = set()
    for folder, dotted in TOP.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder).parts
            found.add(".".join((dotted, *rel)))
    assert found - listed == set(), "add these to [tool.setuptools] packages in pyproject.toml"


def _imports(folder: str, pattern: str) -> list[str]:
    bad = []
    for path in (REPO / folder).rglob("*.py"):
        for line in path.read_text().splitlines():
            if re.match(pattern, line):
                bad.append(f"{path.relative_to(REPO)}: {line.strip()}")
    return bad


def test_runtime_never_imports_torch():
    assert _imports("runtime", r"\s*(import torch|from torch)") == []


def test_server_only_calls_runtime():
    assert _imports("server", r"\s*(import|from)\s+xyzcyl\.(model_export|clients)") == []
    assert _imports("server", r"\s*(import torch|from torch)") == []


def test_cli_help_is_fast_and_torch_free():
    code = ("import sys; from xyzcyl import cli; "
            "cli.build_parser(); assert 'torch' not in sys.modules and 'numba' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_each_layer_declares_its_commands():
    """The console script's table is the layers' own declarations (COMMANDS of their ``commands`` packages), in
    order, with unique names; each command loads a module of the package that declares it, which has
    add_arguments and run."""
    from xyzcyl import cli
    from xyzcyl.clients import commands as clients
    from xyzcyl.model_export import commands as model_export
    from xyzcyl.runtime import commands as runtime
    from xyzcyl.server import commands as server

    # server/commands declares its command in cli.py until server/commands/__init__.py holds COMMANDS
    declared = {runtime: runtime.COMMANDS, model_export: model_export.COMMANDS,
                server: getattr(server, "COMMANDS", cli.SERVER_COMMANDS), clients: clients.COMMANDS}
    assert cli.COMMANDS == tuple(c for commands in declared.values() for c in commands)
    names = [c.name for c in cli.COMMANDS]
    assert len(names) == len(set(names)), names
    for package, commands in declared.items():
        for cmd in commands:
            module = cmd.load()
            assert module.__name__.startswith(package.__name__ + "."), f"{cmd.name}: {module.__name__}"
            assert callable(module.add_arguments) and callable(module.run), cmd.name


def test_testing_package_imports_without_torch():
    """xyzcyl.testing (what tests and benchmarks share) imports in the serving install, which has no torch: with
    torch unimportable, every module imports and the tiny config and rigs are built."""
    code = ("import sys; sys.modules['torch'] = None; "
            "import xyzcyl.testing, xyzcyl.testing.rigs, xyzcyl.testing.serve, xyzcyl.testing.model as m; "
            "m.tiny_config(); m.synth_test_config(); m.tiny_export_config(); m.overlap_rig(6); "
            "xyzcyl.testing.rigs.rig_files()")
    subprocess.run([sys.executable, "-c", code], check=True)


# -- one version -------------------------------------------------------------------------------------------------

def test_one_version():
    """pyproject.toml's version is the installed distribution's and xyzcyl.common.version's, which the console
    script prints (tests/clients/test_cli.py) and the server reports."""
    from xyzcyl.common.version import __version__

    assert __version__ == importlib.metadata.version("xyzcyl") == PYPROJECT["project"]["version"]


def test_python_m_xyzcyl_is_the_console_script():
    done = subprocess.run([sys.executable, "-m", "xyzcyl", "--version"], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == f"xyzcyl {PYPROJECT['project']['version']}"


# -- the wheel ---------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, list[str]]:
    """The wheel `pip wheel` builds from the package's sources (copied: the build writes build/ and an egg-info
    beside them), unpacked as `pip install` lays it out in site-packages; and its file names. About 2 s."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", *ROOT_MODULES):
        shutil.copy2(REPO / name, src / name)
    for folder in TOP:
        shutil.copytree(REPO / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.py[co]",
                                                                                    "*.nbi", "*.nbc"))
    # no build isolation: setuptools from the environment (the dev extra), no index needed
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "--disable-pip-version-check", "-q", "-w", str(tmp / "dist"), str(src)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    (whl,) = (tmp / "dist").glob("xyzcyl-*.whl")
    site = tmp / "site"
    with zipfile.ZipFile(whl) as z:
        z.extractall(site)
        return site, z.namelist()


def test_the_wheel_holds_the_package_and_nothing_else(wheel):
    site, names = wheel
    tops = {n.split("/")[0] for n in names}
    assert tops == {"xyzcyl", f"xyzcyl-{PYPROJECT['project']['version']}.dist-info"}, tops
    inside = {n.split("/")[1] for n in names if n.startswith("xyzcyl/")}
    assert inside == {*TOP, *ROOT_MODULES}, inside            # no __init__.py: a namespace package
    for folder in TOP:                                         # every module of every package folder
        modules = {f"xyzcyl/{p.relative_to(REPO).as_posix()}" for p in (REPO / folder).rglob("*.py")}
        assert modules <= set(names), sorted(modules - set(names))
    assert {"xyzcyl/server/sensorsim/sensorsim.proto", "xyzcyl/model_export/data/photos/README.md",
            "xyzcyl/server/viewer/web/index.html", "xyzcyl/server/viewer/web/viewer.js",
            "xyzcyl/server/viewer/web/viewer.css"} <= set(names)
    dist = next(n.split("/")[0] for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "xyzcyl = xyzcyl.cli:entry" in (site / dist / "entry_points.txt").read_text()


WHEEL_CHECK = r"""
import json, os, sys
from pathlib import Path
site, repo = Path(sys.argv[1]), Path(sys.argv[2])
import xyzcyl.cli, xyzcyl.testing, xyzcyl.testing.model, xyzcyl.testing.rigs, xyzcyl.testing.serve
from xyzcyl.common.version import __version__
from xyzcyl.testing import NoCheckout, checkout
files = [m.__file__ for m in (xyzcyl.cli, xyzcyl.testing, xyzcyl.testing.rigs)]
assert all(Path(f).is_relative_to(site) for f in files), files      # the wheel's modules, not the checkout's
out = {"version": __version__, "checkout_elsewhere": str(checkout())}
try:
    xyzcyl.testing.EXAMPLE_RIG
except NoCheckout as e:
    out["no_checkout"] = str(e)
os.chdir(repo)                  # a checkout's tests run against the wheel: the checkout is the working folder's
checkout.cache_clear()
out["checkout_in_repo"] = str(checkout())
out["example_rig"] = xyzcyl.testing.EXAMPLE_RIG.is_file()
out["cameras"] = len(xyzcyl.testing.rigs.example_rig()["cameras"])
try:
    xyzcyl.cli.main(["--version"])
except SystemExit:
    pass
out["heavy"] = sorted(m for m in ("numba", "onnxruntime", "torch") if m in sys.modules)
print(json.dumps(out))
"""


def test_testing_works_from_the_wheel(wheel, tmp_path):
    """xyzcyl.testing, installed from the wheel: no checkout where it is run outside one (REPO & co. say so),
    the checkout it is run in otherwise; `xyzcyl --version` prints the package's version and the model's."""
    site, _ = wheel
    env = {**os.environ, "PYTHONPATH": str(site), "XYZCYL_MODEL": str(REPO / "models" / "xyzcyl-cpu-v1")}
    done = subprocess.run([sys.executable, "-c", WHEEL_CHECK, str(site), str(REPO)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    *printed, last = done.stdout.splitlines()
    out = json.loads(last)
    assert out["checkout_elsewhere"] == "None" and "no source checkout" in out["no_checkout"]
    assert out["checkout_in_repo"] == str(REPO.resolve()) and out["example_rig"] and out["cameras"] == 6
    model = json.loads((REPO / "models" / "xyzcyl-cpu-v1" / "model.json").read_text())
    assert printed[-2:] == [f"xyzcyl {PYPROJECT['project']['version']}",
                            f"model: {model['name']} {model['version']} ({REPO / 'models' / 'xyzcyl-cpu-v1'})"]
    assert out["version"] == PYPROJECT["project"]["version"] and out["heavy"] == []


def test_ray_is_the_batch_extras_only():
    """`xyzcyl batch` needs Ray (the batch extra); the serving install has none and the server's modules import
    without it (server/batch.py imports Ray inside its functions only)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    serving = project["dependencies"] + project["optional-dependencies"]["server"]
    assert not [d for d in serving if d.lower().startswith("ray")]
    assert [d for d in project["optional-dependencies"]["batch"] if d.startswith("ray[data]")]
    code = ("import sys; sys.modules['ray'] = None; import xyzcyl.server.app, xyzcyl.server.batch, "
            "xyzcyl.server.commands.batch; from xyzcyl import cli; cli.build_parser()")
    subprocess.run([sys.executable, "-c", code], check=True)
