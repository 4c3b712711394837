"""HTTP service benchmark (issue 12, "Speed"): one JSON document, against a real `xyzcyl serve` subprocess on
loopback (the shipped model unless --serve-args names another).

Input: the example rig (examples/synth_nuscenes, 6 cameras) upscaled to 1600x900 and stored as JPEG (quality 90),
calibrations scaled with Camera.resized; posted as multipart (`rig` + one part per camera) with `?wait=`.

Cases (each with the 1/5/15-minute load averages before and after it; latencies are client-side wall times over
one kept-alive httpx connection, p50/p95/p99 by linear interpolation over the n requests):
- ``reconstruct``: upload to ready (POST /v1/scenes?wait=120 answering 201) for 6 x 1600x900 JPEG, median of
  --recon-runs after one warm-up post (``first_s``: the worker's first rig, lifting inputs computed; later posts of
  the same calibration reuse them, as a client posting consecutive timestamps of one rig does), plus the server's
  own stage timings (median).
- ``render_1600x900_png`` and ``render_800x600_jpeg``: GET .../render with distinct poses (the camera moves
  forward by 1 mm per request, so the server's render cache never hits), after --warmup renders.
  ``server_render_mean_s`` is the server's render + encode time (Prometheus histogram) over the same requests.
- ``concurrency``: throughput (requests/s) of 1 and of 4 client threads, each with its own connection and a fixed
  number of requests (--concurrent-requests each), distinct poses, for both sizes; ratio 4 / 1.
  ``server_cpu_cores``: the server process's CPU time over the wall time (how many cores it kept busy).
- ``cache``: the same pose again (a render cache hit) and If-None-Match with its ETag (304).
- ``rss``: VmRSS of the server process (not its child processes: the reconstruction worker and multiprocessing's
  resource tracker, reported apart under server.children) after --warmup renders and
  after --renders more (800x600 JPEG, distinct poses). The render cache keeps up to --render-cache-bytes of encoded
  views by design; the estimate of what it holds at the end is reported next to the growth.

Targets (issue 12): reconstruct <= 1.5 s median; 1600x900 PNG <= 0.3 s median; 800x600 JPEG <= 0.1 s median;
4 clients >= 1.6x the throughput of 1; RSS growth < 50 MB over 1,000 renders. Each is reported pass/fail.

    .venv/bin/python benchmarks/server_bench.py [--quick] [--out FILE] [--recon-runs 5] [--renders 1000]
        [--serve-args "--render-threads 2"]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import shlex
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from xyzcyl.testing.rigs import make_rig, rig_files  # make_rig: the example rig as 6 JPEGs at width x height
from xyzcyl.testing.serve import XYZCYL, serve

REPO = Path(__file__).resolve().parents[1]

TARGETS = {"reconstruct_median_s": 1.5, "render_1600x900_png_median_s": 0.3, "render_800x600_jpeg_median_s": 0.1,
           "concurrency_4_over_1": 1.6, "rss_growth_mb": 50.0}


# ----------------------------------------------------------------------------------------------- machine


def load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def machine() -> dict:
    model = None
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        m = re.search(r"^Model name:\s*(.+)$", out, re.MULTILINE)
        model = m.group(1).strip() if m else None
    except OSError:
        pass
    flags = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    try:
        mem = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1)) // 1024
    except (OSError, AttributeError):
        mem = None
    return {"cores": os.cpu_count(), "cores_usable": len(os.sched_getaffinity(0)), "cpu_model": model,
            "avx512f": "avx512f" in flags, "avx2": "avx2" in flags, "memory_mb": mem,
            "python": platform.python_version(), "kernel": platform.release(),
            "env": {k: os.environ[k] for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OMP_WAIT_POLICY")
                    if k in os.environ}}


def other_jobs(seconds: float = 1.0) -> list[dict]:
    """Processes other than this benchmark and its server that used >= 10 % of a core over ``seconds``: the
    work sharing the machine while a figure was taken."""
    mine = {os.getpid(), *children(os.getpid())}
    mine |= {c for p in list(mine) for c in children(p)}
    def cpu_all() -> dict[int, float]:
        return {pid: t for pid in (int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit())
                if (t := cpu_seconds(pid)) is not None}

    a = cpu_all()
    time.sleep(seconds)
    b = cpu_all()
    out = []
    for pid, t in b.items():
        share = (t - a.get(pid, t)) / seconds
        if share >= 0.1 and pid not in mine:
            cmd = cmdline(pid, 400)
            out.append({"pid": pid, "cpu": round(share, 2), "cmd": cmd if len(cmd) <= 120 else
                        cmd[:60] + " ... " + cmd[-55:]})
    return sorted(out, key=lambda d: -d["cpu"])


def git_state() -> dict:
    """The commit measured and the files that differed from it (others may edit the working tree)."""
    def git(*a):
        return subprocess.run(["git", *a], capture_output=True, text=True, check=False, cwd=REPO).stdout.rstrip("\n")

    try:
        return {"commit": git("rev-parse", "HEAD"),
                "modified": [ln[3:] for ln in git("status", "--porcelain", "--untracked-files=no").splitlines()]}
    except OSError:
        return {}


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        return ""


def rss_mb(pid: int, key: str = "VmRSS") -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        return None
    return None


def cmdline(pid: int, keep: int = 120) -> str:
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return ""
    return " ".join(w.decode(errors="replace") for w in words if w)[-keep:]


def children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


# ----------------------------------------------------------------------------------------------- the server


def resolved_settings(store: Path, extra: list[str]) -> dict:
    out = subprocess.run([str(XYZCYL), "serve", "--store", str(store), *extra, "--print-settings"],
                         capture_output=True, text=True, check=True, cwd=REPO).stdout
    return json.loads(out)


def metric(text: str, name: str, label: str = "") -> float:
    """Sum of the samples of one Prometheus metric (all label sets, or those containing ``label``)."""
    total = 0.0
    for line in text.splitlines():
        if line.startswith((name + " ", name + "{")) and label in line:
            total += float(line.rsplit(" ", 1)[1])
    return total


# ----------------------------------------------------------------------------------------------- input


class Poses:
    """Distinct render requests: CAM_FRONT's pose moved forward by ``step`` metres per request (thread-safe)."""

    def __init__(self, rig_json: Path, step: float = 1e-3):
        doc = json.loads(rig_json.read_text())
        cam = next(c for c in doc["cameras"] if c["name"] == "CAM_FRONT")
        self.pose = np.asarray(cam["cam_to_ego"], dtype=np.float64)
        self.K = np.asarray(cam["K"], dtype=np.float64)
        self.size = (cam["width"], cam["height"])
        self.step = step
        self._n = itertools.count()
        self._lock = threading.Lock()

    def next(self, width: int, height: int, fmt: str) -> dict:
        with self._lock:
            i = next(self._n)
        return self.params(i, width, height, fmt)

    def params(self, i: int, width: int, height: int, fmt: str) -> dict:
        T = self.pose.copy()
        T[0, 3] += self.step * i
        p = {"cam_to_ego": ",".join(repr(float(v)) for v in T.ravel()), "width": width, "height": height,
             "format": fmt}
        if (width, height) == self.size:
            p |= {"fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]), "cx": float(self.K[0, 2]),
                  "cy": float(self.K[1, 2])}
        else:
            p["fx"] = float(self.K[0, 0]) * width / self.size[0]      # same focal length per pixel of width
        return p


