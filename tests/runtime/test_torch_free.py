"""The serving path needs no torch: with torch made unimportable (a sys.meta_path finder that refuses it), the
runtime loads the model folder, reconstructs the example rig, saves and renders the scene, and the CLI does too."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from xyzcyl.testing import EXAMPLE_RIG

pytestmark = pytest.mark.slow   # the session's ONNX export (tests/conftest.py)

BLOCK = """
import importlib.abc, sys
class NoTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"{name} is blocked: the runtime must not need torch")
        return None
sys.meta_path.insert(0, NoTorch())
"""

RUN = BLOCK + """
model, rig_json, out = sys.argv[1:4]
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import Scene, render_view, rig_camera
scene = Reconstructor.load(model, threads=1).reconstruct(load_rig(rig_json))
scene.save(out)
rgb, depth, alpha = render_view(Scene.load(out), rig_camera(scene.rig.cameras[0], width=80, height=45))
from xyzcyl import cli
assert cli.main(["reconstruct", rig_json, "--out", out + "_cli", "--model", model, "--quiet"]) == 0
assert cli.main(["render", out + "_cli", "--camera", "CAM_FRONT", "--width", "80", "--height", "45",
                 "--out", out + ".png"]) == 0
import numpy as np
np.save(out + "_sweep.npy", np.array([[12.0, y, z] for y in range(-8, 9) for z in (0.0, 1.0, 2.0)]))
assert cli.main(["reconstruct", rig_json, "--out", out + "_lidar", "--model", model, "--quiet", "--lidar-file",
                 out + "_sweep.npy"]) == 0
assert cli.main(["lidar-eval", rig_json, "--scene", out + "_lidar", "--lidar-file", out + "_sweep.npy",
                 "--width", "80", "--quiet"]) == 0
assert not any(m == "torch" or m.startswith("torch.") for m in sys.modules)
print("OK", len(scene.gaussians), rgb.shape)
"""


def test_runtime_reconstructs_and_renders_without_torch(tiny_export, tmp_path):
    r = subprocess.run([sys.executable, "-c", RUN, str(tiny_export.dir), str(EXAMPLE_RIG), str(tmp_path / "s")],
                       capture_output=True, text=True, timeout=600, check=False,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0 and "OK" in r.stdout, r.stderr[-3000:]


def test_blocker_really_blocks_torch():
    r = subprocess.run([sys.executable, "-c", BLOCK + "import torch"], capture_output=True, text=True, timeout=120,
                       check=False)
    assert r.returncode != 0 and "blocked" in r.stderr
