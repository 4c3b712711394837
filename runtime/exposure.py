"""Exposure and white balance harmonised over a drive's cameras and keyframes: a gain per colour channel for each
camera of each keyframe, solved on what two of them both saw (docs/inference.md "Exposure").

Each camera exposes and white-balances on its own, so the same sky or wall has another colour in each camera's
detail cells, and a view shows a seam where one camera's cells meet another's. The model: a camera's colour is
its gain (per channel) times the scene's radiance. Two views' cells of one surface (a cell of view a that lands on
a kept cell of view b at the same depth, within MATCH_DEPTH) give, per channel, log c_a - log c_b = x_a - x_b for
the log gains x; their median over all such cells is one equation (weighted by the square root of their count, at
least MIN_PAIRS cells, enough of them agreeing with the median: AGREE_SHARE within AGREE_LOG, or AGREE_MIN when that
is AGREE_OVER_CHANCE times the share that would by chance). Per keyframe, as the drive streams: its cameras against each other and against the
previous keyframe's cameras, whose cells are already harmonised (their x fixed at 0); the first keyframe's gains
have a mean of 1 (log mean 0). A small pull of every x towards 0 (RIDGE) keeps a camera that overlaps nothing
at gain 1. Each camera's detail cells are then divided by its gain (harmonise), and a view drawn near an input
camera gets that camera's gain at the view's primary keyframe back (Scene.render), so a view at a recorded camera
looks like its recording and a novel view sees one consistent exposure.

The model's own Gaussians blend the cameras that saw them: each is divided by the geometric mean of the gains of
its keyframe's cameras whose view holds it (Harmoniser.coarse).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numba import prange

from .numba_cache import njit
from .render import Gaussians
from .render.sh import SH_C0
from .threads import in_threads

MATCH_DEPTH = 0.03          # of the depth: a cell of another view within this is the same surface
MIN_PAIRS = 200             # cells two views share before their ratio counts (a median of fewer is noise)
MAX_SOURCE_CELLS = 40000    # cells of a view projected into another (a random subset: the median is stable)
COLOUR_RANGE = (0.03, 0.97) # colours outside are clipped or black in one of the two: no ratio
AGREE_LOG = 0.1             # a matched cell's log ratio this near the median agrees (10 %: shading, view angle)
AGREE_SHARE = 0.5           # ... and this share of a pair's cells must agree,
AGREE_MIN = 0.3             # ... or at least this share, when that is AGREE_OVER_CHANCE times the share that agrees
AGREE_OVER_CHANCE = 2.0     # with each of a's cells paired with a random one of b's (colours that agree by chance).
                            # Real camera pairs of the PandaSet drive with LiDAR agree 0.34-0.75 against a chance of
                            # 0.04-0.24: cells at another camera's image edge, seen at another angle and resolution,
                            # spread more than 10 % (the front and front-left cameras: 0.44 against 0.13), and the
                            # share alone left those cameras unrelated (a bright rectangle where their cells met).
                            # The share alone still counts: camera only, that pair's matches are the sky (0.86
                            # against a chance of 0.62: one colour, the same wherever a cell is paired)
AGREE_MIN_RATIO = float(np.log(1.5))   # ... and a pair counted by AGREE_MIN must say the two cameras' exposures
                            # differ by less than 1.5x in every channel: the nuScenes rig's front and front-left
                            # cameras' matches agree 0.33 against a chance of 0.09 but say 2.7x (their narrow overlap,
                            # cells of other surfaces at the same depth), which no two cameras of one rig are apart;
                            # PandaSet's front and front-left are 1.3x (1.17-1.28x in their recordings). AGREE_MIN:
                            # the PandaSet pairs it adds agree 0.34-0.44; the nuScenes rig's other doubtful pairs
                            # 0.24-0.27 (1.3x, which made its back-right camera's own view 3 dB worse at 0.25): two
                            # rigs, so a rule of thumb, not a measured boundary
RIDGE = 0.05                # a pull of each log gain towards 0 (relative to a pair's weight of ~sqrt(200) = 14)
MAX_LOG_GAIN = float(np.log(2.0))   # gains are kept within 1/2..2: more is a wrong match, not an exposure


def base_colours(g: Gaussians) -> np.ndarray:
    """[N, 3] float64: the Gaussians' view-independent colour (the SH DC term: 0.5 + SH_C0 dc)."""
    return 0.5 + SH_C0 * g.sh[:, 0, :].astype(np.float64)


