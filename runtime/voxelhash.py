"""The drive fusion's voxel owners in hash tables (runtime.drive.VoxelOwners): numba kernels over open-addressing
tables of packed voxel keys, so that deduping a keyframe's cells against the scene's costs a lookup per voxel and
a pass over the keyframe's cells, with no sort of them and no array of all the scene's cells rebuilt.

A table is a power-of-two number of slots (``keys`` [S] int64, EMPTY where free; linear probing from a Fibonacci
hash of the key) with arrays of the same length beside it. Keys are runtime.drive._pack's: 21 bits an axis of the
voxel's integer coordinates, offset by 2^20 and clamped, so never negative. VoxelOwners (drive.py) holds one owner
table per voxel level and, for each voxel, a chain of the kept cells at exactly that level (``head`` of the slot,
then ``nxt`` of each entry; an entry is a cell's caller id). Nothing here allocates: the caller sizes the arrays
(``capacity``, a load of at most one half) and grows them (``rehash``, ``compact``)."""

from __future__ import annotations

import math

import numpy as np

from .numba_cache import njit

EMPTY = -1                          # a free slot's key (a packed key is never negative)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)     # Fibonacci hashing: 2^64 / the golden ratio, odd
_LIM = (1 << 21) - 1
_OFF = 1 << 20


def capacity(n: int) -> int:
    """Slots of a table that holds ``n`` keys at a load of at most one half (a power of two, at least 1024)."""
    return max(1024, 1 << int(math.ceil(math.log2(max(2 * n, 1)))))


def empty_table(slots: int) -> np.ndarray:
    """[slots] int64, every slot free."""
    return np.full(slots, EMPTY, np.int64)


@njit(cache=True, nogil=True)
def _shift(slots):
    """64 - log2(slots) (a power of two, at least 2): the shift that leaves a hash's top bits, one per slot bit."""
    bits = 0
    while (1 << bits) < slots:
        bits += 1
    return np.uint64(64 - bits)


@njit(cache=True, nogil=True)
def _find(keys, key, mask, shift):
    """The slot of ``key`` in the table ``keys``, or the free slot where it would go: the probe starts at the top
    bits of key x _GOLDEN (``shift``: _shift of the table's length)."""
    s = np.int64((np.uint64(key) * _GOLDEN) >> shift)
    while keys[s] != EMPTY and keys[s] != key:
        s = (s + 1) & mask
    return s


@njit(cache=True, nogil=True)
def _pack1(c0, c1, c2):
    """runtime.drive._pack of one voxel's integer coordinates."""
    return ((min(max(c0 + _OFF, 0), _LIM) << 42) | (min(max(c1 + _OFF, 0), _LIM) << 21) |
            min(max(c2 + _OFF, 0), _LIM))


