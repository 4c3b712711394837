"""The README's commands a new user copies (issue 27 defect 10): the `xyzcyl render` example's pose looks ahead
along ego x from 1.6 m (it looked straight up from the ground: an almost empty picture), and the quick start's
`python3 -c` after `curl POST /v1/scenes` prints the id, or the server's error body with exit status 1 (it raised
a KeyError traceback on any error)."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
from xyzcyl.testing import REPO

README = (REPO / "README.md").read_text()


def test_the_render_example_looks_ahead_from_1_6_m():
    line = next(ln for ln in README.splitlines() if "xyzcyl render " in ln and "--cam-to-world" in ln)
    T = np.array([float(v) for v in re.search(r"--cam-to-world((?:\s+-?[\d.]+){16})", line).group(1).split()])
    T = T.reshape(4, 4)
    R, t = T[:3, :3], T[:3, 3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(T[3], [0, 0, 0, 1])
    # OpenCV camera axes in the ego frame (x forward, y left, z up): x right, y down, z forward
    assert np.allclose(R[:, 2], [1, 0, 0]) and np.allclose(R[:, 0], [0, -1, 0]) and np.allclose(R[:, 1], [0, 0, -1])
    assert np.allclose(t, [0, 0, 1.6])
    fx, fy, cx, cy = (float(v) for v in re.search(r"--K((?:\s+[\d.]+){4})", line).group(1).split())
    w, h = int(re.search(r"--width (\d+)", line).group(1)), int(re.search(r"--height (\d+)", line).group(1))
    assert (cx, cy) == ((w - 1) / 2, (h - 1) / 2) and fx == fy > 0


def _snippet() -> str:
    line = next(ln for ln in README.splitlines() if ln.startswith("ID=$(curl") and "/v1/scenes" in ln)
    return re.search(r"python3 -c '([^']*)'", line).group(1)


def _run(stdin: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _snippet()], input=stdin, capture_output=True, text=True,
                          check=False)


def test_the_quick_start_prints_the_id_or_the_error_body():
    ok = _run(json.dumps({"id": "q3R1x9Z2bC7dE5fG8hJ0kA", "state": "ready"}))
    assert ok.returncode == 0 and ok.stdout == "q3R1x9Z2bC7dE5fG8hJ0kA\n"
    body = json.dumps({"error": {"code": "invalid", "message": "no image part for camera 'CAM_FRONT'",
                                 "field": "CAM_FRONT"}})
    bad = _run(body)
    assert bad.returncode == 1 and bad.stdout == "" and body in bad.stderr
    assert "Traceback" not in bad.stderr
    for nothing in ("", "<html>502 Bad Gateway</html>"):
        r = _run(nothing)
        assert r.returncode == 1 and r.stdout == "" and "Traceback" not in r.stderr
        assert "POST /v1/scenes failed" in r.stderr


def test_the_readme_commands_write_nothing_git_tracks():
    """Issue 35 item 11: the quick start wrote v.png and eval-real/ into the repository root. Every output of a
    README command (--out, --picture, curl -o) lies under /tmp or a path git ignores (out/, runs/, data/)."""
    outputs = []
    for line in README.splitlines():
        if ".venv/bin/xyzcyl" in line or line.startswith("curl") or "curl -s" in line:
            outputs += re.findall(r"(?:--out|--picture|\s-o)\s+(\S+)", line.split("  #")[0])
    assert len(outputs) >= 10, outputs
    for path in outputs:
        if path.startswith("/tmp/") or path.isupper():      # /tmp, or a placeholder (SCENE_DIR)
            continue
        probe = path.rstrip("/") + ("/x" if path.endswith("/") else "")
        ignored = subprocess.run(["git", "check-ignore", "-q", probe], cwd=REPO, check=False).returncode == 0
        assert ignored, f"README writes {path!r}, which git does not ignore"
