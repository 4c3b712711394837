"""benchmarks/export_bench.py (the export sizes and times docs/api.md quotes) runs as a user runs it (a subprocess
from the repository root) on a small scene, prints one JSON line, and refuses bad flags naming them (exit 2)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from xyzcyl.testing import EXAMPLE_RIG, REPO


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / "export_bench.py"), *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)


def test_export_bench_times_and_sizes_each_format(tmp_path):
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import Scene

    rng = np.random.default_rng(0)
    n = 500
    g = Gaussians(rng.uniform(-5, 5, (n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  np.full((n, 3), -2.0, np.float32), np.zeros(n, np.float32), rng.normal(0, 0.3, (n, 1, 3)))
    Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG)).save(tmp_path / "scene")
    r = _bench(str(tmp_path / "scene"), "--out-dir", str(tmp_path), "--formats", "ply,SPZ,glb")
    assert r.returncode == 0, r.stderr[-2000:]
    (doc,) = [json.loads(line) for line in r.stdout.splitlines() if line.strip()]
    assert doc["gaussians"] == n and doc["actors"] == 0 and doc["load_seconds"] >= 0
    assert [row["format"] for row in doc["formats"]] == ["ply", "spz", "glb"]
    for row in doc["formats"]:
        assert row["bytes"] == (tmp_path / f"scene.{row['format']}").stat().st_size and row["seconds"] >= 0
        assert row["gaussians"] == n
    sizes = {row["format"]: row["bytes_per_gaussian"] for row in doc["formats"]}
    assert sizes["spz"] < sizes["glb"] < sizes["ply"]            # 20 quantised bytes, 60 floats + colour, 68
    for args, says in ((["--formats", "obj"], "--formats: obj"), (["--repeat", "0"], "--repeat"),
                       (["--formats", "ply"], "--out-dir")):
        out_dir = [] if says == "--out-dir" else ["--out-dir", str(tmp_path)]
        bad = _bench(str(tmp_path / "scene"), *out_dir, *args)
        assert bad.returncode == 2 and says in bad.stderr, bad.stderr[-500:]
