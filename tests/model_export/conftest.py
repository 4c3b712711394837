"""Fixtures of the torch tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def one_thread():
    """Tiny tensors: one intra-op thread is faster than two and immune to OpenMP spin-waiting when the CI
    machine's two cores are shared with other jobs. Restored afterwards. The modules that want it say
    ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
