"""What the tests (tests/) and the benchmark scripts (benchmarks/) share: the repository's example data, the tiny
model configuration and small rigs, a harness that runs `xyzcyl serve` on loopback, and the multipart body of
POST /v1/scenes.

- ``xyzcyl.testing.rigs``: the example rig (``example_rig``, ``example_images``), ``rig_files`` (the multipart
  parts of POST /v1/scenes), ``drive_files`` (those of a recorded drive) and ``multipart_body``, ``make_rig`` (the
  example rig as JPEGs at another size), ``png_header_only`` (a PNG whose header claims a size its data does not have);
- ``xyzcyl.testing.serve``: ``Server`` / ``serve`` (`xyzcyl serve` in a subprocess on 127.0.0.1 and a free port,
  a bounded wait for /v2/health/ready, SIGTERM or kill), ``free_port``, ``XYZCYL`` (the console script);
- ``xyzcyl.testing.model``: ``tiny_config``, ``synth_test_config`` (the network at test size) and ``overlap_rig``;
- ``xyzcyl.testing.drives``: ``write_drive`` (the example rig as a small drive file, optionally with tracks),
  ``moving_car`` (a tracks file with one moving box), ``pose``;
- ``xyzcyl.testing.sensorsim``: the gRPC SensorsimService's (grpc and protobuf needed): ``ego_pose``,
  ``rig_with_pose``, AlpaSim's ``rgb_request``, the HTTP ``view_query`` of the same view, ``grpc_port``.

Nothing here imports torch at import time (``xyzcyl.testing.model`` builds its configs without it), so the
package imports in the serving install; httpx (the ``server`` and ``client`` extras) is imported where it is used.

The package ships in the wheel, the data it points at does not: the example rig and the shipped model are files of
the source checkout. ``REPO`` is that checkout, found on first use (``checkout``): the folder the installed
distribution was installed from (``pip install -e .`` or ``pip install .``: its direct_url.json, PEP 610), else the
working folder or the nearest folder above it that holds xyzcyl's pyproject.toml (a wheel installed elsewhere, the
tests run from a checkout). ``REPO``, ``EXAMPLE``, ``EXAMPLE_RIG`` and ``SHIPPED_MODEL`` raise NoCheckout, which
says so, where there is none; the serve harness needs none.
"""

from __future__ import annotations

import functools
import json
import tomllib
from pathlib import Path
from urllib.parse import unquote, urlparse

PROJECT = "xyzcyl"


class NoCheckout(LookupError):
    """No source checkout of xyzcyl is found (see the package's docstring), so its files cannot be named."""


def _is_checkout(folder: Path) -> bool:
    try:
        return tomllib.loads((folder / "pyproject.toml").read_text())["project"]["name"] == PROJECT
    except (OSError, KeyError, TypeError, tomllib.TOMLDecodeError):
        return False


def _installed_from() -> Path | None:
    """The local folder the installed distribution was built from (PEP 610 ``dir_info``), or None (installed from
    a wheel file or an index, or not installed)."""
    from importlib.metadata import PackageNotFoundError, distribution

    try:
        text = distribution(PROJECT).read_text("direct_url.json")
    except PackageNotFoundError:
        return None
    try:
        doc = json.loads(text) if text else {}
    except json.JSONDecodeError:
        return None
    url = urlparse(str(doc.get("url", "")))
    return Path(unquote(url.path)) if "dir_info" in doc and url.scheme == "file" else None


@functools.cache
def checkout() -> Path | None:
    """The source checkout of xyzcyl (absolute), or None where there is none (see the package's docstring)."""
    cwd = Path.cwd().resolve()
    for folder in (_installed_from(), cwd, *cwd.parents):
        if folder is not None and _is_checkout(folder):
            return folder.resolve()
    return None


_PATHS = {
    "REPO": (),
    "EXAMPLE": ("examples", "synth_nuscenes"),
    "EXAMPLE_RIG": ("examples", "synth_nuscenes", "rig.json"),
    "SHIPPED_MODEL": ("models", "xyzcyl-cpu-v1"),
}


def __getattr__(name: str) -> Path:
    if name not in _PATHS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    root = checkout()
    if root is None:
        raise NoCheckout(f"xyzcyl.testing.{name}: no source checkout of xyzcyl here (the example rig and the shipped "
                         f"model are files of it): run from a checkout, or install from one (pip install -e .)")
    return root.joinpath(*_PATHS[name])


__all__ = ["EXAMPLE", "EXAMPLE_RIG", "REPO", "SHIPPED_MODEL", "NoCheckout", "checkout"]
