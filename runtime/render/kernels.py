"""numba kernels of the fast renderer: projection, tile binning, tile rasterisation (forward and backward).

Numbers: projection in float64, rasterisation in float32 with Gaussian means stored relative to their
tile's origin (so float32 keeps ~1e-6 px precision at any image size). exp(-power) is a polynomial
(`_exp_neg`, relative error < 2e-6 on the footprint range) because numba from PyPI has no SVML, so np.exp
would not vectorise. The backward pass replays the forward decisions with the same float32 expressions.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

TILE = 16
TILE_PIX = TILE * TILE
NCG = 16    # per-Gaussian float32 row (64 bytes): mean x, y (px) as float32 hi + lo pairs (float64 precision),
#             bounding half-height ry, A, B, C (half conic), opacity, pmax, r, g, b, depth, pad, pad
ROW_PAD = 1e-3  # px added to ry when choosing the tile rows a Gaussian is evaluated on (float32 ry rounding)
STOP_CHECK = 16  # the raster tests for a fully stopped tile every this many instances (a power of 2)
GATHER = 128  # instances gathered per batch into the raster's per-tile buffer (8 KB: stays in L1)
NFEAT = 16  # per-instance features (one 64-byte row): mx, my (tile-local px), A = a/2, B = b, C = c/2 (conic),
#             opacity, pmax, r, g, b, depth, first row, last row (tile-local rows the footprint can touch),
#             pad

F0 = np.float32(0.0)
F1 = np.float32(1.0)
HALF = np.float32(0.5)
A_MAX = np.float32(0.99)
A_MIN = np.float32(1.0 / 255.0)
T_STOP = np.float32(1e-4)
P_CLIP = np.float32(6.0)      # the exp argument is clamped here; powers above every cutoff (<= 5.55) anyway
INV16 = np.float32(1.0 / 16.0)


def _fit_exp_coefficients():
    """Degree-5 least-squares fit of exp(t) on t in [-6/16, 0] (Chebyshev nodes): max relative error ~1e-9,
    far below float32 rounding, so exp(-p) = fit(-p/16)^16 is accurate to ~1e-6 relative."""
    k = np.arange(200)
    t = -0.1875 * (1 + np.cos(np.pi * (k + 0.5) / 200))
    c = np.polyfit(t, np.exp(t), 5)  # highest power first
    return tuple(np.float32(v) for v in c)


E5, E4, E3, E2, E1, E0 = _fit_exp_coefficients()
RASTER_MATH = {"contract"}  # allow FMA contraction in the raster kernels (forward and backward alike)


@njit(inline="always", fastmath=RASTER_MATH)
def _exp_neg(p):
    """exp(-p) for float32 p in [0, 6], relative error < 2e-6 (see _fit_exp_coefficients)."""
    t = -p * INV16
    e = E0 + t * (E1 + t * (E2 + t * (E3 + t * (E4 + t * E5))))
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(inline="always", fastmath=RASTER_MATH)
def _power(dx, dy, A, B, C):
    return (A * dx + B * dy) * dx + C * dy * dy


@njit(inline="always", fastmath=RASTER_MATH)
def _alpha(dx, dy, A, B, C, op, pmax):
    """(ok, alpha, G) for one pixel and one Gaussian, float32; ok = contributes (before the stop test)."""
    power = _power(dx, dy, A, B, C)
    g = _exp_neg(min(max(power, F0), P_CLIP))
    a = min(A_MAX, op * g)
    ok = (power >= F0) and (power <= pmax) and (a >= A_MIN)
    return ok, a, g


# ------------------------------------------------------------------------------------------------ projection
@njit(cache=True, parallel=True, nogil=True)
def project_kernel(means, quats, log_scales, opacity_logits, sh, campos, Rw, tw, model, fx, fy, cx, cy,
                   lxn, lxp, lyn, lyp, width, height, near, far, low_pass, antialiased, opacity_mode,
                   rows, trange, depth_out):
    """Per Gaussian i (computed in float64): rows[i] = its 64-byte float32 row (layout: NCG), trange[i] [n, 2]
    int32 = (tx0 | tx1 << 16, ty0 | ty1 << 16) the tiles its bounding box touches (tx1 < tx0: the range wraps
    around the azimuth seam, equirect), depth_out[i] [n] float64 = depth, or -1 when culled (rows[i] and
    trange[i] are then left unwritten). model 0 = pinhole, 1 = equirect."""
    n = means.shape[0]
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for i in prange(n):
        depth_out[i] = -1.0
        mxw, myw, mzw = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        x = Rw[0, 0] * mxw + Rw[0, 1] * myw + Rw[0, 2] * mzw + tw[0]
        y = Rw[1, 0] * mxw + Rw[1, 1] * myw + Rw[1, 2] * mzw + tw[1]
        z = Rw[2, 0] * mxw + Rw[2, 1] * myw + Rw[2, 2] * mzw + tw[2]
        if model == 0:
            depth = z
            if not (z >= near and z <= far):
                continue
            sx = x / z
            sy = y / z
            u = fx * sx + cx
            v = fy * sy + cy
            sxc = min(max(sx, -lxn), lxp)
            syc = min(max(sy, -lyn), lyp)
            # cheap conservative cull before the covariance: sigma_u <= |J row 0| * max scale, etc.
            smax = math.exp(max(np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]),
                                np.float64(log_scales[i, 2])))
            ru = 3.34 * math.sqrt((fx / z) ** 2 * (1.0 + sxc * sxc) * smax * smax + low_pass)
            rv = 3.34 * math.sqrt((fy / z) ** 2 * (1.0 + syc * syc) * smax * smax + low_pass)
            if u - ru > width - 1 or u + ru < 0.0 or v - rv > height - 1 or v + rv < 0.0:
                continue
            j00 = fx / z
            j01 = 0.0
            j02 = -fx * sxc / z
            j10 = 0.0
            j11 = fy / z
            j12 = -fy * syc / z
        else:
            r = math.sqrt(x * x + y * y + z * z)
            depth = r
            if not (r >= near and r <= far):
                continue
            rho = math.sqrt(x * x + z * z)
            rho_j = max(rho, r * math.sin(math.pi / (2.0 * height)))
            u = width * (math.atan2(x, z) + math.pi) / (2.0 * math.pi) - 0.5
            v = height * math.atan2(rho, -y) / math.pi - 0.5
            ku = width / (2.0 * math.pi)
            kv = height / math.pi
            j00 = ku * z / (rho_j * rho_j)
            j01 = 0.0
            j02 = -ku * x / (rho_j * rho_j)
            j10 = -kv * y * x / (r * r * rho_j)
            j11 = kv * rho / (r * r)
            j12 = -kv * y * z / (r * r * rho_j)
        # rotation from the normalised quaternion
        qw, qx, qy, qz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), \
            np.float64(quats[i, 3])
        qn = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw *= qn
        qx *= qn
        qy *= qn
        qz *= qn
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        s0 = math.exp(np.float64(log_scales[i, 0]))
        s1 = math.exp(np.float64(log_scales[i, 1]))
        s2 = math.exp(np.float64(log_scales[i, 2]))
        # T = J Rw (2x3); A = T R S (2x3); cov2 = A A^T
        t00 = j00 * Rw[0, 0] + j01 * Rw[1, 0] + j02 * Rw[2, 0]
        t01 = j00 * Rw[0, 1] + j01 * Rw[1, 1] + j02 * Rw[2, 1]
        t02 = j00 * Rw[0, 2] + j01 * Rw[1, 2] + j02 * Rw[2, 2]
        t10 = j10 * Rw[0, 0] + j11 * Rw[1, 0] + j12 * Rw[2, 0]
        t11 = j10 * Rw[0, 1] + j11 * Rw[1, 1] + j12 * Rw[2, 1]
        t12 = j10 * Rw[0, 2] + j11 * Rw[1, 2] + j12 * Rw[2, 2]
        a00 = (t00 * r00 + t01 * r10 + t02 * r20) * s0
        a01 = (t00 * r01 + t01 * r11 + t02 * r21) * s1
        a02 = (t00 * r02 + t01 * r12 + t02 * r22) * s2
        a10 = (t10 * r00 + t11 * r10 + t12 * r20) * s0
        a11 = (t10 * r01 + t11 * r11 + t12 * r21) * s1
        a12 = (t10 * r02 + t11 * r12 + t12 * r22) * s2
        c00 = a00 * a00 + a01 * a01 + a02 * a02
        c01 = a00 * a10 + a01 * a11 + a02 * a12
        c11 = a10 * a10 + a11 * a11 + a12 * a12
        det_raw = c00 * c11 - c01 * c01
        c00 += low_pass
        c11 += low_pass
        det = c00 * c11 - c01 * c01
        if not (det > 0.0):
            continue
        opa = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[i])))
        if antialiased:
            opa *= math.sqrt(max(det_raw / det, 0.0))
        if not (opa >= 1.0 / 255.0):
            continue
        if opacity_mode:
            ext = min(3.33, math.sqrt(2.0 * math.log(opa * 255.0)))
        else:
            ext = 3.0
        pmax = 0.5 * ext * ext
        rx = ext * math.sqrt(c00)
        ry = ext * math.sqrt(c11)
        v_lo = max(0, int(math.ceil(max(v - ry, -1e9))))
        v_hi = min(height - 1, int(math.floor(min(v + ry, 1e9))))
        if v_lo > v_hi:
            continue
        u_lo_f = math.ceil(max(u - rx, -1e9))
        u_hi_f = math.floor(min(u + rx, 1e9))
        if model == 0:
            u_lo = max(0, int(u_lo_f))
            u_hi = min(width - 1, int(u_hi_f))
            if u_lo > u_hi:
                continue
            tx0 = u_lo // TILE
            tx1 = u_hi // TILE
            nx = tx1 - tx0 + 1
        else:
            if u_hi_f < u_lo_f:
                continue
            if u_hi_f - u_lo_f + 1 >= width:
                tx0 = 0
                tx1 = ntx - 1
            else:
                tx0 = (int(u_lo_f) % width) // TILE
                tx1 = (int(u_hi_f) % width) // TILE
                if int(u_lo_f) % width > int(u_hi_f) % width and tx1 >= tx0:
                    tx0 = 0
                    tx1 = ntx - 1
            nx = tx1 - tx0 + 1 if tx1 >= tx0 else ntx - tx0 + tx1 + 1
        ty0 = v_lo // TILE
        ty1 = v_hi // TILE
        hi = np.float32(u)
        rows[i, 0] = hi
        rows[i, 1] = np.float32(u - np.float64(hi))
        hi = np.float32(v)
        rows[i, 2] = hi
        rows[i, 3] = np.float32(v - np.float64(hi))
        rows[i, 4] = ry
        rows[i, 5] = 0.5 * c11 / det
        rows[i, 6] = -c01 / det
        rows[i, 7] = 0.5 * c00 / det
        rows[i, 8] = opa
        rows[i, 9] = pmax
        vx, vy, vz = mxw - campos[0], myw - campos[1], mzw - campos[2]
        for c in range(3):
            rows[i, 10 + c] = _sh_colour(sh, i, c, vx, vy, vz)
        rows[i, 13] = depth
        rows[i, 14] = 0.0
        rows[i, 15] = 0.0
        trange[i, 0] = tx0 | (tx1 << 16)
        trange[i, 1] = ty0 | (ty1 << 16)
        depth_out[i] = depth
    _ = nty
    _ = nx


@njit(inline="always")
def _sh_colour(sh, i, c, vx, vy, vz):
    """3DGS SH evaluation (degree from sh.shape[1]) of channel c, clamped at 0 (float64). v = mean - camera
    centre."""
    k = sh.shape[1]
    r = 0.28209479177387814 * sh[i, 0, c]
    if k > 1:
        nrm = math.sqrt(vx * vx + vy * vy + vz * vz)
        nrm = 1.0 / max(nrm, 1e-12)
        x = vx * nrm
        y = vy * nrm
        z = vz * nrm
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        r += -0.4886025119029199 * y * sh[i, 1, c] + 0.4886025119029199 * z * sh[i, 2, c] \
            - 0.4886025119029199 * x * sh[i, 3, c]
        if k > 4:
            r += (1.0925484305920792 * xy * sh[i, 4, c] - 1.0925484305920792 * yz * sh[i, 5, c]
                  + 0.31539156525252005 * (2 * zz - xx - yy) * sh[i, 6, c]
                  - 1.0925484305920792 * xz * sh[i, 7, c] + 0.5462742152960396 * (xx - yy) * sh[i, 8, c])
        if k > 9:
            r += (-0.5900435899266435 * y * (3 * xx - yy) * sh[i, 9, c]
                  + 2.890611442640554 * xy * z * sh[i, 10, c]
                  - 0.4570457994644658 * y * (4 * zz - xx - yy) * sh[i, 11, c]
                  + 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy) * sh[i, 12, c]
                  - 0.4570457994644658 * x * (4 * zz - xx - yy) * sh[i, 13, c]
                  + 1.445305721320277 * z * (xx - yy) * sh[i, 14, c]
                  - 0.5900435899266435 * x * (xx - 3 * yy) * sh[i, 15, c])
    return max(r + 0.5, 0.0)


# --------------------------------------------------------------------------------------------------- binning
@njit(cache=True, nogil=True)
def depth_order(visible, keys):
    """Stable LSD radix sort of `visible` (Gaussian ids, ascending) by keys [n] uint64 (the bit patterns of
    positive float64 depths, which order like the values): 4 passes of 16 bits, passes where all keys share
    the digit skipped. Ties keep id order, as the reference's lexsort."""
    n = visible.shape[0]
    src = visible.astype(np.int32)
    srck = keys
    dst = np.empty(n, np.int32)
    dstk = np.empty(n, np.uint64)
    for shift in range(0, 64, 16):
        hist = np.zeros(65537, np.int64)
        sh_ = np.uint64(shift)
        for k in range(n):
            hist[((srck[k] >> sh_) & np.uint64(0xFFFF)) + 1] += 1
        if n == 0 or hist.max() == n:
            continue
        for b in range(65536):
            hist[b + 1] += hist[b]
        for k in range(n):
            b = (srck[k] >> sh_) & np.uint64(0xFFFF)
            pos = hist[b]
            hist[b] = pos + 1
            dst[pos] = src[k]
            dstk[pos] = srck[k]
        src, dst = dst, src
        srck, dstk = dstk, srck
    return src


