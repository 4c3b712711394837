"""Spatial tiles of a drive scene's shared Gaussians (docs/inference.md "Tiles").

A drive's shared Gaussians grow with the road (docs/results.md: about 0.6 M a metre at city speed), so a long drive
does not fit in a server's memory whole, and most of it is behind or beside any one camera. The scene's ground plane
(x, y of the scene frame) is cut into square tiles of TILE_M; scene.ply holds the Gaussians tile after tile, and
within a tile keyframe after keyframe (each keyframe's in the order the fusion made them). scene.json's ``tiles``
block lists each tile's cell, its run of scene.ply's rows, the box of its centres and its largest log scale.

A view asks ``visible`` for the tiles its camera can see: the renderer's own chunk test (runtime.render.core
.chunk_planes: near, far and the image's sides, widened by each Gaussian's largest extent), applied to a tile's box,
so a tile left out holds only Gaussians the renderer would cull one by one; the picture is the same. Beyond
HORIZON_M of the camera a drive's view draws its primary keyframe's Gaussians alone (``within``; runtime.scene). A
scene loaded from its folder reads a tile's rows from scene.ply when a view first needs it
(Gaussians.load_ply_rows; beyond the horizon the primary keyframe's rows alone, ``part(alone=True)``) and keeps the
runs it used last, up to CACHE_BYTES; the whole set is read only when something asks for all of it (an export, the
PLY download). A scene made in memory (a reconstruction) slices its Gaussians instead."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np

from .errors import FieldError
from .numba_cache import njit
from .render import FIELDS, GaussianError, Gaussians

TILE_M = 25.0               # metres: a tile's side on the scene's ground plane (x, y). A 1920x1080 camera on a drive
                            # sees ~200 m ahead; 25 m tiles leave a side or back camera out of most of the road ahead
CACHE_BYTES = 2 << 30       # a loaded scene keeps the tiles it used last up to this many bytes (a view needing more
                            # reads them all, and keeps the most recent)
HORIZON_M = 200.0           # metres from a view's camera: beyond, a drive's view draws its primary keyframe's
                            # Gaussians alone (runtime.scene). The detail layer trusts depths to 150 m (max_depth)
                            # and puts what lies beyond on a 300 m sphere about its keyframe (far_depth): another
                            # keyframe's copy of that far background adds nothing the primary's does not draw, and a
                            # long drive has one such sphere per keyframe, each read and drawn by every view
SLACK_M = 1e-4              # metres: a tile is left out only this far beyond the renderer's own cull (rounding of
                            # the box test against the per-Gaussian test it stands for)


class TileError(FieldError):
    """A scene's tiles block is invalid, or a tile's rows cannot be read: ``field`` names the entry."""


@dataclass(frozen=True)
class Tile:
    """One tile: ``cell`` (ix, iy) covers x in [ix, ix + 1) * size, y in [iy, iy + 1) * size metres (the scene's
    frame); its Gaussians are rows ``start`` .. ``start + count - 1`` of scene.ply; ``lo``, ``hi`` the box of their
    centres (metres, scene frame), ``max_log_scale`` the largest of their log scales."""

    cell: tuple[int, int]
    start: int
    count: int
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    max_log_scale: float

    def to_dict(self) -> dict[str, Any]:
        return {"cell": list(self.cell), "start": self.start, "count": self.count,
                "bounds": {"min": list(self.lo), "max": list(self.hi)}, "max_log_scale": self.max_log_scale}


def tile_order(means: np.ndarray, keyframe_of: np.ndarray, size: float = TILE_M) -> tuple[np.ndarray, np.ndarray]:
    """(order [N] int64, cells [N, 2] int64 after ordering): the permutation that puts Gaussians with centres
    ``means`` [N, 3] (metres, scene frame) tile after tile (cells increasing in x, then y), within a tile keyframe
    after keyframe (``keyframe_of`` [N]), and each tile's keyframe's run in spatial order (runtime.viewpoints
    .spatial_order over all of them, ties in index order: a view's later layers skip runs of 1024 of them whole)."""
    from .render import kernels as K
    from .viewpoints import spatial_order

    cells = np.floor(np.asarray(means[:, :2], np.float64) / size).astype(np.int64)             # [N, 2]
    if not len(cells):
        return np.zeros(0, np.int64), cells
    lo = cells.min(axis=0)
    span = int(cells[:, 1].max() - lo[1]) + 1
    n_keys = int(keyframe_of.max()) + 1
    # one key in (ix, iy, keyframe) order (np.unique over rows took 2.9 s of a drive's 4.8 M; this one sort 0.6 s)
    key = ((cells[:, 0] - lo[0]) * span + (cells[:, 1] - lo[1])) * n_keys + np.asarray(keyframe_of, np.int64)
    near = spatial_order(means)
    if int(key.max()) < 2 ** 32:        # the runs' key sorted stably after the spatial order: two radix sorts
        order = K.depth_order(near, key[near].astype(np.uint32)).astype(np.int64)
    else:
        order = near[np.argsort(key[near], kind="stable")].astype(np.int64)
    return order, cells[order]


def in_tile_order(parts: Sequence[Gaussians], keyframe_of: np.ndarray, n_keys: int
                  ) -> tuple[Gaussians, np.ndarray, Tiles]:
    """The Gaussians of ``parts`` (joined in order; each one's keyframe ``keyframe_of`` [N]) in tile order
    (tile_order), their keyframes in that order ([N] int16) and their Tiles (``n_keys`` keyframes; in memory): the
    parts joined straight into place (concat_gaussians' ``to``), one copy; one set is taken in that order (its
    dtype kept), not copied when it is in order already."""
    from .render.gaussians import concat_gaussians

    kf = np.asarray(keyframe_of, np.int16)
    means = parts[0].means if len(parts) == 1 else np.concatenate([p.means for p in parts])
    order, cells = tile_order(means, kf)
    if len(parts) == 1:
        g = parts[0] if np.array_equal(order, np.arange(len(order))) else parts[0].subset(order)
    else:
        to = np.empty(len(order), np.int64)
        to[order] = np.arange(len(order))
        g = concat_gaussians(list(parts), to=to)
    kf = kf[order]
    return g, kf, Tiles(build_tiles(g, cells), kf, n_keys, source=g)


def build_tiles(g: Gaussians, cells: np.ndarray) -> list[Tile]:
    """The tiles of Gaussians ``g`` already in tile order (tile_order) with their ``cells`` [N, 2]."""
    if not len(g):
        return []
    change = np.flatnonzero(np.any(cells[1:] != cells[:-1], axis=1)) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, len(g)]
    # rounded outwards (to a millimetre, a ten-thousandth of a log scale): short in scene.json, still holding them
    lo, hi, ls = _run_boxes(np.ascontiguousarray(g.means), np.ascontiguousarray(g.log_scales),
                            starts.astype(np.int64), stops.astype(np.int64))
    lo = np.floor(lo.astype(np.float64) * 1e3) / 1e3
    hi = np.ceil(hi.astype(np.float64) * 1e3) / 1e3
    ls = np.ceil(ls.astype(np.float64) * 1e4) / 1e4
    return [Tile((int(cells[a, 0]), int(cells[a, 1])), int(a), int(b - a), tuple(float(v) for v in lo[i]),
                 tuple(float(v) for v in hi[i]), float(ls[i])) for i, (a, b) in enumerate(zip(starts, stops))]


