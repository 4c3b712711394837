"""Reliability and security benchmarks of the HTTP service (issue 14, items 3-8): one JSON document per subcommand,
all traffic on 127.0.0.1 against a real `xyzcyl serve` subprocess (xyzcyl.testing.serve), every
loop bounded in count and in time. docs/reliability.md has what each case checks, its targets and the last figures.

    .venv/bin/python benchmarks/reliability.py load      [--quick] [--out FILE]   # 4 clients x 60 s (+ 2 reconstructions)
    .venv/bin/python benchmarks/reliability.py overload  ...   # 4x capacity for 60 s, health probe, reconstruct burst
    .venv/bin/python benchmarks/reliability.py limits    ...   # 413 before read, bombs, 17 cameras, PLY 1e9, slowloris
    .venv/bin/python benchmarks/reliability.py crash     ...   # kill -9 + restart, worker kill, disk full, disconnect
    .venv/bin/python benchmarks/reliability.py soak      ...   # 10,000 renders: RSS, fds; store eviction
    .venv/bin/python benchmarks/reliability.py security  ...   # API keys on every /v1 route, ids, huge values, headers

The input rig is the example rig (examples/synth_nuscenes, 6 cameras 800x450) stored as JPEG (quality 90).
Renders use distinct poses (CAM_FRONT moved forward a little per request) so the render cache never answers.
Every case reports ``pass`` against the issue's target; the document's ``pass`` is all of them.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import random
import re
import secrets
import select
import signal
import socket
import string
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from server_bench import (  # a sibling script: its folder is on the path (run as a script, or pytest's pythonpath)
    Poses,
    children,
    cmdline,
    load,
    machine,
    metric,
    other_jobs,
    rss_mb,
    stats,
    uptime,
)
from xyzcyl.testing.rigs import make_rig, multipart_body, png_header_only, rig_files
from xyzcyl.testing.serve import XYZCYL, serve

HOST = "127.0.0.1"
TARGETS = {
    "load_errors": 0, "overload_health_max_s": 0.1, "overload_other_5xx": 0, "overload_timeouts": 0,
    "rss_growth_mb": 100.0, "soak_renders": 10_000,
}


# ----------------------------------------------------------------------------------------------- small helpers


def now_s() -> float:
    return time.perf_counter()


def port_of(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


def fds(pid: int) -> list[str]:
    """Targets of the open file descriptors of ``pid`` ("socket:[..]", "/tmp/x (deleted)", ...)."""
    out = []
    d = Path(f"/proc/{pid}/fd")
    try:
        names = os.listdir(d)
    except OSError:
        return out
    for n in names:
        try:
            out.append(os.readlink(d / n))
        except OSError:
            pass
    return out


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:   # a zombie is dead for our purposes
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def worker_pids(server_pid: int) -> list[int]:
    """The reconstruction worker processes (multiprocessing spawn children of the server; not its resource
    tracker)."""
    return [p for p in children(server_pid) if "spawn_main" in cmdline(p) or "multiprocessing.spawn" in cmdline(p)]


def kill_all(pids) -> None:
    for p in pids:
        with contextlib.suppress(OSError):
            os.kill(p, signal.SIGKILL)


def count(d: dict, key) -> None:
    d[str(key)] = d.get(str(key), 0) + 1


def pct(xs: list[float], q: float) -> float | None:
    return round(float(np.percentile(np.asarray(xs), q)), 4) if xs else None


def verdict(value, target, op: str, note: str | None = None) -> dict:
    ok = value is not None and {"<": value < target if value is not None else False,
                                "<=": value <= target if value is not None else False,
                                "==": value == target, ">=": value >= target if value is not None else False}[op]
    v = {"value": value, "target": f"{op} {target}", "pass": bool(ok)}
    if note:
        v["note"] = note
    return v


def check(ok: bool, what: str, value=None) -> dict:
    return {"what": what, "value": value, "pass": bool(ok)}


class Ctx:
    """The work folder, the rig and its multipart parts, distinct poses, and the server log."""

    def __init__(self, work: Path, quick: bool, extra: list[str] | None = None):
        self.work = work
        self.extra = list(extra or [])          # --serve-args: added to every server's flags
        self.quick = quick
        self.rig_json = make_rig(work, 800, 450)
        self.files = rig_files(rig_json=self.rig_json)
        self.rig = json.loads(self.rig_json.read_text())
        self.poses = Poses(self.rig_json, step=2e-4)
        self.log = work / "serve.log"
        self._n = 0

    def store(self, name: str) -> Path:
        self._n += 1
        return self.work / f"store-{self._n:02d}-{name}"

    @contextlib.contextmanager
    def serve(self, store: Path, flags: list[str]):
        """A ready `xyzcyl serve` (xyzcyl.testing.serve) on ``store`` with ``flags``: yields (process, base url,
        seconds to ready); SIGTERM when the block ends (killed if it does not exit in 30 s)."""
        with serve(store, self.log, ["--log-level", "warning", *flags, *self.extra], ready_s=180.0, stop_s=30.0,
                   every=0.1) as server:
            yield server.proc, server.url, server.ready_s


def client(url: str, timeout: float = 120.0, headers: dict | None = None):
    import httpx

    return httpx.Client(base_url=url, timeout=timeout, headers=headers or {})


def new_scene(c, ctx: Ctx, wait: float = 120.0) -> dict:
    r = c.post("/v1/scenes", params={"wait": wait}, files=ctx.files)
    if r.status_code != 201:
        raise RuntimeError(f"POST /v1/scenes?wait answered {r.status_code}: {r.text[:400]}")
    return r.json()


def wait_state(c, sid: str, states: tuple[str, ...], timeout: float = 120.0, every: float = 0.05) -> dict | None:
    deadline = now_s() + timeout
    while now_s() < deadline:
        r = c.get(f"/v1/scenes/{sid}")
        if r.status_code == 200 and r.json()["state"] in states:
            return r.json()
        time.sleep(every)
    return None


def all_records(c) -> list[dict]:
    out, offset = [], 0
    for _ in range(100):                                  # bounded: 100 pages of 1000
        r = c.get("/v1/scenes", params={"offset": offset, "limit": 1000})
        r.raise_for_status()
        page = r.json()
        out += page["scenes"]
        if not page["next"]:
            break
        offset += 1000
    return out


# ----------------------------------------------------------------------------------------------- render load


def render_clients(url: str, sid: str, poses: Poses, clients: int, seconds: float, max_per_client: int,
                   size=(800, 600, "jpeg"), backoff_s: float = 0.0, timeout: float = 60.0, nice: int = 0) -> dict:
    """``clients`` threads, each with its own kept-alive connection, GET .../render with distinct poses until
    ``seconds`` have passed or ``max_per_client`` requests. Latencies of 200s; every other answer counted by
    status, with whether it carried Retry-After; transport errors (time-outs) counted apart. ``nice``: the client
    threads run that much nicer (on this 2-core machine the load generator shares the server's cores; in a
    deployment it runs elsewhere)."""
    import httpx

    w, h, fmt = size
    lat: list[float] = []
    rejected_lat: list[float] = []
    statuses: dict[str, int] = {}
    no_retry_after: dict[str, int] = {}
    transport: dict[str, int] = {}
    bodies: dict[str, str] = {}
    lock = threading.Lock()
    start = threading.Barrier(clients + 1)
    stop_at = [0.0]

    def run():
        if nice:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        with httpx.Client(base_url=url, timeout=timeout) as c:
            c.get("/v2/health/live")
            start.wait()
            for _ in range(max_per_client):
                if now_s() >= stop_at[0]:
                    break
                p = poses.next(w, h, fmt)
                t0 = now_s()
                try:
                    r = c.get(f"/v1/scenes/{sid}/render", params=p)
                except httpx.TransportError as e:
                    with lock:
                        count(transport, type(e).__name__)
                    continue
                dt = now_s() - t0
                with lock:
                    count(statuses, r.status_code)
                    if r.status_code == 200:
                        lat.append(dt)
                    else:
                        rejected_lat.append(dt)
                        bodies.setdefault(str(r.status_code), r.text[:300])
                        if "retry-after" not in r.headers:
                            count(no_retry_after, r.status_code)
                if r.status_code != 200 and backoff_s:
                    time.sleep(backoff_s)

    threads = [threading.Thread(target=run, daemon=True) for _ in range(clients)]
    for t in threads:
        t.start()
    before = load()
    stop_at[0] = now_s() + seconds + 3600          # set for real once everyone is connected
    start.wait(timeout=60)
    t0 = now_s()
    stop_at[0] = t0 + seconds
    for t in threads:
        t.join(max(1.0, seconds + timeout + 30 - (now_s() - t0)))
    wall = now_s() - t0
    stuck = sum(t.is_alive() for t in threads)
    ok = statuses.get("200", 0)
    return {"clients": clients, "seconds": seconds, "size": f"{w}x{h}", "format": fmt, "wall_s": round(wall, 2),
            "requests": sum(statuses.values()) + sum(transport.values()), "ok": ok,
            "requests_per_s": round(ok / wall, 2) if wall else None, "latency": stats(lat),
            "statuses": statuses, "non_200_without_retry_after": no_retry_after, "transport_errors": transport,
            "rejected_latency": stats(rejected_lat), "example_bodies": bodies, "threads_stuck": stuck,
            "load_before": before, "load_after": load()}


class HealthProbe:
    """GET /v2/health/live every ``every`` s on a new connection (as a load balancer's probe), until stopped. The
    probe runs in its own process (this script's ``_probe`` mode): in this one, the load's client threads would hold
    the GIL and add their waits to the figures."""

    def __init__(self, url: str, every: float = 0.5, max_probes: int = 10_000):
        self.url, self.every, self.max = url, every, max_probes
        self.lat: list[float] = []
        self.failures: dict[str, int] = {}

    def __enter__(self):
        self._dir = tempfile.TemporaryDirectory(prefix="xyzcyl_probe_")
        self._stop = Path(self._dir.name) / "stop"
        self._p = subprocess.Popen([sys.executable, __file__, "_probe", str(port_of(self.url)), str(self.every),
                                    str(self.max), str(self._stop)], stdout=subprocess.PIPE, text=True)
        return self

    def __exit__(self, *exc):
        self._stop.touch()
        try:
            out, _ = self._p.communicate(timeout=30)
            doc = json.loads(out)
            self.lat, self.failures = doc["lat"], doc["failures"]
        except (subprocess.TimeoutExpired, ValueError) as e:
            self._p.kill()
            self.failures = {f"probe process: {type(e).__name__}": 1}
        self._dir.cleanup()


    def report(self, limit_s: float = 0.1) -> dict:
        return {"probes": len(self.lat) + sum(self.failures.values()), "every_s": self.every,
                "max_s": round(max(self.lat), 4) if self.lat else None, "p99_s": pct(self.lat, 99),
                "p50_s": pct(self.lat, 50), "over_limit": sum(x >= limit_s for x in self.lat),
                "failures": self.failures}

def _probe_main(port: int, every: float, max_probes: int, stop: Path) -> None:
    """The probe process: GET /v2/health/live over a raw socket (connect + answer) every ``every`` s until the
    file ``stop`` exists (at most ``max_probes``); prints {"lat": [...], "failures": {...}}."""
    lat: list[float] = []
    failures: dict[str, int] = {}
    for _ in range(max_probes):
        if stop.exists():
            break
        t0 = now_s()
        try:
            with socket.create_connection((HOST, port), timeout=5.0) as s:
                s.sendall(f"GET /v2/health/live HTTP/1.1\r\nHost: {HOST}\r\nConnection: close\r\n\r\n".encode())
                data = b""
                while len(data) < 65536:
                    more = s.recv(65536)
                    if not more:
                        break
                    data += more
            dt = now_s() - t0
            status = data.split(b" ", 2)[1].decode() if data.startswith(b"HTTP/1.1 ") else "no answer"
            if status == "200":
                lat.append(dt)
            else:
                count(failures, status)
        except OSError as e:
            count(failures, type(e).__name__)
        time.sleep(max(0.0, every - (now_s() - t0)))
    print(json.dumps({"lat": lat, "failures": failures}))


def reconstruction_loop(url: str, ctx: Ctx, stop: threading.Event, out: list, max_posts: int = 100):
    """POST the rig with ?wait=120 again and again until ``stop`` (bounded by ``max_posts``); each scene is
    deleted when ready so the store stays small."""
    import httpx

    with httpx.Client(base_url=url, timeout=180.0) as c:
        for _ in range(max_posts):
            if stop.is_set():
                break
            t0 = now_s()
            try:
                r = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files)
            except httpx.TransportError as e:
                out.append({"status": type(e).__name__, "s": now_s() - t0})
                continue
            out.append({"status": r.status_code, "s": now_s() - t0,
                        "total": (r.json().get("timings") or {}).get("total") if r.status_code == 201 else None})
            if r.status_code == 201:
                c.delete(f"/v1/scenes/{r.json()['id']}")


def cmd_load(args, ctx: Ctx) -> dict:
    seconds = 5.0 if args.quick else args.seconds
    flags = ["--render-threads", "2", "--render-queue", "8", "--reconstruct-workers", "2",
             "--reconstruct-queue", "2", "--ort-threads", "1"]
    doc: dict = {"flags": flags}
    with ctx.serve(ctx.store("load"), flags) as (proc, url, ready_s):
        doc["server"] = {"pid": proc.pid, "ready_s": round(ready_s, 2)}
        with client(url) as c:
            sid = new_scene(c, ctx)["id"]
        size = (args.width, args.height, args.format)
        render_clients(url, sid, ctx.poses, 2, 3.0 if args.quick else 10.0, 50, size)     # warm-up
        doc["renders_only"] = render_clients(url, sid, ctx.poses, 4, seconds, 100_000, size)
        stop = threading.Event()
        posts: list = []
        recon = [threading.Thread(target=reconstruction_loop, args=(url, ctx, stop, posts), daemon=True)
                 for _ in range(2)]
        for t in recon:
            t.start()
        time.sleep(1.0)                   # both reconstructions under way before the clock starts
        doc["with_2_reconstructions"] = render_clients(url, sid, ctx.poses, 4, seconds, 100_000, size)
        stop.set()
        for t in recon:
            t.join(200)
        ok = [p for p in posts if p["status"] == 201]
        doc["reconstructions"] = {"posts": len(posts), "ready": len(ok),
                                  "statuses": {str(s): sum(p["status"] == s for p in posts)
                                               for s in {p["status"] for p in posts}},
                                  "upload_to_ready": stats([p["s"] for p in ok]),
                                  "worker_total": stats([p["total"] for p in ok if p["total"]])}
        with client(url) as c:
            doc["server"]["rss_mb"] = rss_mb(proc.pid)
            doc["server"]["rejected_total"] = metric(c.get("/metrics").text, "xyzcyl_rejected_total")
    a, b = doc["renders_only"], doc["with_2_reconstructions"]
    errs = lambda d: d["requests"] - d["ok"]
    doc["targets"] = {
        "renders_only_errors": verdict(errs(a), 0, "=="),
        "with_2_reconstructions_errors": verdict(errs(b), 0, "=="),
        "reconstructions_all_ready": verdict(len(posts) - len(ok), 0, "==", "every POST during the load is 201"),
    }
    return doc


# ----------------------------------------------------------------------------------------------- overload


def cmd_overload(args, ctx: Ctx) -> dict:
    seconds = 5.0 if args.quick else args.seconds
    threads, queue, rworkers, rqueue = 2, 4, 1, 2
    capacity = threads + queue
    flags = ["--render-threads", str(threads), "--render-queue", str(queue), "--reconstruct-workers",
             str(rworkers), "--reconstruct-queue", str(rqueue), "--ort-threads", "1", "--retry-after-s", "1"]
    doc: dict = {"flags": flags, "capacity": capacity, "clients": 4 * capacity, "client_nice": args.client_nice,
                 "client_backoff_s": 0.05}
    store = ctx.store("overload")
    with ctx.serve(store, flags) as (proc, url, ready_s):
        doc["server"] = {"pid": proc.pid, "ready_s": round(ready_s, 2)}
        with client(url) as c:
            sid = new_scene(c, ctx)["id"]
        size = (args.width, args.height, args.format)
        render_clients(url, sid, ctx.poses, 2, 2.0, 20, size)                                    # warm-up
        with HealthProbe(url) as probe:
            run = render_clients(url, sid, ctx.poses, 4 * capacity, seconds, 100_000, size, backoff_s=0.05,
                                 timeout=30.0, nice=args.client_nice)
        doc["renders"] = run
        doc["health_live"] = probe.report()
        st = run["statuses"]
        doc["accepted"] = st.get("200", 0)
        doc["rejected"] = {k: v for k, v in st.items() if k != "200"}
        doc["accepted_p99_s"] = run["latency"].get("p99_s")
        # reconstruction burst: 3 x (workers + queue) posts at once
        n = 3 * (rworkers + rqueue)
        doc["reconstruct_burst"] = burst(url, ctx, n, rworkers + rqueue, store)
        with client(url) as c:
            m = c.get("/metrics").text
            doc["server"]["rejected_total"] = metric(m, "xyzcyl_rejected_total")
    other5 = {k: v for k, v in st.items() if k.startswith("5") and k != "503"}
    bad = {k: v for k, v in st.items() if k not in ("200", "429", "503")}
    b = doc["reconstruct_burst"]
    doc["targets"] = {
        "non_2xx_only_429_503": verdict(sum(bad.values()), 0, "==", f"other statuses: {bad}"),
        "other_5xx": verdict(sum(other5.values()), TARGETS["overload_other_5xx"], "=="),
        "rejections_with_retry_after": verdict(sum(run["non_200_without_retry_after"].values()), 0, "=="),
        "client_timeouts": verdict(sum(run["transport_errors"].values()), TARGETS["overload_timeouts"], "=="),
        "health_live_max_s": verdict(doc["health_live"]["max_s"], TARGETS["overload_health_max_s"], "<"),
        "health_live_failures": verdict(sum(doc["health_live"]["failures"].values()), 0, "=="),
        "some_rejected_at_4x": verdict(sum(doc["rejected"].values()), 1, ">=", "4x capacity must be shed"),
        "burst_accepted_exactly_capacity": verdict(b["accepted"], b["capacity"], "=="),
        "burst_rest_503": verdict(b["statuses"].get("503", 0), n - b["capacity"], "=="),
        "burst_accepted_all_ready": verdict(b["ready"], b["capacity"], "=="),
        "burst_tmp_empty": verdict(b["tmp_left"], 0, "=="),
    }
    return doc


def burst(url: str, ctx: Ctx, n: int, capacity: int, store: Path) -> dict:
    """``n`` POST /v1/scenes at once (a barrier, one connection each): how many 202 vs 503 (with Retry-After)."""
    import httpx

    results: list = [None] * n
    gate = threading.Barrier(n)

    def post(i):
        with httpx.Client(base_url=url, timeout=120.0) as c:
            c.get("/v2/health/live")
            gate.wait(timeout=60)
            r = c.post("/v1/scenes", files=ctx.files)
            results[i] = (r.status_code, r.headers.get("retry-after"), r.json().get("id") if r.status_code == 202
                          else (r.json().get("error") or {}).get("code"))

    ts = [threading.Thread(target=post, args=(i,), daemon=True) for i in range(n)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(180)
    statuses: dict[str, int] = {}
    for r in results:
        count(statuses, r[0] if r else "none")
    ids = [r[2] for r in results if r and r[0] == 202]
    ready = 0
    with client(url) as c:
        for sid in ids:
            rec = wait_state(c, sid, ("ready", "failed"), timeout=120 * capacity)
            ready += bool(rec and rec["state"] == "ready")
    time.sleep(0.5)
    tmp_left = len(os.listdir(store / "tmp"))
    return {"posts": n, "capacity": capacity, "accepted": statuses.get("202", 0), "statuses": statuses,
            "rejected_without_retry_after": sum(1 for r in results if r and r[0] == 503 and not r[1]),
            "ready": ready, "tmp_left": tmp_left}


# ----------------------------------------------------------------------------------------------- limits


def raw_over_limit(port: int, pid: int, limit: int, chunked: bool, path: str = "/v1/scenes",
                   seconds: float = 20.0, headers: dict | None = None, headers_alone_s: float = 0.0) -> dict:
    """A POST whose body is limit+1 bytes (Content-Length) or unbounded (chunked), sent in 64 KiB pieces while
    watching for the answer. Reports the status and the body bytes the client had sent when it came: an upper bound
    on what the server read (the rest of them may still sit in the socket buffers, ~200 kB on loopback). With
    ``headers_alone_s`` > 0, the headers are first sent alone and the answer awaited that long: a 413 then proves
    that the server answered having read none of the body."""
    s = socket.create_connection((HOST, port), timeout=10)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 16)
    boundary = "x" * 16
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    head = (f"POST {path} HTTP/1.1\r\nHost: {HOST}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\n"
            + extra + ("Transfer-Encoding: chunked\r\n" if chunked else f"Content-Length: {limit + 1}\r\n") + "\r\n")
    total = 4 * limit if chunked else limit + 1
    # the body is a well-formed multipart file part that never ends, so the parser reads on until the limit
    prefix = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"CAM_FRONT\"; filename=\"a.png\"\r\n"
              "Content-Type: image/png\r\n\r\n").encode()
    piece = b"x" * (1 << 16)
    t0 = now_s()
    s.sendall(head.encode())
    answer = b""
    headers_only = None
    if headers_alone_s > 0:
        rd, _, _ = select.select([s], [], [], headers_alone_s)
        if rd:
            answer = s.recv(65536)
            headers_only = {"answered_s": round(now_s() - t0, 4), "body_bytes_sent": 0}
    s.setblocking(False)
    sent, out, closed_early = 0, b"", None
    pending, done, head_n = 0, 0, 0
    if answer:
        total = 0
    deadline = t0 + seconds
    while now_s() < deadline and b"\r\n\r\n" not in answer:
        if not out and sent < total:
            data = (prefix + piece)[:len(piece)] if sent == 0 else piece
            n = min(len(data), total - sent)
            head_n = len(f"{n:x}\r\n") if chunked else 0       # the chunk's framing before its data
            out = (f"{n:x}\r\n".encode() + data[:n] + b"\r\n") if chunked else data[:n]
            pending, done = n, 0
        rd, wr, _ = select.select([s], [s] if out else [], [], 1.0)
        if rd:
            try:
                data = s.recv(65536)
            except OSError as e:
                closed_early = type(e).__name__
                break
            answer += data
            if not data or b"\r\n\r\n" in answer:
                break
        elif wr:
            try:
                k = s.send(out)
            except OSError as e:
                closed_early = type(e).__name__
                break
            out = out[k:]
            done += k
            if not out:
                sent += pending
                done = 0
        elif sent >= total and not out:
            continue
    t_answer = now_s() - t0
    # the data bytes of a piece the answer interrupted count too (the server may have read them all)
    sent += min(max(done - head_n, 0), pending) if out else 0
    s.setblocking(True)
    s.settimeout(3)
    with contextlib.suppress(OSError):
        while b"\r\n\r\n" in answer and len(answer) < 65536:
            more = s.recv(65536)
            if not more:
                break
            answer += more
    s.close()
    status = int(answer.split(b" ", 2)[1]) if answer.startswith(b"HTTP/1.1 ") else None
    body = answer.split(b"\r\n\r\n", 1)[1] if b"\r\n\r\n" in answer else b""
    code = None
    with contextlib.suppress(ValueError, AttributeError, TypeError, IndexError):
        code = json.loads(body[body.index(b"{"):body.rindex(b"}") + 1])["error"]["code"]
    return {"framing": "chunked" if chunked else "content-length", "limit": limit,
            "declared": None if chunked else limit + 1, "status": status, "code": code,
            "seconds_to_answer": round(t_answer, 4), "answered_on_headers_alone": headers_only,
            "body_bytes_sent_before_answer": sent, "send_error": closed_early}


def png_bomb(width: int = 30000, height: int = 30000) -> bytes:
    """A valid-looking PNG of ~60 bytes whose header says width x height 8-bit RGB (2.7 GB decoded)."""
    return png_header_only(width, height)


def jpeg_bomb(width: int = 30000, height: int = 30000) -> bytes:
    """A tiny real JPEG whose SOF0 header is patched to width x height."""
    import cv2

    _ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    b = bytearray(buf.tobytes())
    i = b.index(b"\xff\xc0")
    b[i + 5:i + 9] = struct.pack(">HH", height, width)
    return bytes(b)


def post_bomb(url: str, ctx: Ctx, pid: int, data: bytes, media: str) -> dict:
    files = [f for f in ctx.files]
    name = ctx.rig["cameras"][0]["name"]
    files = [(k, (v[0], data, media)) if k == name else (k, v) for k, v in files]
    rss0, hwm0 = rss_mb(pid), rss_mb(pid, "VmHWM")
    with client(url) as c:
        t0 = now_s()
        r = c.post("/v1/scenes", files=files)
        dt = now_s() - t0
    time.sleep(0.3)
    err = r.json().get("error") or {} if r.headers.get("content-type", "").startswith("application/json") else {}
    return {"file_bytes": len(data), "media": media, "status": r.status_code, "code": err.get("code"),
            "field": err.get("field"), "message": err.get("message"), "seconds": round(dt, 4),
            "server_rss_before_mb": rss0, "server_rss_after_mb": rss_mb(pid),
            "server_peak_rss_before_mb": hwm0, "server_peak_rss_after_mb": rss_mb(pid, "VmHWM"),
            "worker_peak_rss_mb": [rss_mb(p, "VmHWM") for p in worker_pids(pid)]}


def rig_17(ctx: Ctx) -> list:
    """The rig with 17 copies of its first camera (one more than max_cameras), each sending that camera's JPEG."""
    doc = json.loads(ctx.rig_json.read_text())
    base = doc["cameras"][0]
    doc["cameras"] = [{**base, "name": f"CAM_{i:02d}", "image": f"CAM_{i:02d}.jpg"} for i in range(17)]
    return rig_files(doc, rig_json=ctx.rig_json)


def ply_bomb(path: Path, n: int = 10**9) -> Path:
    props = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
    head += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    path.write_bytes(head.encode() + np.zeros(len(props) * 4, np.float32).tobytes())
    return path


def case_ply(ctx: Ctx) -> dict:
    path = ply_bomb(ctx.work / "bomb.ply")
    out: dict = {"file_bytes": path.stat().st_size, "claims_vertices": 10**9,
                 "note": "the service has no PLY upload endpoint (scenes are only made by reconstruction), so the "
                         "reader is checked through the CLI and the library"}
    argv = [str(XYZCYL), "render", str(path), "--width", "64", "--height", "48", "--K", "50", "50", "31.5", "23.5",
            "--cam-to-world", *["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"], "--out", str(ctx.work / "bomb.png")]
    t0 = now_s()
    p = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    out["cli"] = {"exit": p.returncode, "seconds": round(now_s() - t0, 3), "stderr": p.stderr.strip()[-300:]}
    from xyzcyl.runtime.render.gaussians import GaussianError, Gaussians

    rss0 = rss_mb(os.getpid())
    t0 = now_s()
    try:
        Gaussians.load_ply(path)
        out["load_ply"] = {"raised": None}
    except Exception as e:  # noqa: BLE001 - the type is the finding
        out["load_ply"] = {"raised": type(e).__name__, "is_GaussianError": isinstance(e, GaussianError),
                           "message": str(e)[:300]}
    out["load_ply"] |= {"seconds": round(now_s() - t0, 4), "rss_growth_mb": round(rss_mb(os.getpid()) - rss0, 1)}
    return out


def slowloris(url: str, pid: int, sid: str, ctx: Ctx, k: int, seconds: float, size,
              headers: dict | None = None) -> dict:
    """``k`` sockets each send a partial request (request line, then one header byte) one byte per second for
    ``seconds``; meanwhile one client renders. Also one socket that connects and sends nothing. Reports the
    render latency before and during, health, how many slow sockets the server closed and when."""
    import httpx

    w, h, fmt = size
    with httpx.Client(base_url=url, timeout=60, headers=headers or {}) as c:
        def renders(n: int, until: float) -> tuple[list[float], dict]:
            lat, errs = [], {}
            for _ in range(n):
                if now_s() >= until:
                    break
                t0 = now_s()
                r = c.get(f"/v1/scenes/{sid}/render", params=ctx.poses.next(w, h, fmt))
                if r.status_code == 200:
                    lat.append(now_s() - t0)
                else:
                    count(errs, r.status_code)
            return lat, errs

        base, e0 = renders(15, now_s() + 60)
        fd0 = len(fds(pid))
        payload = b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 10_000
        t_start = now_s()                   # closing times are counted from the connections
        socks = [socket.create_connection((HOST, port_of(url)), timeout=5) for _ in range(k)]
        idle = socket.create_connection((HOST, port_of(url)), timeout=5)
        time.sleep(0.5)                      # the server accepts them
        fd1 = len(fds(pid))
        closed: dict[int, float] = {}
        idle_closed = [None]
        stop = threading.Event()

        def drip():
            for i in range(int(seconds) + 1):
                if stop.is_set():
                    break
                for j, s in enumerate(socks):
                    if j in closed:
                        continue
                    try:
                        s.send(payload[i:i + 1])
                    except OSError:
                        closed[j] = round(now_s() - t_start, 2)
                live = [s for j, s in enumerate(socks) if j not in closed] + ([idle] if idle_closed[0] is None
                                                                                 else [])
                rd, _, _ = select.select(live, [], [], 0)
                for s in rd:
                    try:
                        data = s.recv(4096)
                    except OSError:
                        data = b""
                    if s is idle:
                        idle_closed[0] = (round(now_s() - t_start, 2), data[:40].decode(errors="replace"))
                    else:
                        closed[socks.index(s)] = round(now_s() - t_start, 2)
                stop.wait(max(0.0, t_start + i + 1 - now_s()))

        dripper = threading.Thread(target=drip, daemon=True)
        dripper.start()
        with HealthProbe(url) as probe:
            during, e1 = renders(100_000, t_start + seconds)
        dripper.join(seconds + 10)
        stop.set()
        still_open = k - len(closed)
        for s in socks + [idle]:
            s.close()
        return {"slow_sockets": k, "seconds": seconds, "bytes_per_socket": min(int(seconds) + 1, len(payload)),
                "render": f"{w}x{h} {fmt}", "baseline": stats(base), "during": stats(during),
                "p50_ratio": round(float(np.median(during)) / float(np.median(base)), 2) if base and during else None,
                "render_errors": {**e0, **e1}, "health_live": probe.report(),
                "server_fds_before": fd0, "server_fds_with_slow_sockets": fd1,
                "slow_sockets_closed_by_server": len(closed), "slow_sockets_still_open_at_end": still_open,
                "closed_at_s": sorted(closed.values())[:5], "last_closed_at_s": max(closed.values(), default=None),
                "idle_socket_closed": idle_closed[0]}


def cmd_limits(args, ctx: Ctx) -> dict:
    limit = 1 << 20
    k, secs = (10, 4.0) if args.quick else (args.slow_sockets, args.slow_seconds)
    head_timeout = 2.0 if args.quick else args.header_timeout
    flags = ["--max-body-bytes", str(limit), "--render-threads", "2", "--ort-threads", "1", "--header-timeout-s",
             str(head_timeout)]
    doc: dict = {"flags": flags}
    with ctx.serve(ctx.store("limits"), flags) as (proc, url, ready_s):
        port, pid = port_of(url), proc.pid
        doc["server"] = {"pid": pid, "ready_s": round(ready_s, 2)}
        doc["body_limit"] = {"content_length_headers_alone": raw_over_limit(port, pid, limit, False,
                                                                            headers_alone_s=2.0),
                             "content_length": raw_over_limit(port, pid, limit, False),
                             "chunked": raw_over_limit(port, pid, limit, True)}
        doc["png_bomb"] = post_bomb(url, ctx, pid, png_bomb(), "image/png")
        doc["jpeg_bomb"] = post_bomb(url, ctx, pid, jpeg_bomb(), "image/jpeg")
        with client(url) as c:
            r = c.post("/v1/scenes", files=rig_17(ctx))
            doc["cameras_17"] = {"status": r.status_code, **(r.json().get("error") or {})}
            sid = new_scene(c, ctx)["id"]
        doc["slowloris"] = slowloris(url, pid, sid, ctx, k, secs, (args.width, args.height, args.format))
        with client(url) as c:
            doc["alive_after"] = c.get("/v2/health/live").status_code
    doc["ply_1e9_vertices"] = case_ply(ctx)
    ca, cl, ch = (doc["body_limit"][k] for k in ("content_length_headers_alone", "content_length", "chunked"))
    sl = doc["slowloris"]
    doc["targets"] = {
        "content_length_413_on_headers_alone": verdict(ca["status"], 413, "==", "no body byte sent"),
        "content_length_413": verdict(cl["status"], 413, "=="),
        "content_length_413_before_body_sent": verdict(cl["body_bytes_sent_before_answer"], limit + 1, "<",
                                                       "body bytes sent when the 413 came (an upper bound on those "
                                                       "read) < the declared body"),
        "chunked_413": verdict(ch["status"], 413, "=="),
        "chunked_413_soon_after_limit": verdict(ch["body_bytes_sent_before_answer"], limit + (1 << 20), "<",
                                                "answered within 1 MiB past the limit"),
        "png_bomb_422": verdict(doc["png_bomb"]["status"], 422, "=="),
        "png_bomb_not_decoded": verdict(round(doc["png_bomb"]["server_peak_rss_after_mb"]
                                              - doc["png_bomb"]["server_peak_rss_before_mb"], 1), 50, "<",
                                        "server peak RSS growth, MB (decoding would need 2,700 MB)"),
        "jpeg_bomb_422": verdict(doc["jpeg_bomb"]["status"], 422, "=="),
        "cameras_17_422": verdict(doc["cameras_17"]["status"], 422, "=="),
        "ply_1e9_cli_exit_2": verdict(doc["ply_1e9_vertices"]["cli"]["exit"], 2, "=="),
        "ply_1e9_GaussianError": verdict(doc["ply_1e9_vertices"]["load_ply"].get("raised"), "GaussianError", "=="),
        "ply_1e9_fast_s": verdict(doc["ply_1e9_vertices"]["load_ply"]["seconds"], 1.0, "<"),
        "slowloris_renders_ok": verdict(sum(sl["render_errors"].values()), 0, "=="),
        "slowloris_p50_ratio": verdict(sl["p50_ratio"], 2.0, "<", "render p50 during / before"),
        "slowloris_health_max_s": verdict(sl["health_live"]["max_s"], 0.1, "<"),
        "slowloris_sockets_closed": verdict(sl["slow_sockets_closed_by_server"], k, "==",
                                            f"by the header timeout of {head_timeout} s"),
        "slowloris_closed_in_time_s": verdict(sl["last_closed_at_s"], head_timeout + 1.5, "<="),
        "idle_socket_closed": verdict(sl["idle_socket_closed"] is not None, True, "=="),
    }
    return doc


# ----------------------------------------------------------------------------------------------- crash


def check_store(url: str, store: Path, posted: list[str]) -> dict:
    """Every record after a restart: ready ones have a whole scene folder (scene.json parses, scene.ply loads) and
    render; none is queued/running; the posted ones are ready or failed ``interrupted``; no stray folders; tmp/
    empty."""
    from xyzcyl.runtime.render.gaussians import Gaussians

    problems: list[str] = []
    states: dict[str, int] = {}
    with client(url) as c:
        recs = all_records(c)
        by_id = {r["id"]: r for r in recs}
        for r in recs:
            count(states, r["state"] if r["state"] != "failed" else f"failed:{(r['error'] or {}).get('code')}")
            if r["state"] in ("queued", "running"):
                problems.append(f"{r['id']} is {r['state']} after the restart")
            if r["state"] == "ready":
                d = store / "scenes" / r["id"]
                try:
                    json.loads((d / "scene.json").read_text())
                    Gaussians.load_ply(d / "scene.ply")
                except Exception as e:  # noqa: BLE001
                    problems.append(f"{r['id']}: ready but its folder is not whole: {type(e).__name__}: {e}")
                q = c.get(f"/v1/scenes/{r['id']}/render", params={"camera": "CAM_FRONT", "width": 160,
                                                                  "format": "jpeg"})
                if q.status_code != 200:
                    problems.append(f"{r['id']}: ready but render answered {q.status_code}")
        for sid in posted:
            r = by_id.get(sid)
            if r is None:
                problems.append(f"{sid} was accepted (202) but has no record after the restart")
            elif not (r["state"] == "ready" or (r["state"] == "failed"
                                                 and (r["error"] or {}).get("code") == "interrupted")):
                problems.append(f"{sid} is {r['state']} {r['error']}")
    ready = {r["id"] for r in recs if r["state"] == "ready"}
    folders = {p.name for p in (store / "scenes").iterdir()}
    if folders - ready:
        problems.append(f"scene folders without a ready record: {sorted(folders - ready)}")
    tmp = os.listdir(store / "tmp")
    if tmp:
        problems.append(f"tmp/ not empty: {tmp[:5]}")
    for p in (store / "records").iterdir():
        if p.suffix != ".json" or p.name.startswith("."):
            problems.append(f"stray file in records/: {p.name}")
            continue
        try:
            json.loads(p.read_text())
        except ValueError:
            problems.append(f"records/{p.name} does not parse")
    return {"records": len(recs), "states": states, "problems": problems,
            "posted": {sid: (by_id.get(sid) or {}).get("state") for sid in posted}}


MODES = ("random", "writing", "random", "written")


def _wait_for_scene_files(tmp: Path, mode: str, timeout: float) -> str | None:
    """Poll (every 2 ms, up to ``timeout`` s) the store's tmp/ for a reconstruction's scene folder: ``writing``: the
    worker's temporary sibling ``.scene.*`` (files being written); ``written``: the finished ``scene/`` not yet
    moved into scenes/. Returns what was seen (None on time-out)."""
    deadline = now_s() + timeout
    while now_s() < deadline:
        with contextlib.suppress(OSError):
            for work in tmp.iterdir():
                for e in work.iterdir():
                    if (mode == "writing" and e.name.startswith(".scene.")) or (mode == "written"
                                                                                 and e.name == "scene"):
                        with contextlib.suppress(OSError):
                            files = {x.name: x.stat().st_size for x in e.iterdir()}
                            if files:             # a file of the scene is being (or has been) written
                                return f"{e.name}/ with {files}"
        time.sleep(0.002)
    return None


def crash_kill_loop(ctx: Ctx, iterations: int, window: tuple[float, float], seed: int = 14) -> dict:
    """``iterations`` rounds of: start the server on the same store, post two rigs (one runs, one waits), kill -9 the
    server, and check the store after the next start. The kill comes at a random time, or (every other round) the
    moment the worker is writing the scene folder, or has just written it (before it is moved into scenes/)."""
    rng = random.Random(seed)
    store = ctx.store("crash")
    flags = ["--reconstruct-workers", "1", "--reconstruct-queue", "4", "--ort-threads", "1",
             "--render-threads", "1"]
    rounds, orphans_total = [], []
    for i in range(iterations + 1):
        with ctx.serve(store, flags) as (proc, url, ready_s):
            rnd: dict = {"iteration": i, "ready_s": round(ready_s, 2)}
            if i > 0:                     # check what the previous kill left, on the restarted server
                rnd["check"] = check_store(url, store, rounds[-1]["posted"])
            if i == iterations:
                rounds.append(rnd)
                break
            posted = []
            with client(url) as c:
                for _ in range(2):        # one runs, one waits in the queue
                    r = c.post("/v1/scenes", files=ctx.files)
                    if r.status_code == 202:
                        posted.append(r.json()["id"])
                mode = MODES[i % len(MODES)]
                t_post = now_s()
                if mode == "random":
                    time.sleep(rng.uniform(*window))
                else:                     # the moment the worker writes the scene / has written it (not yet moved)
                    seen = _wait_for_scene_files(store / "tmp", mode, 60.0)
                    time.sleep(rng.uniform(0.0, 0.02))
                delay = now_s() - t_post
                states = {}
                if mode == "random":          # (not when aiming at the write: the kill must come at once)
                    with contextlib.suppress(Exception):
                        for sid in posted:
                            states[sid] = c.get(f"/v1/scenes/{sid}", timeout=2).json()["state"]
            kids = children(proc.pid)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
            time.sleep(2.0)
            left = [p for p in kids if alive(p)]
            orphans_total += left
            kill_all(left)
            rnd |= {"posted": posted, "mode": mode, "saw": None if mode == "random" else seen,
                    "kill_after_s": round(delay, 3), "states_just_before_kill": states,
                    "children_alive_2s_after_kill": len(left)}
            rounds.append(rnd)
    problems = [p for r in rounds if "check" in r for p in r["check"]["problems"]]
    finals: dict[str, int] = {}
    for r in rounds:
        if "check" in r:
            for st in r["check"]["posted"].values():
                count(finals, st)
    modes: dict[str, int] = {}
    for r in rounds:
        if "mode" in r:
            count(modes, f"{r['mode']}{'' if r['mode'] == 'random' or r['saw'] else ' (not seen)'}")
    return {"iterations": iterations, "kill_window_s": list(window), "kill_modes": modes, "rounds": rounds,
            "posted_outcomes": finals, "problems": problems, "orphaned_children": len(orphans_total)}


def crash_worker(ctx: Ctx) -> dict:
    flags = ["--reconstruct-workers", "1", "--reconstruct-queue", "2", "--ort-threads", "1"]
    with ctx.serve(ctx.store("worker"), flags) as (proc, url, _ready_s), client(url) as c:
        r = c.post("/v1/scenes", files=ctx.files)
        sid = r.json()["id"]
        rec = wait_state(c, sid, ("running", "ready", "failed"), 60, 0.02)
        time.sleep(0.3)
        victims = worker_pids(proc.pid)
        t0 = now_s()
        kill_all(victims)
        rec = wait_state(c, sid, ("ready", "failed"), 60, 0.02)
        t_failed = now_s() - t0
        live = c.get("/v2/health/live")
        t1 = now_s()
        nxt = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files)
        return {"killed_pids": victims, "state_when_killed": "running", "final": rec and rec["state"],
                "error": rec and rec["error"], "seconds_to_failed": round(t_failed, 3),
                "live_after": live.status_code, "next_post": nxt.status_code,
                "next_post_s": round(now_s() - t1, 2), "new_worker": worker_pids(proc.pid)}


def crash_disk_full(ctx: Ctx, size_mb: int, posts: int) -> dict:
    mnt = ctx.work / "tmpfs"
    mnt.mkdir(exist_ok=True)
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(mnt)], capture_output=True,
                       text=True, check=False)
    if p.returncode != 0:
        return {"skipped": f"mount -t tmpfs failed: {p.stderr.strip()}"}
    store = mnt / "store"
    flags = ["--reconstruct-workers", "1", "--reconstruct-queue", "2", "--ort-threads", "1"]
    out: dict = {"tmpfs_mb": size_mb, "posts": []}
    try:
        with ctx.serve(store, flags) as (_proc, url, _ready_s), client(url) as c:
            for _ in range(posts):
                t0 = now_s()
                r = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files)
                err = (r.json().get("error") or {}) if r.status_code >= 400 else {}
                out["posts"].append({"status": r.status_code, "code": err.get("code") or r.json().get("state"),
                                     "message": err.get("message"), "s": round(now_s() - t0, 2),
                                     "df_used_mb": round(_used_mb(mnt), 1)})
            time.sleep(0.5)
            out["live_after"] = c.get("/v2/health/live").status_code
            out["check"] = check_store(url, store, [])
            out["render_after"] = [c.get(f"/v1/scenes/{r['id']}/render", params={"camera": "CAM_FRONT", "width": 160})
                                   .status_code for r in all_records(c) if r["state"] == "ready"]
            out["queue_alive"] = _queue_alive(c, ctx)
        with ctx.serve(store, flags) as (_proc, url, _ready_s):
            out["after_restart"] = check_store(url, store, [])
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True, check=False)
    return out


