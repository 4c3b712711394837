"""runtime.directio (files written and read past the page cache) and the PLY reads and writes built on it
(save_ply_parts(direct=True), Gaussians.read_ply_take) against the page cache's own: the same bytes, the same rows;
where the file system refuses O_DIRECT, the same through the cache."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest
from xyzcyl.runtime import directio
from xyzcyl.runtime.directio import ALIGN, DirectReader, DirectWriter, aligned_buffer
from xyzcyl.runtime.render import gaussians as G
from xyzcyl.runtime.render.gaussians import FIELDS, GaussianError, Gaussians, save_ply_parts


def _random(rng, n: int, k: int = 1) -> Gaussians:
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                     rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                     rng.normal(size=(n, k, 3)).astype(np.float32))


def _equal(a: Gaussians, b: Gaussians) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)    # copies: exact


def test_aligned_buffer_is_aligned():
    for n in (1, ALIGN - 1, 3 * ALIGN + 5):
        b = aligned_buffer(n)
        assert b.ctypes.data % ALIGN == 0 and len(b) == n and b.dtype == np.uint8


@pytest.mark.parametrize("refuse", [False, True])
def test_writer_and_reader_move_the_same_bytes(tmp_path, monkeypatch, refuse):
    """Pieces of every size (less than a block, more than the buffer, in place through space/advance) make the
    file they add up to, cut back to its size; any byte range reads back. ``refuse``: a platform without O_DIRECT
    or os.preadv (macOS), the page cache's way."""
    if refuse:
        monkeypatch.setattr(directio, "_O_DIRECT", 0)
        monkeypatch.delattr(directio.os, "preadv")
    rng = np.random.default_rng(0)
    want = bytearray()
    path = tmp_path / "f.bin"
    with DirectWriter(path, 3 * ALIGN) as w:
        if refuse:
            assert not w.direct
        for size in (5, ALIGN, 1, 7 * ALIGN + 3, 0, 2 * ALIGN - 1, 17):
            data = rng.integers(0, 256, size, dtype=np.uint8)
            if size <= ALIGN:               # in place
                w.space(size)[:] = data
                w.advance(size)
            else:
                w.write(data.tobytes())
            want += data.tobytes()
        assert w.size == len(want)
    assert path.read_bytes() == bytes(want)
    buf = aligned_buffer(DirectReader.buffer_bytes(len(want)))
    with DirectReader(path) as r:
        for a, b in ((0, len(want)), (1, 2), (ALIGN - 1, ALIGN + 1), (len(want) - 3, len(want)), (5, 5)):
            assert r.read(a, b, buf).tobytes() == bytes(want[a:b])
        with pytest.raises(OSError):
            r.read(0, len(want) + 1, buf)           # past the end
        with pytest.raises(OSError):
            r.read(0, len(want), aligned_buffer(ALIGN))      # a buffer too small


def test_writer_turns_to_the_page_cache_when_a_write_is_refused(tmp_path, monkeypatch):
    """A file system that opens with O_DIRECT but refuses its transfers (EINVAL): the writer goes on through the
    cache, nothing lost."""
    real = os.write
    calls = []

    def write(fd, data):
        calls.append(len(data))
        if len(calls) == 1:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, data)

    monkeypatch.setattr(directio.os, "write", write)
    data = np.random.default_rng(1).integers(0, 256, 5 * ALIGN + 11, dtype=np.uint8)
    with DirectWriter(tmp_path / "g.bin", 2 * ALIGN) as w:
        w.write(data)
    assert (tmp_path / "g.bin").read_bytes() == data.tobytes() and len(calls) > 2 and not w.direct


def test_writer_space_refuses_what_cannot_fit(tmp_path):
    with DirectWriter(tmp_path / "h.bin", ALIGN) as w:       # two blocks at least
        w.write(b"abc")
        with pytest.raises(ValueError, match="nbytes"):
            w.space(2 * ALIGN)
    assert (tmp_path / "h.bin").read_bytes() == b"abc"


