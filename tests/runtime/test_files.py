"""runtime.files.atomic_file: readers see the old file or the new one, never a half-written one."""

from __future__ import annotations

import pytest
from xyzcyl.common.files import atomic_file


def test_atomic_file_replaces_on_success_and_keeps_the_old_file_on_error(tmp_path):
    path = tmp_path / "doc.json"
    path.write_text("old")
    with atomic_file(path, "w", fsync=True) as f:
        f.write("new")
        assert path.read_text() == "old"            # not visible before the block completes
    assert path.read_text() == "new"
    with pytest.raises(RuntimeError), atomic_file(path) as f:
        f.write(b"half")
        raise RuntimeError("writer failed")
    assert path.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["doc.json"]   # no temporary file left


def test_atomic_file_refuses_other_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"), atomic_file(tmp_path / "x", "a"):
        pass