def match_cells(a_detail, a_colours: np.ndarray, b_detail, b_colours: np.ndarray, seed: int = 0
                ) -> tuple[np.ndarray, np.ndarray]:
    """(ca [M, 3], cb [M, 3]): the colours of the cells of view a that land on a kept cell of view b at the same
    depth (within MATCH_DEPTH of it), and that cell's colour. a_detail, b_detail: runtime.detail.CameraDetail in one
    frame (the scene's); a_colours [Ma, 3], b_colours [Mb, 3]: their cells' colours in Gaussian order."""
    return _View(a_detail, a_colours.__getitem__, seed).onto(_View(b_detail, b_colours.__getitem__, seed, False))


def _dc_colours(dc: np.ndarray, gain: np.ndarray | None = None):
    """rows -> [n, 3] float64 base colours (base_colours) of the cells with SH DC ``dc`` [M, 3], divided by ``gain``
    ([3] or None): only the rows a match looks at are computed, not a keyframe's millions."""
    def colours(rows: np.ndarray) -> np.ndarray:
        c = 0.5 + SH_C0 * dc[rows].astype(np.float64)
        return c if gain is None else c / gain
    return colours


class _View:
    """A view's cells as match_cells uses them, prepared once for all the pairs a keyframe's views make: a subset of
    at most MAX_SOURCE_CELLS of them (random, ``seed``) to project into the other views (``sources``: made here;
    False for a view that is only matched against), and each kept cell's row among the cells (raster order of its
    grid, the Gaussians' order). colours: rows [n] -> their colours [n, 3]."""

    def __init__(self, detail, colours: Callable[[np.ndarray], np.ndarray], seed: int = 0, sources: bool = True):
        self.detail, self.colours, self.seed = detail, colours, seed
        self.row = np.cumsum(detail.keep.ravel()) - 1          # [h w]: a kept cell's row among the kept cells
        self.source = self.source_means = None
        if sources:
            idx = np.arange(len(detail.means))
            if len(idx) > MAX_SOURCE_CELLS:
                idx = np.sort(np.random.default_rng(seed).choice(len(idx), MAX_SOURCE_CELLS, replace=False))
            self.source = idx                                   # the rows of the cells projected into other views
            self.source_means = detail.means[idx]              # [S, 3] their centres

    def onto(self, b: _View) -> tuple[np.ndarray, np.ndarray]:
        """match_cells(self's cells, b's)."""
        grid, bd = b.detail.grid, b.detail
        uv, z, front = grid.project_depth(self.source_means)
        ok = front & grid.inside(uv)
        k = np.flatnonzero(ok)                                  # the rest never read a cell
        u = np.clip(np.rint(uv[k, 0]).astype(np.int64), 0, grid.width - 1)
        v = np.clip(np.rint(uv[k, 1]).astype(np.int64), 0, grid.height - 1)
        cell = v * grid.width + u
        zk = z[k]
        ok = bd.keep.ravel()[cell] & (np.abs(bd.depth.ravel()[cell] - zk) <= MATCH_DEPTH * np.maximum(zk, 1e-6))
        return self.colours(self.source[k[ok]]), b.colours(b.row[cell[ok]])


def pair_offset(ca: np.ndarray, cb: np.ndarray, seed: int = 0) -> tuple[np.ndarray, int] | None:
    """([3] the median over cells of log ca - log cb per channel, the count of cells used) or None when fewer than
    MIN_PAIRS cells have both colours within COLOUR_RANGE, or when the share of them within AGREE_LOG of the median in
    every channel is under AGREE_SHARE and either under AGREE_MIN, or under AGREE_OVER_CHANCE times the share that
    agrees with ca's cells paired with cb's shuffled (``seed``), or the median says more than AGREE_MIN_RATIO: the
    matches are then not one surface seen twice (a car that moved, a wrong depth)."""
    lo, hi = COLOUR_RANGE
    ok = np.all((ca > lo) & (ca < hi) & (cb > lo) & (cb < hi), axis=1)
    if ok.sum() < MIN_PAIRS:
        return None
    la, lb = np.log(ca[ok]), np.log(cb[ok])
    agree, med = _agreeing(la - lb), np.median(la - lb, axis=0)
    if agree < AGREE_SHARE:
        chance = _agreeing(la - lb[np.random.default_rng(seed).permutation(len(lb))])
        if agree < AGREE_MIN or agree < AGREE_OVER_CHANCE * chance or np.abs(med).max() > AGREE_MIN_RATIO:
            return None
    return med, int(ok.sum())


