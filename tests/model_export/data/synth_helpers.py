"""Helpers shared by the synthetic data generator tests."""

from __future__ import annotations

import pytest


def check_probability_field(tmp_path, capsys, field: str) -> None:
    """A probability field of SceneConfig and SynthConfig (near_cars, photo_textures): out of [0, 1] it is refused
    naming it, by both configs and by `xyzcyl data synth --field-name` (exit 2); then check_index_field."""
    from xyzcyl.cli import main
    from xyzcyl.model_export.data.scene import SceneConfig
    from xyzcyl.model_export.data.synth import SynthConfig

    with pytest.raises(ValueError, match=f"^{field}"):
        SceneConfig(**{field: 1.5})
    with pytest.raises(ValueError, match=f"^{field}"):
        SynthConfig(**{field: -0.1}).validate()
    flag = "--" + field.replace("_", "-")
    assert main(["data", "synth", "--out", str(tmp_path / "x"), "--scenes", "1", flag, "2"]) == 2
    assert field in capsys.readouterr().err
    check_index_field(tmp_path, field, 0.5)


def check_index_field(tmp_path, field: str, value) -> None:
    """A SynthConfig field added after generator v1 (near_cars, photo_textures): index.json records it, a rerun
    with another value is refused naming it, and a folder made before it existed (absent from index.json)
    resumes as its default 0."""
    import json
    from dataclasses import replace

    from xyzcyl.model_export.data.synth import SynthConfig, synth

    cfg = SynthConfig(height=24, width=40, targets=(), voxels=(0.8,), seed=2, **{field: value})
    assert synth(tmp_path / "a", 1, cfg, progress=False) == 1
    assert json.loads((tmp_path / "a" / "index.json").read_text())["config"][field] == value
    with pytest.raises(ValueError, match=f"^{field}"):
        synth(tmp_path / "a", 1, replace(cfg, **{field: 0.0}), progress=False)
    old = replace(cfg, **{field: 0.0})
    assert synth(tmp_path / "b", 1, old, progress=False) == 1
    idx = json.loads((tmp_path / "b" / "index.json").read_text())
    del idx["config"][field]
    (tmp_path / "b" / "index.json").write_text(json.dumps(idx))
    assert synth(tmp_path / "b", 2, old, progress=False) == 1