def _used_mb(path: Path) -> float:
    st = os.statvfs(path)
    return (st.f_blocks - st.f_bfree) * st.f_frsize / 2**20


def _queue_alive(c, ctx: Ctx) -> dict:
    """Free the store and post once more: the reconstruction queue still runs jobs after the disk was full."""
    for r in all_records(c):
        c.delete(f"/v1/scenes/{r['id']}")
    r = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files)
    return {"status": r.status_code, "state": r.json().get("state") if r.status_code < 400 else r.text[:200]}


def noise_rig(ctx: Ctx) -> tuple[bytes, str]:
    """A multipart body of the rig with incompressible 800x450 PNGs (~1.1 MB each: Starlette spools each part
    over 1 MiB to a temporary file on disk)."""
    import cv2

    rng = np.random.default_rng(0)
    noise = {cam["name"]: cv2.imencode(".png", rng.integers(0, 256, (cam["height"], cam["width"], 3),
                                                            dtype=np.uint8))[1].tobytes()
             for cam in ctx.rig["cameras"]}
    body, content_type = multipart_body(rig_files(images=noise, rig_json=ctx.rig_json))
    return body, content_type.partition("boundary=")[2]


def disconnect_upload(port: int, pid: int, store: Path, body: bytes, boundary: str, fraction: float,
                      headers: dict | None = None) -> dict:
    """Send ``fraction`` of a multipart upload (Content-Length of the whole), close the socket, and watch the
    store's tmp/ and the server's open files for up to 5 s."""
    s = socket.create_connection((HOST, port), timeout=10)
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    s.sendall(f"POST /v1/scenes HTTP/1.1\r\nHost: {HOST}\r\nContent-Type: multipart/form-data; boundary={boundary}"
              f"\r\n{extra}Content-Length: {len(body)}\r\n\r\n".encode())
    cut = int(len(body) * fraction)
    s.sendall(body[:cut])
    time.sleep(0.5)
    during = {"tmp": len(os.listdir(store / "tmp")), "deleted_fds": sum("(deleted)" in f for f in fds(pid))}
    s.close()
    deadline = now_s() + 5.0
    after = None
    while now_s() < deadline:                  # bounded: up to 5 s for the server to notice and clean up
        time.sleep(0.1)
        after = {"tmp": len(os.listdir(store / "tmp")), "deleted_fds": sum("(deleted)" in f for f in fds(pid))}
        if after == {"tmp": 0, "deleted_fds": 0}:
            break
    return {"sent_bytes": cut, "body_bytes": len(body), "during": during, "after": after,
            "after_s": round(5.0 - (deadline - now_s()), 2)}


