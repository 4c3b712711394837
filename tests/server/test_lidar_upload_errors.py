"""POST /v1/scenes with a 'lidar' part that holds nothing usable (issue 35, items 4 and 7): a 0-byte file, text named
.npy, raw float32 rows named .npy, a .npy of zero points. Each answers 422 with the one error body, field `lidar`, a
message that names the part and the client's file name (never the store's temporary path) and says what
runtime.lidar.read_points says of the same file on the command line; no scene is created. The app is
tests/server/conftest.py's ``env``."""

from __future__ import annotations

import io

import numpy as np
import pytest
from api_helpers import err
from xyzcyl.runtime.lidar import LidarError, read_points
from xyzcyl.testing.rigs import rig_files


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


# the client's file name -> the part's bytes
CASES = {
    "empty.npy": b"",
    "empty.bin": b"",
    "empty.pcd.bin": b"",
    "empty": b"",                                                      # a name of neither kind: sniffed
    "x.npy": b"hello\n",                                               # 6 bytes of text
    "rows.npy": np.ones((4, 4), "<f4").tobytes(),                      # raw float32 rows named .npy
    "zero.npy": _npy(np.zeros((0, 3), np.float32)),
}


def _cli_message(tmp_path, name: str, data: bytes) -> str:
    """What read_points says of the same bytes as a local file called ``name``, after the file's name."""
    p = tmp_path / (name if "." in name else name + ".bin")
    p.write_bytes(data)
    with pytest.raises(LidarError) as info:
        read_points(p)
    return info.value.message.removeprefix(repr(str(p)))


@pytest.mark.parametrize("name", list(CASES))
def test_post_refuses_a_lidar_part_without_points(client, env, tmp_path, name):
    """Regression (issue 35): an empty .npy answered 201 with the LiDAR dropped (detail_lidar 0); text named .npy
    was read as float32 rows; messages named 'xyzcyl-store/tmp/<id>/lidar.npy'."""
    records = env.service.store.list()[1]
    data = CASES[name]
    r = client.post("/v1/scenes?wait=5", files=rig_files(extra=[("lidar", (name, data, "application/octet-stream"))]))
    e = err(r, 422, "lidar", "invalid")
    msg = e["message"]
    assert msg.startswith(f"part 'lidar' (file {name!r}) "), msg
    assert "xyzcyl-store" not in msg and "tmp" not in msg and str(env.store_root) not in msg, msg
    assert msg.endswith(_cli_message(tmp_path, name, data)), msg          # the CLI's words for the same file
    assert env.service.store.list()[1] == records                         # no scene was created


def test_points_left_out_for_a_non_finite_coordinate_are_counted(client):
    """A sweep with NaN / inf rows reconstructs, and the scene says how many points were left out (they were dropped
    silently over HTTP: the CLI printed the count, the service's scene had no trace of it)."""
    from xyzcyl.runtime.warmup import lidar_sweep

    pts = lidar_sweep(seed=3)
    pts[:7, 0] = np.nan
    pts[7:9, 2] = np.inf
    r = client.post("/v1/scenes?wait=120", files=[*rig_files(), ("lidar", ("sweep.npy", _npy(pts),
                                                                            "application/octet-stream"))])
    assert r.status_code == 201, r.text
    counts = r.json()["counts"]
    assert counts["lidar_nonfinite"] == 9 and counts["lidar_points"] == len(pts) - 9, counts
    assert client.delete(f"/v1/scenes/{r.json()['id']}").status_code == 204
