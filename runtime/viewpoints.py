"""A drive's viewpoint chunks: what each viewpoint saw beyond the shared Gaussians (docs/inference.md, "Layers").

A drive's scene keeps each surface once in its shared Gaussians (runtime.drive.dedupe_frames: the finest
observation, as finely from nearer by). That set alone is a sieve from any one viewpoint: the keyframe a view is
drawn from keeps only the cells it resolved best, and through the holes show other keyframes' copies of the same
surfaces, seen from metres away (their discs edge-on, their depth a few centimetres off, their exposure). So each
keyframe also keeps, in a chunk of its own, its cells that the dedupe gave to other keyframes. A view is drawn from
its primary keyframe as that keyframe saw the scene (its shared cells and its chunk), over the
other keyframes of its viewpoint group (runtime.drive.viewpoint_groups: keyframes whose ego stood within
VIEWPOINT_RADIUS_M of the group's first; their shared cells) and the two neighbouring groups (their first
keyframe's chunk and their keyframes' shared cells), over the other keyframes' shared cells
(runtime.scene.Scene.render). An ego that stands still is one viewpoint group (its surfaces kept once in the shared
cells, from its first keyframe) but each of its keyframes keeps its own chunk: a view is drawn from the keyframe
nearest its time, which saw what moved, the light and the ego's pose then (the PandaSet drive's right camera was
1.5-1.8 dB behind one frame alone at frames 6-18 when a still ego's views were all drawn from its first keyframe:
docs/results.md "Drives: a still ego drawn from its keyframe nearest in time"). Keyframes
are picked by distance and at least every 2 s (runtime.drive.pick_keyframes), so a still ego adds a chunk every 2 s
and a moving one a chunk per keyframe. Scene folders written before kept one chunk per group (its first keyframe's
cells), and are drawn as they were.

On disk a chunk is a 3DGS PLY in the scene folder's ``viewpoints/`` (scene.json's ``viewpoints`` block: each
chunk's file, keyframes, viewpoint group, count and bounds); a loaded scene reads a chunk when a view first needs it
and keeps the last CACHE_CHUNKS it used: a view reads at most three. A drive with camera layers (runtime.cameralayers)
holds every cell of a keyframe's chunk in that keyframe's layers already (the cells its cameras kept, of which the
fusion kept fewer): such a chunk's PLY holds only the model's Gaussians, and its ``layer_rows`` entry names a
``.npy`` of the rows of the keyframe's layer file that follow them (LayerRows; int32, in the chunk's order): a
PandaSet keyframe's chunk is 12 MB of rows instead of 170 MB of Gaussians, written in a fraction of the time."""

from __future__ import annotations

import os
import shutil
import threading
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .errors import FieldError
from .numba_cache import njit
from .render import GaussianError, Gaussians

CHUNKS_DIR = "viewpoints"
CACHE_CHUNKS = 4            # chunks a loaded scene keeps in memory: a view's group and its two neighbours, and one
                            # more, so that a camera moving along the drive reads one new chunk per group it enters