def crash_disconnect(ctx: Ctx, repeats: int) -> dict:
    body, boundary = noise_rig(ctx)
    store = ctx.store("disconnect")
    with ctx.serve(store, ["--ort-threads", "1"]) as (proc, url, _ready_s):
        port, pid = port_of(url), proc.pid
        fd0 = len(fds(pid))
        runs = [disconnect_upload(port, pid, store, body, boundary, f) for f in
                ([0.3, 0.6, 0.9] * repeats)[: max(3, 3 * repeats)]]
        time.sleep(0.5)
        with client(url) as c:
            live = c.get("/v2/health/live").status_code
            nxt = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files).status_code
            m = c.get("/metrics").text
        return {"uploads_cut": len(runs), "runs": runs, "server_fds_before": fd0, "server_fds_after": len(fds(pid)),
                "deleted_fds_left": [f for f in fds(pid) if "(deleted)" in f], "tmp_left": os.listdir(store / "tmp"),
                "live_after": live, "next_post": nxt,
                "requests_500_on_post": sum(float(line.rsplit(" ", 1)[1]) for line in m.splitlines()
                                            if line.startswith("xyzcyl_http_requests_total{") and 'status="500"' in line
                                            and 'method="POST"' in line)}


def cmd_crash(args, ctx: Ctx) -> dict:
    iters = 2 if args.quick else args.iterations
    doc: dict = {}
    doc["kill_server"] = crash_kill_loop(ctx, iters, (0.0, args.kill_window))
    doc["kill_worker"] = crash_worker(ctx)
    doc["disk_full"] = crash_disk_full(ctx, args.tmpfs_mb, 3 if args.quick else 5)
    doc["client_disconnect"] = crash_disconnect(ctx, 1 if args.quick else 3)
    ks, kw, df, cd = doc["kill_server"], doc["kill_worker"], doc["disk_full"], doc["client_disconnect"]
    df_status = {p["status"] for p in df.get("posts", [])}
    doc["targets"] = {
        "kill9_no_corrupt_or_half_visible": verdict(len(ks["problems"]), 0, "=="),
        "kill9_no_orphaned_workers": verdict(ks["orphaned_children"], 0, "==",
                                             "worker processes still alive 2 s after the server was killed"),
        "worker_kill_failed_worker_crashed": verdict((kw["error"] or {}).get("code"), "worker_crashed", "=="),
        "worker_kill_api_live": verdict(kw["live_after"], 200, "=="),
        "worker_kill_next_post_201": verdict(kw["next_post"], 201, "=="),
        "disk_full_only_201_507": verdict(sorted(df_status - {201, 507}), [], "==", f"statuses {sorted(df_status)}"),
        "disk_full_some_507": verdict(507 in df_status, True, "=="),
        "disk_full_nothing_corrupt": verdict(len((df.get("check") or {}).get("problems", ["no check"])), 0, "=="),
        "disk_full_alive": verdict(df.get("live_after"), 200, "=="),
        "disk_full_queue_alive": verdict((df.get("queue_alive") or {}).get("status"), 201, "=="),
        "disconnect_tmp_empty": verdict(len(cd["tmp_left"]), 0, "=="),
        "disconnect_no_deleted_fds": verdict(len(cd["deleted_fds_left"]), 0, "=="),
        "disconnect_fds_flat": verdict(cd["server_fds_after"] - cd["server_fds_before"], 2, "<="),
        "disconnect_next_post_201": verdict(cd["next_post"], 201, "=="),
    }
    return doc