@njit(cache=True, parallel=True, nogil=True)
def bin_kernel(order, trange, ntx, nty, nchunks):
    """List, per 16x16 tile, the ids of the Gaussians whose footprint's bounding box touches it (trange, see
    project_kernel), front to back (`order`: visible Gaussian ids in depth order). Returns
    (tile_start [ntiles + 1] int64, ids [n_inst] int32). The per-instance features are not built here: the
    raster gathers each tile's rows (gather_row), one 64-byte line per instance.

    Counting sort by tile over `nchunks` contiguous chunks of `order` (parallel): per-chunk tile histograms,
    a tile-major prefix sum, then each chunk writes its ids in order, so lists stay depth-ordered."""
    nv = order.shape[0]
    ntiles = ntx * nty
    ct = np.empty((nv, 4), np.int32)
    for k in prange(nv):
        i = order[k]
        ct[k, 0] = trange[i, 0] & 0xFFFF
        ct[k, 1] = trange[i, 0] >> 16
        ct[k, 2] = trange[i, 1] & 0xFFFF
        ct[k, 3] = trange[i, 1] >> 16
    hist = np.zeros((nchunks, ntiles), np.int64)
    for ch in prange(nchunks):
        k0 = nv * ch // nchunks
        k1 = nv * (ch + 1) // nchunks
        for k in range(k0, k1):
            tx0 = ct[k, 0]
            tx1 = ct[k, 1]
            a_hi = tx1 if tx1 >= tx0 else ntx - 1
            for ty in range(ct[k, 2], ct[k, 3] + 1):
                row = ty * ntx
                for tx in range(tx0, a_hi + 1):
                    hist[ch, row + tx] += 1
                if tx1 < tx0:
                    for tx in range(tx1 + 1):
                        hist[ch, row + tx] += 1
    start = np.empty(ntiles + 1, np.int64)
    run = 0
    for t in range(ntiles):
        start[t] = run
        for ch in range(nchunks):
            c = hist[ch, t]
            hist[ch, t] = run
            run += c
    start[ntiles] = run
    ids = np.empty(run, np.int32)
    for ch in prange(nchunks):
        k0 = nv * ch // nchunks
        k1 = nv * (ch + 1) // nchunks
        for k in range(k0, k1):
            tx0 = ct[k, 0]
            tx1 = ct[k, 1]
            a_hi = tx1 if tx1 >= tx0 else ntx - 1
            for ty in range(ct[k, 2], ct[k, 3] + 1):
                row = ty * ntx
                for tx in range(tx0, a_hi + 1):
                    pos = hist[ch, row + tx]
                    hist[ch, row + tx] = pos + 1
                    ids[pos] = order[k]
                if tx1 < tx0:
                    for tx in range(tx1 + 1):
                        pos = hist[ch, row + tx]
                        hist[ch, row + tx] = pos + 1
                        ids[pos] = order[k]
    return start, ids


