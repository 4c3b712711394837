"""The network at test size and small synthetic rigs (xyzcyl.runtime.rig.ring_rig). The configs are plain
dataclasses (xyzcyl.model_export.config imports no torch), so this module imports without torch too."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from xyzcyl.model_export.config import ModelConfig
    from xyzcyl.runtime.rig import Rig


def tiny_config(**changes) -> ModelConfig:
    """The cpu preset shrunk to test size: 64x128 input, 8x64 cylinder, 20x20x4 grid of 4 m voxels."""
    from xyzcyl.model_export.config import GridConfig, preset

    cfg = preset("cpu")
    cfg = cfg.replace(backbone=cfg.backbone.replace(input_height=64, input_width=128, pretrained=False),
                      cylinder=cfg.cylinder.replace(height=8, width=64), pixel=cfg.pixel.replace(k_out=2),
                      grid=GridConfig(voxel_size=4.0))
    return cfg.replace(**changes)


def synth_test_config(**changes) -> ModelConfig:
    """tiny_config for the 32x56 ``tiny_synth_data`` scenes: 32x56 backbone input, 1.6 m grid, ground-truth
    volume selection, at most 3000 voxels x G_v Gaussians (about a second of CPU splatting per stage-2 step)."""
    from xyzcyl.model_export.config import GridConfig

    cfg = tiny_config(volume_selection="ground_truth")
    cfg = cfg.replace(grid=GridConfig(voxel_size=1.6), volume=cfg.volume.replace(max_voxels=3000),
                      backbone=cfg.backbone.replace(input_height=32, input_width=56))
    return cfg.replace(**changes)


def tiny_export_config() -> ModelConfig:
    """tiny_config with at most 300 voxels (the 20x20x4 grid's random occupancy head selects ~half of its 1600
    voxels, so the top-k branch of the selection runs), the focal-aware depth head (the graphs then take each
    camera's focal_n: the 5-, 6- and 8-camera test rigs have three different focal lengths) and the standardised
    backbone input (input_norm: its per-image reductions are in the encode graph)."""
    cfg = tiny_config()
    return cfg.replace(volume=cfg.volume.replace(max_voxels=300),
                       backbone=cfg.backbone.replace(depth_focal_ref=0.9, input_norm="standardize"))


def overlap_rig(n: int, width: int = 128, height: int = 64, ring_radius: float = 0.5) -> Rig:
    """n outward cameras with overlapping fields of view (1.3 x 360/n degrees each)."""
    from xyzcyl.runtime.rig import ring_rig

    return ring_rig(n, hfov_deg=min(1.3 * 360.0 / n, 150.0), width=width, height=height, ring_radius=ring_radius)
