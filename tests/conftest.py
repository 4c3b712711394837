"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Servers the tests start (in process and `xyzcyl serve` subprocesses, which inherit the environment) skip the
# start-up warm-up (~2 s each with a warm numba cache, dozens of starts in the suite): tests/server/test_warmup.py
# turns it back on for the test of the warm-up itself.
os.environ.setdefault("XYZCYL_WARM_UP", "false")


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