@njit(inline="always")
def gather_row(cg, k, x0, y0, width, wrap, out, j):
    """Per-instance features of compact Gaussian k seen from the tile at (x0, y0) -> out[j, :NFEAT] float32:
    tile-local mean (the copy nearest the tile for equirect), half conic A B C, opacity, pmax, r g b, depth,
    first and last tile-local rows the bounding box touches. Forward and backward use this same code."""
    mx = (np.float64(cg[k, 0]) + np.float64(cg[k, 1])) - x0
    if wrap:
        mx -= width * np.floor((mx - 7.5) / width + 0.5)
    my = (np.float64(cg[k, 2]) + np.float64(cg[k, 3])) - y0
    # rows: the bounding box widened by ROW_PAD px, so float32 ry never drops a row the footprint touches
    # (the power test decides per pixel; an extra row only costs time)
    ry = np.float64(cg[k, 4]) + ROW_PAD
    out[j, 0] = mx
    out[j, 1] = my
    for c in range(9):
        out[j, 2 + c] = cg[k, 5 + c]
    out[j, 11] = max(0.0, math.floor(my - ry))
    out[j, 12] = min(TILE - 1.0, math.ceil(my + ry))


@njit(cache=True, parallel=True, nogil=True)
def instance_features(start, ids, rows, ntx, width, wrap):
    """feat [n_inst, NFEAT] float32: every tile instance's features (gather_row), for the backward pass."""
    ntiles = start.shape[0] - 1
    feat = np.zeros((ids.shape[0], NFEAT), np.float32)
    for t in prange(ntiles):
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        for j in range(start[t], start[t + 1]):
            gather_row(rows, ids[j], x0, y0, width, wrap, feat, j)
    return feat