@pytest.mark.parametrize("k", [1, 4])
def test_direct_ply_is_the_cached_ply_with_an_aligned_header(tmp_path, k):
    """save_ply_parts(direct=True): the same records, its header padded by a comment to a multiple of 4 bytes;
    every reader reads it as the other (plyfile's too)."""
    from plyfile import PlyData

    rng = np.random.default_rng(2)
    parts = [_random(rng, n, k) for n in (300, 7, 1 << 10, 2345)]
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    save_ply_parts(a, parts, normals=False)
    save_ply_parts(b, parts, normals=False, direct=True)
    da, db = a.read_bytes(), b.read_bytes()
    ha, hb = da.index(b"end_header\n") + 11, db.index(b"end_header\n") + 11
    assert hb % 4 == 0 and da[ha:] == db[hb:]
    assert [x for x in db[:hb].split(b"\n") if not x.startswith(b"comment")] == da[:ha].split(b"\n")
    _equal(Gaussians.load_ply(a), Gaussians.load_ply(b))
    assert len(PlyData.read(str(b))["vertex"]) == sum(map(len, parts))


@pytest.mark.parametrize("direct", [True, False])
def test_read_ply_take_is_load_ply_take(tmp_path, monkeypatch, direct):
    """Rows in any order, repeated, few or all, over many windows (a window of 64 KiB here), and the box of other
    rows' means found in the same pass: load_ply_take's Gaussians and numpy's box. ``direct`` False: a header of a
    length not a multiple of 4 (a PLY written through the cache), read through a map instead."""
    monkeypatch.setattr(G, "READ_WINDOW_BYTES", 1 << 16)
    rng = np.random.default_rng(3)
    parts = [_random(rng, n) for n in (30000, 7, 12345)]
    path = tmp_path / "l.ply"
    save_ply_parts(path, parts, normals=False, direct=direct)
    n = sum(map(len, parts))
    if not direct:
        assert (path.read_bytes().index(b"end_header\n") + 11) % 4     # the map's way is the one taken
    means = np.concatenate([p.means for p in parts]).astype(np.float64)
    for rows in (rng.integers(0, n, 5000), np.arange(n), np.array([n - 1, 0, 5, 5]), np.zeros(0, np.int64)):
        for box_of in (rng.choice(n, 300, replace=False), np.array([n - 1]), rng.integers(0, n, 100000)):
            box = np.array([[np.inf] * 3, [-np.inf] * 3])
            got = Gaussians.read_ply_take(path, rows, box_of=box_of, box=box)
            _equal(got, Gaussians.load_ply_take(path, rows))
            np.testing.assert_array_equal(box, [means[box_of].min(axis=0), means[box_of].max(axis=0)])
        _equal(Gaussians.read_ply_take(path, rows), Gaussians.load_ply_take(path, rows))


def test_read_ply_take_errors(tmp_path):
    rng = np.random.default_rng(4)
    path = tmp_path / "e.ply"
    save_ply_parts(path, [_random(rng, 1000)], normals=False, direct=True)
    with pytest.raises(GaussianError, match="outside") as e:
        Gaussians.read_ply_take(path, np.array([0, 1000]))
    assert e.value.field == "rows"
    with pytest.raises(ValueError, match="box_of"):
        Gaussians.read_ply_take(path, np.array([0]), box_of=np.array([1]))      # no box to widen
    bad = _random(rng, 1000)
    bad.means[17, 1] = np.nan
    save_ply_parts(path, [bad], normals=False, direct=True)
    assert len(Gaussians.read_ply_take(path, np.array([16, 18]))) == 2         # only the rows taken are checked
    with pytest.raises(GaussianError, match="1 non-finite") as e:
        Gaussians.read_ply_take(path, np.array([17]))
    assert e.value.field == "means"
    with open(path, "r+b") as f:                    # cut short after its header was read
        f.truncate(os.path.getsize(path) - 100)
    with pytest.raises(GaussianError) as e:
        Gaussians.read_ply_take(path, np.array([999]))
    assert e.value.field == "body"
