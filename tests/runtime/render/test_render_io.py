"""PLY (INRIA 3DGS layout) and .splat I/O."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from plyfile import PlyData
from render_scenes import pinhole, random_gaussians
from xyzcyl.runtime.render import GaussianError, Gaussians, render
from xyzcyl.runtime.render.gaussians import SH_C0


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_renders_identically(tmp_path, degree):
    g = random_gaussians(np.random.default_rng(degree), 200, degree=degree)
    path = tmp_path / "g.ply"
    g.save_ply(path)
    h = Gaussians.load_ply(path)
    assert h.sh_degree == degree
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(g, f), getattr(h, f)), f
        # contiguous, not views of the PLY's records: every render would gather a strided column again
        assert getattr(h, f).flags.c_contiguous, f
    a, b = render(g, pinhole(), (0.1, 0.2, 0.3)), render(h, pinhole(), (0.1, 0.2, 0.3))
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)


def test_ply_layout_is_inria(tmp_path):
    g = random_gaussians(np.random.default_rng(1), 7, degree=2)
    g.save_ply(tmp_path / "g.ply")
    ply = PlyData.read(str(tmp_path / "g.ply"))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(24)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert all(p.val_dtype in ("f4", "<f4", "float32") or str(p.val_dtype).endswith("f4") for p in v.properties)
    # channel-major f_rest: index c * 8 + (k - 1) holds sh[:, k, c]
    assert np.array_equal(v["f_rest_9"], g.sh[:, 2, 1])      # c = 1, k = 2
    assert np.array_equal(v["f_rest_23"], g.sh[:, 8, 2])     # c = 2, k = 8
    assert np.array_equal(v["rot_0"], g.quats[:, 0])         # w first


@pytest.mark.parametrize("degree", [0, 1, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ply_rows_equal_a_field_by_field_reference(degree, dtype):
    """Gaussians.ply_rows (one float32 block viewed as the structured rows) against the obvious construction:
    every property assigned from its source column, float64 sources rounded to float32 once; bit-exact."""
    g = random_gaussians(np.random.default_rng(10 + degree), 300, degree=degree).astype(dtype)
    k = g.sh.shape[1]
    src = {"x": g.means[:, 0], "y": g.means[:, 1], "z": g.means[:, 2], "nx": 0.0, "ny": 0.0, "nz": 0.0,
           "opacity": g.opacity_logits}
    for c in range(3):
        src[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(1, k):
            src[f"f_rest_{c * (k - 1) + j - 1}"] = g.sh[:, j, c]
        src[f"scale_{c}"] = g.log_scales[:, c]
    for c in range(4):
        src[f"rot_{c}"] = g.quats[:, c]
    rows = g.ply_rows()
    assert list(rows.dtype.names) == g.ply_names() and rows.shape == (len(g),)
    ref = np.empty(len(g), rows.dtype)
    for name in g.ply_names():
        ref[name] = np.float32(src[name]) if np.isscalar(src[name]) else np.asarray(src[name]).astype(np.float32)
    assert ref.tobytes() == rows.tobytes()


@pytest.mark.parametrize("degree", [0, 2])
def test_ply_written_in_blocks_is_plyfiles_file_byte_for_byte(tmp_path, degree, monkeypatch):
    """save_ply writes its header and then PLY_WRITE_ROWS rows at a time (no copy of the whole scene): the same
    bytes as plyfile writes from the whole structured array, across block boundaries and for no rows."""
    import xyzcyl.runtime.render.gaussians as G
    from plyfile import PlyElement

    monkeypatch.setattr(G, "PLY_WRITE_ROWS", 64)
    for n in (0, 64, 1000):
        g = random_gaussians(np.random.default_rng(n), n, degree=degree) if n else Gaussians.empty(degree)
        g.save_ply(tmp_path / "ours.ply")
        PlyData([PlyElement.describe(g.ply_rows(), "vertex")], text=False, byte_order="<").write(
            str(tmp_path / "plyfile.ply"))
        assert (tmp_path / "ours.ply").read_bytes() == (tmp_path / "plyfile.ply").read_bytes()


def test_ply_properties_by_name_in_any_order(tmp_path):
    rng = np.random.default_rng(2)
    n = 5
    names = ["rot_3", "scale_2", "opacity", "f_dc_2", "z", "rot_0", "f_dc_0", "x", "scale_0", "rot_1", "y",
             "scale_1", "f_dc_1", "rot_2", "extra_field"]
    data = np.zeros(n, dtype=[(nm, "<f4") for nm in names])
    for nm in names:
        data[nm] = rng.normal(size=n)
    from plyfile import PlyElement
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "p.ply"))
    g = Gaussians.load_ply(tmp_path / "p.ply")
    assert np.array_equal(g.means[:, 1], data["y"]) and np.array_equal(g.quats[:, 3], data["rot_3"])
    assert g.sh_degree == 0 and np.array_equal(g.sh[:, 0, 2], data["f_dc_2"])


@pytest.mark.parametrize("degree", [0, 3])
def test_packed_float32_records_read_as_one_block_equal_the_field_by_field_read(tmp_path, degree):
    """The records save_ply writes (float32 properties packed in order) are read as one [N, P] block, a run of columns
    at a time; records of any other layout (here a float64 property added) field by field: the same Gaussians."""
    g = random_gaussians(np.random.default_rng(4), 300, degree=degree)
    g.save_ply(tmp_path / "g.ply")
    fast = Gaussians.load_ply_rows(tmp_path / "g.ply", 10, 290)
    names = g.ply_names()
    rec = np.frombuffer(g.ply_rows().tobytes(), dtype=[(nm, "<f4") for nm in names])[10:290]
    other = np.zeros(len(rec), dtype=[(nm, "<f4") for nm in names] + [("extra", "<f8")])
    for nm in names:
        other[nm] = rec[nm]
    slow = Gaussians._from_vertices(other, "test")
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(fast, f), getattr(slow, f))
        assert getattr(fast, f).flags.writeable and getattr(fast, f).flags.c_contiguous


def _write(tmp_path, g, name="g.ply"):
    path = tmp_path / name
    g.save_ply(path)
    return path


def test_ply_refusals(tmp_path):
    g = random_gaussians(np.random.default_rng(3), 50, degree=1)
    path = _write(tmp_path, g)
    raw = path.read_bytes()
    # truncated body
    (tmp_path / "t.ply").write_bytes(raw[:-5])
    with pytest.raises(GaussianError, match="truncated"):
        Gaussians.load_ply(tmp_path / "t.ply")
    # header claiming more points than allowed: refused before reading data (the body here is tiny)
    big = raw.replace(b"element vertex 50", b"element vertex 900000000", 1)
    (tmp_path / "b.ply").write_bytes(big)
    with pytest.raises(GaussianError, match="more than the maximum"):
        Gaussians.load_ply(tmp_path / "b.ply")
    with pytest.raises(GaussianError, match="more than the maximum 10"):
        Gaussians.load_ply(path, max_points=10)
    # non-finite values, counted
    means = g.means.copy()
    means[3, 1] = np.nan
    means[7, 0] = np.inf
    bad = Gaussians.__new__(Gaussians)
    for f in ("quats", "log_scales", "opacity_logits", "sh"):
        object.__setattr__(bad, f, getattr(g, f))
    object.__setattr__(bad, "means", means)
    Gaussians.save_ply(bad, tmp_path / "n.ply")
    with pytest.raises(GaussianError, match="means: 2 non-finite"):
        Gaussians.load_ply(tmp_path / "n.ply")
    # not a PLY; an f_rest count that is no SH degree
    (tmp_path / "x.ply").write_bytes(b"hello")
    with pytest.raises(GaussianError, match="not a PLY"):
        Gaussians.load_ply(tmp_path / "x.ply")
    odd = raw.replace(b"property float f_rest_8\n", b"", 1)
    odd = odd.replace(b"element vertex 50", b"element vertex 0", 1)
    head = odd[: odd.index(b"end_header\n") + len(b"end_header\n")]
    (tmp_path / "o.ply").write_bytes(head)
    with pytest.raises(GaussianError, match="f_rest"):
        Gaussians.load_ply(tmp_path / "o.ply")
    # a property line cut short (found by the long property run: it was an IndexError)
    for cut in (b"property\n", b"property float\n"):
        (tmp_path / "p.ply").write_bytes(raw.replace(b"property float x\n", cut, 1))
        with pytest.raises(GaussianError, match="not understood"):
            Gaussians.load_ply(tmp_path / "p.ply")


def test_gaussians_validation_names_the_field():
    g = random_gaussians(np.random.default_rng(4), 4)
    with pytest.raises(GaussianError, match="quats: expected shape"):
        Gaussians(g.means, g.quats[:, :3], g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(GaussianError, match="sh: expected shape"):
        Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.zeros((4, 5, 3)))
    ls = g.log_scales.copy()
    ls[0, 0] = np.nan
    with pytest.raises(GaussianError, match="log_scales: 1 non-finite"):
        Gaussians(g.means, g.quats, ls, g.opacity_logits, g.sh)
    with pytest.raises(GaussianError, match="quats: 1 quaternions with zero norm"):
        Gaussians(g.means, np.vstack([np.zeros((1, 4)), g.quats[1:]]), g.log_scales, g.opacity_logits, g.sh)


def test_splat_layout(tmp_path):
    g = random_gaussians(np.random.default_rng(5), 30, degree=1)
    g.save_splat(tmp_path / "g.splat")
    raw = (tmp_path / "g.splat").read_bytes()
    assert len(raw) == 32 * 30
    opa = 1 / (1 + np.exp(-g.opacity_logits.astype(np.float64)))
    key = np.exp(g.log_scales.astype(np.float64).sum(1)) * opa
    first = int(np.argmax(key))                                  # largest splat first
    rec = struct.unpack("<3f3f4B4B", raw[:32])
    assert np.allclose(rec[0:3], g.means[first]) and np.allclose(rec[3:6], np.exp(g.log_scales[first]), rtol=1e-6)
    rgb = np.clip((0.5 + SH_C0 * g.sh[first, 0].astype(np.float64)) * 255, 0, 255).astype(np.uint8)
    assert rec[6:9] == tuple(rgb) and rec[9] == int(opa[first] * 255)
    q = g.quats[first].astype(np.float64) / np.linalg.norm(g.quats[first])
    assert rec[10:14] == tuple(np.clip(q * 128 + 128, 0, 255).astype(np.uint8))
    # every row sorted by volume * opacity, descending (antimatter15's convert.py order)
    rows = np.frombuffer(raw, dtype=np.float32).reshape(30, 8)
    order = np.argsort(-key, kind="stable")
    assert np.array_equal(rows[:, 0:3], g.means[order])
    assert np.all(np.diff(key[order]) <= 0)


def test_camera_errors_name_their_field_as_an_attribute():
    """CameraError carries ``field`` and ``message`` (runtime.errors.FieldError): callers map the field to their
    own names (a CLI flag, a request field) without parsing the message, and the error survives pickling."""
    import pickle

    from xyzcyl.runtime.camera import Camera, CameraError
    from xyzcyl.runtime.errors import FieldError

    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    cases = ((dict(K=K * np.array([[-1], [1], [1]])), "K"), (dict(cam_to_ego=np.zeros((4, 4))), "cam_to_ego"),
             (dict(width=0), "width"), (dict(height=40000), "height"))
    for change, field in cases:
        args = dict(K=K, cam_to_ego=np.eye(4), width=100, height=80) | change
        with pytest.raises(CameraError) as info:
            Camera(**args)
        e = info.value
        assert isinstance(e, FieldError) and e.root_field == field and str(e) == f"{e.field}: {e.message}"
        again = pickle.loads(pickle.dumps(e))
        assert (type(again), again.field, again.message) == (CameraError, e.field, e.message)


def test_zero_quaternions_counted_as_numpy_counts_them():
    """Gaussians' check of zero quaternions (a kernel: _zero_quats) counts the rows numpy's float64 squared norms
    put below 1e-20, float32 and float64 rows, those just above and below the bound included."""
    from xyzcyl.runtime.render.gaussians import _zero_quats, _zero_quats_reference

    rng = np.random.default_rng(4)
    q = rng.normal(size=(20000, 4))
    q[::97] = 0.0
    q[1] = [1e-11, 0, 0, 0]                 # 1e-22: zero
    q[2] = [1e-9, 0, 0, 0]                  # 1e-18: not
    q[3] = [0, 0, -2e-11, 1e-11]            # 5e-22: zero
    for a in (q, q.astype(np.float32)):
        assert _zero_quats(np.ascontiguousarray(a)) == _zero_quats_reference(a) == len(range(0, len(q), 97)) + 2
