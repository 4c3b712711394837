"""The web viewer in a real browser, for tests/server/test_viewer_browser.py and scripts/viewer_screenshots.py
(docs/viewer.md): ``ViewServer`` runs `xyzcyl view SCENE_DIR` and reads the URL it prints; ``browse`` drives headless
Chromium (Debian's, through npm's playwright-core: tests/server/viewer_browser.mjs, one browser launch for a plan of
pages); ``fetch_image`` reads a rendered view; ``chromium`` finds the browser."""

from __future__ import annotations

import io
import json
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any, Self

import numpy as np
import xyzcyl.testing as _testing

URL = re.compile(r"(http://127\.0\.0\.1:\d+/v1/scenes/[\w-]+/viewer)")


def chromium() -> str | None:
    """The Chromium executable on PATH, or None."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


class ViewServer:
    """`xyzcyl view SCENE_DIR --camera CAMERA` in a child process: ``url`` is the viewer's URL (without a query),
    ``scene_url`` the scene's API path (…/v1/scenes/ID). A context manager; ``stop`` ends it (SIGINT, then kill)."""

    def __init__(self, scene: Path | str, camera: str | None = None, timeout: float = 90.0, cwd: Path | None = None):
        args = [sys.executable, "-m", "xyzcyl", "view", str(scene)] + (["--camera", camera] if camera else [])
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in self.proc.stdout], daemon=True).start()
        seen, url, deadline = [], None, time.monotonic() + timeout
        while url is None and time.monotonic() < deadline and self.proc.poll() is None:
            try:
                seen.append(lines.get(timeout=1))
            except queue.Empty:
                continue
            m = URL.search(seen[-1])
            url = m.group(1) if m else None
        if url is None:
            self.stop()
            raise RuntimeError(f"`xyzcyl view` printed no URL: {''.join(seen)[-2000:]}")
        self.url = url
        self.scene_url = url.rsplit("/", 1)[0]
        self.base = url.split("/v1/")[0]

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def browse(pages: list[dict[str, Any]], workdir: Path, timeout_s: float = 60.0) -> dict[str, Any]:
    """viewer_browser.mjs's report of ``pages`` (its plan's pages: url, viewport, keys, script, screenshot, selector,
    refuse) in one headless Chromium; ``browser_s`` added: the seconds it all took. RuntimeError when node fails."""
    plan = {"executable": chromium(), "timeout_ms": int(timeout_s * 1000), "pages": pages}
    path = Path(workdir) / "plan.json"
    path.write_text(json.dumps(plan))
    t0 = time.monotonic()
    driver = Path(_testing.REPO) / "tests" / "server" / "viewer_browser.mjs"
    done = subprocess.run(["node", str(driver), str(path)], capture_output=True, text=True,
                          timeout=60 + 3 * timeout_s * len(pages), cwd=_testing.REPO)
    if done.returncode != 0:
        raise RuntimeError(f"the browser's driver failed: {done.stderr[-3000:]}")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    report["browser_s"] = time.monotonic() - t0
    return report


def fetch_image(url: str, timeout: float = 600.0) -> np.ndarray:
    """The PNG or JPEG at ``url`` as float32 RGB [H, W, 3] in [0, 1]."""
    from PIL import Image

    with urllib.request.urlopen(url, timeout=timeout) as r:
        return np.asarray(Image.open(io.BytesIO(r.read())).convert("RGB"), np.float32) / 255.0


def compare(webgl: np.ndarray, ours: np.ndarray, alpha: np.ndarray) -> dict[str, float]:
    """PSNR (dB) and mean absolute difference (levels of 255) of two views over the pixels our render covers
    (``alpha`` >= 0.99), and that share of the image."""
    covered = alpha >= 0.99
    diff = webgl[covered] - ours[covered]
    return {"psnr_db": float(10 * np.log10(1.0 / max(float(np.mean(diff ** 2)), 1e-12))),
            "mean_abs_levels": float(np.mean(np.abs(diff)) * 255), "covered": float(covered.mean())}


__all__ = ["URL", "ViewServer", "browse", "chromium", "compare", "fetch_image"]
