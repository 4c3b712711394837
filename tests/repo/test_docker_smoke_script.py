"""scripts/docker-smoke.sh chooses runc as podman's OCI runtime itself (issue 27 defect 9: Debian's podman came with
crun, which fails on a cgroup v1 / hybrid host, and the script worked only with XYZCYL_PODMAN_FLAGS="--runtime
runc"). Run against stub podman / runc / apt-get / curl on a PATH of their own: with XYZCYL_SKIP_BUILD=1 and no
image the script stops at its first `podman image exists`, after choosing the runtime; the stub podman records
every call's arguments."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from xyzcyl.testing import REPO

SCRIPT = REPO / "scripts" / "docker-smoke.sh"
BASH = shutil.which("bash")
TOOLS = ("dirname", "mktemp", "mkdir", "date", "timeout", "cat", "tail", "python3")

pytestmark = pytest.mark.skipif(BASH is None or any(shutil.which(t) is None for t in TOOLS[:-1]),
                                reason="needs bash and coreutils")


def test_the_script_parses():
    subprocess.run([BASH, "-n", str(SCRIPT)], check=True)


def _stub(path: Path, body: str) -> None:
    path.write_text("#!" + BASH + "\n" + body)
    path.chmod(0o755)


def _run(tmp_path: Path, runc: bool, apt: bool = False, flags: str | None = None):
    bindir = tmp_path / "bin"
    bindir.mkdir()
    for tool in TOOLS:
        found = shutil.which(tool) if tool != "python3" else (shutil.which("python3") or shutil.which("python"))
        if found:
            (bindir / tool).symlink_to(found)
    log = tmp_path / "podman.log"
    _stub(bindir / "podman", f'echo "$*" >> {log}\n[ "$1" = --version ] && echo "podman version 4.3.1"\nexit 1\n')
    _stub(bindir / "curl", "exit 0\n")
    if runc:
        _stub(bindir / "runc", "exit 0\n")
    if apt:     # installing makes a runc appear, as Debian's package would
        _stub(bindir / "apt-get", f'echo "$*" >> {tmp_path / "apt.log"}\n'
                                  f'[ "$1" = install ] && printf "#!{BASH}\\nexit 0\\n" > {bindir / "runc"} '
                                  f'&& chmod +x {bindir / "runc"}\nexit 0\n')
    env = {"PATH": str(bindir), "HOME": str(tmp_path), "XYZCYL_SKIP_BUILD": "1",
           "XYZCYL_SMOKE_OUT": str(tmp_path / "out"), "XYZCYL_IMAGE": "localhost/xyzcyl:test"}
    if flags is not None:
        env["XYZCYL_PODMAN_FLAGS"] = flags
    r = subprocess.run([BASH, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 1 and "there is no image localhost/xyzcyl:test" in r.stderr, r.stderr
    calls = log.read_text().splitlines()
    exists = [c for c in calls if c.endswith("image exists localhost/xyzcyl:test")]
    assert len(exists) == 1, calls
    return exists[0].removesuffix("image exists localhost/xyzcyl:test").strip(), r.stderr, bindir


def test_runc_is_chosen_where_it_is_installed(tmp_path):
    flags, err, bindir = _run(tmp_path, runc=True)
    assert flags == f"--runtime {bindir / 'runc'}"
    assert f"OCI runtime {bindir / 'runc'} (podman --runtime)" in err


def test_runc_is_installed_with_apt_get_when_absent(tmp_path):
    flags, _, bindir = _run(tmp_path, runc=False, apt=True)
    assert flags == f"--runtime {bindir / 'runc'}"
    install = [c for c in (tmp_path / "apt.log").read_text().splitlines() if c.startswith("install")]
    assert len(install) == 1 and " runc " in f" {install[0]} ", install


@pytest.mark.parametrize("given", ["--runtime crun --cgroup-manager=cgroupfs", "--runtime=/usr/bin/crun"])
def test_a_runtime_in_xyzcyl_podman_flags_wins(tmp_path, given):
    flags, err, _ = _run(tmp_path, runc=True, flags=given)
    assert flags == given
    assert "(XYZCYL_PODMAN_FLAGS)" in err


def test_without_runc_and_apt_get_podmans_default_with_a_warning(tmp_path):
    flags, err, _ = _run(tmp_path, runc=False)
    assert flags == ""
    assert "WARNING: no runc and no apt-get" in err


def test_other_podman_flags_are_kept(tmp_path):
    flags, _, bindir = _run(tmp_path, runc=True, flags="--storage-driver=vfs")
    assert flags == f"--runtime {bindir / 'runc'} --storage-driver=vfs"
    assert os.access(bindir / "runc", os.X_OK)
