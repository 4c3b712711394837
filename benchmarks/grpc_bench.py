"""gRPC SensorsimService benchmark (issue 29): AlpaSim's per-step call, ``batch_render_rgb`` of the six cameras of
the example scene at 512x320 (AlpaSim's default render size), against a real `xyzcyl serve --grpc-port` subprocess
on loopback, and the same views over HTTP. One JSON document on stdout (and --out).

The scene: examples/synth_nuscenes (6 cameras, 800x450) posted with a name and an ego_to_world (yaw 30 degrees,
100 m out), the cameras from get_available_cameras, the sensor poses composed as AlpaSim does (ego pose @ camera ->
rig), the ego moving 0.5 m forward per step and 5 cm during each exposure, so no two views are alike. The server
runs with its render cache off (every view rendered) and its defaults otherwise (render_threads = cores).

Cases, --rounds rounds after --warmup rounds, each round running every case once (round-robin, so that other
processes' load falls on every case alike; client-side wall times; median, p90, min):
- ``grpc_batch``: one batch_render_rgb of the 6 views (the target: median <= 0.5 s on 2 cores);
- ``http_concurrent``: the same 6 views as 6 GET /render at once (one connection each): HTTP's batch;
- ``grpc_sequential`` / ``http_sequential``: the 6 views one call after the other (render_rgb / GET /render);
- ``server_render_mean_s``: the server's own render + encode time of one view (Prometheus histogram), per case
  (top level: in the grpc_batch calls).
``overhead``: grpc_batch - http_concurrent (what the gRPC front end adds to a step), and per view
(grpc_sequential - http_sequential) / 6. Every gRPC image of the last round is checked byte for byte against the
HTTP render of the same view (``identical``).

    .venv/bin/python benchmarks/grpc_bench.py [--rounds 20] [--warmup 3] [--out FILE] [--serve-args "..."]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import re
import shlex
import statistics
import tempfile
import time
from pathlib import Path

from xyzcyl.testing.rigs import example_rig, rig_files
from xyzcyl.testing.serve import serve

NAME = "clipgt-grpc-bench"
TARGET_S = 0.5


def stats(xs: list[float]) -> dict:
    s = sorted(xs)
    return {"n": len(s), "median_s": round(statistics.median(s), 4),
            "p90_s": round(s[min(len(s) - 1, math.ceil(0.9 * len(s)) - 1)], 4), "min_s": round(s[0], 4)}


def metric_sum_count(text: str, name: str) -> tuple[float, float]:
    def one(suffix):
        m = re.search(rf"^{name}_{suffix} ([0-9.e+-]+)$", text, re.M)
        return float(m.group(1)) if m else 0.0
    return one("sum"), one("count")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=320)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--serve-args", default="", help="more `xyzcyl serve` flags")
    args = ap.parse_args()

    import grpc
    import httpx
    from xyzcyl.server.sensorsim import sensorsim_pb2 as pb
    from xyzcyl.server.sensorsim.sensorsim_pb2_grpc import SensorsimServiceStub
    from xyzcyl.testing.sensorsim import ego_pose, grpc_port, rgb_request, rig_with_pose, view_query

    E = ego_pose()
    with tempfile.TemporaryDirectory(prefix="xyzcyl-grpc-bench-") as tmp:
        tmp = Path(tmp)
        serve_args = ["--grpc-port", "0", "--render-cache-bytes", "0", *shlex.split(args.serve_args)]
        with serve(tmp / "store", tmp / "serve.log", serve_args, ready_s=300) as server:
            port = grpc_port(server.output())
            http = httpx.Client(base_url=server.url, timeout=120.0)
            r = http.post("/v1/scenes", params={"wait": 120, "name": NAME},
                          files=rig_files(rig_with_pose(example_rig(), E)))
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            channel = grpc.insecure_channel(f"127.0.0.1:{port}")
            stub = SensorsimServiceStub(channel)
            cams = stub.get_available_cameras(pb.AvailableCamerasRequest(scene_id=NAME)).available_cameras
            step = [0]

            def views() -> list:
                """The six requests of the next step (the ego 0.5 m further on, 5 cm during the exposure)."""
                k = step[0]
                step[0] += 1
                start, end = E.copy(), E.copy()
                start[:3, 3] += E[:3, 0] * 0.5 * k
                end[:3, 3] += E[:3, 0] * (0.5 * k + 0.05)
                return [rgb_request(c, start, end, scene=NAME, width=args.width, height=args.height) for c in cams]

            def http_params(req) -> dict:
                return view_query(req, E)

            def grpc_batch() -> list[bytes]:
                items = [pb.BatchRGBRenderRequestItem(camera_name=c.logical_id, request=v)
                         for c, v in zip(cams, views())]
                out = stub.batch_render_rgb(pb.BatchRGBRenderRequest(items=items), timeout=120)
                assert all(i.success for i in out.items), [i.error_message for i in out.items]
                return [i.result.image_bytes for i in out.items]

            async def _concurrent(params: list[dict]) -> list[bytes]:
                async with httpx.AsyncClient(base_url=server.url, timeout=120.0,
                                             limits=httpx.Limits(max_connections=6)) as c:
                    rs = await asyncio.gather(*(c.get(f"/v1/scenes/{sid}/render", params=p) for p in params))
                assert all(r.status_code == 200 for r in rs), [r.text for r in rs if r.status_code != 200]
                return [r.content for r in rs]

            def http_concurrent() -> list[bytes]:
                return asyncio.run(_concurrent([http_params(v) for v in views()]))

            def grpc_sequential() -> list[bytes]:
                return [stub.render_rgb(v, timeout=120).image_bytes for v in views()]

            def http_sequential() -> list[bytes]:
                out = []
                for v in views():
                    r = http.get(f"/v1/scenes/{sid}/render", params=http_params(v))
                    assert r.status_code == 200, r.text
                    out.append(r.content)
                return out

            cases = {"grpc_batch": grpc_batch, "http_concurrent": http_concurrent,
                     "grpc_sequential": grpc_sequential, "http_sequential": http_sequential}
            for _ in range(args.warmup):
                for fn in cases.values():
                    fn()
            # round-robin: each round runs every case once, so the other processes' load falls on all alike
            times: dict[str, list[float]] = {name: [] for name in cases}
            render: dict[str, list[float]] = {name: [0.0, 0.0] for name in cases}
            load0 = os.getloadavg()
            for _ in range(args.rounds):
                for name, fn in cases.items():
                    before = metric_sum_count(http.get("/metrics").text, "xyzcyl_render_duration_seconds")
                    t0 = time.perf_counter()
                    fn()
                    times[name].append(time.perf_counter() - t0)
                    after = metric_sum_count(http.get("/metrics").text, "xyzcyl_render_duration_seconds")
                    render[name][0] += after[0] - before[0]
                    render[name][1] += after[1] - before[1]
            result: dict = {"cases": {name: {**stats(times[name]), "server_render_mean_s": round(
                render[name][0] / max(render[name][1], 1), 4)} for name in cases},
                "loadavg_before": [round(x, 2) for x in load0],
                "loadavg_after": [round(x, 2) for x in os.getloadavg()]}
            render_mean = render["grpc_batch"][0] / max(render["grpc_batch"][1], 1)
            # the last step's gRPC images against HTTP's renders of the same views
            k = step[0]
            reqs = views()
            step[0] = k
            got = grpc_batch()
            identical = sum(g == http.get(f"/v1/scenes/{sid}/render", params=http_params(v)).content
                            for g, v in zip(got, reqs))
            channel.close()
            http.close()
            server.stop(check=False)
    c = result["cases"]
    med = c["grpc_batch"]["median_s"]
    result.update({
        "benchmark": "grpc_bench", "views": f"6 cameras at {args.width}x{args.height} PNG, example scene",
        "machine": {"cores": len(os.sched_getaffinity(0)), "cpu": platform.processor() or platform.machine(),
                    "python": platform.python_version()},
        "server_args": serve_args, "server_render_mean_s": None if render_mean is None else round(render_mean, 4),
        "overhead": {"batch_s": round(med - c["http_concurrent"]["median_s"], 4),
                     "batch_ratio": round(med / c["http_concurrent"]["median_s"], 3),
                     "per_view_s": round((c["grpc_sequential"]["median_s"] - c["http_sequential"]["median_s"]) / 6,
                                         4)},
        "identical_to_http": f"{identical}/6",
        "target": {"grpc_batch_median_s": TARGET_S, "pass": med <= TARGET_S}})
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0 if identical == 6 else 1


if __name__ == "__main__":
    raise SystemExit(main())
