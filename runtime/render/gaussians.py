"""3D Gaussians: the container, its validation, and the INRIA 3DGS PLY / antimatter15 `.splat` formats.

Raw (optimised) parameters are stored, as in 3DGS: `log_scales`, `opacity_logits`, `quats` (wxyz, not
necessarily normalised) and spherical-harmonic coefficients `sh` [N, (d+1)^2, 3] with `sh[:, 0, :]` the DC
term (colour = SH_C0 * dc + 0.5 + higher bands, clamped at 0). See docs/renderer.md.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import prange

from ..directio import ALIGN, DirectReader, DirectWriter, aligned_buffer
from ..errors import FieldError
from ..numba_cache import njit
from .kernels import prefetch_row

SH_C0 = 0.28209479177387814
PLY_WRITE_ROWS = 1 << 18         # rows a PLY is written in at a time (18 MB of them at SH degree 0)
READ_WINDOW_BYTES = 16 << 20     # read_ply_take's reads (the disk measured: 1.2 GB/s in 16 MB reads, 1.4 in 64 MB)
READ_AHEAD = 3                   # and the windows it has asked for beyond the one it takes rows from (the disk kept
                                 # busy while the cores do other work too: a drive's chunks)
DEFAULT_MAX_POINTS = 20_000_000  # PLY reader refuses headers claiming more vertices (memory guard)
_PLY_DTYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "<i2", "ushort": "<u2",
               "int16": "<i2", "uint16": "<u2", "int": "<i4", "uint": "<u4", "int32": "<i4", "uint32": "<u4",
               "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}   # little endian


class GaussianError(FieldError):
    """Invalid Gaussian parameters or file: ``field`` the array ("means", "quats", ...), the PLY property or
    header entry ("rot_0", "f_rest", "element vertex", "format", "header", "body") or the .splat record field
    ("scale"); ``where`` the file ("PLY 'g.ply'", "splat"); field "splat" for .splat data as a whole."""


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def _n_rest_to_degree(n_rest: int) -> int | None:
    for d in range(4):
        if 3 * ((d + 1) ** 2 - 1) == n_rest:
            return d
    return None


FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")     # a Gaussians' arrays, in order


@dataclass(frozen=True)
class Gaussians:
    """N anisotropic 3D Gaussians in a world frame (the ego frame in this project).

    means: np.ndarray           # [N, 3] metres, world frame
    quats: np.ndarray           # [N, 4] rotation wxyz, any non-zero norm (normalised when used)
    log_scales: np.ndarray      # [N, 3] log of the standard deviations along the rotated axes (metres)
    opacity_logits: np.ndarray  # [N] logit of the opacity
    sh: np.ndarray              # [N, (d+1)^2, 3] SH coefficients, d in 0..3, sh[:, 0, :] DC

    Arrays keep their floating dtype (float32 normally; float64 is accepted for gradient checks).
    Construction validates shapes and finiteness and raises GaussianError naming the field.
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        fields = {}
        for name in FIELDS:
            arr = np.asarray(getattr(self, name))
            if not np.issubdtype(arr.dtype, np.floating):
                arr = arr.astype(np.float32)
            object.__setattr__(self, name, arr)
            fields[name] = arr
        means = fields["means"]
        if means.ndim != 2 or means.shape[1] != 3:
            raise GaussianError("means", f"expected shape [N, 3], got {list(means.shape)}")
        n = means.shape[0]
        expect = {"quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        for name, shape in expect.items():
            if fields[name].shape != shape:
                raise GaussianError(name, f"expected shape {list(shape)}, got {list(fields[name].shape)}")
        sh = fields["sh"]
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
            raise GaussianError("sh", f"expected shape [N, (d+1)^2 with d in 0..3, 3] with N={n}, got {list(sh.shape)}")
        for name, arr in fields.items():
            bad = int(np.count_nonzero(~np.isfinite(arr)))
            if bad:
                raise GaussianError(name, f"{bad} non-finite values")
        zero = _zero_quats(np.ascontiguousarray(fields["quats"]))
        if zero:
            raise GaussianError("quats", f"{zero} quaternions with zero norm")

    # ----------------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def scales(self) -> np.ndarray:  # [N, 3] metres
        return np.exp(self.log_scales)

    @property
    def opacities(self) -> np.ndarray:  # [N] in (0, 1)
        return sigmoid(self.opacity_logits)

    @classmethod
    def empty(cls, sh_degree: int = 0, dtype=np.float32) -> Gaussians:
        k = (sh_degree + 1) ** 2
        return cls(np.zeros((0, 3), dtype), np.zeros((0, 4), dtype), np.zeros((0, 3), dtype),
                   np.zeros((0,), dtype), np.zeros((0, k, 3), dtype))

    def with_opacity_logits(self, logits: np.ndarray) -> Gaussians:
        """The same Gaussians with other opacity logits [N] (the other fields shared, not copied or checked again:
        runtime.detail.OwnViews builds an input camera's own view this way, per render)."""
        a = np.asarray(logits, self.opacity_logits.dtype)
        if a.shape != self.opacity_logits.shape:
            raise GaussianError("opacity_logits", f"expected shape {list(self.opacity_logits.shape)}, got "
                                                  f"{list(a.shape)}")
        bad = int(np.count_nonzero(~np.isfinite(a)))
        if bad:
            raise GaussianError("opacity_logits", f"{bad} non-finite values")
        out = Gaussians.joined(means=self.means, quats=self.quats, log_scales=self.log_scales, opacity_logits=a,
                               sh=self.sh)
        object.__setattr__(out, "_box_parent", (self, 0))      # the same means and scales: the same boxes
        return out

    def transformed(self, T: np.ndarray) -> Gaussians:
        """The Gaussians moved by the rigid [4, 4] ``T`` (frame -> another frame, metres): means and rotations, in
        one numba pass (transformed_reference is its numpy definition: the same quaternions bit for bit, the means
        within a rounding; tested). SH of degree 0 (a colour) does not turn with the Gaussian; higher degrees would
        (GaussianError: not implemented). The other fields are shared, not copied; GaussianError naming the field
        when a result is not finite (a T with non-finite or huge entries)."""
        if self.sh_degree > 0:
            raise GaussianError("sh", f"moving Gaussians needs SH degree 0 (got degree {self.sh_degree}): rotating "
                                      "higher SH bands is not implemented")
        from ..rotations import rotmats_to_quats

        T = np.asarray(T, np.float64)
        q1 = np.ascontiguousarray(rotmats_to_quats(T[None, :3, :3])[0], np.float64)
        means, quats = np.empty_like(self.means), np.empty_like(self.quats)
        bad_m, bad_q = _rigid_kernel(np.ascontiguousarray(self.means), np.ascontiguousarray(self.quats),
                                     np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), q1, means, quats)
        for name, bad in (("means", bad_m), ("quats", bad_q)):
            if bad:
                raise GaussianError(name, f"{bad} non-finite values")
        return Gaussians.joined(means=means, quats=quats, log_scales=self.log_scales,
                                opacity_logits=self.opacity_logits, sh=self.sh)

    def slice(self, start: int, stop: int) -> Gaussians:
        """Gaussians start..stop - 1 as views of these arrays (no copy; Scene draws a drive's keyframes this way,
        per render). It draws with these Gaussians' pre-cull boxes (box_grid)."""
        out = self._taken(slice(start, stop))
        object.__setattr__(out, "_box_parent", (self, slice(start, stop).indices(len(self))[0]))
        return out

    def __getstate__(self) -> dict:
        """The fields alone: a pickled slice (a worker's result, a process pool's argument) does not carry its
        parent or the pre-cull boxes (box_grid, made again where they are needed)."""
        return {f: getattr(self, f) for f in FIELDS}

    def box_grid(self) -> tuple[np.ndarray, int]:
        """(boxes [B, 7] float64, phase): the renderer's pre-cull boxes (kernels.sub_boxes: the box of each run of
        kernels.SUB_CHUNK rows) of the set these Gaussians are rows phase .. of, read by each render instead of the
        means (a drive's later layers test millions of Gaussians against the tiles the layers before covered). A
        slice's are its parent's (made when first asked for), and so are those of the same Gaussians with other
        opacities (with_opacity_logits: an input camera's own view); a set's are made once and kept with it: a set's
        arrays are not changed once it is made (every change makes new Gaussians)."""
        got = self.__dict__.get("_box_grid")
        if got is None:
            parent = self.__dict__.get("_box_parent")
            if parent is not None:
                boxes, phase = parent[0].box_grid()
                got = (boxes, phase + parent[1])
            else:
                from .kernels import sub_boxes

                got = (sub_boxes(np.ascontiguousarray(self.means), np.ascontiguousarray(self.log_scales)), 0)
            object.__setattr__(self, "_box_grid", got)
        return got

    def subset(self, keep: np.ndarray) -> Gaussians:
        """The Gaussians where ``keep`` ([N] bool, or indices) selects, in order."""
        return self._taken(keep)

    @classmethod
    def joined(cls, **fields: np.ndarray) -> Gaussians:
        """Gaussians of the given arrays (every field by name), not checked again: rows of checked Gaussians taken
        or put together (subset, with_opacity_logits, concat_gaussians; a drive's millions)."""
        out = object.__new__(cls)
        for name in FIELDS:
            object.__setattr__(out, name, fields[name])
        return out

    def _taken(self, index) -> Gaussians:
        """These Gaussians indexed by ``index`` along N, not checked again: a selection of checked Gaussians (the
        drive's fusion takes thousands of subsets of millions; take_rows)."""
        if isinstance(index, slice):
            return Gaussians.joined(**{name: getattr(self, name)[index] for name in FIELDS})
        return Gaussians.joined(**dict(zip(FIELDS, take_rows([getattr(self, name) for name in FIELDS], index))))

    def astype(self, dtype) -> Gaussians:
        return Gaussians(*(np.asarray(getattr(self, f), dtype=dtype) for f in
                           FIELDS))

    # ---------------------------------------------------------------------------------------- PLY (INRIA)
    def ply_names(self, normals: bool = True) -> list[str]:
        """The PLY's vertex properties, in order: x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3
        (``normals`` False: without nx ny nz, which 3DGS readers do not use)."""
        k = self.sh.shape[1]
        return (["x", "y", "z", *(("nx", "ny", "nz") if normals else ()), "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(3 * (k - 1))]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])

    def ply_rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """[stop - start] structured array of the PLY's vertices start..stop - 1 (default all; ply_names,
        little-endian float32), a view of one [n, P] float32 block filled a property group at a time (a
        field-by-field fill of a structured array, through float64, took 0.93 s of a 1.1 s save for 2.16 M
        Gaussians; this 0.1 s)."""
        stop = max(start, len(self) if stop is None else min(stop, len(self)))
        names = self.ply_names()
        rows = np.empty((stop - start, len(names)), "<f4")
        self._fill_ply_rows(start, stop, rows)
        return rows.view(np.dtype([(name, "<f4") for name in names])).reshape(len(rows))

    def _fill_ply_rows(self, start: int, stop: int, rows: np.ndarray, normals: bool = True) -> None:
        """Write vertices start..stop - 1 (ply_rows' values) into rows[:stop - start] ([m, P] float32, P the count of
        ply_names(normals)), a property group at a time."""
        n, k = stop - start, self.sh.shape[1]
        sh = self.sh[start:stop]
        rows[:n, 0:3] = self.means[start:stop]
        d = 3
        if normals:
            rows[:n, 3:6] = 0.0                                  # normals: unused by 3DGS readers
            d = 6
        rows[:n, d:d + 3] = sh[:, 0, :]
        j = d + 3 + 3 * (k - 1)
        if k > 1:                                                # channel-major: c * (k - 1) + (coefficient - 1)
            rows[:n, d + 3:j] = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))
        rows[:n, j] = self.opacity_logits[start:stop]
        rows[:n, j + 1:j + 4] = self.log_scales[start:stop]
        rows[:n, j + 4:j + 8] = self.quats[start:stop]

    def save_ply(self, path: str | os.PathLike) -> None:
        """Write the INRIA 3DGS layout: binary little endian, float32, properties
        x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3; f_rest channel-major
        (f_rest index = c * ((d+1)^2 - 1) + k for colour channel c and SH coefficient k >= 1)."""
        save_ply_parts(path, [self])

    @classmethod
    def load_ply(cls, path: str | os.PathLike, max_points: int = DEFAULT_MAX_POINTS) -> Gaussians:
        """Read a 3DGS PLY (properties looked up by name; SH degree 0..3 inferred from the f_rest count).

        Refuses (GaussianError naming the field): a header claiming more than `max_points` vertices (checked
        before any data is read), a truncated binary body, missing properties, an f_rest count that is not
        3*((d+1)^2-1), and non-finite values (with their count)."""
        from plyfile import PlyData

        path = Path(path)
        where = _ply_where(path)
        n, props, fmt, header_len = _read_ply_header(path)
        if n > max_points:
            raise GaussianError("element vertex", f"header claims {n} points, more than the maximum {max_points}",
                                where)
        if fmt != "ascii":
            _check_body(path, n, props, header_len)
        try:
            ply = PlyData.read(str(path))
            vert = ply["vertex"].data
        except Exception as exc:  # plyfile raises various types on malformed bodies
            raise GaussianError("body", f"unreadable: {exc}", where) from None
        return cls._from_vertices(vert, where)

    @classmethod
    def load_ply_rows(cls, path: str | os.PathLike, start: int, stop: int) -> Gaussians:
        """Vertices start..stop - 1 of a binary little-endian 3DGS PLY (load_ply's checks on them), read from their
        bytes alone: a drive scene's tile (runtime.tiles) is one run of its scene.ply."""
        path = Path(path)
        where = _ply_where(path)
        n, dtype, header_len = ply_rows_layout(path, check_body=False)
        if not 0 <= start <= stop <= n:
            raise GaussianError("element vertex", f"rows {start}..{stop} outside the file's {n} vertices", where)
        if stop == start:
            return cls._from_vertices(np.zeros(0, dtype), where)
        if path.stat().st_size < header_len + stop * dtype.itemsize:
            raise GaussianError("body", f"truncated: rows {start}..{stop} end past the file's end", where)
        # the rows through a copy-on-write map of the file (load_ply_take: no fresh copy of them to fault in; a
        # writable array: np.frombuffer of bytes is read-only, another signature of the numba reader, compiled on
        # a drive's first view in a service warmed up on a one-rig scene)
        try:
            raw = np.memmap(path, dtype, mode="c", offset=header_len + start * dtype.itemsize, shape=(stop - start,))
        except (ValueError, OSError) as exc:    # cut short since its size was read
            raise GaussianError("body", f"truncated: {exc}", where) from None
        return cls._from_vertices(np.asarray(raw), where)

    @classmethod
    def load_ply_take(cls, path: str | os.PathLike, rows: np.ndarray, head: Gaussians | None = None) -> Gaussians:
        """Vertices ``rows`` ([M] integers, in that order, repeats allowed) of a binary little-endian 3DGS PLY
        (load_ply's checks on them), read through a map of the file: a drive's viewpoint chunk is rows of its
        keyframe's camera layers (runtime.viewpoints). GaussianError "rows" for a row outside the file. ``head``:
        Gaussians put before them (the chunk's own; the result is their concatenation, concat_gaussians), written
        into the same arrays when their SH degree is the file's."""
        path = Path(path)
        where = _ply_where(path)
        n, dtype, header_len = ply_rows_layout(path)
        rows = _checked_rows(rows, n, where)
        p = len(dtype.names or ())
        names = dtype.names or ()
        packed = _packed(n, dtype)
        degree = _n_rest_to_degree(sum(1 for k in names if k.startswith("f_rest_"))) or 0
        # head's rows written into the result's arrays by the unpacking (one allocation, no concatenation after)
        fused = packed and head is not None and len(head) > 0 and head.sh.shape[1] == (degree + 1) ** 2
        if packed:
            # packed float32 records (what save_ply writes): the rows taken from a [n, P] map of the records by the
            # unpacking kernel, straight into the result. Not read into memory first: in a service that has drawn a
            # while, a fresh 250 MB block cost 0.3-0.65 s of page faults (huge pages compacted) where the file's own
            # cached pages cost none; copy-on-write: a writable array, the kernel's one signature. (Through a map of
            # the structured records, 0.4-0.7 s.)
            try:
                block = np.memmap(path, "<f4", mode="c", offset=header_len, shape=(n * p,))
            except (ValueError, OSError) as exc:    # shorter than its header says (changed since checked)
                raise GaussianError("body", f"truncated: {exc}", where) from None
            taken = cls._from_vertices(np.asarray(block).view(dtype).reshape(-1), where, rows, head if fused else None)
        elif n == 0:
            taken = cls._from_vertices(np.zeros(0, dtype), where)
        else:
            body = np.memmap(path, dtype, mode="r", offset=header_len, shape=(n,))
            taken = cls._from_vertices(body[rows], where)
        if fused or head is None or not len(head):
            return taken
        return concat_gaussians([head, taken]) if len(taken) else head

    @classmethod
    def read_ply_take(cls, path: str | os.PathLike, rows: np.ndarray, box_of: np.ndarray | None = None,
                      box: np.ndarray | None = None) -> Gaussians:
        """load_ply_take(path, rows) of a file read once and not again soon (a drive's camera layer files at the end
        of its reconstruction, written past the page cache: save_ply_parts(direct=True)): the windows of
        READ_WINDOW_BYTES that hold a row read past the page cache too (runtime.directio), the next READ_AHEAD on a
        thread while the rows of one are taken. ``box_of`` ([K] integers, checked as ``rows``): rows whose means widen
        ``box`` ([2, 3] float64: min; max) in the same pass (a drive's chunk's box, runtime.viewpoints). A file
        whose records are not packed float32 at a float32's alignment (a header of a length not a multiple of 4)
        is read through a map of it, as load_ply_take does."""
        path = Path(path)
        where = _ply_where(path)
        n, dtype, header_len = ply_rows_layout(path)
        rows = _checked_rows(rows, n, where)
        more = _checked_rows(np.zeros(0, np.intp) if box_of is None else box_of, n, where)
        names = list(dtype.names or ())
        if len(more) and (box is None or names[names.index("x"):names.index("x") + 3] != ["x", "y", "z"]):
            raise ValueError("box_of: a box [2, 3] to widen, and x y z one after the other in the file")
        if not _packed(n, dtype) or header_len % 4 or not (len(rows) or len(more)):
            if len(more):             # the records as they are (any property types)
                body = np.memmap(path, dtype, mode="r", offset=header_len, shape=(n,))[more]
                xyz = np.stack([body[c].astype(np.float64) for c in "xyz"], axis=1)
                box[0], box[1] = np.minimum(box[0], xyz.min(axis=0)), np.maximum(box[1], xyz.max(axis=0))
            return cls.load_ply_take(path, rows)
        k = ((_n_rest_to_degree(sum(1 for p in names if p.startswith("f_rest_"))) or 0) + 1) ** 2
        cols = ply_columns(names, k)
        order = np.argsort(rows, kind="stable")
        ordered = rows[order].astype(np.int64)
        per = max(1, READ_WINDOW_BYTES // dtype.itemsize)                  # records a window
        # box_of's rows marked, not sorted (a drive's chunk: most of the file)
        marked = np.zeros(-(-n // per) * per, bool)
        marked[more] = True
        windows = np.union1d(ordered // per, np.flatnonzero(marked.reshape(-1, per).any(axis=1)))
        cuts = np.searchsorted(ordered, np.concatenate([windows, windows[-1:] + 1]) * per)
        out = _empty_fields(len(rows), k)
        sh = out["sh"].reshape(len(rows), 3 * k)
        bad = np.zeros(6, np.int64)
        bufs = [aligned_buffer(DirectReader.buffer_bytes(per * dtype.itemsize))
                for _ in range(min(READ_AHEAD + 1, len(windows)))]

        def read(w: int, buf: np.ndarray) -> np.ndarray:      # window w's records [records, P] float32
            lo, hi = int(windows[w]) * per, min(int(windows[w] + 1) * per, n)
            got = reader.read(header_len + lo * dtype.itemsize, header_len + hi * dtype.itemsize, buf)
            return got.view("<f4").reshape(hi - lo, len(names))

        try:
            with DirectReader(path) as reader, ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-ply-read") as pool:
                ahead = deque(pool.submit(read, w, bufs[w]) for w in range(len(bufs) - 1))
                for w in range(len(windows)):
                    if w + len(bufs) - 1 < len(windows):     # the buffer the window before used is free again
                        ahead.append(pool.submit(read, w + len(bufs) - 1, bufs[(w + len(bufs) - 1) % len(bufs)]))
                    block = ahead.popleft().result()
                    first = int(windows[w]) * per
                    a, b = cuts[w], cuts[w + 1]
                    if b > a:
                        bad += _unpack_kernel(block, ordered[a:b] - first, True, order[a:b], True, cols,
                                              out["means"], out["quats"], out["log_scales"], out["opacity_logits"],
                                              sh)
                    if len(more):
                        rows_box(block, names.index("x"), np.flatnonzero(marked[first:first + len(block)]), box)
        except OSError as exc:             # shorter than its header says (changed since checked), unreadable
            raise GaussianError("body", f"not read: {exc}", where) from None
        _raise_bad(bad, where)
        return cls.joined(**out)

    @classmethod
    def _from_vertices(cls, vert: np.ndarray, where: str, rows: np.ndarray | None = None,
                       head: Gaussians | None = None) -> Gaussians:
        """Gaussians from a PLY's vertex records [N] (structured: the 3DGS properties by name), checked
        (GaussianError naming the property or field, at ``where``); ``rows`` ([M] in 0..N-1, checked by the caller):
        those records, in that order (None: all); ``head``: Gaussians of the records' SH degree put before them, in
        the same arrays (load_ply_take; packed float32 records only)."""
        names = set(vert.dtype.names or ())
        required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        missing = [p for p in required if p not in names]
        if missing:
            raise GaussianError(missing[0], "vertex property missing", where)
        n_rest = sum(1 for p in names if p.startswith("f_rest_"))
        degree = _n_rest_to_degree(n_rest)
        if degree is None:
            raise GaussianError("f_rest", f"{n_rest} properties, expected 0, 9, 24 or 45 (SH degree 0..3)", where)
        for i in range(n_rest):
            if f"f_rest_{i}" not in names:
                raise GaussianError(f"f_rest_{i}", "vertex property missing", where)

        fields = vert.dtype.fields or {}
        order = list(vert.dtype.names or ())
        k = (degree + 1) ** 2
        if (vert.flags.c_contiguous and vert.dtype.itemsize == 4 * len(order)
                and all(fields[p][0] == np.dtype("<f4") and fields[p][1] == 4 * i for i, p in enumerate(order))):
            # packed float32 records (what save_ply writes; plyfile's too): one pass that takes the rows, splits
            # them into the fields and counts what the checks count (numpy: a strided copy a column group, a take,
            # the checks twice: 0.9 s of a 3 M-row drive chunk)
            return _unpacked(vert.view("<f4").reshape(len(vert), len(order)), order, k, rows, where, head)
        if head is not None:
            raise ValueError("head: only with packed float32 records")
        if rows is not None:
            vert = vert[rows]
        n = len(vert)

        def col(*ps):
            return np.stack([np.asarray(vert[p], dtype=np.float32) for p in ps], axis=1)

        sh = np.empty((n, k, 3), np.float32)
        sh[:, 0, :] = col("f_dc_0", "f_dc_1", "f_dc_2")
        if k > 1:
            rest = col(*[f"f_rest_{i}" for i in range(n_rest)])  # [N, 3*(k-1)] channel-major
            sh[:, 1:, :] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
        arrays = dict(means=col("x", "y", "z"), quats=col("rot_0", "rot_1", "rot_2", "rot_3"),
                      log_scales=col("scale_0", "scale_1", "scale_2"),
                      # a copy: the PLY's column is a strided view (one record apart), which every render
                      # gathered again (~20 ms a drive view); a read-only buffer made numba compile the projection
                      # again for read-only opacities (6 s, mid-service)
                      opacity_logits=np.array(vert["opacity"], dtype=np.float32), sh=sh)
        for name, arr in arrays.items():
            bad = int(np.count_nonzero(~np.isfinite(arr)))
            if bad:
                raise GaussianError(name, f"{bad} non-finite values", where)
        try:
            return cls(**arrays)
        except GaussianError as exc:
            raise GaussianError(exc.field, exc.message, where) from None

    # ---------------------------------------------------------------------------------- .splat (antimatter15)
    def splat_bytes(self) -> bytes:
        """antimatter15/splat `.splat`: 32 bytes per splat, no header, little endian, rows sorted by
        exp(sum log_scales) * sigmoid(opacity) descending (as its convert.py):
          float32 x, y, z | float32 exp(scale_0..2) | uint8 R, G, B, A | uint8 qw, qx, qy, qz
        RGB = clip(255 * (0.5 + SH_C0 * dc), 0, 255) truncated, A = 255 * sigmoid(opacity) truncated,
        quaternion normalised, clip(q * 128 + 128, 0, 255) truncated. Higher SH bands are dropped."""
        n = len(self)
        ls = self.log_scales.astype(np.float64)
        opa = sigmoid(self.opacity_logits.astype(np.float64))
        order = np.argsort(-np.exp(ls.sum(axis=1)) * opa, kind="stable")
        rec = np.empty(n, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
        rec["pos"] = self.means[order]
        rec["scale"] = np.exp(ls[order])
        rgba = np.concatenate([0.5 + SH_C0 * self.sh[order, 0, :].astype(np.float64), opa[order, None]], axis=1)
        rec["rgba"] = np.clip(rgba * 255.0, 0, 255).astype(np.uint8)
        q = self.quats[order].astype(np.float64)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        rec["rot"] = np.clip(q * 128.0 + 128.0, 0, 255).astype(np.uint8)
        return rec.tobytes()

    def save_splat(self, path: str | os.PathLike) -> None:
        Path(path).write_bytes(self.splat_bytes())

    @classmethod
    def from_splat_bytes(cls, data: bytes, max_points: int = DEFAULT_MAX_POINTS) -> Gaussians:
        """Parse antimatter15 `.splat` bytes (the layout of splat_bytes) into SH degree 0 Gaussians. The format is
        lossy: colour and opacity are 8-bit (a stored 0 or 255 opacity is clamped to 0.5/255 from the ends so the
        logit stays finite), the quaternion is 8 bits per component. GaussianError when the length is not a
        multiple of 32, the count is over ``max_points``, a value is not finite, a scale is <= 0 or a quaternion
        is zero."""
        if len(data) % 32:
            raise GaussianError("splat", f"{len(data)} bytes is not a multiple of 32 (one record per Gaussian)")
        n = len(data) // 32
        if n > max_points:
            raise GaussianError("splat", f"{n} records, more than the maximum {max_points}")
        rec = np.frombuffer(data, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                                         ("rot", "u1", 4)], count=n)
        pos, scale = rec["pos"].astype(np.float32), rec["scale"].astype(np.float64)
        for name, a in (("position", pos), ("scale", scale)):
            bad = int(np.count_nonzero(~np.isfinite(a)))
            if bad:
                raise GaussianError(name, f"{bad} non-finite values", "splat")
        if (scale <= 0).any():
            raise GaussianError("scale", f"{int(np.count_nonzero(scale <= 0))} values <= 0", "splat")
        rgba = rec["rgba"].astype(np.float64) / 255.0
        q = (rec["rot"].astype(np.float64) - 128.0) / 128.0
        if (np.linalg.norm(q, axis=1) == 0).any():
            raise GaussianError("rotation", "zero quaternion", "splat")
        a = np.clip(rgba[:, 3], 0.5 / 255.0, 1.0 - 0.5 / 255.0)
        return cls(means=pos, quats=q.astype(np.float32), log_scales=np.log(scale).astype(np.float32),
                   opacity_logits=np.log(a / (1.0 - a)).astype(np.float32),
                   sh=((rgba[:, None, :3] - 0.5) / SH_C0).astype(np.float32))

    @classmethod
    def load_splat(cls, path: str | os.PathLike, max_points: int = DEFAULT_MAX_POINTS) -> Gaussians:
        """Read a `.splat` file (from_splat_bytes); the size is checked before the file is read."""
        path = Path(path)
        size = path.stat().st_size
        if size // 32 > max_points:
            raise GaussianError("splat", f"{path.name!r} has {size // 32} records, more than the maximum {max_points}")
        return cls.from_splat_bytes(path.read_bytes(), max_points)


def save_ply_parts(path: str | os.PathLike, parts: Sequence[Gaussians], normals: bool = True,
                   direct: bool = False) -> None:
    """Write ``parts`` (one SH degree) as one 3DGS PLY of their concatenation, in order (Gaussians.save_ply's
    layout; ``normals`` False: without nx ny nz, a sixth fewer bytes at SH degree 0), a block of each at a time: the
    parts are never joined in memory (a drive's camera layers: runtime.cameralayers). ``direct``: past the page
    cache (runtime.directio: a file that is read once, if at all, while it is written), its header padded by a
    comment to a multiple of 4 bytes so that every record lies at a float32's alignment (read_ply_take)."""
    parts = list(parts)
    if not parts:
        raise ValueError("parts: at least one Gaussians")
    if len({p.sh.shape[1] for p in parts}) > 1:
        raise ValueError("parts: one SH degree for all")
    names = parts[0].ply_names(normals)
    header = "".join(["ply\nformat binary_little_endian 1.0\n", f"element vertex {sum(map(len, parts))}\n",
                      *(f"property float {name}\n" for name in names), "end_header\n"])
    if direct:
        pad = -(len(header) + len("comment records aligned\n")) % 4
        header = header.replace("element", f"comment records aligned{' ' * pad}\nelement", 1)
        _save_ply_parts_direct(path, parts, header.encode("ascii"), len(names), normals)
        return
    # a block at a time through one buffer: no copy of the whole scene, and no fresh pages to fault in for each block
    # (3.4 M Gaussians written, median of 7: 0.47 -> 0.43 s at SH degree 0, 0.98 -> 0.74 s at degree 3)
    rows = np.empty((min(PLY_WRITE_ROWS, max(map(len, parts))), len(names)), "<f4")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for p in parts:
            for a in range(0, len(p), PLY_WRITE_ROWS):
                b = min(a + PLY_WRITE_ROWS, len(p))
                p._fill_ply_rows(a, b, rows, normals)
                f.write(rows[:b - a])


def _save_ply_parts_direct(path: str | os.PathLike, parts: Sequence[Gaussians], header: bytes, props: int,
                           normals: bool) -> None:
    """save_ply_parts(direct=True)'s writing: each block of rows filled in place in the writer's buffer (``header``
    a multiple of 4 bytes long: the rows' floats aligned)."""
    row_bytes = 4 * props
    with DirectWriter(path, PLY_WRITE_ROWS * row_bytes + 2 * ALIGN) as w:
        w.write(header)
        for p in parts:
            for a in range(0, len(p), PLY_WRITE_ROWS):
                b = min(a + PLY_WRITE_ROWS, len(p))
                p._fill_ply_rows(a, b, w.space((b - a) * row_bytes).view("<f4").reshape(b - a, props), normals)
                w.advance((b - a) * row_bytes)


def _checked_rows(rows: np.ndarray, n: int, where: str) -> np.ndarray:
    """``rows`` as [M] intp rows of a PLY of ``n`` vertices (GaussianError "rows" naming what is wrong)."""
    rows = np.asarray(rows)
    if rows.ndim != 1 or not (np.issubdtype(rows.dtype, np.integer) or rows.size == 0):
        raise GaussianError("rows", f"must be a 1-D array of integers, got {rows.dtype} {list(rows.shape)}", where)
    if rows.size and (int(rows.min()) < 0 or int(rows.max()) >= n):
        raise GaussianError("rows", f"rows {int(rows.min())}..{int(rows.max())} outside the file's {n} vertices",
                            where)
    return rows.astype(np.intp, copy=False)


def _packed(n: int, dtype: np.dtype) -> bool:
    """A PLY's records (``n`` of ``dtype``) are packed float32 (what save_ply writes)."""
    names = dtype.names or ()
    return n > 0 and dtype.itemsize == 4 * len(names) and all(dtype.fields[k][0] == np.dtype("<f4") for k in names)


def _ply_where(path: Path) -> str:
    """A PLY file as its errors name it (their ``where``)."""
    return f"PLY {path.name!r}"


def ply_rows_layout(path: Path, check_body: bool = True) -> tuple[int, np.dtype, int]:
    """(vertex count, the record dtype, header bytes) of a binary little-endian PLY whose rows are read by position
    (load_ply_rows; a drive's tiled scene.ply), from its header; ``check_body``: the file holds every row.
    GaussianError naming the header entry or the body otherwise."""
    n, props, fmt, header_len = _read_ply_header(path)
    if fmt != "binary_little_endian":
        raise GaussianError("format", f"{fmt!r}: reading vertices by position needs binary_little_endian",
                            _ply_where(path))
    dtype = _check_body(path, n, props, header_len) if check_body else _record_dtype(props)
    return n, dtype, header_len


def _record_dtype(props: list[tuple[str, str]]) -> np.dtype:
    """The little-endian record of the vertex properties [(name, PLY type)] (the byte order's sizes alike)."""
    return np.dtype([(name, _PLY_DTYPES[t]) for name, t in props])


def _check_body(path: Path, n: int, props: list[tuple[str, str]], header_len: int) -> np.dtype:
    """The record dtype of a binary PLY's vertices, after checking the file holds all ``n`` of them (GaussianError
    "body" truncated, naming the sizes)."""
    dtype = _record_dtype(props)
    need = header_len + n * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise GaussianError("body", f"truncated: {size} bytes, header needs {need} "
                                    f"({n} vertices x {dtype.itemsize} bytes + {header_len} header bytes)",
                            _ply_where(path))
    return dtype


def _read_ply_header(path: Path) -> tuple[int, list[tuple[str, str]], str, int]:
    """Parse only the PLY header: (vertex count, vertex properties [(name, type)], format, header bytes)."""
    where = _ply_where(path)
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise GaussianError("header", "not a PLY file (missing 'ply' magic or 'end_header')", where)
    nl = head.find(b"\n", end)
    if nl < 0:
        raise GaussianError("header", "truncated", where)
    header_len = nl + 1
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt, n, props, element, seen_vertex, before = None, None, [], None, False, 0
    for line in lines:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            element = tok[1]
            if element == "vertex":
                seen_vertex = True
                try:
                    n = int(tok[2])
                except ValueError:
                    raise GaussianError("element vertex", f"bad count {tok[2]!r}", where) from None
            elif not seen_vertex:
                before += 1
        elif tok[0] == "property" and element == "vertex":
            if len(tok) < 3:               # a bare "property" line (it was an IndexError)
                raise GaussianError("header", f"vertex property line {line!r} not understood", where)
            if tok[1] == "list":
                raise GaussianError(tok[-1], "vertex property: list properties not supported", where)
            if len(tok) != 3 or tok[1] not in _PLY_DTYPES:
                raise GaussianError("header", f"vertex property line {line!r} not understood", where)
            if any(name == tok[2] for name, _ in props):     # a record cannot hold two (numpy's ValueError)
                raise GaussianError(tok[2], "vertex property given twice", where)
            props.append((tok[2], tok[1]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise GaussianError("format", f"{fmt!r} not supported", where)
    if n is None:
        raise GaussianError("element vertex", "not in the header", where)
    if n < 0:
        raise GaussianError("element vertex", f"negative count {n}", where)
    if before:
        raise GaussianError("element vertex", "must come first", where)
    return n, props, fmt, header_len


def ply_columns(order: Sequence[str], k: int) -> np.ndarray:
    """[11 + 3 k] int64: the column of a PLY record (its properties ``order``) that each value of a Gaussian comes
    from, in _unpack_kernel's order: x y z, rot_0..3, scale_0..2, opacity, then SH coefficient j's channels c
    (f_dc_c for j = 0; f_rest_{c (k - 1) + j - 1}, channel-major, above)."""
    names = ["x", "y", "z", "rot_0", "rot_1", "rot_2", "rot_3", "scale_0", "scale_1", "scale_2", "opacity"]
    names += [f"f_dc_{c}" if j == 0 else f"f_rest_{c * (k - 1) + j - 1}" for j in range(k) for c in range(3)]
    at = {p: i for i, p in enumerate(order)}
    return np.array([at[p] for p in names], np.int64)


def _unpacked(block: np.ndarray, order: Sequence[str], k: int, rows: np.ndarray | None, where: str,
              head: Gaussians | None = None) -> Gaussians:
    """Gaussians of a PLY's packed float32 records ``block`` [N, P] (properties ``order``; rows ``rows`` or all),
    k SH coefficients, by _unpack_kernel; GaussianError naming the field that holds non-finite values (their
    count) or zero quaternions, as the Gaussians' own checks do. ``head`` (k SH coefficients too): checked
    Gaussians copied in front, in the same arrays."""
    m = len(block) if rows is None else len(rows)
    h = 0 if head is None else len(head)
    take = np.zeros(0, np.int64) if rows is None else np.ascontiguousarray(rows, np.int64)    # one signature
    out = _empty_fields(h + m, k)
    if h:
        for name, dst in out.items():
            dst[:h] = getattr(head, name)
    bad = _unpack_kernel(block, take, rows is not None, _NO_ROWS, False, ply_columns(order, k), out["means"][h:],
                         out["quats"][h:], out["log_scales"][h:], out["opacity_logits"][h:],
                         out["sh"][h:].reshape(m, 3 * k))
    _raise_bad(bad, where)
    return Gaussians.joined(**out)


_NO_ROWS = np.zeros(0, np.int64)


def _empty_fields(m: int, k: int) -> dict[str, np.ndarray]:
    """Uninitialised arrays of m Gaussians with k SH coefficients, by field."""
    return dict(means=np.empty((m, 3), np.float32), quats=np.empty((m, 4), np.float32),
                log_scales=np.empty((m, 3), np.float32), opacity_logits=np.empty(m, np.float32),
                sh=np.empty((m, k, 3), np.float32))


def _raise_bad(bad: np.ndarray, where: str) -> None:
    """GaussianError for _unpack_kernel's counts ``bad`` [6] (the first field with non-finite values, or zero
    quaternions), as the Gaussians' own checks name them."""
    for name, count in zip(FIELDS, bad[:5]):
        if count:
            raise GaussianError(name, f"{int(count)} non-finite values", where)
    if bad[5]:
        raise GaussianError("quats", f"{int(bad[5])} quaternions with zero norm", where)


PREFETCH_ROWS = 32      # _unpack_kernel asks the CPU for the record this many rows ahead of the one it reads: a chunk's
                        # rows are taken from its keyframe's camera layer file in the chunk's (spatial) order, all
                        # over a 250 MB file; with the next records on their way, 3.3 M rows 62 -> 18 ms (the
                        # copy alone, a PandaSet keyframe's chunk; 8 rows ahead: 29 ms, 64: as 32)


@njit(cache=True, nogil=True)
def _zero_quats(q):
    """How many rows of ``q`` [N, 4] have a squared norm below 1e-20 (summed in float64): Gaussians' check, in one
    pass (numpy's float64 einsum of the same took 6 ms for a camera's 500 k cells: the most of the check)."""
    n = 0
    for i in range(q.shape[0]):
        s = 0.0
        for k in range(q.shape[1]):
            v = np.float64(q[i, k])
            s += v * v
        if s < 1e-20:
            n += 1
    return n


def _zero_quats_reference(q: np.ndarray) -> int:
    """_zero_quats with numpy (obviously correct; the tests)."""
    return int(np.count_nonzero(np.einsum("ij,ij->i", q, q, dtype=np.float64) < 1e-20))


@njit(cache=True, parallel=True, nogil=True)
def _unpack_kernel(block, take, taking, put, putting, cols, means, quats, scales, opacity, sh):
    """Row i of the outputs from record take[i] of block [N, P] float32 (``taking``; else record i), each value
    from its column in ``cols`` (ply_columns); ``putting``: into output row put[i] instead (take's length of rows
    written: read_ply_take's windows); returns [6] int64: the non-finite values written to means, quats, log
    scales, opacities, SH, and the quaternions whose float64 squared norm is below 1e-20 (the Gaussians' checks)."""
    m = take.shape[0] if taking else means.shape[0]
    nsh = sh.shape[1]
    b_m = b_q = b_s = b_o = b_sh = b_z = 0
    for j in prange(m):
        r = np.int64(j)
        if taking:
            r = take[j]
            if j + PREFETCH_ROWS < m:
                prefetch_row(block, take[j + PREFETCH_ROWS])
        i = put[j] if putting else np.int64(j)
        for c in range(3):
            v = block[r, cols[c]]
            means[i, c] = v
            b_m += not np.isfinite(v)
        qq = 0.0
        for c in range(4):
            v = block[r, cols[3 + c]]
            quats[i, c] = v
            b_q += not np.isfinite(v)
            qq += np.float64(v) * np.float64(v)
        b_z += qq < 1e-20
        for c in range(3):
            v = block[r, cols[7 + c]]
            scales[i, c] = v
            b_s += not np.isfinite(v)
        v = block[r, cols[10]]
        opacity[i] = v
        b_o += not np.isfinite(v)
        for c in range(nsh):
            v = block[r, cols[11 + c]]
            sh[i, c] = v
            b_sh += not np.isfinite(v)
    out = np.empty(6, np.int64)
    out[0], out[1], out[2], out[3], out[4], out[5] = b_m, b_q, b_s, b_o, b_sh, b_z
    return out


TAKE_ROWS_MIN = 1 << 15     # rows taken below which numpy's indexing is as fast as take_rows' kernel (its launch)


def take_rows(arrays: Sequence[np.ndarray], index: np.ndarray) -> list[np.ndarray]:
    """``[a[index] for a in arrays]`` for arrays of one length N along axis 0 and ``index`` a [N] bool mask or
    integer rows in 0..N-1 (copies, as numpy's indexing makes), taken by one numba kernel over the rows (numpy's
    boolean indexing of an [N, 3] float32 array walks the mask once per array and copies item by item: 3-4x slower
    for 3 M of a drive's Gaussians). Anything else (negative or out-of-range rows, a mask of another length,
    arrays that are not C-contiguous, few rows) goes to numpy's indexing, with its errors."""
    index = np.asarray(index)
    n = len(arrays[0]) if arrays else 0
    rows = None
    if index.dtype == np.bool_ and index.shape == (n,):
        rows = np.flatnonzero(index)
    elif index.ndim == 1 and index.dtype.kind in "iu" and len(index) and int(index.min()) >= 0 \
            and int(index.max()) < n:
        rows = index.astype(np.int64, copy=False)
    if rows is None or len(rows) < TAKE_ROWS_MIN or not all(a.flags.c_contiguous and len(a) == n for a in arrays):
        return [a[index] for a in arrays]
    out = []
    for a in arrays:
        got = np.empty((len(rows),) + a.shape[1:], a.dtype)
        put_rows(a.reshape(n, -1), rows, got.reshape(len(rows), -1), 0)
        out.append(got)
    return out


@njit(cache=True, parallel=True, nogil=True)
def put_rows(src, rows, dst, at):
    """dst[at + i] = src[rows[i]] over src's columns, the rest of dst's row zero; src [N, C], dst [M, >= C] (both
    2-D, any strides); rows [n] int64 (take_rows; concat_gaussians)."""
    c, cd = src.shape[1], dst.shape[1]
    for i in prange(rows.shape[0]):
        r = rows[i]
        for k in range(c):
            dst[at + i, k] = src[r, k]
        for k in range(c, cd):
            dst[at + i, k] = 0



@njit(cache=True, nogil=True)
def rows_box(block, col, rows, box):
    """box [2, 3] float64 (min; max) widened to hold block[r, col:col + 3] of each of ``rows`` ([K] int64 rows of
    block [N, P] float32: a PLY's records, x y z from column ``col``)."""
    for r in rows:
        for a in range(3):
            v = np.float64(block[r, col + a])
            box[0, a] = min(box[0, a], v)
            box[1, a] = max(box[1, a], v)

def transformed_reference(g: Gaussians, T: np.ndarray) -> Gaussians:
    """Gaussians.transformed in numpy: means R x + t in float64 (back to their dtype), quaternions q_R q (the
    Hamilton product, wxyz, float64, back to their dtype); the Gaussians checked again."""
    from ..rotations import rotmats_to_quats

    R = np.asarray(T, np.float64)[:3, :3]
    means = (g.means.astype(np.float64) @ R.T + np.asarray(T, np.float64)[:3, 3]).astype(g.means.dtype)
    w1, x1, y1, z1 = rotmats_to_quats(R[None])[0]
    q = g.quats.astype(np.float64)
    w2, x2, y2, z2 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    quats = np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)
    return Gaussians(means, quats.astype(g.quats.dtype), g.log_scales, g.opacity_logits, g.sh)


@njit(cache=True, nogil=True)
def _rigid_kernel(means, quats, R, t, q1, out_means, out_quats):
    """out_means = R means + t and out_quats = q1 quats (Hamilton, wxyz), row by row in float64, stored in the
    outputs' dtype (transformed_reference's arithmetic); returns (non-finite means values, non-finite quaternion
    values) written."""
    bad_m = 0
    bad_q = 0
    w1, x1, y1, z1 = q1[0], q1[1], q1[2], q1[3]
    for i in range(means.shape[0]):
        m0, m1, m2 = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        for a in range(3):
            v = R[a, 0] * m0 + R[a, 1] * m1 + R[a, 2] * m2 + t[a]
            out_means[i, a] = v
            if not np.isfinite(out_means[i, a]):
                bad_m += 1
        w2, x2, y2, z2 = (np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                          np.float64(quats[i, 3]))
        out_quats[i, 0] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
        out_quats[i, 1] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
        out_quats[i, 2] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
        out_quats[i, 3] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
        for a in range(4):
            if not np.isfinite(out_quats[i, a]):
                bad_q += 1
    return bad_m, bad_q


def concat_gaussians(parts: list[Gaussians], masks: list[np.ndarray | None] | None = None,
                     to: np.ndarray | None = None) -> Gaussians:
    """The Gaussians of ``parts`` in order, each restricted to its boolean mask ([N_i] or None = all): one copy of
    each field, written in place: a masked part's rows by one parallel pass a field (np.compress of [N, 3] rows took
    0.16 s of a PandaSet frame's fusion), a whole part by one block copy; the highest SH degree, lower-degree parts
    padded with zeros. ``to`` ([N] int64, a permutation of 0..N-1; parts without masks): row i of the concatenation
    is put at row to[i] instead, in the same one copy (a drive's Gaussians put in tile order as they are joined, not
    joined and then taken again). concat_gaussians_reference is its numpy definition (tested: the same bits)."""
    masks = masks if masks is not None else [None] * len(parts)
    if to is not None and any(m is not None for m in masks):
        raise ValueError("concat_gaussians: `to` places whole parts (no masks)")
    deg = max(p.sh_degree for p in parts)
    n_sh = (deg + 1) ** 2
    rows = [None if m is None else np.flatnonzero(m) for m in masks]
    sizes = [len(p) if r is None else len(r) for p, r in zip(parts, rows)]
    total = sum(sizes)
    if to is not None:          # checked before it is written through
        to = np.asarray(to, np.int64)
        if to.shape != (total,) or (total and (to.min() < 0 or to.max() >= total or
                                               np.bincount(to, minlength=total).max() != 1)):
            raise ValueError(f"concat_gaussians: `to` must be a permutation of the {total} rows")
    out = {name: np.empty((total, *getattr(parts[0], name).shape[1:]), np.float32)
           for name in ("means", "quats", "log_scales", "opacity_logits")}
    out["sh"] = np.empty((total, n_sh, 3), np.float32)
    at = 0
    for p, r, n in zip(parts, rows, sizes):
        if n:
            src = [np.asarray(getattr(p, name), np.float32).reshape(len(p), -1) for name in FIELDS]
            dst = [out[name].reshape(total, -1) for name in FIELDS]
            if r is not None and all(a.flags.c_contiguous for a in src):
                put_gaussian_rows(*src, r, *dst, at)
            elif r is not None:
                for a2, d2 in zip(src, dst):
                    put_rows(a2, r, d2, at)
            elif to is not None:            # a whole part, each row to its place
                for a2, d2 in zip(src, dst):
                    scatter_rows(a2, to[at:at + n], d2)
            else:                           # a whole part: one block copy (numpy's is as fast as memory)
                for a2, d2 in zip(src, dst):
                    d2[at:at + n, :a2.shape[1]] = a2
                    d2[at:at + n, a2.shape[1]:] = 0
        at += n
    return Gaussians.joined(**out)          # rows of checked Gaussians: not checked again


@njit(cache=True, parallel=True, nogil=True)
def scatter_rows(src, to, dst):
    """dst[to[i]] = src[i] over src's columns, the rest of dst's row zero; src [n, C], dst [M, >= C] (both 2-D,
    any strides); to [n] int64 in 0..M-1 (concat_gaussians' ``to``)."""
    c, cd = src.shape[1], dst.shape[1]
    for i in prange(to.shape[0]):
        j = to[i]
        for k in range(c):
            dst[j, k] = src[i, k]
        for k in range(c, cd):
            dst[j, k] = 0


@njit(cache=True, parallel=True, nogil=True)
def put_gaussian_rows(means, quats, log_scales, opacity, sh, rows, o_means, o_quats, o_log_scales, o_opacity, o_sh,
                      at):
    """put_rows of a part's five fields in one pass over its rows (concat_gaussians): row at + i of each o_* array
    = row rows[i] of the field; the fields C-contiguous, [N, 3], [N, 4], [N, 3], [N, 1], [N, 3 K] (its SH
    flattened), o_sh's columns past sh's zero. One pass instead of one a field: a PandaSet frame's 3.1 M cells
    concatenated 1.5-2x faster (the row index read once, one launch a part)."""
    c, cd = sh.shape[1], o_sh.shape[1]
    for i in prange(rows.shape[0]):
        r, j = rows[i], at + i
        for k in range(3):
            o_means[j, k] = means[r, k]
            o_log_scales[j, k] = log_scales[r, k]
        for k in range(4):
            o_quats[j, k] = quats[r, k]
        o_opacity[j, 0] = opacity[r, 0]
        for k in range(c):
            o_sh[j, k] = sh[r, k]
        for k in range(c, cd):
            o_sh[j, k] = 0


def concat_gaussians_reference(parts: list[Gaussians], masks: list[np.ndarray | None] | None = None,
                               to: np.ndarray | None = None) -> Gaussians:
    """concat_gaussians in numpy: each part's masked rows, the SH padded with zeros to the highest degree; with
    ``to``, row i of that at row to[i]."""
    masks = masks if masks is not None else [None] * len(parts)
    n_sh = (max(p.sh_degree for p in parts) + 1) ** 2
    taken = [p if m is None else p.subset(np.asarray(m, bool)) for p, m in zip(parts, masks)]
    sh = [np.concatenate([t.sh, np.zeros((len(t), n_sh - t.sh.shape[1], 3), np.float32)], axis=1) for t in taken]
    fields = {name: np.concatenate([np.asarray(getattr(t, name), np.float32) for t in taken])
              for name in ("means", "quats", "log_scales", "opacity_logits")}
    fields["sh"] = np.concatenate(sh)
    if to is not None:
        for name, a in fields.items():
            placed = np.empty_like(a)
            placed[np.asarray(to)] = a
            fields[name] = placed
    return Gaussians.joined(**fields)
