"""Every camera model rendered after every other model in one process, each against the float64 reference (issue
35 item 1: f-theta and equirectangular renders failed with an IndexError after pinhole renders in a running
server; the cause was numba's cache handing one model's projection kernel another model's code, see
runtime/numba_cache.py and tests/runtime/test_numba_cache.py)."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import look_at
from test_render_lens import PSNR_MIN, _lens_scene, _psnr, lens_camera
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, core, kernels, render, render_reference
from xyzcyl.runtime.render.projection import RenderOptions

MODELS = ("pinhole", "equirect", "opencv", "fisheye", "ftheta_fw")
# the pinhole and equirectangular paths draw what the reference draws to float32 rounding (1e-4: see
# test_render_forward.TOL); the lenses linearise the lens at each mean, the reference casts each pixel's ray
# (test_render_lens.PSNR_MIN explains the 40 dB bound)
TOL = 1e-4


def _camera(model: str) -> Camera:
    pose = look_at((0.3, -0.2, 0.1), (5.0, 1.0, 0.8))
    if model == "pinhole":
        K = np.array([[90.0, 0, 79.7], [0, 90.0, 60.2], [0, 0, 1.0]])
        return Camera(K=K, cam_to_ego=pose, width=160, height=120)
    if model == "equirect":
        return Camera(model="equirectangular", cam_to_ego=pose, width=160, height=80)
    return lens_camera(model, c2w=pose)


def _scene(cam: Camera) -> Gaussians:
    """Gaussians all around the camera, 3..6 m away (the lens scenes of test_render_lens), so that each model
    culls a different subset (a pinhole keeps the fewest, the equirectangular view all of them)."""
    g = _lens_scene(np.random.default_rng(7), "fisheye", n=1200)
    m = (g.means.astype(np.float64) @ cam.rotation.T + cam.position).astype(np.float32)
    return Gaussians(m, g.quats, g.log_scales, g.opacity_logits, g.sh)


def _every_ordered_pair(n: int) -> list[int]:
    """A sequence of 0..n-1 in which every ordered pair (a, b), a == b included, follows each other once: the de
    Bruijn sequence B(n, 2), closed (n^2 + 1 items)."""
    a = [0] * (2 * n)
    seq: list[int] = []

    def db(t: int, p: int) -> None:
        if t > 2:
            if 2 % p == 0:
                seq.extend(a[1:p + 1])
            return
        a[t] = a[t - p]
        db(t + 1, p)
        for j in range(a[t - p] + 1, n):
            a[t] = j
            db(t + 1, t)

    db(1, 1)
    return seq + seq[:1]


def test_the_sequence_holds_every_ordered_pair():
    seq = _every_ordered_pair(len(MODELS))
    pairs = set(zip(seq[:-1], seq[1:], strict=True))
    assert len(pairs) == len(MODELS) ** 2 == len(seq) - 1


def _check(model: str, fast, ref) -> None:
    if model in ("pinhole", "equirect"):
        assert np.abs(fast.rgb - ref.rgb).max() <= TOL, model
        assert np.abs(fast.alpha - ref.alpha).max() <= TOL, model
        return
    covered = (fast.alpha > 0.01) | (ref.alpha > 0.01)
    assert covered.mean() > 0.2, model                                 # the scene is seen
    assert _psnr(fast.rgb[covered], ref.rgb[covered]) >= PSNR_MIN, model
    assert _psnr(fast.alpha[covered], ref.alpha[covered]) >= PSNR_MIN, model


def test_every_model_after_every_other_matches_the_reference():
    cams = {m: _camera(m) for m in MODELS}
    scenes = {m: _scene(cams[m]) for m in MODELS}
    refs = {m: render_reference(scenes[m], cams[m], (0.05, 0.1, 0.2)) for m in MODELS}
    first = {}
    for k in _every_ordered_pair(len(MODELS)):
        m = MODELS[k]
        fast = render(scenes[m], cams[m], (0.05, 0.1, 0.2))
        if m not in first:
            _check(m, fast, refs[m])
            first[m] = fast
        else:                                              # a render never depends on what was rendered before
            assert np.array_equal(fast.rgb, first[m].rgb) and np.array_equal(fast.depth, first[m].depth), m


def test_the_precull_bounds_the_projection_of_every_model_in_any_order():
    """The projection's per-chunk counts never exceed the pre-cull's (the bound its outputs are sized by), with every
    tile open and with half the tiles covered (kernels.open_slots' summed-area table: a pinhole's pre-cull drops the
    Gaussians whose bound lies on covered tiles, and the projection the same ones)."""
    opts = RenderOptions()
    rng = np.random.default_rng(3)
    for k in _every_ordered_pair(len(MODELS)):
        cam = _camera(MODELS[k])
        g = _scene(cam)
        model, (*cargs, ptab) = core._camera_args(cam)
        camt = (*cargs, cam.width, cam.height, opts.near, opts.far, opts.low_pass)
        nch = (len(g) + kernels.PROJ_CHUNK - 1) // kernels.PROJ_CHUNK
        ntx, nty = -(-cam.width // kernels.TILE), -(-cam.height // kernels.TILE)
        half = np.zeros((nty + 1, ntx + 1), np.int64)
        half[1:, 1:] = np.cumsum(np.cumsum(rng.random((nty, ntx)) < 0.5, axis=0), axis=1)
        seen = []
        for sat in (np.zeros((0, 0), np.int64), half):
            pre, keep = np.zeros(nch, np.int64), np.zeros(len(g), np.uint8)
            kernels.precull_counts(model)(g.means, g.log_scales, camt, ptab, core.chunk_planes(cam, opts), sat,
                                          np.zeros((0, 7)), 0, pre, keep)
            assert [int(keep[c * kernels.PROJ_CHUNK:(c + 1) * kernels.PROJ_CHUNK].sum()) for c in range(nch)] \
                == list(pre), MODELS[k]             # the verdicts the projection reads agree with the counts
            base = np.concatenate([[0], np.cumsum(pre)[:-1]]).astype(np.int64)
            m = int(pre.sum())
            rows, dep = np.zeros((m, kernels.NCG), np.float32), np.zeros(m)
            trange, gid, counts = np.zeros((m, 2), np.int32), np.zeros(m, np.int32), np.zeros(nch, np.int64)
            kernels.project_kernel(model)(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh,
                                          np.ascontiguousarray(cam.cam_to_ego[:3, 3]), camt, ptab, keep, True, True,
                                          pre, base, rows, trange, dep, gid, counts)
            assert np.all(counts <= pre), MODELS[k]
            assert counts.sum() > 0, MODELS[k]
            seen.append(int(pre.sum()))
        if MODELS[k] == "pinhole":
            assert seen[1] < seen[0]                    # the covered tiles' Gaussians are not projected
        else:
            assert seen[1] == seen[0]                   # other models: only open_slots, after the projection


# One camera model's projection per process, then both in one process, all through one on-disk numba cache: the
# closures specialised per model (kernels._chunk_functions, precull_counts, project_kernel) were named alike, and
# numba names machine code by the qualified name and a per-process counter, so the pinhole's chunk function and
# the f-theta's, each compiled first in its own process, carried one symbol; loaded together, the f-theta kernel ran
# the pinhole's pre-count (IndexError in core._prepare, or heap corruption). Only the projection is run (core
# ._prepare): the raster kernels are not specialised per model.
_PREPARE = r"""
import sys
import numpy as np
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.lenses import Lens
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.render.core import _prepare
from xyzcyl.runtime.render.projection import RenderOptions

