"""What the tests (tests/) and the benchmark scripts (benchmarks/) share: the repository's example data, the tiny
model configuration and small rigs, a harness that runs `xyzcyl serve` on loopback, and the multipart body of
POST /v1/scenes.

- ``xyzcyl.testing.rigs``: the example rig (``example_rig``, ``example_images``), ``rig_files`` (the multipart
  parts of POST /v1/scenes) and ``multipart_body``, ``make_rig`` (the example rig as JPEGs at another size),
  ``png_header_only`` (a PNG whose header claims a size its data does not have);
- ``xyzcyl.testing.serve``: ``Server`` / ``serve`` (`xyzcyl serve` in a subprocess on 127.0.0.1 and a free port,
  a bounded wait for /v2/health/ready, SIGTERM or kill), ``free_port``, ``XYZCYL`` (the console script);
- ``xyzcyl.testing.model``: ``tiny_config``, ``synth_test_config`` (the network at test size) and ``overlap_rig``;
- ``xyzcyl.testing.sensorsim``: the gRPC SensorsimService's (grpc and protobuf needed): ``ego_pose``,
  ``rig_with_pose``, AlpaSim's ``rgb_request``, the HTTP ``view_query`` of the same view, ``grpc_port``.

Nothing here imports torch at import time (``xyzcyl.testing.model`` builds its configs without it), so the
package imports in the serving install; httpx (the ``server`` and ``client`` extras) is imported where it is used.
The paths below point into the source checkout this package was installed from (``pip install -e .``).
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "synth_nuscenes"
EXAMPLE_RIG = EXAMPLE / "rig.json"
SHIPPED_MODEL = REPO / "models" / "xyzcyl-cpu-v1"

__all__ = ["EXAMPLE", "EXAMPLE_RIG", "REPO", "SHIPPED_MODEL"]
