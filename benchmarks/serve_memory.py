"""Peak memory of a `xyzcyl serve` replica (issue 13, docs/deploy.md's resource requests): one JSON line.

Starts `xyzcyl serve` (the shipped model, default settings: one reconstruction worker) with a folder store, or
with an s3:// store on a `moto_server` started on loopback (--store s3); posts the example rig
(examples/synth_nuscenes, 6 cameras 800x450) with ?wait; renders every input camera (RGB PNG at its size and
depth EXR), one 1600x900 CARLA view and a batch of the 6 input cameras; downloads the Gaussians as PLY and
.splat. Then reads VmHWM (peak resident set) and VmRSS from /proc/<pid>/status of the server process and of each
of its children (the reconstruction worker; multiprocessing's resource tracker). Linux only.

    .venv/bin/python benchmarks/serve_memory.py [--store folder|s3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from xyzcyl.testing.rigs import example_rig, rig_files
from xyzcyl.testing.serve import free_port, serve

BIN = Path(sys.executable).parent


def _status(pid: int) -> dict[str, str]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        out[k] = v.strip()
    return out


def _children(pid: int) -> list[int]:
    return [int(x) for t in Path(f"/proc/{pid}/task").iterdir() for x in (t / "children").read_text().split()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--store", choices=["folder", "s3"], default="folder")
    args = ap.parse_args()
    env = dict(os.environ)
    work = Path(tempfile.mkdtemp(prefix="xyzcyl-mem-"))
    moto = None
    if args.store == "s3":
        mport = free_port()
        moto = subprocess.Popen([str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(mport)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        env.update(AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1",
                   AWS_ENDPOINT_URL=f"http://127.0.0.1:{mport}")
        deadline = time.time() + 30
        while True:
            try:
                httpx.put(f"http://127.0.0.1:{mport}/xyzcyl-bench")      # create the bucket (moto: no auth)
                break
            except httpx.HTTPError:
                if time.time() > deadline:
                    raise
                time.sleep(0.2)
        store = "s3://xyzcyl-bench/scenes"
        env["XYZCYL_S3_CACHE"] = str(work / "cache")
    else:
        store = str(work / "store")
    try:
        with serve(store, work / "serve.log", ready_s=300.0, stop_s=60.0, env=env, every=0.1) as srv:
            ready_s = srv.ready_s
            c = httpx.Client(base_url=srv.url, timeout=300)
            rig = example_rig()
            files = rig_files()
            t1 = time.time()
            r = c.post("/v1/scenes?wait=300", files=files)
            r.raise_for_status()
            reconstruct_s = time.time() - t1
            scene = r.json()
            sid = scene["id"]
            renders = 0
            for cam in rig["cameras"]:
                for q in ({"camera": cam["name"]}, {"camera": cam["name"], "output": "depth", "format": "exr"}):
                    c.get(f"/v1/scenes/{sid}/render", params=q).raise_for_status()
                    renders += 1
            carla = {"x": 0, "y": 0, "z": 1.6, "pitch": 0, "yaw": 0, "roll": 0, "fov": 90, "width": 1600, "height": 900}
            c.get(f"/v1/scenes/{sid}/render", params=carla).raise_for_status()
            c.post(f"/v1/scenes/{sid}/render",
                   json={"cameras": [{"camera": cam["name"]} for cam in rig["cameras"]]}).raise_for_status()
            renders += 1 + len(rig["cameras"])
            for fmt in ("ply", "splat"):
                c.get(f"/v1/scenes/{sid}/gaussians", params={"format": fmt}).raise_for_status()
            procs = {}
            for pid in [srv.pid, *_children(srv.pid)]:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
                role = ("server" if pid == srv.pid else "resource_tracker" if b"resource_tracker" in b" ".join(cmd)
                        else "worker")
                st = _status(pid)
                procs[f"{role}:{pid}"] = {"VmHWM_kB": int(st["VmHWM"].split()[0]), "VmRSS_kB": int(st["VmRSS"].split()[0])}
            print(json.dumps({"store": args.store, "ready_s": round(ready_s, 1), "reconstruct_s": round(reconstruct_s, 1),
                              "cameras": len(rig["cameras"]), "gaussians": scene["gaussians"],
                              "scene_bytes": scene["bytes"], "renders": renders, "processes": procs,
                              "peak_total_MiB": round(sum(p["VmHWM_kB"] for p in procs.values()) / 1024)}))
    finally:
        if moto is not None:
            moto.terminate()
            moto.wait(10)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