# ----------------------------------------------------------------------------------------------- rasterise
@njit(inline="always", fastmath=RASTER_MATH)
def _blend_px(p, power, op, pm, cr, cg, cbl, z, jj, T, c0, c1, c2, dd, lst):
    """The blend of one Gaussian into pixel p (float32, branch-free: selects, so the caller's loop is SIMD)."""
    g = _exp_neg(min(max(power, F0), P_CLIP))
    a = min(A_MAX, op * g)
    tb = T[p]
    ok = (power >= F0) & (power <= pm) & (a >= A_MIN) & (tb > F0)
    tt = tb * (F1 - a)
    stop = ok & (tt <= T_STOP)
    blend = ok & (tt > T_STOP)
    w = a * tb if blend else F0
    c0[p] += w * cr
    c1[p] += w * cg
    c2[p] += w * cbl
    dd[p] += w * z
    T[p] = tt if blend else (-tb if stop else tb)
    lst[p] = jj if blend else lst[p]


@njit(inline="always", fastmath=RASTER_MATH)
def _blend_one(fb, j, jj, px, py, T, c0, c1, c2, dd, lst, wrap, wf, inv_w):
    """Blend gathered instance fb[j] (global instance index jj) into the tile's pixel state, on the tile rows
    its bounding box touches, one SIMD vector (16 pixels, AVX-512) per row: a constant trip count, so no
    remainder loop. Unsigned pixel indices: numba then emits no negative-index wraparound, which would block
    SIMD. `wrap` is passed as a literal by the caller, so LLVM drops the seam code for pinhole cameras."""
    mx = fb[j, 0]
    my = fb[j, 1]
    A = fb[j, 2]
    B = fb[j, 3]
    C = fb[j, 4]
    op = fb[j, 5]
    pm = fb[j, 6]
    cr = fb[j, 7]
    cg = fb[j, 8]
    cbl = fb[j, 9]
    z = fb[j, 10]
    for row in range(np.uint64(fb[j, 11]), np.uint64(fb[j, 12]) + np.uint64(1)):
        base = row * np.uint64(TILE)
        dy = py[base] - my
        bdy = B * dy
        cdy = C * dy * dy
        for q in range(TILE):
            p = base + np.uint64(q)
            dx = px[p] - mx
            if wrap:
                dx = dx - wf * np.floor(dx * inv_w + HALF)
            power = (A * dx + bdy) * dx + cdy
            _blend_px(p, power, op, pm, cr, cg, cbl, z, jj, T, c0, c1, c2, dd, lst)


