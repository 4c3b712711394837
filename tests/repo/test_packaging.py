"""The distribution maps every package folder, and the layering rules hold."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib

from xyzcyl.testing import REPO

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
# top folder -> package, from [tool.setuptools.package-dir] (a hand-kept copy here missed `common`)
TOP = {folder: dotted for dotted, folder in PYPROJECT["tool"]["setuptools"]["package-dir"].items()}


def test_the_top_packages_are_the_repository_folders():
    assert set(TOP) == {"common", "runtime", "model_export", "server", "clients", "testing"}


def test_every_package_folder_is_listed_in_pyproject():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
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
    code = ("import sys; from xyzcyl.clients import cli; "
            "cli.build_parser(); assert 'torch' not in sys.modules and 'numba' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_cli_commands_resolve():
    import importlib.util

    from xyzcyl.clients import cli
    for cmd in cli.COMMANDS:
        assert importlib.util.find_spec(cmd.module) is not None, f"{cmd.name}: {cmd.module} missing"


def test_testing_package_imports_without_torch():
    """xyzcyl.testing (what tests and benchmarks share) imports in the serving install, which has no torch: with
    torch unimportable, every module imports and the tiny config and rigs are built."""
    code = ("import sys; sys.modules['torch'] = None; "
            "import xyzcyl.testing, xyzcyl.testing.rigs, xyzcyl.testing.serve, xyzcyl.testing.model as m; "
            "m.tiny_config(); m.synth_test_config(); m.tiny_export_config(); m.overlap_rig(6); "
            "xyzcyl.testing.rigs.rig_files()")
    subprocess.run([sys.executable, "-c", code], check=True)
