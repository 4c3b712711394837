"""`xyzcyl data synth --workers N`: a process pool writes the same files, byte for byte, as one process."""

from __future__ import annotations

import shutil
from pathlib import Path

from xyzcyl.cli import main
from xyzcyl.model_export.data.synth import SynthConfig, synth

ARGS = ["--scenes", "2", "--height", "24", "--width", "40", "--inward-views", "2", "--no-shadows",
        "--supersample", "1", "--voxels", "0.8", "--seed", "5", "--quiet"]
CFG = SynthConfig(height=24, width=40, inward_views=2, shadows=False, supersample=1, voxels=(0.8,), seed=5)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_workers_write_identical_files_and_resume(tmp_path):
    assert synth(tmp_path / "one", 2, CFG, progress=False, workers=1) == 2
    assert main(["data", "synth", "--out", str(tmp_path / "two"), "--workers", "2", *ARGS]) == 0
    one, two = _files(tmp_path / "one"), _files(tmp_path / "two")
    assert len(one) > 100 and sorted(one) == sorted(two)
    assert [k for k in one if one[k] != two[k]] == []
    assert not (tmp_path / "two" / ".tmp").exists()
    # resume with a pool: only the missing scene is rendered, into the same bytes
    shutil.rmtree(tmp_path / "two" / "scene_000001")
    assert synth(tmp_path / "two", 2, CFG, progress=False, workers=2) == 1
    assert _files(tmp_path / "two") == one


def test_bad_workers_exit_2_naming_the_field(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["data", "synth", "--out", str(out), "--workers", "0", *ARGS]) == 2
    assert "workers" in capsys.readouterr().err
    assert not out.exists()