@njit(cache=True, parallel=True, nogil=True, fastmath=RASTER_MATH)
def raster_forward(start, ids, rows, ntx, width, height, wrap, bg, rgb, alpha, depth, last, t_final):
    """Front-to-back blend per tile. bg [H, W, 3] f32. Outputs rgb [H, W, 3], alpha, depth [H, W] f32,
    last [H, W] int32 (index of the last blended instance, -1 if none), t_final [H, W] f32.
    wrap (equirect): dx is taken to the nearest copy of the Gaussian across the azimuth seam, per pixel.
    Each Gaussian is evaluated on the tile rows its bounding box touches, in one branch-free SIMD loop.
    A pixel that stopped (or lies outside the image) keeps -T in T: negative T means inactive."""
    ntiles = start.shape[0] - 1
    wf = np.float32(width)
    inv_w = np.float32(1.0 / width)
    for t in prange(ntiles):
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        px = np.empty(TILE_PIX, np.float32)
        py = np.empty(TILE_PIX, np.float32)
        T = np.empty(TILE_PIX, np.float32)
        c0 = np.zeros(TILE_PIX, np.float32)
        c1 = np.zeros(TILE_PIX, np.float32)
        c2 = np.zeros(TILE_PIX, np.float32)
        dd = np.zeros(TILE_PIX, np.float32)
        lst = np.full(TILE_PIX, -1, np.int32)
        nact = 0
        for p in range(TILE_PIX):
            px[p] = p % TILE
            py[p] = p // TILE
            if x0 + p % TILE < width and y0 + p // TILE < height:
                T[p] = F1
                nact += 1
            else:
                T[p] = -F1
        fb = np.empty((GATHER, NFEAT), np.float32)
        for b0 in range(start[t], start[t + 1], GATHER):
            if nact == 0:
                break
            nb = min(GATHER, start[t + 1] - b0)
            for jb in range(nb):  # gather this batch's features into a small contiguous buffer
                gather_row(rows, ids[b0 + jb], x0, y0, width, wrap, fb, jb)
            for jb in range(nb):
                if wrap:
                    _blend_one(fb, jb, np.int32(b0 + jb), px, py, T, c0, c1, c2, dd, lst, True, wf, inv_w)
                else:
                    _blend_one(fb, jb, np.int32(b0 + jb), px, py, T, c0, c1, c2, dd, lst, False, wf, inv_w)
                if (jb & (STOP_CHECK - 1)) == STOP_CHECK - 1 or jb == nb - 1:
                    # every STOP_CHECK instances: does any pixel still blend? (stopped pixels hold T < 0)
                    tmax = -F1
                    for p in range(TILE_PIX):
                        tmax = max(tmax, T[p])
                    if tmax <= F0:
                        nact = 0
                        break
        for p in range(TILE_PIX):
            xx = x0 + p % TILE
            yy = y0 + p // TILE
            if xx < width and yy < height:
                tf = abs(T[p])
                rgb[yy, xx, 0] = c0[p] + tf * bg[yy, xx, 0]
                rgb[yy, xx, 1] = c1[p] + tf * bg[yy, xx, 1]
                rgb[yy, xx, 2] = c2[p] + tf * bg[yy, xx, 2]
                al = F1 - tf
                alpha[yy, xx] = al
                depth[yy, xx] = dd[p] / al if al > F0 else F0
                last[yy, xx] = lst[p]
                t_final[yy, xx] = tf