def stats(xs: list[float]) -> dict:
    if not xs:
        return {"n": 0}
    a = np.asarray(xs)
    return {"n": len(xs), "median_s": round(float(np.median(a)), 4), "mean_s": round(float(a.mean()), 4),
            "p50_s": round(float(np.percentile(a, 50)), 4), "p95_s": round(float(np.percentile(a, 95)), 4),
            "p99_s": round(float(np.percentile(a, 99)), 4), "min_s": round(float(a.min()), 4),
            "max_s": round(float(a.max()), 4)}


# ----------------------------------------------------------------------------------------------- cases


def case_reconstruct(c, rig_json: Path, runs: int) -> tuple[dict, str]:
    files = rig_files(rig_json=rig_json)
    body_mb = sum(len(f[1][1]) for f in files) / 1e6
    times, server, errors, sid = [], [], {}, None
    first = None
    for i in range(runs + 1):
        t0 = time.perf_counter()
        r = c.post("/v1/scenes", params={"wait": 120}, files=files)
        dt = time.perf_counter() - t0
        if r.status_code != 201:
            errors[str(r.status_code)] = errors.get(str(r.status_code), 0) + 1
            errors["last"] = r.text[:300]
            continue
        info = r.json()
        if sid is not None:                       # keep the store small: only the last scene stays
            c.delete(f"/v1/scenes/{sid}")
        sid = info["id"]
        if i == 0:
            first = {"upload_to_ready_s": round(dt, 4), "server_timings_s": info.get("timings")}
            continue
        times.append(dt)
        server.append(info.get("timings") or {})
    if sid is None:
        raise RuntimeError(f"no reconstruction succeeded: {errors}")
    keys = sorted(set().union(*server)) if server else []
    med = {k: round(statistics.median(s[k] for s in server if k in s), 4) for k in keys}
    return {"input": "6 x 1600x900 JPEG q90", "body_mb": round(body_mb, 2), "first": first,
            "upload_to_ready": stats(times), "server_timings_median_s": med, "gaussians": info.get("gaussians"),
            "counts": info.get("counts"), "errors": errors}, sid


