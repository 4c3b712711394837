"""The Docker build context holds what the Dockerfile copies: every `COPY` source from the build context survives
.dockerignore, and the build stage copies every package folder pyproject.toml maps (a package added to
pyproject but filtered out by .dockerignore broke `docker build` once: `COPY common ./common` found nothing).
scripts/docker-smoke.sh builds the image for real (podman; not part of CI)."""

from __future__ import annotations

import re
import tomllib

import pytest
from xyzcyl.testing import REPO

DOCKERFILE = (REPO / "Dockerfile").read_text()


def _rules() -> list[tuple[bool, re.Pattern]]:
    """.dockerignore as (exclude?, regex) in order. Docker's syntax: `*` and `?` stay within a path component,
    `**` spans any number of them (a leading `**/` also none), `!` re-includes; the last matching rule wins, and
    a rule matching a folder covers everything inside it."""
    rules = []
    for line in (REPO / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keep = line.startswith("!")
        pat = line[1:] if keep else line
        rx, i = "", 0
        while i < len(pat):
            if pat.startswith("**/", i):
                rx, i = rx + "(?:.*/)?", i + 3
            elif pat.startswith("**", i):
                rx, i = rx + ".*", i + 2
            elif pat[i] == "*":
                rx, i = rx + "[^/]*", i + 1
            elif pat[i] == "?":
                rx, i = rx + "[^/]", i + 1
            else:
                rx, i = rx + re.escape(pat[i]), i + 1
        rules.append((not keep, re.compile(rx + "(?:/.*)?")))
    return rules


def ignored(path: str) -> bool:
    """Whether .dockerignore leaves `path` (relative to the repository root) out of the build context."""
    out = False
    for exclude, rx in _rules():
        if rx.fullmatch(path):
            out = exclude
    return out


def _context_copies() -> list[str]:
    """The build-context sources of the Dockerfile's COPY lines (not `COPY --from=stage`)."""
    srcs = []
    for m in re.finditer(r"^COPY\s+(?!--from)(.+)$", DOCKERFILE, re.M):
        *sources, _dest = m.group(1).split()
        srcs += sources
    return srcs


def test_the_matcher_reads_docker_syntax():
    assert ignored(".venv/bin/python") and ignored("data/x.npz")               # `*`: everything else is out
    assert not ignored("runtime/render/kernels.py")                            # `!runtime`
    assert ignored("runtime/render/__pycache__/kernels.cpython-311.pyc")       # `**/__pycache__`, after it
    assert ignored("runtime/render/kernels.core.nbi")


@pytest.mark.parametrize("src", _context_copies())
def test_every_copied_path_is_in_the_build_context(src):
    path = REPO / src
    assert path.exists(), f"Dockerfile copies {src}, which does not exist"
    assert not ignored(src), f".dockerignore leaves {src} out of the build context: add !{src}"
    files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path]
    kept = [p for p in files if not ignored(str(p.relative_to(REPO)))]
    assert kept, f".dockerignore leaves every file of {src} out"


def test_the_build_stage_copies_every_package_folder():
    """Every folder pyproject.toml maps, and for the package mapped to the top of the repository ("xyzcyl" = ".":
    cli.py, __main__.py) its modules, not the whole context."""
    folders = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"].values())
    wanted = (folders - {"."}) | ({p.name for p in REPO.glob("*.py")} if "." in folders else set())
    assert wanted - set(_context_copies()) == set(), "the Dockerfile's build stage must COPY these (pip install)"
    assert "." not in _context_copies()


def _stage(name: str) -> str:
    """The Dockerfile's text from `FROM ... AS name` to the next FROM."""
    m = re.search(rf"^FROM\s+\S+\s+AS\s+{name}\s*$(.*?)(?=^FROM\s)", DOCKERFILE, re.M | re.S)
    assert m, f"the Dockerfile has no stage {name}"
    return m.group(1)


def test_the_extras_are_a_build_argument_defaulting_to_the_server():
    """`docker build --build-arg EXTRAS=server,batch -t xyzcyl:batch .` makes deploy/rayjob.yaml's image:
    EXTRAS is declared before the first FROM with the default `server` (the serving image, no ray), declared
    again inside the build stage (an ARG before FROM is not visible inside a stage otherwise, and pip would
    install `.[]`), and the stage's pip install uses it; the torch check stays on the same RUN."""
    first_from = re.search(r"^FROM\s", DOCKERFILE, re.M).start()
    assert re.search(r"^ARG\s+EXTRAS=server\s*$", DOCKERFILE[:first_from], re.M), "ARG EXTRAS=server first"
    build = _stage("build")
    assert re.search(r"^ARG\s+EXTRAS\s*$", build, re.M), "the build stage must redeclare ARG EXTRAS"
    install = re.search(r"^RUN pip install (\S+)(.*?)(?<!\\)\n", build, re.M | re.S)
    assert install, "the build stage installs the package with pip"
    assert install.group(1).strip("'\"") == ".[${EXTRAS}]"
    assert "import torch" in install.group(2) and "exit 1" in install.group(2), "keep the no-torch check"
