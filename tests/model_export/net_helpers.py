"""Helpers for the network tests: a tiny config and synthetic ring rigs (xyzcyl.runtime.rig.ring_rig)."""

from __future__ import annotations

import pytest
import torch
from xyzcyl.model_export.config import GridConfig, ModelConfig, preset
from xyzcyl.runtime.rig import Rig, ring_rig


def tiny_config(**changes) -> ModelConfig:
    """The cpu preset shrunk to test size: 64x128 input, 8x64 cylinder, 20x20x4 grid of 4 m voxels."""
    cfg = preset("cpu")
    cfg = cfg.replace(backbone=cfg.backbone.replace(input_height=64, input_width=128, pretrained=False),
                      cylinder=cfg.cylinder.replace(height=8, width=64), pixel=cfg.pixel.replace(k_out=2),
                      grid=GridConfig(voxel_size=4.0))
    return cfg.replace(**changes)


def synth_test_config(**changes) -> ModelConfig:
    """tiny_config for the 32x56 ``tiny_synth_data`` scenes: 32x56 backbone input, 1.6 m grid, ground-truth
    volume selection, at most 3000 voxels x G_v Gaussians (about a second of CPU splatting per stage-2 step)."""
    cfg = tiny_config(volume_selection="ground_truth")
    cfg = cfg.replace(grid=GridConfig(voxel_size=1.6), volume=cfg.volume.replace(max_voxels=3000),
                      backbone=cfg.backbone.replace(input_height=32, input_width=56))
    return cfg.replace(**changes)


def overlap_rig(n: int, width: int = 128, height: int = 64, ring_radius: float = 0.5) -> Rig:
    """n outward cameras with overlapping fields of view (1.3 x 360/n degrees each)."""
    return ring_rig(n, hfov_deg=min(1.3 * 360.0 / n, 150.0), width=width, height=height, ring_radius=ring_radius)


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: one intra-op thread is faster than two and immune to OpenMP spin-waiting when the CI
    machine's two cores are shared with other jobs. Restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