def timed_renders(c, sid: str, poses: Poses, n: int, width: int, height: int, fmt: str) -> tuple[list, dict, int]:
    times, errors, nbytes = [], {}, 0
    for _ in range(n):
        p = poses.next(width, height, fmt)
        t0 = time.perf_counter()
        r = c.get(f"/v1/scenes/{sid}/render", params=p)
        dt = time.perf_counter() - t0
        if r.status_code != 200:
            errors[str(r.status_code)] = errors.get(str(r.status_code), 0) + 1
            errors["last"] = r.text[:300]
            continue
        times.append(dt)
        nbytes += len(r.content)
    return times, errors, nbytes


def server_render(c) -> tuple[float, float]:
    text = c.get("/metrics").text
    return metric(text, "xyzcyl_render_duration_seconds_sum"), metric(text, "xyzcyl_render_duration_seconds_count")


def case_render(c, sid: str, poses: Poses, n: int, warmup: int, width: int, height: int, fmt: str) -> dict:
    timed_renders(c, sid, poses, warmup, width, height, fmt)
    s0, n0 = server_render(c)
    before = load()
    times, errors, nbytes = timed_renders(c, sid, poses, n, width, height, fmt)
    s1, n1 = server_render(c)
    return {"size": f"{width}x{height}", "format": fmt, "warmup": warmup, **stats(times),
            "server_render_mean_s": round((s1 - s0) / max(1, n1 - n0), 4),
            "bytes_mean": round(nbytes / max(1, len(times))), "errors": errors, "load_before": before,
            "load_after": load()}