@njit(cache=True, parallel=True, nogil=True)
def _run_boxes(means, log_scales, starts, stops):
    """Per run [starts[t], stops[t]) of the rows: the smallest and largest centre ([T, 3], means' dtype) and the
    largest log scale ([T]): numpy's minimum/maximum.reduceat of the means and of log_scales.max(axis=1) (the same
    values: a min or max of floats is exact), one parallel pass over the rows instead of four."""
    n = len(starts)
    lo = np.empty((n, 3), means.dtype)
    hi = np.empty((n, 3), means.dtype)
    ls = np.empty(n, log_scales.dtype)
    for t in numba.prange(n):
        a, b = starts[t], stops[t]
        for k in range(3):
            lo[t, k] = means[a, k]
            hi[t, k] = means[a, k]
        top = log_scales[a, 0]
        for i in range(a, b):
            for k in range(3):
                v = means[i, k]
                if v < lo[t, k]:
                    lo[t, k] = v
                if v > hi[t, k]:
                    hi[t, k] = v
                if log_scales[i, k] > top:
                    top = log_scales[i, k]
        ls[t] = top
    return lo, hi, ls


def run_boxes_reference(means: np.ndarray, log_scales: np.ndarray, starts: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_run_boxes in numpy (its test): reduceat from each run's start (the runs cover the rows, in order)."""
    return (np.minimum.reduceat(means, starts, axis=0), np.maximum.reduceat(means, starts, axis=0),
            np.maximum.reduceat(log_scales.max(axis=1), starts))


class Tiles:
    """A drive scene's tiles (module docstring) over its shared Gaussians: in memory (``source``, the whole set in
    tile order) or read from ``ply`` tile by tile (thread-safe: the service renders views of one scene on several
    threads). ``keyframe_of`` [N] (each Gaussian's keyframe, in the same order) splits each tile into keyframes."""

    def __init__(self, tiles: Sequence[Tile], keyframe_of: np.ndarray, n_keys: int, size: float = TILE_M,
                 source: Gaussians | None = None, ply: Path | None = None, cache_bytes: int = CACHE_BYTES):
        if (source is None) == (ply is None):
            raise ValueError("tiles: either the Gaussians in memory or the PLY to read them from")
        self.tiles = tuple(tiles)
        self.size = float(size)
        self.n_keys = int(n_keys)
        self._source, self.ply, self.cache_bytes = source, ply, int(cache_bytes)
        self._cache: OrderedDict[int, Gaussians] = OrderedDict()
        self._held = 0
        self._lock = threading.Lock()
        kf = np.asarray(keyframe_of)
        # [T, K + 1]: tile t's keyframe k is rows key_starts[t, k] .. key_starts[t, k + 1] - 1 of the tile
        self.key_starts = np.zeros((len(self.tiles), self.n_keys + 1), np.int64)
        for t, tile in enumerate(self.tiles):
            self.key_starts[t] = np.searchsorted(kf[tile.start:tile.start + tile.count], np.arange(self.n_keys + 1))
        self._lo = np.array([t.lo for t in self.tiles], np.float64).reshape(-1, 3)
        self._hi = np.array([t.hi for t in self.tiles], np.float64).reshape(-1, 3)
        self._smax = np.exp(np.array([t.max_log_scale for t in self.tiles], np.float64))

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def count(self) -> int:
        return sum(t.count for t in self.tiles)

    @property
    def sh_degree(self) -> int:
        """The SH degree of the Gaussians (from the PLY's header while none is read)."""
        if self._source is not None:
            return self._source.sh_degree
        from .render.gaussians import _n_rest_to_degree, _read_ply_header

        props = _read_ply_header(self.ply)[1]
        return int(_n_rest_to_degree(sum(1 for p, _ in props if p.startswith("f_rest_"))) or 0)

    @property
    def lazy(self) -> bool:
        """True when the tiles are read from the scene's PLY as views need them."""
        return self._source is None

    def visible(self, camera, **options) -> list[int]:
        """The tiles (indices, increasing) that ``camera`` (runtime.camera.Camera) with render ``options`` can see:
        those whose box, widened by their largest Gaussian's extent, is not wholly outside one of the renderer's
        chunk planes (every tile for an equirect camera or a lens wider than 180 degrees)."""
        from .render.core import chunk_planes
        from .render.projection import RenderOptions

        planes = chunk_planes(camera, RenderOptions.from_kwargs(options))
        if not len(self.tiles) or not len(planes):
            return list(range(len(self.tiles)))
        a, off, ks = planes[:, :3], planes[:, 3], planes[:, 4]
        c, h = 0.5 * (self._lo + self._hi), 0.5 * (self._hi - self._lo)
        top = c @ a.T + h @ np.abs(a).T + off                                  # [T, P]: the box's highest a.x + off
        outside = np.any(top + SLACK_M < -ks * self._smax[:, None], axis=1)
        return [int(t) for t in np.flatnonzero(~outside)]

    def within(self, camera, horizon: float, tiles: Sequence[int]) -> set[int]:
        """Of ``tiles``, those whose box comes within ``horizon`` metres of ``camera``'s centre."""
        if not len(tiles):
            return set()
        idx = np.asarray(tiles, np.int64)
        c = np.asarray(camera.cam_to_ego, np.float64)[:3, 3]
        d = np.linalg.norm(np.clip(c, self._lo[idx], self._hi[idx]) - c, axis=1)
        return {int(t) for t in idx[d <= horizon]}

    def gaussians(self, t: int) -> Gaussians:
        """Tile t's Gaussians (scene frame): a slice of the set in memory, or its rows read from the PLY (TileError
        naming the tile when they cannot be)."""
        tile = self.tiles[t]
        if self._source is not None:
            return self._source.slice(tile.start, tile.start + tile.count)
        return self._read((t,), t, 0, tile.count)

    def part(self, t: int, k0: int, k1: int, alone: bool = False) -> Gaussians:
        """Tile t's Gaussians of keyframes k0 .. k1 - 1: a view of the tile's arrays; ``alone``: when the tile is
        not read already, only those rows are read (a view's primary keyframe beyond the horizon, HORIZON_M)."""
        s = self.key_starts[t]
        a, b = int(s[k0]), int(s[k1])
        if alone and self._source is None:
            with self._lock:
                whole = self._cache.get((t,))
            if whole is None:
                return self._read((t, k0, k1), t, a, b)
        return self.gaussians(t).slice(a, b)

    def _read(self, key: tuple, t: int, a: int, b: int) -> Gaussians:
        """Rows a..b - 1 of tile t, from the cache under ``key`` or read from the PLY and checked against the tile's
        box (TileError naming the tile)."""
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        tile = self.tiles[t]
        where = f"scene PLY {str(self.ply)!r}"
        try:
            g = Gaussians.load_ply_rows(self.ply, tile.start + a, tile.start + b)
        except (GaussianError, OSError) as e:
            raise TileError(f"tiles[{t}]", f"rows {tile.start + a}..{tile.start + b}: {e}", where) from None
        # a box that does not hold its Gaussians would leave them out of views that see them
        m = g.means.astype(np.float64)
        if (np.any(m < np.array(tile.lo)) or np.any(m > np.array(tile.hi))
                or float(g.log_scales.max(initial=-np.inf)) > tile.max_log_scale):
            raise TileError(f"tiles[{t}].bounds", "its Gaussians lie outside its box or have larger scales than "
                                                  "max_log_scale", where)
        size = _nbytes(g)
        with self._lock:
            if key not in self._cache:
                self._cache[key] = g
                self._held += size
            while self._held > self.cache_bytes and len(self._cache) > 1:
                _, old = self._cache.popitem(last=False)
                self._held -= _nbytes(old)
        return g

    @property
    def held_bytes(self) -> int:
        """The bytes of the tiles read and kept (0 for tiles in memory)."""
        return self._held

    def whole(self) -> Gaussians:
        """Every shared Gaussian in tile order: the set in memory, or the whole PLY read (and kept: the tiles are
        then its slices)."""
        if self._source is not None:
            return self._source
        from .render.gaussians import DEFAULT_MAX_POINTS

        try:
            g = Gaussians.load_ply(self.ply, max_points=max(DEFAULT_MAX_POINTS, self.count))
        except GaussianError as e:
            raise TileError("scene.ply", str(e), f"scene PLY {str(self.ply)!r}") from None
        with self._lock:            # from now on the tiles are slices of it: nothing read twice
            self._source = g
            self._cache.clear()
            self._held = 0
        return g

    def to_json(self) -> dict[str, Any]:
        return {"size_m": self.size, "tiles": [t.to_dict() for t in self.tiles],
                "about": "scene.ply holds the shared Gaussians tile after tile (within a tile keyframe after "
                         "keyframe); a view reads and draws only the tiles its camera can see"}

    @classmethod
    def from_json(cls, block: Any, ply: Path, n: int, keyframe_of: np.ndarray, n_keys: int) -> Tiles:
        """A scene folder's tiles (scene.json's block) over its PLY ``ply`` of ``n`` Gaussians, each entry checked
        (TileError naming it): the runs cover the rows in order, each tile's keyframes increase."""
        where = f"scene {str(ply.parent)!r}"
        size = block.get("size_m") if isinstance(block, dict) else None
        entries = block.get("tiles") if isinstance(block, dict) else None
        if not isinstance(size, (int, float)) or isinstance(size, bool) or not np.isfinite(size) or size <= 0:
            raise TileError("tiles.size_m", f"must be a number > 0 (got {size!r})", where)
        if not isinstance(entries, list):
            raise TileError("tiles.tiles", "must be a list", where)
        tiles, at = [], 0
        kf = np.asarray(keyframe_of)
        for i, e in enumerate(entries):
            name = f"tiles.tiles[{i}]"
            try:
                cell = tuple(int(v) for v in e["cell"])
                start, count = e["start"], e["count"]
                lo = tuple(float(v) for v in e["bounds"]["min"])
                hi = tuple(float(v) for v in e["bounds"]["max"])
                ls = float(e["max_log_scale"])
            except (KeyError, TypeError, ValueError):
                raise TileError(name, "must have cell [ix, iy], start, count, bounds {min, max} and max_log_scale",
                                where) from None
            if len(cell) != 2 or len(lo) != 3 or len(hi) != 3 or not all(np.isfinite(lo + hi + (ls,))):
                raise TileError(name, "cell must be 2 integers, bounds 3 finite numbers each, max_log_scale "
                                      "finite", where)
            if not isinstance(start, int) or not isinstance(count, int) or start != at or count <= 0:
                raise TileError(f"{name}.start", f"tiles must cover scene.ply's rows in order: expected start {at} "
                                                 f"and count > 0 (got {start!r}, {count!r})", where)
            run = kf[start:start + count]
            if np.any(run[1:] < run[:-1]):
                raise TileError(name, "its Gaussians' keyframes (keyframe_of.npy) must increase", where)
            at += count
            tiles.append(Tile(cell, start, count, lo, hi, ls))
        if at != n:
            raise TileError("tiles.tiles", f"cover {at} Gaussians, scene.ply holds {n}", where)
        return cls(tiles, kf, n_keys, float(size), ply=ply)


def _nbytes(g: Gaussians) -> int:
    return sum(getattr(g, f).nbytes for f in FIELDS)


__all__ = ["CACHE_BYTES", "HORIZON_M", "TILE_M", "Tile", "TileError", "Tiles", "build_tiles", "in_tile_order",
           "run_boxes_reference", "tile_order"]