@njit(cache=True, nogil=True)
def cell_voxel(points, p, size, origin, with_origin):
    """Point p of points [N, 3] (metres)'s voxel of edge ``size``: (its integer coordinates floor(point / size) in
    float64, its packed key, the distance from its centre to ``origin`` [3] metres when ``with_origin``, else 0):
    the arithmetic of runtime.drive._pack and _voxel_distance_reference, the same bits (drive._cell_voxels,
    local_owners)."""
    c0 = np.int64(math.floor(np.float64(points[p, 0]) / size))
    c1 = np.int64(math.floor(np.float64(points[p, 1]) / size))
    c2 = np.int64(math.floor(np.float64(points[p, 2]) / size))
    d = 0.0
    if with_origin:
        dx = (np.float64(c0) + 0.5) * size - origin[0]
        dy = (np.float64(c1) + 0.5) * size - origin[1]
        dz = (np.float64(c2) + 0.5) * size - origin[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
    return c0, c1, c2, _pack1(c0, c1, c2), d


@njit(cache=True, nogil=True)
def local_owners(prev_c, prev_l, prev_d, points, idx, size, level, origin, with_origin, scratch, scratch_v,
                 out_c, out_l, out_d, out_k, cell_owner):
    """One voxel level of one keyframe's own dedupe (runtime.drive.dedupe_frames within one keyframe, whose cells
    never drop each other): the best (lowest level, then nearest) of the owners of the level below (``prev_c`` [P,
    3] int64 their voxel coordinates there, halved here; ``prev_l`` [P] their level, ``prev_d`` [P] their distance,
    metres) and of this level's cells (``points`` [N, 3] metres, the rows ``idx`` [n]; voxel edge ``size`` metres,
    ``level`` their level; distance from their voxel's centre to ``origin`` [3] metres when ``with_origin``, else
    0: the arithmetic of drive._cell_voxels, the same bits) in each voxel. Writes the owners (coordinates, level,
    distance, packed key) to out_c [V, 3], out_l, out_d, out_k and each cell's owner (its index there) to
    cell_owner [n]; returns V, or -1 when the voxels outnumber half the slots (nothing written then: call again with
    more). ``scratch`` [S] (all EMPTY; left so) and ``scratch_v`` [S] int64: a table of a power of two slots (2 (P +
    n) always hold them; a keyframe has several cells a voxel). Among equals the first kept (the level below's, then
    the cells in order): they are one voxel with one rank."""
    mask, shift = len(scratch) - 1, _shift(len(scratch))
    full = len(scratch) // 2
    v = 0
    for i in range(len(prev_l)):
        if v >= full:
            break
        c0, c1, c2 = prev_c[i, 0] // 2, prev_c[i, 1] // 2, prev_c[i, 2] // 2
        key = _pack1(c0, c1, c2)
        s = _find(scratch, key, mask, shift)
        if scratch[s] == EMPTY:
            scratch[s] = key
            scratch_v[s] = v
            out_c[v, 0], out_c[v, 1], out_c[v, 2] = c0, c1, c2
            out_l[v], out_d[v], out_k[v] = prev_l[i], prev_d[i], key
            v += 1
        else:
            j = scratch_v[s]
            if prev_l[i] < out_l[j] or (prev_l[i] == out_l[j] and prev_d[i] < out_d[j]):
                out_c[j, 0], out_c[j, 1], out_c[j, 2] = c0, c1, c2
                out_l[j], out_d[j] = prev_l[i], prev_d[i]
    for i in range(len(idx)):
        if v >= full:
            break
        c0, c1, c2, key, d = cell_voxel(points, idx[i], size, origin, with_origin)
        s = _find(scratch, key, mask, shift)
        if scratch[s] == EMPTY:
            scratch[s] = key
            scratch_v[s] = v
            out_c[v, 0], out_c[v, 1], out_c[v, 2] = c0, c1, c2
            out_l[v], out_d[v], out_k[v] = level, d, key
            j = v
            v += 1
        else:
            j = scratch_v[s]
            if level < out_l[j] or (level == out_l[j] and d < out_d[j]):
                out_c[j, 0], out_c[j, 1], out_c[j, 2] = c0, c1, c2
                out_l[j], out_d[j] = level, d
        cell_owner[i] = j
    # the scratch table left empty for the next call: the keys taken out last in first out, so that each one's
    # probe finds it (the slots it passed were taken before it, and are still)
    for j in range(v - 1, -1, -1):
        scratch[_find(scratch, out_k[j], mask, shift)] = EMPTY
    return v if v < full else -1


@njit(cache=True, nogil=True)
def take_over(keys, t_lev, t_dist, t_frame, head, o_key, o_lev, o_dist, v, frame, cell_owner, cell_ids,
              ent_id, nxt, n_ent, lost, n_lost, wins, slots, keep):
    """One voxel level of VoxelOwners.add: keyframe ``frame``'s owners there (o_key, o_lev, o_dist, the first ``v``)
    against the table's (keys, t_lev, t_dist, t_frame, head [S]). A voxel is the keyframe's where the table has none
    or the keyframe's owner ranks lower (level, distance, keyframe); the kept cells of the voxel taken over go: their
    ids are written to lost[n_lost:]. Then each of this level's cells (its owner ``cell_owner`` [n], its id
    ``cell_ids`` [n]) is kept where its voxel is the keyframe's (keep [n] bool, written) and chained into its
    voxel's entries (ent_id, nxt from ``n_ent`` on). ``wins``, ``slots`` [>= v]: scratch. The table must have room
    for v more keys at a load of at most one half, the entries for n more. Returns (keys added to the table, the
    entries' count, the lost count)."""
    mask, shift = len(keys) - 1, _shift(len(keys))
    added = 0
    for j in range(v):
        key = o_key[j]
        s = _find(keys, key, mask, shift)
        slots[j] = s
        if keys[s] == EMPTY:
            keys[s] = key
            t_lev[s], t_dist[s], t_frame[s], head[s] = o_lev[j], o_dist[j], frame, -1
            wins[j] = True
            added += 1
            continue
        el, ed = o_lev[j], o_dist[j]
        if el < t_lev[s] or (el == t_lev[s] and (ed < t_dist[s] or (ed == t_dist[s] and frame < t_frame[s]))):
            t_lev[s], t_dist[s], t_frame[s] = el, ed, frame
            e = head[s]
            while e >= 0:
                lost[n_lost] = ent_id[e]
                n_lost += 1
                e = nxt[e]
            head[s] = -1
            wins[j] = True
        else:
            wins[j] = False
    for i in range(len(cell_owner)):
        j = cell_owner[i]
        keep[i] = wins[j]
        if wins[j]:
            s = slots[j]
            ent_id[n_ent] = cell_ids[i]
            nxt[n_ent] = head[s]
            head[s] = n_ent
            n_ent += 1
    return added, n_ent, n_lost


@njit(cache=True, nogil=True)
def rehash(keys, t_lev, t_dist, t_frame, head, new_keys, new_lev, new_dist, new_frame, new_head):
    """The table (keys, t_lev, t_dist, t_frame, head) put into the larger free table of new_* (all its keys EMPTY)."""
    mask, shift = len(new_keys) - 1, _shift(len(new_keys))
    for s in range(len(keys)):
        if keys[s] != EMPTY:
            d = _find(new_keys, keys[s], mask, shift)
            new_keys[d] = keys[s]
            new_lev[d], new_dist[d], new_frame[d], new_head[d] = t_lev[s], t_dist[s], t_frame[s], head[s]


@njit(cache=True, nogil=True)
def compact(keys, head, ent_id, nxt, new_id, new_nxt, n_new):
    """The chains of one table (its voxels ``keys``, their ``head`` [S], rewritten) copied from (ent_id, nxt) to
    (new_id, new_nxt) from ``n_new`` on, without the entries no chain reaches (cells lost); returns the new count.
    A chain's order is reversed (it is a set)."""
    for s in range(len(head)):
        if keys[s] == EMPTY:
            continue
        e = head[s]
        h = -1
        while e >= 0:
            new_id[n_new] = ent_id[e]
            new_nxt[n_new] = h
            h = n_new
            n_new += 1
            e = nxt[e]
        head[s] = h
    return n_new