@njit(cache=True, parallel=True, nogil=True, fastmath=RASTER_MATH)
def raster_backward(start, feat, ntx, width, height, wrap, bg, depth, last, t_final, d_rgb, d_alpha, d_depth,
                    g_inst, g_bg):
    """Reverse traversal per pixel. g_inst [n_inst, 10] f64 (d mx, d my, d conic a, b, c, d opacity,
    d r, d g, d b, d depth) is written only by the instance's own tile, so tiles run in parallel.
    g_bg [H, W, 3] f64 receives dL/dbackground per pixel."""
    ntiles = start.shape[0] - 1
    wf = np.float32(width)
    inv_w = np.float32(1.0 / width)
    for t in prange(ntiles):
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        s = start[t]
        for p in range(TILE_PIX):
            xx = x0 + p % TILE
            yy = y0 + p // TILE
            if xx >= width or yy >= height:
                continue
            tf = np.float64(t_final[yy, xx])
            gc0 = np.float64(d_rgb[yy, xx, 0])
            gc1 = np.float64(d_rgb[yy, xx, 1])
            gc2 = np.float64(d_rgb[yy, xx, 2])
            g_bg[yy, xx, 0] = gc0 * tf
            g_bg[yy, xx, 1] = gc1 * tf
            g_bg[yy, xx, 2] = gc2 * tf
            j_last = last[yy, xx]
            if j_last < s:
                continue
            al = 1.0 - tf
            g_dn = np.float64(d_depth[yy, xx]) / al
            g_tf = -(np.float64(d_alpha[yy, xx]) - np.float64(d_depth[yy, xx]) * np.float64(depth[yy, xx]) / al)
            acc0 = np.float64(bg[yy, xx, 0])
            acc1 = np.float64(bg[yy, xx, 1])
            acc2 = np.float64(bg[yy, xx, 2])
            accd = 0.0
            T = tf
            pxf = np.float32(p % TILE)
            pyf = np.float32(p // TILE)
            for j in range(j_last, s - 1, -1):
                dx = pxf - feat[j, 0]
                if wrap:
                    dx = dx - wf * np.floor(dx * inv_w + HALF)  # as the forward (nearest copy)
                dy = pyf - feat[j, 1]
                ok, a32, g32 = _alpha(dx, dy, feat[j, 2], feat[j, 3], feat[j, 4], feat[j, 5], feat[j, 6])
                if not ok:
                    continue
                a = np.float64(a32)
                tb = T / (1.0 - a)
                w = a * tb
                cr = np.float64(feat[j, 7])
                cg = np.float64(feat[j, 8])
                cb_ = np.float64(feat[j, 9])
                z = np.float64(feat[j, 10])
                g_inst[j, 6] += w * gc0
                g_inst[j, 7] += w * gc1
                g_inst[j, 8] += w * gc2
                g_inst[j, 9] += w * g_dn
                g_a = tb * ((cr - acc0) * gc0 + (cg - acc1) * gc1 + (cb_ - acc2) * gc2 + (z - accd) * g_dn) \
                    - g_tf * tf / (1.0 - a)
                acc0 = a * cr + (1.0 - a) * acc0
                acc1 = a * cg + (1.0 - a) * acc1
                acc2 = a * cb_ + (1.0 - a) * acc2
                accd = a * z + (1.0 - a) * accd
                T = tb
                op = np.float64(feat[j, 5])
                g = np.float64(g32)
                if op * g < 0.99:  # unclamped alpha = o G
                    g_inst[j, 5] += g * g_a
                    g_pow = -op * g * g_a
                    fdx = np.float64(dx)
                    fdy = np.float64(dy)
                    ca = 2.0 * np.float64(feat[j, 2])
                    cb = np.float64(feat[j, 3])
                    cc = 2.0 * np.float64(feat[j, 4])
                    g_inst[j, 0] += -g_pow * (ca * fdx + cb * fdy)
                    g_inst[j, 1] += -g_pow * (cb * fdx + cc * fdy)
                    g_inst[j, 2] += g_pow * 0.5 * fdx * fdx
                    g_inst[j, 3] += g_pow * fdx * fdy
                    g_inst[j, 4] += g_pow * 0.5 * fdy * fdy


@njit(cache=True, nogil=True)
def reduce_kernel(ids, g_inst, n):
    """Sum instance gradients per Gaussian -> [n, 10] float64."""
    out = np.zeros((n, g_inst.shape[1]), np.float64)
    for j in range(ids.shape[0]):
        i = ids[j]
        for k in range(g_inst.shape[1]):
            out[i, k] += g_inst[j, k]
    return out