rng = np.random.default_rng(3)
n = 3000
d = rng.normal(size=(n, 3))
d /= np.linalg.norm(d, axis=1, keepdims=True)
g = Gaussians((d * rng.uniform(2.0, 8.0, (n, 1))).astype(np.float32), np.tile([1.0, 0, 0, 0], (n, 1)),
              np.full((n, 3), -2.5), np.zeros(n), rng.random((n, 1, 3)))
K = np.array([[70.0, 0, 79.7], [0, 70.0, 60.2], [0, 0, 1.0]])
lens = {"pinhole": None, "ftheta": Lens("ftheta", max_angle_deg=100.0,
                                        angle_to_pixeldist_poly=(0.0, 52.0, 0.0, -1.5, 0.1))}
out = {}
for name in sys.argv[2:]:
    cam = Camera(K=K, cam_to_ego=np.eye(4), width=160, height=120, distortion=lens[name])
    ntx, start, ids, rows, gid, _ = _prepare(g, cam, RenderOptions())
    out[name] = np.sort(gid[ids]) if len(ids) else np.zeros(0, np.int32)
np.savez(sys.argv[1], **out)
"""


@pytest.mark.heavy
def test_models_compiled_in_different_processes_load_together(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    script = tmp_path / "prepare.py"
    script.write_text(_PREPARE)

    def start(out: str, *models: str) -> tuple[subprocess.Popen, Path]:
        return subprocess.Popen([sys.executable, str(script), str(tmp_path / out), *models], env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE), tmp_path / out

    def result(job: tuple[subprocess.Popen, Path]) -> dict:
        proc, out = job
        _, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err[-3000:]
        return dict(np.load(out))

    # each model compiled first in its own process (both at once: a core each), then both loaded into a third
    first = [start("p.npz", "pinhole"), start("f.npz", "ftheta")]
    alone = {k: v for job in first for k, v in result(job).items()}
    together = result(start("both.npz", "pinhole", "ftheta"))
    for name in ("pinhole", "ftheta"):
        np.testing.assert_array_equal(together[name], alone[name])
    assert len(alone["ftheta"]) > len(alone["pinhole"]) > 0          # the models see different Gaussians
