"""`xyzcyl serve` warms up before it reports ready (issue: "no silent cold start"): a real server subprocess on a
free loopback port, with a fresh empty NUMBA_CACHE_DIR so every numba kernel must be compiled (the worst case: a
first start after an install). /v2/health/ready must answer 200 only after the warm-up, so neither the first
reconstruction (with a LiDAR sweep: the LiDAR path and the detail layer) nor the first render after ready may pay
for a compile. Without the warm-up the first render took 32 s and the first LiDAR reconstruction 35 s on a cold
cache, against well under a second per render and a few seconds per reconstruction warm."""

from __future__ import annotations

import io
import json
import os
import statistics
import sys
import time

import numpy as np
import pytest
from xyzcyl.testing import EXAMPLE
from xyzcyl.testing.rigs import rig_files
from xyzcyl.testing.serve import XYZCYL, Server

httpx = pytest.importorskip("httpx")

READY_S = 300.0          # compiling every kernel on 2 busy shared cores: about a minute; bounded well above that
VIEWS = 7                # renders after ready: the first and 6 more for the median
NOTICE = "xyzcyl: compiling numba kernels ("


def _lidar_part() -> tuple:
    """A synthetic sweep in the ego frame (runtime.warmup's: the ground and two walls) as the 'lidar' part."""
    from xyzcyl.runtime.warmup import lidar_sweep

    buf = io.BytesIO()
    np.save(buf, lidar_sweep(seed=7))
    return ("lidar", ("sweep.npy", buf.getvalue(), "application/octet-stream"))


def _poses(n: int) -> list[str]:
    """n distinct views: CAM_FRONT's pose moved 0.4 m forward (ego x) per view (distinct poses: no render cache
    hit, the same work each)."""
    rig = json.loads((EXAMPLE / "rig.json").read_text())
    T = np.array(next(c for c in rig["cameras"] if c["name"] == "CAM_FRONT")["cam_to_ego"], np.float64)
    out = []
    for k in range(n):
        P = T.copy()
        P[0, 3] += 0.4 * k
        out.append(",".join(f"{v:.9g}" for v in P.ravel()))
    return out


def _lens_renders_after_pinhole(c, server, sid: str) -> None:
    """An f-theta view over HTTP and over gRPC (AlpaSim's render_rgb with NuRec's FthetaCameraParam) after the
    pinhole renders (issue 35 item 1: both answered 500 / INTERNAL in a running server)."""
    import grpc
    from xyzcyl.server.sensorsim import sensorsim_pb2 as pb
    from xyzcyl.server.sensorsim.sensorsim_pb2_grpc import SensorsimServiceStub
    from xyzcyl.testing.sensorsim import grpc_port, rgb_request

    lens = {"model": "ftheta", "pixeldist_to_angle_poly": [0.0, 2.45e-3, 1.2e-7], "max_angle_deg": 80.0}
    r = c.get(f"/v1/scenes/{sid}/render", params={"camera": "CAM_FRONT", "distortion": json.dumps(lens)})
    assert r.status_code == 200 and r.content.startswith(b"\x89PNG\r\n\x1a\n"), r.text
    with grpc.insecure_channel(f"127.0.0.1:{grpc_port(server.output(100_000))}") as channel:
        stub = SensorsimServiceStub(channel)
        cams = stub.get_available_cameras(pb.AvailableCamerasRequest(scene_id=sid), timeout=120).available_cameras
        req = rgb_request(cams[0], np.eye(4), scene=sid)
        req.camera_intrinsics.ftheta_param.CopyFrom(pb.FthetaCameraParam(
            principal_point_x=255.5, principal_point_y=159.5, reference_poly=pb.FthetaCameraParam.PIXELDIST_TO_ANGLE,
            pixeldist_to_angle_poly=[0, 2.45e-3, 1.2e-7], max_angle=np.radians(80)))
        got = stub.render_rgb(req, timeout=120).image_bytes
        assert got.startswith(b"\x89PNG\r\n\x1a\n")


