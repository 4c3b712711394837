"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


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