def _agreeing(r: np.ndarray) -> float:
    """The share of log ratios r [M, 3] within AGREE_LOG of their median in every channel."""
    return float(np.mean(np.all(np.abs(r - np.median(r, axis=0)) <= AGREE_LOG, axis=1)))


def solve_log_gains(n: int, pairs: Sequence[tuple[int, int | None, np.ndarray, int]]) -> np.ndarray:
    """[n, 3] log gains of n views from pairs (a, b, offset [3], count): x_a - x_b = offset, b None for a view whose
    cells are already harmonised (x_b = 0). Weighted least squares (sqrt(count)), each x pulled towards 0 by RIDGE,
    and when no pair reaches a harmonised view, the mean of the x of the views in some pair held at 0 (the gauge: a
    view in no pair stays at 0 with them); clipped to +-MAX_LOG_GAIN."""
    rows, rhs, w = [], [], []
    anchored = any(b is None for _, b, _, _ in pairs)
    for a, b, off, count in pairs:
        r = np.zeros(n)
        r[a] = 1.0
        if b is not None:
            r[b] = -1.0
        rows.append(r)
        rhs.append(np.asarray(off, np.float64))
        w.append(np.sqrt(count))
    for i in range(n):
        r = np.zeros(n)
        r[i] = 1.0
        rows.append(r)
        rhs.append(np.zeros(3))
        w.append(RIDGE)
    linked = sorted({a for a, *_ in pairs} | {b for _, b, *_ in pairs if b is not None})
    if not anchored and linked:
        r = np.zeros(n)
        r[linked] = 1.0 / len(linked)
        rows.append(r)
        rhs.append(np.zeros(3))
        w.append(np.sqrt(sum(c for *_, c in pairs)) if pairs else 1.0)
    A = np.array(rows) * np.array(w)[:, None]
    B = np.array(rhs) * np.array(w)[:, None]
    x = np.linalg.lstsq(A, B, rcond=None)[0]
    return np.clip(x, -MAX_LOG_GAIN, MAX_LOG_GAIN)


def apply_gain(g: Gaussians, gain: np.ndarray) -> Gaussians:
    """``g`` with its colours divided by ``gain`` ([3] per channel, or [N, 3] per Gaussian; positive): the SH DC term
    so that 0.5 + SH_C0 dc is divided, the higher bands divided (in float64, stored in the SH's dtype)."""
    gain = np.asarray(gain, np.float64)
    if not np.all(np.isfinite(gain)) or np.any(gain <= 0):
        raise ValueError("gain: must be finite and positive")
    sh = np.empty_like(g.sh)
    # ((0.5 + SH_C0 dc) / gain - 0.5) / SH_C0 in float64, the same operations in the same order as numpy's
    # (apply_gain_reference: the same bits), in one parallel pass
    _divide_dc(g.sh[:, 0, :], np.ascontiguousarray(gain.reshape(-1, 3)), sh[:, 0, :])
    if sh.shape[1] > 1:
        sh[:, 1:, :] = g.sh[:, 1:, :].astype(np.float64) / (gain[..., None, :] if gain.ndim == 2 else gain)
    # the rows of checked Gaussians, their colours divided by a finite positive gain: not checked again
    return Gaussians.joined(means=g.means, quats=g.quats, log_scales=g.log_scales, opacity_logits=g.opacity_logits,
                            sh=sh)


def apply_gain_reference(g: Gaussians, gain: np.ndarray) -> Gaussians:
    """apply_gain in numpy (tests: the same bits)."""
    gain = np.asarray(gain, np.float64)
    dc = g.sh[:, 0, :].astype(np.float64)
    sh = np.empty_like(g.sh)
    sh[:, 0, :] = ((dc * SH_C0 + 0.5) / gain - 0.5) / SH_C0
    if sh.shape[1] > 1:
        sh[:, 1:, :] = g.sh[:, 1:, :].astype(np.float64) / (gain[..., None, :] if gain.ndim == 2 else gain)
    return Gaussians.joined(means=g.means, quats=g.quats, log_scales=g.log_scales, opacity_logits=g.opacity_logits,
                            sh=sh)


@njit(cache=True, parallel=True, nogil=True)
def _divide_dc(dc, gain, out):
    """out[i] = ((dc[i] SH_C0 + 0.5) / gain - 0.5) / SH_C0 per channel in float64, stored in out's dtype; dc, out
    [N, 3] (any strides), gain [N, 3] or [1, 3] float64 (apply_gain)."""
    step = 0 if gain.shape[0] == 1 else 1        # gain's row of Gaussian i: i x step
    for i in prange(dc.shape[0]):
        gi = i * step
        for c in range(3):
            v = np.float64(dc[i, c]) * SH_C0
            v = v + 0.5
            v = v / gain[gi, c]
            v = v - 0.5
            out[i, c] = v / SH_C0


