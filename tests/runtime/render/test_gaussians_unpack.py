"""A PLY's packed float32 records split into the Gaussians' fields by one numba pass (Gaussians._from_vertices
through _unpacked: load_ply, load_ply_rows, load_ply_take) against the numpy path that reads any other layout: the
same arrays bit for bit at SH degrees 0-3, rows taken in any order; the same errors for non-finite values and zero
quaternions, naming the field."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl.runtime.render import GaussianError, Gaussians
from xyzcyl.runtime.render.gaussians import FIELDS, concat_gaussians


def _gaussians(rng, n: int, degree: int) -> Gaussians:
    g = random_gaussians(rng, n, lo=(-30, -30, -2), hi=(30, 30, 8))
    sh = rng.normal(size=(n, (degree + 1) ** 2, 3)).astype(np.float32)
    return Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh)


def _padded(vert: np.ndarray) -> np.ndarray:
    """The same records with a float64 property appended: not packed float32, so read by the numpy path."""
    dt = np.dtype(vert.dtype.descr + [("pad", "<f8")])
    out = np.zeros(len(vert), dt)
    for name in vert.dtype.names:
        out[name] = vert[name]
    return out


def _same(a: Gaussians, b: Gaussians) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32 and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)      # float32 values copied: exact
        assert x.flags.c_contiguous and x.flags.writeable, name


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_packed_records_read_as_the_numpy_path_reads_them(tmp_path, degree):
    rng = np.random.default_rng(11 + degree)
    g = _gaussians(rng, 5000, degree)
    path = tmp_path / "g.ply"
    g.save_ply(path)
    vert = g.ply_rows()
    slow = Gaussians._from_vertices(_padded(vert), "test")
    _same(slow, g)                                              # the numpy path reads back what was written
    _same(Gaussians.load_ply(path), g)
    _same(Gaussians.load_ply_rows(path, 700, 3100), g.subset(np.arange(700, 3100)))
    rows = rng.integers(0, len(g), 7000)                        # repeats, any order
    _same(Gaussians.load_ply_take(path, rows), g.subset(rows))
    _same(Gaussians._from_vertices(vert, "test", rows), Gaussians._from_vertices(_padded(vert), "test", rows))


@pytest.mark.parametrize("field,column,value,message", [
    ("means", "y", np.nan, "1 non-finite values"),
    ("quats", "rot_2", np.inf, "1 non-finite values"),
    ("log_scales", "scale_0", -np.inf, "1 non-finite values"),
    ("opacity_logits", "opacity", np.nan, "1 non-finite values"),
    ("sh", "f_rest_4", np.nan, "1 non-finite values"),
    ("quats", None, 0.0, "1 quaternions with zero norm"),
])
def test_bad_records_are_refused_as_by_the_numpy_path(field, column, value, message):
    rng = np.random.default_rng(3)
    vert = _gaussians(rng, 300, 1).ply_rows().copy()
    if column is None:
        for c in ("rot_0", "rot_1", "rot_2", "rot_3"):
            vert[c][17] = value
    else:
        vert[column][17] = value
    for records in (vert, _padded(vert)):
        with pytest.raises(GaussianError) as e:
            Gaussians._from_vertices(records, "PLY 'x.ply'")
        assert e.value.field == field and message in str(e.value) and "x.ply" in str(e.value)
    # a bad record not taken is not read
    rows = np.delete(np.arange(len(vert)), 17)
    assert len(Gaussians._from_vertices(vert, "test", rows)) == len(vert) - 1


@pytest.mark.parametrize("head_degree,file_degree,n_head", [(1, 1, 300), (0, 0, 1), (2, 1, 40), (0, 3, 25), (1, 1, 0)])
def test_take_with_a_head_is_the_head_then_the_rows(tmp_path, head_degree, file_degree, n_head):
    """load_ply_take(head=...) (a drive's viewpoint chunk: its own Gaussians, then rows of its camera layers, read
    in one set of arrays) is concat_gaussians([head, the rows]) bit for bit, also where the SH degrees differ (the
    lower padded with zeros) and with an empty head."""
    rng = np.random.default_rng(5 + head_degree + 7 * file_degree)
    g = _gaussians(rng, 4000, file_degree)
    path = tmp_path / "layer.ply"
    g.save_ply(path)
    head = _gaussians(rng, n_head, head_degree)
    rows = rng.permutation(len(g))[:2500]
    got = Gaussians.load_ply_take(path, rows, head=head)
    want = concat_gaussians([p for p in (head, g.subset(rows)) if len(p)])
    _same(got, want)
    assert len(got) == n_head + 2500


def test_take_from_a_cut_file_is_refused(tmp_path):
    """A camera layer cut short after it was checked: a GaussianError naming the body, not a crash."""
    rng = np.random.default_rng(2)
    g = _gaussians(rng, 1000, 0)
    path = tmp_path / "layer.ply"
    g.save_ply(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 68 * 10])
    with pytest.raises(GaussianError) as e:
        Gaussians.load_ply_take(path, np.arange(5))
    assert e.value.field in ("body", "element vertex")
