"""MODEL_CARD.md text (export.model_card) for models with and without the volume branch."""

from xyzcyl.model_export.config import preset
from xyzcyl.model_export.export import model_card


def _meta(volume_per_voxel: int) -> dict:
    return {"name": "m", "version": "1.2.3", "opset": 20, "config": preset("cpu").to_dict(),
            "counts": {"pixel": 114688, "volume_per_voxel": volume_per_voxel, "max_voxels": 60000},
            "graphs": ["encode"] + (["volume"] if volume_per_voxel else []),
            "files": {"encode.onnx": {"bytes": 2_000_000}, "MODEL_CARD.md": {"bytes": 10}}}


def test_card_states_the_volume_branch():
    with_vol = model_card(_meta(2), [])
    assert "2 per occupied voxel (at most 60000 voxels) + 114688 pixel Gaussians" in with_vol
    assert "gets volume Gaussians" in with_vol and "no volume branch" not in with_vol
    without = model_card(_meta(0), [])
    assert "no volume branch (trained and exported without it), 114688 pixel Gaussians" in without
    assert "per occupied voxel" not in without and "gets volume Gaussians" not in without
    assert "no volume Gaussians: only what an input camera sees is reconstructed" in without
    assert "`encode.onnx` (2.0 MB)" in without
