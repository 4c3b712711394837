"""LiDAR files that hold nothing usable (issue 35, items 4 and 7): runtime.lidar.read_points refuses a 0-byte file, a
text file named .npy, a .npy of zero points and a sweep of only non-finite points, each in one line naming the file
as the user gave it (``label``: the CLI's path, the HTTP upload's part and file name); `xyzcyl reconstruct
--lidar-file` with a 0-byte file exits 2 with that line, before the model loads. The HTTP side is
tests/server/test_lidar_upload_errors.py."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.runtime.lidar import LidarError, read_points

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_RIG = REPO / "examples" / "synth_nuscenes" / "rig.json"


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


# name -> (bytes, what the one line says after the file's name)
BAD_FILES = {
    "empty.npy": (b"", "is empty (0 bytes)"),
    "empty.bin": (b"", "is empty (0 bytes)"),
    "empty.pcd.bin": (b"", "is empty (0 bytes)"),
    "x.npy": (b"hello\n", "is not a .npy array (it does not start with the .npy magic bytes)"),
    "rows.npy": (np.ones((4, 4), "<f4").tobytes(), "is not a .npy array (it does not start with the .npy magic bytes)"),
    "zero.npy": (_npy(np.zeros((0, 3), np.float32)), "holds no points (shape [0, 3])"),
    "nan.npy": (_npy(np.array([[np.nan, 0, 0], [1, np.inf, 2]], np.float32)),
                "holds no point with a finite x, y and z (a non-finite coordinate in every one of its 2 rows)"),
    "cut.npy": (_npy(np.ones((4, 3), np.float32))[:-4], "is not a readable .npy array ("),
    "complex.npy": (_npy(np.ones((2, 3), np.complex64)), "must hold real numbers of shape [N, C >= 3] (got complex64"),
}


@pytest.mark.parametrize("name", list(BAD_FILES))
def test_read_points_refuses_a_file_without_points(tmp_path, name):
    data, says = BAD_FILES[name]
    p = tmp_path / name
    p.write_bytes(data)
    with pytest.raises(LidarError) as info:
        read_points(p)
    e = info.value
    assert e.field == "lidar" and e.where is None, (e.field, e.where)
    assert e.message.startswith(f"{str(p)!r} {says}"), e.message


@pytest.mark.parametrize("name", ["x.npy", "empty.bin", "zero.npy"])
def test_read_points_names_the_file_by_its_label(tmp_path, name):
    """An upload is read from the server's store under a name of the server's: ``label`` is what the message calls it
    (the path appears nowhere)."""
    data, says = BAD_FILES[name]
    p = tmp_path / "lidar.npy" if name.endswith(".npy") else tmp_path / "lidar.bin"
    p.write_bytes(data)
    label = f"part 'lidar' (file {name!r})"
    with pytest.raises(LidarError) as info:
        read_points(p, label=label)
    assert info.value.message.startswith(f"{label} {says}"), info.value.message
    assert str(tmp_path) not in str(info.value)


def test_read_points_takes_a_bin_holding_a_npy_array(tmp_path):
    """The Python client sends a sweep given as bytes as 'lidar.bin' (docs/client.md: .npy or raw float32): a .bin
    whose bytes start with the .npy magic is that array, not float32 rows of its header."""
    (tmp_path / "s.bin").write_bytes(_npy(np.array([[1, 2, 3], [4, 5, 6]], np.float32)))
    xyz, bad = read_points(tmp_path / "s.bin")
    assert xyz.tolist() == [[1, 2, 3], [4, 5, 6]] and bad == 0


def test_reconstruct_refuses_an_empty_lidar_file(tmp_path, capfd, monkeypatch):
    """Regression (issue 35, item 4): a 0-byte .npy ended in an EOFError traceback. Now: exit 2, one line naming the
    file as given, before the model loads (the --model folder here is an empty one; loading it fails the test)."""
    from xyzcyl.runtime.inference import Reconstructor

    def no_load(*a, **kw):
        raise AssertionError("the model was loaded before the LiDAR file was refused")

    monkeypatch.setattr(Reconstructor, "load", no_load)
    empty = tmp_path / "empty.npy"
    empty.write_bytes(b"")
    rc = cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--model", str(tmp_path),
                   "--lidar-file", str(empty), "--quiet"])
    err = capfd.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"xyzcyl reconstruct: lidar: {str(empty)!r} is empty (0 bytes)"], err
    assert not (tmp_path / "s").exists()