PAIR_THREADS = 2     # threads matching a keyframe's pairs of views: numpy releases the GIL in each pair's projection
#                      and gathers (a PandaSet frame's 30 pairs 81 -> ~50 ms on 2 cores)


class Harmoniser:
    """The gains of a drive's keyframes, one keyframe at a time in drive order (module docstring). ``add`` takes a
    keyframe's detail layers and Gaussians per camera (in the scene's frame) and returns its Gaussians harmonised;
    ``gains`` [K][C] of [3] (C: the rig's cameras; 1 for a camera without a detail layer)."""

    def __init__(self, n_cameras: int) -> None:
        self.n_cameras = n_cameras
        self.gains: list[np.ndarray] = []          # per keyframe [C, 3]
        self.pairs: list[int] = []                 # per keyframe, the pairs that counted
        self._prev: tuple = ()                     # the previous keyframe's (details, DC terms, gains)

    def add(self, details: Sequence, parts: Sequence[Gaussians], owners: Sequence[int]) -> list[Gaussians]:
        dcs = [g.sh[:, 0, :] for g in parts]
        views = [_View(d, _dc_colours(dc)) for d, dc in zip(details, dcs)]
        prev = self._prev_views()
        n = len(parts)
        # every ordered pair of this keyframe's views, then each view against the previous keyframe's (harmonised)
        jobs = [(i, j, views[j] if j is not None else p) for i in range(n)
                for j, p in [*((j, None) for j in range(n) if j != i), *((None, p) for p in prev)]]
        offsets = in_threads(lambda job: pair_offset(*views[job[0]].onto(job[2])), jobs, PAIR_THREADS)
        pairs = [(i, j, r[0], r[1]) for (i, j, _), r in zip(jobs, offsets) if r is not None]
        x = solve_log_gains(n, pairs) if n else np.zeros((0, 3))
        gains = np.ones((self.n_cameras, 3))
        out = []
        for i, g in enumerate(parts):
            gains[owners[i]] = np.exp(x[i])
            out.append(apply_gain(g, np.exp(x[i])))
        self.gains.append(gains)
        self.pairs.append(len(pairs))
        self._prev = (list(details), dcs, np.exp(x))   # their views made by the next add (one frame: never)
        self._last = ([d.grid for d in details], x)
        return out

    def _prev_views(self) -> list[_View]:
        """The previous keyframe's views, with its harmonised colours."""
        if not self._prev:
            return []
        details, dcs, gains = self._prev
        return [_View(d, _dc_colours(dc, gain), sources=False) for d, dc, gain in zip(details, dcs, gains)]

    def details(self, details: Sequence, owners: Sequence[int]) -> list:
        """The last added keyframe's detail layers (runtime.detail.CameraDetail, as given to ``add``) with their split
        cells' colours divided by their camera's gain, as ``add`` divided its Gaussians'."""
        gains = self.gains[-1]
        return [d if d.split is None else replace(d, split=d.split.divided(gains[o])) for d, o in zip(details, owners)]

    def coarse(self, g: Gaussians) -> Gaussians:
        """The last added keyframe's model Gaussians ``g`` (scene frame) harmonised: each divided by the geometric
        mean of the gains of that keyframe's cameras whose view holds its centre (the model blends what they saw);
        one that no camera with a detail layer sees is left as it is."""
        grids, x = self._last
        if not len(g) or not grids:
            return g
        total = np.zeros((len(g), 3))
        seen = np.zeros(len(g))
        for grid, xi in zip(grids, x):
            uv, _, front = grid.project(g.means)
            inside = front & grid.inside(uv)
            total[inside] += xi
            seen[inside] += 1
        gain = np.exp(total / np.maximum(seen, 1)[:, None])
        return apply_gain(g, gain)

    def to_json(self, names: Sequence[str]) -> dict:
        """scene.json's ``exposure`` block: the cameras' names and gains [K][C][3] (rounded to 1e-4)."""
        return {"cameras": list(names), "gains": [np.round(g, 4).tolist() for g in self.gains],
                "pairs": list(self.pairs),
                "about": "per keyframe and camera, the per-channel gain its detail cells were divided by; a view "
                         "near an input camera gets that camera's gain back"}


__all__ = ["Harmoniser", "apply_gain", "base_colours", "match_cells", "pair_offset", "solve_log_gains"]