def cpu_seconds(pid: int) -> float | None:
    """utime + stime of a process (all its threads), seconds."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def throughput(url: str, sid: str, poses: Poses, clients: int, per_client: int, width: int, height: int,
               fmt: str, pid: int) -> dict:
    import httpx

    lat: list[float] = []
    errors: dict[str, int] = {}
    lock = threading.Lock()
    start = threading.Barrier(clients + 1)

    def client():
        with httpx.Client(base_url=url, timeout=120.0) as c:
            c.get("/v2/health/live")                  # connect before the clock starts
            start.wait()
            for _ in range(per_client):
                p = poses.next(width, height, fmt)
                t0 = time.perf_counter()
                r = c.get(f"/v1/scenes/{sid}/render", params=p)
                dt = time.perf_counter() - t0
                with lock:
                    if r.status_code == 200:
                        lat.append(dt)
                    else:
                        errors[str(r.status_code)] = errors.get(str(r.status_code), 0) + 1

    threads = [threading.Thread(target=client, daemon=True) for _ in range(clients)]
    for t in threads:
        t.start()
    before = load()
    start.wait()
    t0, cpu0 = time.perf_counter(), cpu_seconds(pid)
    for t in threads:
        t.join(600)
    wall, cpu1 = time.perf_counter() - t0, cpu_seconds(pid)
    if any(t.is_alive() for t in threads):
        errors["timeout"] = sum(t.is_alive() for t in threads)
    return {"clients": clients, "requests": clients * per_client, "ok": len(lat), "wall_s": round(wall, 3),
            "requests_per_s": round(len(lat) / wall, 3),
            "server_cpu_cores": round((cpu1 - cpu0) / wall, 2) if cpu0 is not None and cpu1 is not None else None,
            "latency": stats(lat), "errors": errors,
            "load_before": before, "load_after": load()}


def case_concurrency(url: str, sid: str, poses: Poses, per_client: int, sizes, pid: int) -> dict:
    out = {}
    for width, height, fmt in sizes:
        one = throughput(url, sid, poses, 1, per_client, width, height, fmt, pid)
        four = throughput(url, sid, poses, 4, per_client, width, height, fmt, pid)
        out[f"{width}x{height}_{fmt}"] = {"one": one, "four": four,
                                          "four_over_one": round(four["requests_per_s"] / one["requests_per_s"], 3)
                                          if one["requests_per_s"] else None}
    return out


def case_cache(c, sid: str, poses: Poses, n: int) -> dict:
    p = poses.next(1600, 900, "png")
    r = c.get(f"/v1/scenes/{sid}/render", params=p)
    etag = r.headers.get("etag")
    before = load()
    hits, not_mod, errors = [], [], {}
    for _ in range(n):
        t0 = time.perf_counter()
        r2 = c.get(f"/v1/scenes/{sid}/render", params=p)
        dt = time.perf_counter() - t0
        if r2.status_code == 200 and r2.content == r.content:
            hits.append(dt)
        else:
            errors[f"hit_{r2.status_code}"] = errors.get(f"hit_{r2.status_code}", 0) + 1
        t0 = time.perf_counter()
        r3 = c.get(f"/v1/scenes/{sid}/render", params=p, headers={"If-None-Match": etag or ""})
        dt = time.perf_counter() - t0
        if r3.status_code == 304:
            not_mod.append(dt)
        else:
            errors[f"etag_{r3.status_code}"] = errors.get(f"etag_{r3.status_code}", 0) + 1
    return {"size": "1600x900", "format": "png", "etag": etag, "cache_hit": stats(hits), "not_modified_304":
            stats(not_mod), "errors": errors, "load_before": before, "load_after": load()}


def case_rss(c, sid: str, poses: Poses, pid: int, warmup: int, n: int, cache_limit: int) -> dict:
    before = load()
    _, e0, b0 = timed_renders(c, sid, poses, warmup, 800, 600, "jpeg")
    rss0 = rss_mb(pid)
    t0 = time.perf_counter()
    times, e1, b1 = timed_renders(c, sid, poses, n, 800, 600, "jpeg")
    wall = time.perf_counter() - t0
    rss1 = rss_mb(pid)
    cache_est = min(cache_limit, b0 + b1) / 2**20
    return {"size": "800x600", "format": "jpeg", "warmup": warmup, "renders": n, "ok": len(times),
            "wall_s": round(wall, 1), "rss_after_warmup_mb": rss0, "rss_after_mb": rss1,
            "rss_growth_mb": round(rss1 - rss0, 1) if rss0 is not None and rss1 is not None else None,
            "peak_rss_mb": rss_mb(pid, "VmHWM"), "render_cache_holds_at_most_mb": round(cache_est, 1),
            "median_s": round(statistics.median(times), 4) if times else None,
            "errors": {**e0, **e1}, "load_before": before, "load_after": load()}


# ----------------------------------------------------------------------------------------------- main


def verdict(value, target, better: str) -> dict:
    if value is None:
        return {"value": None, "target": target, "pass": False}
    ok = value <= target if better == "le" else value >= target if better == "ge" else value < target
    return {"value": value, "target": f"{ {'le': '<=', 'ge': '>=', 'lt': '<'}[better]} {target}", "pass": ok}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few iterations (a smoke run; figures not meaningful)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON document here")
    ap.add_argument("--recon-runs", type=int, default=5, help="timed reconstructions (after one warm-up)")
    ap.add_argument("--render-runs", type=int, default=60, help="timed 1600x900 PNG renders")
    ap.add_argument("--jpeg-runs", type=int, default=120, help="timed 800x600 JPEG renders")
    ap.add_argument("--warmup", type=int, default=50, help="renders before each timed series and the RSS reading")
    ap.add_argument("--concurrent-requests", type=int, default=24, help="requests per client thread")
    ap.add_argument("--cache-runs", type=int, default=50, help="repeated-pose and 304 requests")
    ap.add_argument("--renders", type=int, default=1000, help="renders between the two RSS readings")
    ap.add_argument("--serve-args", default="", help="extra `xyzcyl serve` flags, e.g. \"--render-threads 2\"")
    ap.add_argument("--work", type=Path, default=None, help="folder for the rig and the store (default: a temp one)")
    args = ap.parse_args()
    if args.quick:
        args.recon_runs, args.render_runs, args.jpeg_runs = 2, 6, 10
        args.warmup, args.concurrent_requests, args.cache_runs, args.renders = 3, 4, 5, 30

    extra = shlex.split(args.serve_args)
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="xyzcyl_server_bench_")
        args.work = Path(tmp.name)
    args.work.mkdir(parents=True, exist_ok=True)
    store, log = args.work / "store", args.work / "serve.log"
    import httpx

    doc = {"benchmark": "server_bench", "issue": 12, "quick": args.quick,
           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "git": git_state(), "machine": machine(),
           "uptime_start": uptime(), "load_start": load(), "other_jobs_start": other_jobs(),
           "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
           "serve_flags": extra}
    try:
        rig_json = make_rig(args.work)
        settings = resolved_settings(store, extra)
        doc["settings"] = settings
        poses = Poses(rig_json)
        with serve(store, log, ["--log-level", "warning", *extra], ready_s=120.0, stop_s=30.0, every=0.1) as server:
            proc, url, t_ready = server.proc, server.url, server.ready_s
            doc["server"] = {"pid": proc.pid, "ready_s": round(t_ready, 2), "rss_ready_mb": rss_mb(proc.pid)}
            with httpx.Client(base_url=url, timeout=300.0) as c:
                doc["server"]["version"] = c.get("/v2").json()
                others = other_jobs()
                doc["reconstruct"], sid = case_reconstruct(c, rig_json, args.recon_runs)
                doc["reconstruct"] |= {"load_after": load(), "others_before": others}
                cases = (
                    ("render_1600x900_png",
                     lambda: case_render(c, sid, poses, args.render_runs, args.warmup, 1600, 900, "png")),
                    ("render_800x600_jpeg",
                     lambda: case_render(c, sid, poses, args.jpeg_runs, args.warmup, 800, 600, "jpeg")),
                    ("concurrency", lambda: case_concurrency(url, sid, poses, args.concurrent_requests,
                                                             ((1600, 900, "png"), (800, 600, "jpeg")), proc.pid)),
                    ("cache", lambda: case_cache(c, sid, poses, args.cache_runs)),
                    ("rss", lambda: case_rss(c, sid, poses, proc.pid, args.warmup, args.renders,
                                             int(settings.get("render_cache_bytes", 0)))),
                )
                for key, fn in cases:
                    others = other_jobs()
                    doc[key] = fn() | {"others_before": others}
                doc["server"]["children"] = [{"pid": p, "rss_mb": rss_mb(p), "cmd": cmdline(p)}
                                             for p in children(proc.pid)]
                doc["server"]["rss_end_mb"] = rss_mb(proc.pid)
                r = c.get("/metrics")
                doc["server"]["rejected"] = metric(r.text, "xyzcyl_rejected_total")
                doc["server"]["render_cache"] = {k: metric(r.text, "xyzcyl_render_cache_total", f'result="{k}"')
                                                 for k in ("hit", "miss")}
        doc["server"]["stop"] = server.stop_info
    finally:
        doc["uptime_end"] = uptime()
        doc["load_end"] = load()
        doc["other_jobs_end"] = other_jobs()
        if "concurrency" in doc:
            conc = doc["concurrency"]
            doc["targets"] = {
                "reconstruct_median_s": verdict(doc["reconstruct"]["upload_to_ready"].get("median_s"),
                                                TARGETS["reconstruct_median_s"], "le"),
                "render_1600x900_png_median_s": verdict(doc["render_1600x900_png"].get("median_s"),
                                                        TARGETS["render_1600x900_png_median_s"], "le"),
                "render_800x600_jpeg_median_s": verdict(doc["render_800x600_jpeg"].get("median_s"),
                                                        TARGETS["render_800x600_jpeg_median_s"], "le"),
                "concurrency_4_over_1_1600x900_png": verdict(conc["1600x900_png"]["four_over_one"],
                                                             TARGETS["concurrency_4_over_1"], "ge"),
                "concurrency_4_over_1_800x600_jpeg": verdict(conc["800x600_jpeg"]["four_over_one"],
                                                             TARGETS["concurrency_4_over_1"], "ge"),
            }
            if "rss" in doc:
                doc["targets"]["rss_growth_mb"] = verdict(doc["rss"]["rss_growth_mb"], TARGETS["rss_growth_mb"],
                                                          "lt")
                if doc["rss"]["renders"] != 1000:
                    doc["targets"]["rss_growth_mb"]["note"] = f"over {doc['rss']['renders']} renders, not 1,000"
        text = json.dumps(doc, indent=1)
        print(text, flush=True)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")
        if tmp is not None:
            tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
