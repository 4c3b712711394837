"""Fixtures for the synthetic data generator tests: tiny rendered scenes, shared per session."""

from __future__ import annotations

import pytest
from xyzcyl.model_export.data.synth import SynthConfig, render_scene

TINY = SynthConfig(height=32, width=56, inward_views=4, seed=7)


@pytest.fixture(scope="session")
def tiny_cfg() -> SynthConfig:
    return TINY


@pytest.fixture(scope="session")
def tiny_scenes():
    """Scenes 0 and 3 of the tiny config (scene 3 is drawn with an intersection under seed 7 or not: either way
    the tests hold for any scene)."""
    return [render_scene(TINY, i) for i in (0, 3)]