@pytest.mark.slow
@pytest.mark.heavy
def test_serve_warms_up_before_ready_first_requests_not_slow(tmp_path):
    assert XYZCYL.is_file(), f"{XYZCYL} not installed (pip install -e .)"
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    log = tmp_path / "serve.log"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "XYZCYL_WARM_UP": "true"}   # tests/conftest.py turns it off
    with Server(tmp_path / "store", log, ["--grpc-port", "0"], env=env) as server:
        url = server.url
        try:
            waited = server.wait_ready(READY_S)
            text = log.read_text(errors="replace")
            # a cold cache: the compile was announced (the server's line through its log, the worker's on
            # stderr), and the warm-up finished, all before ready
            assert NOTICE in text, text[-4000:]
            assert "warm-up took" in text, text[-4000:]
            assert "Traceback" not in text, text[-4000:]
            assert "warm-up reconstruction took" in text, text[-4000:]
            assert any(cache.rglob("*.nbi")), "numba wrote nothing into NUMBA_CACHE_DIR"

            with httpx.Client(base_url=url, timeout=120.0) as c:
                # two LiDAR reconstructions of the same rig: the first must not be much slower than the second
                # (a compile would add ~10-30 s to a job of a few seconds)
                files = [*rig_files(), _lidar_part()]
                took = []
                for _ in range(2):
                    t0 = time.perf_counter()
                    r = c.post("/v1/scenes", params={"wait": 120}, files=files)
                    took.append(time.perf_counter() - t0)
                    assert r.status_code == 201, r.text
                    assert r.json()["counts"]["lidar_cameras"] == 6, r.json()["counts"]
                sid = r.json()["id"]
                assert took[0] <= 3.0 * took[1] + 1.0, f"first LiDAR reconstruction {took[0]:.2f} s, second {took[1]:.2f} s"

                times = []
                for pose in _poses(VIEWS):
                    t0 = time.perf_counter()
                    r = c.get(f"/v1/scenes/{sid}/render", params={"cam_to_ego": pose, "fov": 70, "width": 1600,
                                                                   "height": 900})
                    times.append(time.perf_counter() - t0)
                    assert r.status_code == 200, r.text
                    assert r.content.startswith(b"\x89PNG\r\n\x1a\n")
                # the lens kernels compile after ready (issue 35 item 8: ready no longer waits for them) in a child
                # process and load into the server, which then renders f-theta after pinhole views over HTTP and
                # gRPC (issue 35 item 1: both failed in a running server); wait for that warm-up, bounded (an
                # f-theta request before it would compile in the server beside the child: twice the work)
                t1 = time.monotonic()
                while "lens warm-up took" not in log.read_text(errors="replace") and time.monotonic() - t1 < READY_S:
                    time.sleep(0.5)
                _lens_renders_after_pinhole(c, server, sid)
            first, median = times[0], statistics.median(times[1:])
            print(f"ready after {waited:.1f} s; LiDAR reconstructions {[round(t, 2) for t in took]} s; renders "
                  f"{[round(t, 3) for t in times]} s")
            # 3x the median plus 1 s: the first render of a scene also loads it into the scene cache (its PLY and
            # EXR, 0.1-0.2 s, next to 0.08-0.3 s for a 1600x900 view: a ratio alone failed at 0.267 s against a
            # 0.087 s median) and the machine is shared (a render's time varies by tens of per cent); without the
            # warm-up the first render compiles the kernels (10 s or more on a cold cache, as here), far above 1 s
            bound = 3.0 * median + 1.0
            assert first <= bound, (f"first render after ready {first:.3f} s > 3 x the median {median:.3f} s + 1 s "
                                    f"(all: {[round(t, 3) for t in times]}; ready after {waited:.1f} s)")
            text = log.read_text(errors="replace")
            assert text.index("loaded; ready") < text.index("lens warm-up took"), text[-4000:]
            assert "Traceback" not in text and "warm-up failed" not in text, text[-4000:]
            server.stop(30)
        except BaseException:
            sys.stderr.write(f"--- xyzcyl serve output ({log}) ---\n{log.read_text(errors='replace')[-8000:]}\n")
            raise
