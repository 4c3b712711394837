"""Shared test fixtures. Shared helpers (paths, rigs, the multipart builder, the `xyzcyl serve` harness, the tiny
model config) are in the xyzcyl.testing package: import them from there, never from a conftest."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest
from xyzcyl.testing import REPO

# Servers the tests start (in process and `xyzcyl serve` subprocesses, which inherit the environment) skip the
# start-up warm-up (~2 s each with a warm numba cache, dozens of starts in the suite): tests/server/test_warmup.py
# turns it back on for the test of the warm-up itself.
os.environ.setdefault("XYZCYL_WARM_UP", "false")


# The README's test command runs the suite on two processes (pytest-xdist, ``-n 2 --dist loadgroup``: CI's machine
# has two cores and much of the suite waits on one: exports, compiles, servers). A session fixture is built once per
# process that uses it, so the tests of each expensive one are marked to run in one process. The groups follow from
# the fixtures a test uses (its whole closure). But pytest 9 keeps a node's id in ``_id``, and xdist 3.8 still writes
# the group into ``_nodeid``: the scheduler never sees the groups (checked: two tests of one static group ran on both
# workers), so the costliest fixture, the tiny ONNX export, is shared between the workers by a file lock instead
# (tiny_export below). The marks stay for an xdist that reads them again.
_GROUPS = {"tiny_export": "tiny-export", "tiny_synth_data": "tiny-synth", "tiny_scenes": "tiny-synth"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        names = getattr(item, "fixturenames", ())
        group = next((g for fx, g in _GROUPS.items() if fx in names), None)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))


@pytest.fixture(scope="session")
def _default_numba_threads() -> int:
    """numba's thread count as the test session found it."""
    import numba

    return numba.get_num_threads()


@pytest.fixture(autouse=True)
def _restore_numba_threads(_default_numba_threads):
    """Commands run in-process (`cli.main([... "--threads", "1"])`, also from module fixtures) set numba's
    process-wide thread count; after each test it goes back to the session's default, so a later test does not run
    with another test's setting (the training overfit check's loss ratio moved from 0.46 to 0.52 that way)."""
    yield
    import numba

    numba.set_num_threads(_default_numba_threads)


def real_data_dir() -> Path | None:
    """The shared real rigs (nuScenes, PandaSet, panoramas), or None when absent (tests then skip)."""
    env = os.environ.get("XYZCYL_REAL_DATA")
    path = Path(env) if env else REPO.parent / "shared" / "data" / "real"
    return path if path.is_dir() else None


@pytest.fixture
def real_data() -> Path:
    path = real_data_dir()
    if path is None:
        pytest.skip("real data (../shared/data/real or $XYZCYL_REAL_DATA) not present")
    return path


@pytest.fixture(scope="session")
def tiny_synth_data(tmp_path_factory) -> Path:
    """Two synthetic scenes (nuScenes rig, 32x56 px, 3 inward views, 0.8 and 1.6 m occupancy) in a temp folder."""
    from xyzcyl.model_export.data.synth import SynthConfig, synth

    out = tmp_path_factory.mktemp("tiny_synth")
    cfg = SynthConfig(rig="nuscenes", height=32, width=56, inward_views=3, supersample=1, shadows=False,
                      voxels=(0.8, 1.6), seed=3)
    synth(out, 2, cfg, progress=False)
    return out


@dataclass
class TinyExport:
    model: object          # the torch XYZCylinder (eval mode) the graphs were exported from
    dir: Path              # the model folder
    checkpoint: Path


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory) -> TinyExport:
    """One ONNX export of the tiny test config (xyzcyl.testing.model.tiny_export_config) per pytest session,
    through `xyzcyl export-model` (which is thereby tested), shared by the tests of the exported graphs
    (tests/model_export) and of the runtime that runs them (tests/runtime): the export takes about a minute
    whatever the config's size."""
    import torch
    from xyzcyl import cli
    from xyzcyl.model_export.model import XYZCylinder
    from xyzcyl.testing.model import tiny_export_config

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        cfg = tiny_export_config()
        model = XYZCylinder(cfg).eval()
        with torch.no_grad():
            # random weights give the occupancy head margins of one sign (no voxel selected); spread them and
            # centre them on a 6-camera example so that about half of the voxels are occupied (volume Gaussians to
            # compare, the top-k branch of the selection to exercise)
            from xyzcyl.model_export.lifting import rig_inputs
            from xyzcyl.testing.model import overlap_rig

            last = model.occ_head[-1]
            last.weight.normal_(0.0, 1.0)
            last.bias.zero_()
            occ = model(torch.rand(6, 3, 64, 128), rig_inputs(overlap_rig(6), cfg))["occ_logits"]
            last.bias[1] -= float((occ[1] - occ[0]).median())
        # XYZCYL_TINY_EXPORT=DIR (development only): export into DIR once and reuse it in later sessions. Under
        # xdist the workers share one export: the first to need it writes it beside their base temp folders (the
        # run's common parent), under a file lock, and the others read it (xdist's "session fixtures once" recipe;
        # the test groups of tests/conftest.py do not reach its scheduler, so both workers may need it)
        reuse = os.environ.get("XYZCYL_TINY_EXPORT")
        if reuse:
            root = Path(reuse)
        elif os.environ.get("PYTEST_XDIST_WORKER"):
            root = tmp_path_factory.getbasetemp().parent / "tiny_export_shared"
        else:
            root = tmp_path_factory.mktemp("tiny_export")
        root.mkdir(parents=True, exist_ok=True)
        ck = root / "tiny.pt"
        out = root / "tiny-model"
        from filelock import FileLock

        with FileLock(str(root) + ".lock"):
            if (reuse or root.name == "tiny_export_shared") and (out / "model.json").is_file():
                return TinyExport(model=model, dir=out, checkpoint=ck)
            torch.save({"model": model.state_dict(), "model_cfg": cfg.to_dict(), "step": 0,
                        "train_cfg": {"stage": "render", "steps": 0}}, ck)
            rc = cli.main(["export-model", "--checkpoint", str(ck), "--out", str(out), "--name", "tiny-test",
                           "--version", "0.0.1", "--threads", "1", "--quiet"])
            assert rc == 0
    finally:
        torch.set_num_threads(threads)
    return TinyExport(model=model, dir=out, checkpoint=ck)