def link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` made to hold ``src``'s bytes: a hard link where both lie on one file system (a chunk's file is written
    once and never changed: 20 PandaSet keyframes' chunks are 4 GB that a copy read and wrote again), else a copy. An
    existing ``dst`` is replaced (never written through: it may be ``src`` itself, linked by an earlier save)."""
    if dst.exists() and dst.samefile(src):
        return
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:                 # another file system, or one without hard links
        shutil.copyfile(src, dst)


class Recent:
    """The values last put, by key (thread-safe): ``get`` a kept one (now the most recent) or None, ``put`` one and
    keep at most ``size`` (the least recently used let go): a loaded scene's chunks, its camera layers."""

    def __init__(self):
        self._items: OrderedDict[Any, Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any) -> Any:
        with self._lock:
            if key not in self._items:
                return None
            self._items.move_to_end(key)
            return self._items[key]

    def put(self, key: Any, value: Any, size: int) -> None:
        with self._lock:
            self._items[key] = value
            while len(self._items) > size:
                self._items.popitem(last=False)

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self):
        """The keys kept, least recently used first."""
        with self._lock:
            return iter(list(self._items))


def ply_count(path: Path, field: str, error: type[FieldError], where: str) -> int:
    """The vertex count in the header of a scene folder's PLY ``path`` (a chunk, a camera layer): ``error`` naming
    ``field`` when the file is missing or its header unreadable."""
    from .render.gaussians import _read_ply_header

    if not path.is_file():
        raise error(field, f"{str(path)!r} is missing", where)
    try:
        return _read_ply_header(path)[0]
    except GaussianError as exc:
        raise error(field, f"{str(path)!r}: {exc}", where) from None


class ViewpointError(FieldError):
    """A scene's viewpoints block or chunk file is invalid: ``field`` names the entry."""


SPATIAL_BITS = 10          # bits per axis of spatial_order's Morton code: 1024 steps across a chunk's box


def spatial_order(means: np.ndarray) -> np.ndarray:
    """[N] int32: the order of points ``means`` ([N, 3] metres) along a Morton (Z-order) curve over their box,
    SPATIAL_BITS bits an axis, ties in index order. A chunk's cells in this order lie together in runs, so that
    the projection skips a run of them as a whole (runtime.render.kernels: a run of PROJ_CHUNK Gaussians whose
    box is outside the view, or over tiles the layers in front already covered); a keyframe's cells come camera
    after camera in image rows, each run of a thousand a strip across the image from the road to the sky."""
    from .render import kernels as K

    m = np.ascontiguousarray(means, np.float32)
    if not len(m):
        return np.zeros(0, np.int32)
    return K.depth_order(np.arange(len(m), dtype=np.int32), _morton_codes(m, SPATIAL_BITS))


@njit(cache=True, nogil=True)
def _morton_codes(means, bits):
    """[N] uint32: each point's cell in the box of all (``bits`` an axis: floor((x - lo) * step), step =
    2^bits / (hi - lo), clamped) with the bits interleaved, x lowest (spatial_order; its test holds the plain
    definition)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    grow_box(means, np.ones(0, np.bool_), lo, hi)
    step = box_steps(lo, hi, bits)
    out = np.empty(means.shape[0], np.uint32)
    for i in range(means.shape[0]):
        out[i] = morton_code(means, i, lo, step, bits)
    return out


@njit(cache=True, nogil=True)
def grow_box(means, mask, lo, hi):
    """lo, hi [3] float64 (written) grown to hold the points means [N, 3] (float64 of each value) where ``mask``
    [N] holds (an empty mask: all)."""
    every = mask.shape[0] == 0
    for i in range(means.shape[0]):
        if every or mask[i]:
            for a in range(3):
                x = np.float64(means[i, a])
                lo[a] = min(lo[a], x)
                hi[a] = max(hi[a], x)


@njit(cache=True, nogil=True)
def box_steps(lo, hi, bits):
    """[3]: 2^bits cells across the box (lo, hi) an axis (morton_code's step)."""
    step = np.empty(3)
    for a in range(3):
        step[a] = (1 << bits) / max(hi[a] - lo[a], 1e-9)
    return step


@njit(cache=True, nogil=True)
def morton_code(means, i, lo, step, bits):
    """Point i of means [N, 3]'s Morton code in the box from lo with box_steps ``step`` (_morton_codes)."""
    top = (1 << bits) - 1
    code = 0
    for a in range(3):
        q = min(max(int((np.float64(means[i, a]) - lo[a]) * step[a]), 0), top)
        if bits <= 10:
            code |= _spread3(q) << a
        else:
            for b in range(bits):
                code |= ((q >> b) & 1) << (3 * b + a)
    return code


@njit(cache=True, nogil=True)
def _spread3(q):
    """The bits of q (< 2^10) moved to every third place (bit b to bit 3 b): the 'magic numbers' of a Morton
    code, four shifts and masks instead of a loop over the bits (the same code)."""
    q &= 0x3FF
    q = (q | (q << 16)) & 0x030000FF
    q = (q | (q << 8)) & 0x0300F00F
    q = (q | (q << 4)) & 0x030C30C3
    return (q | (q << 2)) & 0x09249249


class LayerRows(NamedTuple):
    """A chunk's Gaussians that are rows of a camera layer file: ``file`` (relative to the scene folder, a keyframe's
    runtime.cameralayers file) and ``rows`` ([M] int32, the rows in the chunk's order); ``box`` the box of their
    means ([2, 3] float64: min; max) where known (a drive's reconstruction finds it as it reads the file:
    Gaussians.read_ply_take), else None: read from the file when the chunk is made."""

    file: str
    rows: np.ndarray
    box: np.ndarray | None = None


@dataclass(frozen=True)
class Chunk:
    """One keyframe's own cells (a folder written before: one viewpoint group's, its first keyframe's):
    ``keyframes`` its keyframe (the group's keyframes; indices into the drive's keyframes, increasing), ``count`` its
    Gaussians, ``bbox`` the box of their centres ({"min", "max"}: metres, the scene's frame; None when empty),
    ``file`` its PLY's path relative to the scene folder, ``viewpoint`` the first keyframe of its viewpoint group
    (None: the chunk's first keyframe, a group of its own); ``rows`` the file of its rows of a camera layer
    (``layer``, relative to the scene folder; ``layer_count`` rows) that follow the PLY's Gaussians, None when the
    PLY holds them all (module docstring)."""

    keyframes: tuple[int, ...]
    count: int
    bbox: dict[str, list[float]] | None
    file: str
    viewpoint: int | None = None
    rows: str | None = None
    layer: str | None = None
    layer_count: int = 0

    @property
    def group(self) -> int:
        """The first keyframe of this chunk's viewpoint group."""
        return self.keyframes[0] if self.viewpoint is None else self.viewpoint

    def to_dict(self) -> dict[str, Any]:
        out = {"file": self.file, "keyframes": list(self.keyframes), "viewpoint": self.group, "count": self.count,
               "bbox": self.bbox}
        if self.rows is not None:
            out["layer_rows"] = {"file": self.rows, "of": self.layer, "count": self.layer_count}
        return out


def _chunk(i: int, keyframes: Sequence[int], g: Gaussians, viewpoints: Sequence[int] | None,
           rows: LayerRows | None = None, folder: Path | None = None) -> Chunk:
    """Chunk i (file group_NNN.ply) of ``keyframes`` holding ``g`` and, with ``rows``, those rows of a camera
    layer in ``folder``; its viewpoint group from ``viewpoints`` (each keyframe's group's first keyframe; None: its
    own)."""
    vpt = None if viewpoints is None else int(viewpoints[keyframes[0]])
    ks, file = tuple(int(k) for k in keyframes), f"{CHUNKS_DIR}/group_{i:03d}.ply"
    if rows is None:
        return Chunk(ks, len(g), _bbox(g.means), file, vpt)
    from .render.gaussians import ply_rows_layout, rows_box

    n, dtype, header = ply_rows_layout(folder / rows.file)
    at = np.asarray(rows.rows, np.int64)
    box = np.array([[np.inf] * 3, [-np.inf] * 3])
    if len(at) and (int(at.min()) < 0 or int(at.max()) >= n):
        raise ValueError(f"rows of {rows.file!r} outside its {n} rows")
    if len(at) and rows.box is not None:
        box = np.asarray(rows.box, np.float64)
    elif len(at):
        x = dtype.names.index("x")
        if dtype.names[x:x + 3] != ("x", "y", "z") or any(dtype.fields[k][0] != np.dtype("<f4") for k in "xyz"):
            raise ValueError(f"{rows.file!r}: x, y, z are not float32 one after the other")
        # only the means of the rows, through a map of the file (its records as [n, P/4] float32 words)
        words = np.memmap(folder / rows.file, "<u1", mode="r", offset=header, shape=(n * dtype.itemsize,))
        rows_box(words.view("<f4").reshape(n, dtype.itemsize // 4), dtype.fields["x"][1] // 4, at, box)
    means = np.concatenate([g.means.astype(np.float64), box]) if len(at) else g.means
    return Chunk(ks, len(g) + len(at), _bbox(means), file, vpt, f"{CHUNKS_DIR}/group_{i:03d}_rows.npy", rows.file,
                 len(at))


def _bbox(means: np.ndarray) -> dict[str, list[float]] | None:
    if not len(means):
        return None
    return {"min": [float(means[:, c].min()) for c in range(3)],
            "max": [float(means[:, c].max()) for c in range(3)]}


class Viewpoints:
    """A drive scene's viewpoint chunks (module docstring): in memory after a reconstruction, or read from a scene
    folder chunk by chunk (thread-safe: the service renders views of one scene on several threads)."""

    def __init__(self, chunks: Sequence[Chunk], gaussians: Sequence[Gaussians | None], folder: Path | None = None):
        if len(chunks) != len(gaussians):
            raise ValueError("one Gaussians (or None, read from the folder) per chunk")
        self.chunks = tuple(chunks)
        self._group = {k: i for i, c in enumerate(self.chunks) for k in c.keyframes}
        self._given = list(gaussians)
        self._folder = folder
        self._cache = Recent()
        self._tmp = None            # a temporary folder the chunks live in (spilled), removed with them

    @classmethod
    def build(cls, groups: Sequence[Sequence[int]], gaussians: Sequence[Gaussians],
              viewpoints: Sequence[int] | None = None) -> Viewpoints:
        """From each chunk's keyframes and Gaussians (in memory; files named group_NN.ply); ``viewpoints``: each
        keyframe's viewpoint group (its first keyframe; None: each chunk a group of its own)."""
        chunks = [_chunk(i, ks, g, viewpoints) for i, (ks, g) in enumerate(zip(groups, gaussians))]
        return cls(chunks, list(gaussians))

    @classmethod
    def spilled(cls, groups: Sequence[Sequence[int]], gaussians: Iterable[Gaussians | tuple[Gaussians, LayerRows]],
                tmp, viewpoints: Sequence[int] | None = None) -> Viewpoints:
        """From each chunk's keyframes and Gaussians, each written as it comes into the temporary folder ``tmp`` (a
        tempfile.TemporaryDirectory, kept alive as long as these chunks) and read back when used; a chunk given as
        (Gaussians, LayerRows) is those Gaussians followed by rows of a camera layer file already in ``tmp``
        (module docstring); ``viewpoints``: each keyframe's viewpoint group (its first keyframe; None: each chunk a
        group of its own)."""
        folder = Path(tmp.name)
        (folder / CHUNKS_DIR).mkdir(exist_ok=True)
        chunks = []
        for i, (ks, g) in enumerate(zip(groups, gaussians)):
            g, rows = g if isinstance(g, tuple) else (g, None)
            c = _chunk(i, ks, g, viewpoints, rows, folder)
            g.save_ply(folder / c.file)
            if rows is not None:
                np.save(folder / c.rows, np.asarray(rows.rows, np.int32), allow_pickle=False)
            chunks.append(c)
        out = cls(chunks, [None] * len(chunks), folder)
        out._tmp = tmp
        return out

    def __len__(self) -> int:
        return len(self.chunks)

    @property
    def count(self) -> int:
        """The Gaussians of all chunks."""
        return sum(c.count for c in self.chunks)

    def group_of(self, keyframe: int) -> int:
        """The chunk (index) holding ``keyframe`` (an index into the drive's keyframes)."""
        return self._group[int(keyframe)]

    def groups(self) -> list[int]:
        """The viewpoint groups (each its first keyframe), in drive order."""
        return sorted({c.group for c in self.chunks})

    def group_keyframes(self, group: int) -> list[int]:
        """The keyframes of viewpoint group ``group`` (its first keyframe)."""
        return sorted(k for c in self.chunks if c.group == group for k in c.keyframes)

    def gaussians(self, i: int) -> Gaussians:
        """Chunk i's Gaussians (scene frame): in memory, or read from its file (ViewpointError naming the file)."""
        given = self._given[i]
        if given is not None:
            return given
        kept = self._cache.get(i)
        if kept is not None:
            return kept
        c = self.chunks[i]
        path = self._folder / c.file
        try:
            g = Gaussians.load_ply(path, max_points=max(1, c.count - c.layer_count))
            if c.rows is not None:
                rows = np.load(self._folder / c.rows, allow_pickle=False)
                if rows.shape != (c.layer_count,):
                    raise GaussianError("rows", f"{c.rows!r} holds {rows.shape} rows, scene.json says "
                                                f"{c.layer_count}")
                g = Gaussians.load_ply_take(self._folder / c.layer, rows, head=g)     # g's rows first
        except (GaussianError, OSError, ValueError) as e:
            raise ViewpointError("viewpoints", f"chunk {c.file!r}: {e}", f"scene {str(self._folder)!r}") from None
        if len(g) != c.count:
            raise ViewpointError("viewpoints", f"chunk {c.file!r} holds {len(g)} Gaussians, scene.json says "
                                               f"{c.count}", f"scene {str(self._folder)!r}")
        self._cache.put(i, g, CACHE_CHUNKS)
        return g

    def to_json(self) -> dict[str, Any]:
        return {"dir": CHUNKS_DIR, "chunks": [c.to_dict() for c in self.chunks], "count": self.count,
                "about": "per keyframe, its cells that the shared Gaussians keep from another keyframe, and its "
                         "viewpoint group: a view draws its primary keyframe whole, over the rest"}

    def save(self, folder: Path) -> None:
        """Write every chunk's PLY into ``folder`` (a scene folder being written)."""
        (folder / CHUNKS_DIR).mkdir(exist_ok=True)
        for i, c in enumerate(self.chunks):
            if self._given[i] is None:              # on disk already: linked or copied, not read
                link_or_copy(self._folder / c.file, folder / c.file)
                if c.rows is not None:              # (its camera layer's file: CameraLayers.save)
                    link_or_copy(self._folder / c.rows, folder / c.rows)
            else:
                self._given[i].save_ply(folder / c.file)

    @classmethod
    def from_json(cls, block: Any, folder: Path, keyframes: int) -> Viewpoints:
        """A scene folder's viewpoints (scene.json's block) over ``keyframes`` keyframes: each chunk's entry checked
        and its file's header read (ViewpointError naming the entry); the Gaussians are read when first used."""
        where = f"scene {str(folder)!r}"
        entries = block.get("chunks") if isinstance(block, dict) else None
        if not isinstance(entries, list) or not entries:
            raise ViewpointError("viewpoints.chunks", "must be a non-empty list", where)
        chunks, seen = [], set()
        for i, e in enumerate(entries):
            name = f"viewpoints.chunks[{i}]"
            if not isinstance(e, dict):
                raise ViewpointError(name, "must be an object", where)
            f, ks, n, vpt = e.get("file"), e.get("keyframes"), e.get("count"), e.get("viewpoint")
            if not isinstance(f, str) or not f.startswith(CHUNKS_DIR + "/") or ".." in Path(f).parts:
                raise ViewpointError(f"{name}.file", f"must be a file in {CHUNKS_DIR}/ (got {f!r})", where)
            if (not isinstance(ks, list) or not ks or not all(isinstance(k, int) and 0 <= k < keyframes for k in ks)
                    or ks != sorted(set(ks)) or seen & set(ks)):
                raise ViewpointError(f"{name}.keyframes", f"must be increasing keyframe indices in 0.."
                                                          f"{keyframes - 1}, each in one chunk (got {ks!r})", where)
            seen |= set(ks)
            if vpt is not None and (not isinstance(vpt, int) or isinstance(vpt, bool) or not 0 <= vpt <= ks[0]):
                raise ViewpointError(f"{name}.viewpoint", f"must be the first keyframe of the chunk's viewpoint "
                                                          f"group, an index in 0..{ks[0]} (got {vpt!r})", where)
            if not isinstance(n, int) or isinstance(n, bool) or n < 0:
                raise ViewpointError(f"{name}.count", f"must be an integer >= 0 (got {n!r})", where)
            rows = _layer_rows_entry(e.get("layer_rows"), f"{name}.layer_rows", folder, where)
            have = ply_count(folder / f, f"{name}.file", ViewpointError, where)
            if have + rows[2] != n:
                raise ViewpointError(f"{name}.count", f"{str(folder / f)!r} holds {have} Gaussians" +
                                     (f" and {rows[2]} layer rows" if rows[0] else "") + f", not {n}", where)
            chunks.append(Chunk(tuple(ks), n, e.get("bbox"), f, vpt, *rows))
        if seen != set(range(keyframes)):
            raise ViewpointError("viewpoints.chunks", f"must place each of the {keyframes} keyframes in a chunk "
                                                      f"(missing {sorted(set(range(keyframes)) - seen)})", where)
        out = cls(chunks, [None] * len(chunks), folder)
        for i, c in enumerate(chunks):      # a group's first keyframe is its own group's
            if chunks[out.group_of(c.group)].group != c.group:
                raise ViewpointError(f"viewpoints.chunks[{i}].viewpoint", f"keyframe {c.group} is not the first of "
                                                                          "a viewpoint group", where)
        return out


def _layer_rows_entry(block: Any, name: str, folder: Path, where: str) -> tuple[str | None, str | None, int]:
    """A chunk entry's ``layer_rows`` block (None: absent) checked: (its rows file, the layer file, the row count);
    the rows file's header read (its shape and type), the layer file's existence (each row is checked against it
    when the chunk is read: Gaussians.load_ply_take)."""
    if block is None:
        return None, None, 0
    if not isinstance(block, dict):
        raise ViewpointError(name, "must be an object", where)
    f, of, n = block.get("file"), block.get("of"), block.get("count")
    for key, v, top in (("file", f, CHUNKS_DIR), ("of", of, None)):
        if not isinstance(v, str) or (top and not v.startswith(top + "/")) or ".." in Path(v).parts \
                or Path(v).is_absolute():
            raise ViewpointError(f"{name}.{key}", f"must be a file in the scene folder{f' under {top}/' if top else ''}"
                                                  f" (got {v!r:.200})", where)
        if not (folder / v).is_file():
            raise ViewpointError(f"{name}.{key}", f"{str(folder / v)!r} is missing", where)
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ViewpointError(f"{name}.count", f"must be an integer >= 0 (got {n!r})", where)
    try:
        rows = np.load(folder / f, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ViewpointError(f"{name}.file", f"{str(folder / f)!r}: {exc}", where) from None
    if rows.shape != (n,) or not np.issubdtype(rows.dtype, np.integer):
        raise ViewpointError(f"{name}.file", f"{str(folder / f)!r} holds {rows.dtype} {list(rows.shape)}, not {n} "
                                             "integer rows", where)
    return f, of, n


__all__ = ["CACHE_CHUNKS", "CHUNKS_DIR", "SPATIAL_BITS", "Chunk", "LayerRows", "ViewpointError", "Viewpoints",
           "spatial_order"]