# ----------------------------------------------------------------------------------------------- soak


def cmd_soak(args, ctx: Ctx) -> dict:
    n, warm = (300, 50) if args.quick else (args.renders, 200)
    w, h, fmt = 320, 240, "jpeg"
    flags = ["--render-threads", "2", "--ort-threads", "1"]
    doc: dict = {"flags": flags, "renders": n, "warmup": warm, "size": f"{w}x{h}", "format": fmt}
    with ctx.serve(ctx.store("soak"), flags) as (proc, url, _ready_s), client(url) as c:
        pid = proc.pid
        sid = new_scene(c, ctx)["id"]
        errors: dict[str, int] = {}
        lat: list[float] = []
        nbytes = 0
        for _ in range(warm):
            c.get(f"/v1/scenes/{sid}/render", params=ctx.poses.next(w, h, fmt))
        rss0, fd0 = rss_mb(pid), len(fds(pid))
        series = [{"i": 0, "rss_mb": rss0, "fds": fd0}]
        deadline = now_s() + args.soak_max_s
        t0 = now_s()
        i = 0
        for i in range(1, n + 1):
            if now_s() > deadline:
                break
            q0 = now_s()
            r = c.get(f"/v1/scenes/{sid}/render", params=ctx.poses.next(w, h, fmt))
            if r.status_code == 200:
                lat.append(now_s() - q0)
                nbytes += len(r.content)
            else:
                count(errors, r.status_code)
            if i % max(1, n // 20) == 0:
                series.append({"i": i, "rss_mb": rss_mb(pid), "fds": len(fds(pid)), "t_s": round(now_s() - t0, 1)})
        m = c.get("/metrics").text
        doc["run"] = {"done": i, "wall_s": round(now_s() - t0, 1), "errors": errors, "latency": stats(lat),
                      "bytes_mean": round(nbytes / max(1, len(lat))),
                      "render_cache_misses": metric(m, 'xyzcyl_render_cache_total{result="miss"}')}
        fd_series = [s["fds"] for s in series]
        doc["rss_after_warmup_mb"], doc["rss_end_mb"] = rss0, rss_mb(pid)
        doc["rss_growth_mb"] = round(doc["rss_end_mb"] - rss0, 1)
        doc["render_cache_holds_at_most_mb"] = round(min(64 * 2**20, nbytes) / 2**20, 1)
        doc["fds"] = {"after_warmup": fd0, "end": fd_series[-1], "min": min(fd_series), "max": max(fd_series)}
        doc["series"] = series
    doc["eviction_count"] = eviction(ctx, "count")
    doc["eviction_bytes"] = eviction(ctx, "bytes")
    ec, eb = doc["eviction_count"], doc["eviction_bytes"]
    doc["targets"] = {
        "renders_done": verdict(doc["run"]["done"], n, ">=", "all renders ran within --soak-max-s"),
        "renders_errors": verdict(sum(doc["run"]["errors"].values()), 0, "=="),
        "rss_growth_mb": verdict(doc["rss_growth_mb"], TARGETS["rss_growth_mb"], "<",
                                 None if n == 10_000 else f"over {n} renders, not 10,000"),
        "fds_flat": verdict(doc["fds"]["max"] - doc["fds"]["min"], 2, "<=", "max - min open fds over the run"),
        "eviction_count_kept": verdict(sorted(ec["kept"]), sorted(ec["expected"]), "=="),
        "eviction_bytes_kept": verdict(sorted(eb["kept"]), sorted(eb["expected"]), "=="),
        "eviction_bytes_within_quota": verdict(eb["store_bytes"], eb["quota_bytes"], "<="),
    }
    return doc


def eviction(ctx: Ctx, kind: str) -> dict:
    """Post 6 rigs one after the other (touching the first scene with a render after the third post, so LRU is
    not FIFO) under --max-scenes 3, or --max-store-bytes of 2.5 scenes: the scenes kept must be the most recently
    used ones, as many as the quota allows."""
    scene_bytes = None
    if kind == "bytes":                                 # one scene's size decides the quota
        with ctx.serve(ctx.store("evict-probe"), ["--ort-threads", "1"]) as (_proc, url, _), client(url) as c:
            scene_bytes = new_scene(c, ctx)["bytes"]
        quota = int(2.5 * scene_bytes)
        flags, keep = ["--max-store-bytes", str(quota)], 2
    else:
        quota, flags, keep = 3, ["--max-scenes", "3"], 3
    store = ctx.store(f"evict-{kind}")
    used: list[str] = []                                # least recently used first
    with ctx.serve(store, flags + ["--ort-threads", "1"]) as (_proc, url, _), client(url) as c:
        for i in range(6):
            sid = new_scene(c, ctx)["id"]
            used.append(sid)
            if i == keep - 1:                           # use the oldest scene again: it must survive the next post
                first = used[0]
                assert c.get(f"/v1/scenes/{first}/render", params={"camera": "CAM_FRONT", "width": 64}
                             ).status_code == 200
                used.remove(first)
                used.append(first)
                time.sleep(0.01)
            used = [s for s in used if c.get(f"/v1/scenes/{s}").status_code == 200]
        recs = all_records(c)
        kept = [r["id"] for r in recs if r["state"] == "ready"]
        m = c.get("/metrics").text
        return {"quota": kind, "flags": flags, "quota_bytes": quota if kind == "bytes" else None,
                "scene_bytes": scene_bytes, "posted": 6, "kept": kept, "expected": used[-keep:],
                "records": len(recs), "store_bytes": sum(r["bytes"] or 0 for r in recs if r["state"] == "ready"),
                "evictions_metric": metric(m, "xyzcyl_store_evictions_total"),
                "folders": len(os.listdir(store / "scenes"))}


# ----------------------------------------------------------------------------------------------- security


def cmd_security(args, ctx: Ctx) -> dict:
    key = "reliability-" + secrets.token_urlsafe(12)
    # --api-docs true: with keys the OpenAPI document is off by default, and this reads every route from it
    flags = ["--api-keys", key, "--api-docs", "true", "--ort-threads", "1", "--max-body-bytes", str(8 << 20)]
    auth = {"Authorization": f"Bearer {key}"}
    doc: dict = {"flags": ["--api-keys", "<generated>", *flags[2:]]}
    with ctx.serve(ctx.store("security"), flags) as (_proc, url, _ready_s), client(url, 60, auth) as c, \
            client(url, 60) as anon:
        sid = new_scene(c, ctx)["id"]
        spec = anon.get("/openapi.json").json()
        routes = []
        for path, ops in spec["paths"].items():
            for method in ops:
                if method.upper() not in ("GET", "POST", "DELETE", "PUT", "PATCH"):
                    continue
                routes.append((method.upper(), path))
        fake = secrets.token_urlsafe(16)
        auth_rows, open_rows = [], []
        for method, path in routes:
            concrete = path.replace("{scene_id}", fake).replace("{name}", "xyzcyl-cpu-v1")
            if path.startswith("/v1"):
                row = {"route": f"{method} {path}"}
                for label, hdrs in (("none", {}), ("wrong_bearer", {"Authorization": "Bearer wrong-key-123456"}),
                                    ("wrong_x_api_key", {"X-API-Key": "wrong-key-123456"}),
                                    ("right", auth)):
                    r = anon.request(method, concrete, headers=hdrs)
                    row[label] = r.status_code
                    if label == "none":
                        row["www_authenticate"] = r.headers.get("www-authenticate")
                auth_rows.append(row)
            else:
                r = anon.request(method, concrete)
                open_rows.append({"route": f"{method} {path}", "status": r.status_code})
        for path in ("/metrics",):
            open_rows.append({"route": f"GET {path}", "status": anon.get(path).status_code})
        doc["auth"] = {"v1_routes": auth_rows, "open_routes": open_rows}

        # scene ids
        from xyzcyl.server.store import new_scene_id

        ids = [new_scene_id() for _ in range(1000)]
        real = [sid] + [new_scene(c, ctx)["id"] for _ in range(0 if args.quick else 2)]
        # 16 random bytes in base64url: 21 characters of 6 bits and a last one of 2 bits (4 values)
        pos_top = max(max(sum(i[p] == ch for i in ids) for ch in {i[p] for i in ids}) for p in range(21))
        srt = sorted(ids)
        lcp = max(len(os.path.commonprefix([a, b])) for a, b in itertools.pairwise(srt))
        alphabet = string.ascii_letters + string.digits + "-_"
        near = [sid[:-1] + ("A" if sid[-1] != "A" else "B"), sid[:21], sid + "A", sid.upper() if sid.upper() != sid
                else sid.lower(), ("B" if sid[0] != "B" else "C") + sid[1:]]
        rand = ["".join(secrets.choice(alphabet) for _ in range(22)) for _ in range(100 if not args.quick else 20)]
        doc["ids"] = {
            "generated": len(ids), "unique": len(set(ids)), "all_22_urlsafe": all(re.fullmatch(r"[A-Za-z0-9_-]{22}", i)
                                                                                 for i in ids),
            "max_same_char_at_positions_1_21": pos_top, "expected_about": round(1000 / 64, 1),
            "last_char_values": sorted({i[-1] for i in ids}),
            "longest_common_prefix_of_neighbours": lcp, "real_ids": real,
            "random_get": _statuses(c, [f"/v1/scenes/{r}" for r in rand]),
            "near_miss_get": _statuses(c, [f"/v1/scenes/{r}" for r in near]),
            "near_miss_render": _statuses(c, [f"/v1/scenes/{r}/render?camera=CAM_FRONT" for r in near])}

        # path-like ids and huge values
        paths = ["/v1/scenes/..%2F..%2Fetc%2Fpasswd", "/v1/scenes/%2e%2e", "/v1/scenes/..", "/v1/scenes/%00",
                 "/v1/scenes/a%00b", "/v1/scenes/..%2F..%2Frecords%2F" + sid, f"/v1/scenes/{sid}%2F..",
                 f"/v1/scenes/{sid}/../../{sid}", "/v1/scenes/%2F%2F%2F", "/v1/scenes/" + "A" * 5000,
                 f"/v1/scenes/{sid}/gaussians?format=..%2F..%2Fscene.json"]
        doc["path_like"] = [_raw_get(port_of(url), p, key) for p in paths]
        big = []
        big_name = "C" * 100_000
        rig = json.loads(ctx.rig_json.read_text())
        rig["cameras"][0]["name"] = big_name
        files = [("rig", ("rig.json", json.dumps(rig).encode(), "application/json"))] + [
            (big_name if k == ctx.rig["cameras"][0]["name"] else k, v) for k, v in ctx.files[1:]]
        t0 = now_s()
        r = c.post("/v1/scenes", files=files)
        big.append({"case": "100 kB camera name", "status": r.status_code, "s": round(now_s() - t0, 3),
                    "code": (r.json().get("error") or {}).get("code") if r.status_code >= 400 else None})
        for label, target in (("1 MB query string", f"/v1/scenes/{sid}/render?camera=" + "C" * (1 << 20)),
                              ("100 kB query string", f"/v1/scenes/{sid}/render?camera=" + "C" * 100_000),
                              ("1 MB header", "/v1/scenes")):
            hdr = {"X-Big": "h" * (1 << 20)} if "header" in label else {}
            big.append({"case": label, **_raw_get(port_of(url), target, key, hdr)})
        r = c.get(f"/v1/scenes/{sid}/render", params={"cam_to_ego": ",".join(["1e308"] * 16), "width": 64,
                                                      "height": 48, "fov": 90})
        big.append({"case": "cam_to_ego of 1e308", "status": r.status_code})
        doc["huge_values"] = big

        # headers
        version = anon.get("/v2").json().get("version")
        samples = {"GET /v2/health/live": anon.get("/v2/health/live"), "GET /v2": anon.get("/v2"),
                   "GET /metrics": anon.get("/metrics"), "GET scene": c.get(f"/v1/scenes/{sid}"),
                   "GET render": c.get(f"/v1/scenes/{sid}/render", params={"camera": "CAM_FRONT", "width": 64}),
                   "401": anon.get("/v1/scenes"), "404": c.get("/v1/scenes/" + fake),
                   "404 route": anon.get("/nope"), "405": anon.put("/v2/health/live"),
                   "422": c.get(f"/v1/scenes/{sid}/render", params={"camera": "NOPE"}),
                   "413": c.post("/v1/scenes", content=b"x" * ((8 << 20) + 1), headers={"Content-Type": "multipart/"
                                                                                                 "form-data; boundary=x"}),
                   "gaussians": c.get(f"/v1/scenes/{sid}/gaussians")}
        leaks = []
        names: set[str] = set()
        for label, r in samples.items():
            for k, v in r.headers.items():
                names.add(k.lower())
                low = f"{k}: {v}".lower()
                if k.lower() == "content-type" and "text/plain; version=" in v:
                    continue                # the Prometheus exposition format's version, not the stack's
                if k.lower() in ("server", "x-powered-by", "via", "x-aspnet-version") or re.search(
                        r"uvicorn|starlette|fastapi|python|h11|pydantic|onnx|numpy", low):
                    leaks.append({"response": label, "header": f"{k}: {v}"})
                vers = [m for m in re.findall(r"\b\d+\.\d+(?:\.\d+)?\b", v) if m != version]
                if vers and k.lower() not in ("content-length", "date", "etag", "retry-after", "content-disposition"):
                    leaks.append({"response": label, "header": f"{k}: {v}", "versions": vers})
        doc["headers"] = {"responses": {k: r.status_code for k, r in samples.items()},
                          "header_names": sorted(names), "leaks": leaks, "v2_version": version}
        doc["alive_after"] = anon.get("/v2/health/live").status_code
    a = doc["auth"]["v1_routes"]
    doc["targets"] = {
        "v1_routes_401_without_key": verdict(sum(r["none"] != 401 for r in a), 0, "==", f"{len(a)} routes"),
        "v1_routes_401_wrong_key": verdict(sum(r["wrong_bearer"] != 401 or r["wrong_x_api_key"] != 401
                                               for r in a), 0, "=="),
        "v1_routes_not_401_with_key": verdict(sum(r["right"] == 401 for r in a), 0, "=="),
        "open_routes_200": verdict(sum(r["status"] != 200 for r in doc["auth"]["open_routes"]), 0, "=="),
        "ids_unique": verdict(doc["ids"]["unique"], 1000, "=="),
        "ids_no_prefix_structure": verdict(doc["ids"]["longest_common_prefix_of_neighbours"], 5, "<"),
        "ids_position_uniform": verdict(doc["ids"]["max_same_char_at_positions_1_21"], 45, "<",
                                        "most frequent character at any of positions 1-21 of 1,000 ids (uniform: "
                                        "~16 of each of 64; the 22nd carries 2 bits)"),
        "random_ids_404": verdict(set(doc["ids"]["random_get"]), {"404"}, "=="),
        "near_miss_ids_404": verdict(set(doc["ids"]["near_miss_get"]) | set(doc["ids"]["near_miss_render"]),
                                     {"404"}, "=="),
        "path_like_4xx": verdict(sum(not (400 <= (p.get("followed") or p["status"] or 0) < 500)
                                     for p in doc["path_like"]), 0, "==", "a redirect counts by where it leads"),
        "huge_values_4xx": verdict(sum(not (400 <= (b["status"] or 0) < 500) for b in big), 0, "=="),
        "no_version_leaks": verdict(len(doc["headers"]["leaks"]), 0, "=="),
    }
    return doc


def _statuses(c, urls: list[str]) -> dict:
    out: dict[str, int] = {}
    for u in urls:
        count(out, c.get(u).status_code)
    return out


def _raw_get(port: int, target: str, key: str, headers: dict | None = None, follow: bool = True) -> dict:
    """GET ``target`` exactly as written (no client normalisation of .. or %2F) over a raw socket."""
    s = socket.create_connection((HOST, port), timeout=15)
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    t0 = now_s()
    s.sendall(f"GET {target} HTTP/1.1\r\nHost: {HOST}\r\nAuthorization: Bearer {key}\r\n{extra}"
              "Connection: close\r\n\r\n".encode())
    data = b""
    with contextlib.suppress(OSError):
        while len(data) < 1 << 20:
            more = s.recv(65536)
            if not more:
                break
            data += more
    s.close()
    status = int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/1.1 ") else None
    shown = target if len(target) < 80 else target[:60] + f"...({len(target)} chars)"
    out = {"target": shown, "status": status, "s": round(now_s() - t0, 3),
           "body": data.split(b"\r\n\r\n", 1)[-1][:120].decode(errors="replace")}
    m = re.search(rb"\r\nlocation: ([^\r]*)", data.split(b"\r\n\r\n", 1)[0], re.IGNORECASE)
    if status and 300 <= status < 400 and m and follow:
        loc = m.group(1).decode(errors="replace")
        loc = loc.split(f"{HOST}:{port}", 1)[-1] if loc.startswith("http") else loc
        out["location"] = loc
        out["followed"] = _raw_get(port, loc, key, headers, follow=False)["status"]
    return out


# ----------------------------------------------------------------------------------------------- main


COMMANDS = {"load": cmd_load, "overload": cmd_overload, "limits": cmd_limits, "crash": cmd_crash,
            "soak": cmd_soak, "security": cmd_security}


def main() -> int:
    if len(sys.argv) == 6 and sys.argv[1] == "_probe":         # HealthProbe's own process
        _probe_main(int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), Path(sys.argv[5]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=sorted(COMMANDS))
    ap.add_argument("--quick", action="store_true", help="a short smoke run (figures not meaningful)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON document here")
    ap.add_argument("--work", type=Path, default=None, help="folder for the rig and stores (default: a temp one)")
    ap.add_argument("--seconds", type=float, default=60.0, help="load/overload: seconds of each phase")
    ap.add_argument("--width", type=int, default=800, help="load/overload/slowloris render width")
    ap.add_argument("--height", type=int, default=600, help="render height")
    ap.add_argument("--format", default="jpeg", choices=["png", "jpeg"], help="render format")
    ap.add_argument("--slow-sockets", type=int, default=50, help="limits: slowloris sockets")
    ap.add_argument("--slow-seconds", type=float, default=20.0, help="limits: slowloris duration")
    ap.add_argument("--header-timeout", type=float, default=10.0, help="limits: the server's --header-timeout-s")
    ap.add_argument("--iterations", type=int, default=10, help="crash: kill -9 / restart rounds")
    ap.add_argument("--kill-window", type=float, default=3.0, help="crash: kill 0..this many s after the posts")
    ap.add_argument("--tmpfs-mb", type=int, default=20, help="crash: size of the tmpfs store")
    ap.add_argument("--renders", type=int, default=10_000, help="soak: renders after the warm-up")
    ap.add_argument("--client-nice", type=int, default=10, help="overload: the load generator's threads run this "
                                                                "much nicer than the server (0: the same)")
    ap.add_argument("--serve-args", default="", help="extra `xyzcyl serve` flags for every server, e.g. "
                                                     "\"--compute-nice 0\"")
    ap.add_argument("--soak-max-s", type=float, default=1800.0, help="soak: stop the render loop after this long")
    args = ap.parse_args()

    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix=f"xyzcyl_reliability_{args.command}_")
        args.work = Path(tmp.name)
    args.work.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": "reliability", "command": args.command, "issue": 14, "quick": args.quick,
           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine(),
           "uptime_start": uptime(), "load_start": load(), "other_jobs_start": other_jobs(),
           "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    t0 = now_s()
    try:
        import shlex

        ctx = Ctx(args.work, args.quick, shlex.split(args.serve_args))
        doc.update(COMMANDS[args.command](args, ctx))
        doc["pass"] = all(v["pass"] for v in doc.get("targets", {}).values())
    except Exception as e:  # noqa: BLE001 - reported in the document, then a non-zero exit
        import traceback

        doc["error"] = f"{type(e).__name__}: {e}"
        doc["traceback"] = traceback.format_exc()[-3000:]
        doc["pass"] = False
        log = args.work / "serve.log"
        if log.is_file():
            doc["serve_log_tail"] = log.read_text(errors="replace")[-3000:]
    finally:
        doc["wall_s"] = round(now_s() - t0, 1)
        doc["uptime_end"] = uptime()
        doc["load_end"] = load()
        doc["other_jobs_end"] = other_jobs()
        text = json.dumps(doc, indent=1, default=str)
        print(text, flush=True)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")
        if tmp is not None:
            tmp.cleanup()
    return 0 if doc["pass"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
