"""numba kernels of the fast renderer: projection, tile binning, tile rasterisation (forward and backward).

An opencv lens camera is drawn on its undistorted image plane (the "plane" paths: lensmap.opencv_pixel_map gives
each pixel's position there, i.e. its ray; lensmap.opencv_plane_footprint each Gaussian's power at a ray, measured
on the Gaussian's tangent plane as the reference does), so the lens is never linearised across a footprint.

Numbers: projection in float64, rasterisation in float32 with Gaussian means stored relative to their
tile's origin (so float32 keeps ~1e-6 px precision at any image size). exp(-power) is a polynomial
(`_exp_neg`, relative error < 2e-6 on the footprint range) because numba from PyPI has no SVML, so np.exp
would not vectorise. The backward pass replays the forward decisions with the same float32 expressions.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from llvmlite import ir
from numba import prange, types
from numba.core import cgutils
from numba.extending import intrinsic, overload

from ..numba_cache import njit
from .lensmap import lens_project, opencv_plane_box, opencv_plane_footprint, opencv_plane_reach, plane_weights

TILE = 16
TILE_PIX = TILE * TILE
NCG = 16    # per-Gaussian float32 row (64 bytes): mean x, y (px) as float32 hi + lo pairs (float64 precision),
#             bounding half-height ry, A, B, C (half conic), opacity, pmax, r, g, b, depth, pad, pad; an opencv
#             camera (plane layout, lensmap.opencv_plane_footprint): mean on its undistorted image plane, first
#             image row, a0, a1, b0, opacity, pmax, r, g, b, depth, b1, last image row
ROW_PAD = 1e-3  # px added to ry when choosing the tile rows a Gaussian is evaluated on (float32 ry rounding)
STOP_CHECK = 16  # the raster tests for a fully stopped tile every this many instances (a power of 2)
PROJ_CHUNK = 1024  # Gaussians per projection chunk: the unit of the frustum test on bounding boxes, of the
#                   parallel schedule and of the output's compaction (chunk c writes from its offset on)
SUB_CHUNK = 128  # a projection chunk's runs tested by their own box against the covered tiles (_box_closed) before
#                 their Gaussians one by one (a drive view's later layers: a quarter to a third of those tested)
SPREAD = 16  # parallel loops visit their items in a G-strided order (_spread): numba splits a prange into one
#             contiguous block per thread (numba.parallel_chunksize did not balance here), and the work is clustered
#             (dense tiles in parts of the image, the visible Gaussians in stretches of the array)
GATHER_AHEAD = 16  # the raster's gather asks for the projected row this many instances ahead
GATHER = 128  # instances gathered per batch into the raster's per-tile buffer (8 KB: stays in L1)
NFEAT = 16  # per-instance features (one 64-byte row): mx, my (tile-local px), A = a/2, B = b, C = c/2 (conic),
#             opacity, pmax, r, g, b, depth, first row, last row (tile-local rows the footprint can touch),
#             pad (plane layout: a0, a1, b0 for A, B, C; b1, n0, n1 for the pad, see gather_row)

F0 = np.float32(0.0)
F1 = np.float32(1.0)
HALF = np.float32(0.5)
A_MAX = np.float32(0.99)
A_MIN = np.float32(1.0 / 255.0)
T_STOP = np.float32(1e-4)
# raster_forward's resume: a pixel whose light left is below 1/255 starts stopped: what lies behind changes its colour
# (at most 1) by less than one step of an 8-bit picture (a drive's view: most pixels are covered by its first layers)
T_RESUME = np.float32(1.0 / 255.0)
P_CLIP = np.float32(6.0)      # the exp argument is clamped here; powers above every cutoff (<= 5.55) anyway
P_FAR = np.float32(1e30)      # the power of a pixel that sees none of a Gaussian (beyond every cutoff)
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


@intrinsic
def prefetch_row(typingctx, arr, row):
    """(numba only) ``prefetch_row(arr, row)``: a hint that row ``row`` of the 2-D array ``arr`` will be read soon
    (LLVM's prefetch: a read, kept in every cache level); it never faults and changes no value (a row index
    outside the array is the caller's to avoid all the same)."""
    if not (isinstance(arr, types.Array) and arr.ndim == 2 and isinstance(row, types.Integer)):
        return None
    sig = types.void(arr, row)

    def codegen(context, builder, signature, args):
        aryty, rowty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        row = context.cast(builder, args[1], rowty, types.intp)       # an int32 index too (the raster's ids)
        zero = context.get_constant(types.intp, 0)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [row, zero], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = builder.module.declare_intrinsic("llvm.prefetch", fnty=ir.FunctionType(ir.VoidType(),
                                                                                      [i8p, i32, i32, i32]))
        # read (0), locality 3 (keep in all levels), data cache (1)
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(inline="always")
def _spread(k, n):
    """Item of iteration k (0 <= k < SPREAD * ceil(n / SPREAD)) of a loop over n items, or -1: iterations
    k = j * m + i (m = ceil(n / SPREAD)) visit item i * SPREAD + j, so every contiguous block of iterations
    (a thread's share) covers the whole range evenly."""
    m = (n + SPREAD - 1) // SPREAD
    t = (k % m) * SPREAD + k // m
    return t if t < n else -1


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
@njit(inline="always")
def _camera_point(means, i, Rw, tw):
    """Gaussian i's mean in the camera frame (float64): Rw m + tw."""
    mxw, myw, mzw = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
    x = Rw[0, 0] * mxw + Rw[0, 1] * myw + Rw[0, 2] * mzw + tw[0]
    y = Rw[1, 0] * mxw + Rw[1, 1] * myw + Rw[1, 2] * mzw + tw[1]
    z = Rw[2, 0] * mxw + Rw[2, 1] * myw + Rw[2, 2] * mzw + tw[2]
    return x, y, z


@njit(inline="always")
def _precull(means, log_scales, i, Rw, tw, model, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, ptab, width,
             height, near, far, low_pass, sat):
    """(keep, x, y, z): Gaussian i's camera-frame mean (float64) and whether it survives the cheap conservative
    culls: depth (camera z, equirect: distance) within [near, far]; pinhole: its box of 3.34 x (the largest
    scale through the clamped Jacobian's row norms, plus the low-pass) reaches the image and, with ``sat`` (the
    summed-area table of a render's open tiles, [nty + 1, ntx + 1] int64, see open_slots; [0, 0]: every tile open),
    touches an open tile (a Gaussian of a later layer that falls wholly on tiles the layers before it covered is
    never projected: open_slots would drop it after projecting it); an opencv lens: the
    box on its undistorted image plane of a disc of 3.34 x (the largest scale, plus the low-pass through the
    lens) on the mean's tangent plane (lensmap.opencv_plane_reach) meets the plane's extent of a pixel column
    and of a pixel row (_plane_span). Every Gaussian the full projection keeps is kept here (the full test
    bounds the footprint by <= 3.33 sigma of a covariance no larger than this)."""
    x, y, z = _camera_point(means, i, Rw, tw)
    if model == 0:
        if not (z >= near and z <= far):
            return False, x, y, z
        sx = x / z
        sy = y / z
        u = fx * sx + cx
        v = fy * sy + cy
        if u >= 0.0 and u <= width - 1 and v >= 0.0 and v <= height - 1:
            # the mean is on the image: its box reaches it (no exp, no sqrt), and it touches the mean's tile
            if sat.shape[0] == 0:
                return True, x, y, z
            tx = int(u) // TILE
            ty = int(v) // TILE
            if _rect_sum(sat, tx, tx, ty, ty) > 0:
                return True, x, y, z
        sxc = min(max(sx, -lxn), lxp)
        syc = min(max(sy, -lyn), lyp)
        smax = math.exp(max(np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]),
                            np.float64(log_scales[i, 2])))
        ru = 3.34 * math.sqrt((fx / z) ** 2 * (1.0 + sxc * sxc) * smax * smax + low_pass)
        rv = 3.34 * math.sqrt((fy / z) ** 2 * (1.0 + syc * syc) * smax * smax + low_pass)
        if u - ru > width - 1 or u + ru < 0.0 or v - rv > height - 1 or v + rv < 0.0:
            return False, x, y, z
        if sat.shape[0] == 0:
            return True, x, y, z
        # the tiles of that box (it holds the projection's exact tile range, so nothing open_slots keeps is lost)
        tx0 = int(max(u - ru, 0.0)) // TILE
        tx1 = int(min(u + ru, width - 1.0)) // TILE
        ty0 = int(max(v - rv, 0.0)) // TILE
        ty1 = int(min(v + rv, height - 1.0)) // TILE
        return _rect_sum(sat, tx0, tx1, ty0, ty1) > 0, x, y, z
    if model == 1:
        r = math.sqrt(x * x + y * y + z * z)
        return r >= near and r <= far, x, y, z
    if model == 2:
        # opencv: z in [near, far], inside the unfolded disc, and the bound of its footprint's box on the
        # undistorted image plane meets a pixel column's and a pixel row's extent there
        if not (z >= near and z <= far):
            return False, x, y, z
        sx = x / z
        sy = y / z
        if not (sx * sx + sy * sy <= lp[12]):
            return False, x, y, z
        ucols, urows = ptab[0], ptab[1]
        u = fx * sx + cx
        v = fy * sy + cy
        if u >= ucols[0, 1] and u <= ucols[-1, 0] and v >= urows[0, 1] and v <= urows[-1, 0]:
            return True, x, y, z            # the mean lies within the image's box on the plane
        _, _, _, j00, j01, j02, j10, j11, j12 = lens_project(model, lp, fx, fy, cx, cy, x, y, z)
        s2 = math.exp(2.0 * max(np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]),
                                np.float64(log_scales[i, 2])))
        ok, xlo, xhi, ylo, yhi = opencv_plane_reach(x, y, z, j00, j01, j02, j10, j11, j12, s2, low_pass, 3.34,
                                                    fx, fy, cx, cy)
        if not ok:
            return False, x, y, z
        c0, c1 = _plane_span(ucols, xlo, xhi)
        r0, r1 = _plane_span(urows, ylo, yhi)
        return c0 <= c1 and r0 <= r1, x, y, z
    # fisheye, f-theta (lensmap): the distance in [near, far], the lens images the mean (within max_angle), and
    # the box of 3.34 x (the largest scale through the lens Jacobian's row norms, plus the low-pass) reaches the
    # image
    d = math.sqrt(x * x + y * y + z * z)
    if not (d >= near and d <= far):
        return False, x, y, z
    ok, u, v, j00, j01, j02, j10, j11, j12 = lens_project(model, lp, fx, fy, cx, cy, x, y, z)
    if not ok:
        return False, x, y, z
    if u >= 0.0 and u <= width - 1 and v >= 0.0 and v <= height - 1:
        return True, x, y, z
    s2 = math.exp(2.0 * max(np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]),
                            np.float64(log_scales[i, 2])))
    ru = 3.34 * math.sqrt((j00 * j00 + j01 * j01 + j02 * j02) * s2 + low_pass)
    rv = 3.34 * math.sqrt((j10 * j10 + j11 * j11 + j12 * j12) * s2 + low_pass)
    return not (u - ru > width - 1 or u + ru < 0.0 or v - rv > height - 1 or v + rv < 0.0), x, y, z


@njit(inline="always")
def _plane_span(table, a, b):
    """(first, last): the pixel columns (or rows) whose extent on an opencv camera's undistorted image plane
    (lensmap.opencv_pixel_map's search table: running max of the lines' largest coordinate, running min from the
    end of their smallest, both non-decreasing) can meet the interval [a, b] of that coordinate: the first line
    with table[k, 0] >= a, the last with table[k, 1] <= b (binary searches). first > last: none."""
    n = table.shape[0]
    lo = 0
    hi = n
    while lo < hi:
        mid = (lo + hi) // 2
        if table[mid, 0] >= a:
            hi = mid
        else:
            lo = mid + 1
    first = lo
    lo = -1
    hi = n - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if table[mid, 1] <= b:
            lo = mid
        else:
            hi = mid - 1
    return first, lo


# ------------------------------------------------------------------ kernels specialised per camera model
# The projection's kernels are compiled per camera model (0 = pinhole, 1 = equirect, 2..4 the lensmap lenses:
# opencv, opencv_fisheye, ftheta): `model` is a constant of each variant's code (a closure variable, which numba's
# branch pruning resolves, inside the inlined helpers too), so a variant holds its own model's code only: one
# kernel taking the model as a run-time value held all five, and its pinhole projection ran ~45 % slower than
# before the lens models came (docs/renderer.md "numba compile cache"; the price: every variant compiles apart,
# ~2x the compile of all models). numba caches each variant apart (a closure's values are part of its cache key).
# The raster stays one kernel for every model. The
# per-chunk functions stay plain (not parallel) functions called from the prange loops, as parfor compiles a big
# inlined loop body slowly; the parallel kernels reach their model's chunk function through an overload on the
# model constant (_precull_chunk_call, _project_chunk_call), since a closure over a compiled function is not
# cacheable (its pickle holds a per-process id).
#
# cam, the camera tuple of every projection kernel: (Rw, tw, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height,
# near, far, low_pass): world -> camera [3, 3], [3]; the lens parameters (lensmap.lens_params); K; the Jacobian
# clamp box (pinhole_limits); the image size (px); the depth range (m); the low-pass (px^2). ptab, apart (a tuple
# nested in a tuple does not pass into a prange loop): the opencv plane tables (core._camera_args).


def per_model(fn, model: int):
    """``fn`` (a closure specialised to one camera model) renamed for that model: ``<name>_m<model>``. numba names a
    compiled function's machine code by its qualified name and a per-process counter, so two closures of one
    qualified name compiled in two processes (a server's warm-up, its workers, another command) can carry the same
    symbol; loaded from the cache into one process, a kernel of one model then linked to the chunk function of the
    other (an f-theta render ran the pinhole's pre-count and wrote past its outputs). One name per model, also one
    cache index per model."""
    fn.__name__ = f"{fn.__name__}_m{int(model)}"
    fn.__qualname__ = f"{fn.__qualname__}_m{int(model)}"
    return fn


@functools.cache
def _chunk_functions(model: int):
    """(precull_chunk, project_chunk): one chunk of precull_counts / project_kernel, compiled for one camera
    model (the closure's `model`)."""
    model = int(model)

    def precull_chunk(means, log_scales, cam, ptab, planes, sat, boxes, phase, ch, keep_out):
        """How many Gaussians of chunk ch survive _precull (0 when the chunk's box lies outside one of planes);
        keep_out[i] = 1 for each that does, 0 for each that does not (left unwritten for a chunk whose box alone
        returns 0). boxes (or empty: the boxes made here from the means): sub_boxes of a set whose row phase is
        these Gaussians' row 0 (Gaussians.box_grid: a slice of a set keeps its parent's boxes), read instead of
        the means; a run of the chunk is then the part of one of those boxes' rows within the chunk, tested with
        the box of all its rows (a larger box: the same verdicts, the per-Gaussian test deciding where it does not
        close)."""
        Rw, tw, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near, far, low_pass = cam
        i0 = ch * PROJ_CHUNK
        i1 = min(means.shape[0], i0 + PROJ_CHUNK)
        closing = model == 0 and sat.shape[0] > 0
        given = boxes.shape[0] > 0
        if planes.shape[0] or closing:          # the chunk's box, read once for both tests
            if given:
                box = _boxes_union(boxes, (i0 + phase) // SUB_CHUNK, (i1 - 1 + phase) // SUB_CHUNK + 1)
            else:
                box = _chunk_box(means, log_scales, i0, i1)
            if planes.shape[0] and _box_outside(box, planes):
                return 0
            if closing and _box_closed(box, Rw, tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near,
                                       low_pass, sat):
                return 0
        c = 0
        s0 = i0
        while s0 < i1:
            if given:                           # to the end of the box holding row s0
                j = (s0 + phase) // SUB_CHUNK
                s1 = min(i1, (j + 1) * SUB_CHUNK - phase)
            else:
                j = 0
                s1 = min(i1, s0 + SUB_CHUNK)
            # (pinhole, behind a layer) a run of the chunk on covered tiles alone: none of it tested one by one
            if closing and _box_closed(_box_row(boxes, j) if given else _chunk_box(means, log_scales, s0, s1), Rw,
                                       tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near, low_pass, sat):
                for i in range(s0, s1):
                    keep_out[i] = 0
                s0 = s1
                continue
            for i in range(s0, s1):
                keep, _, _, _ = _precull(means, log_scales, i, Rw, tw, model, lp, fx, fy, cx, cy, lxn, lxp, lyn,
                                         lyp, ptab, width, height, near, far, low_pass, sat)
                keep_out[i] = keep
                c += keep
            s0 = s1
        return c

    def project_chunk(means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased,
                      opacity_mode, rows, trange, depth_out, gid, ch, slot0, ntx):
        """One chunk of project_kernel, writing from slot slot0 on, of the Gaussians its pre-cull kept (keep[i]:
        precull_counts' verdicts, not tested again); returns the number of visible Gaussians written."""
        Rw, tw, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near, far, low_pass = cam
        i0 = ch * PROJ_CHUNK
        i1 = min(means.shape[0], i0 + PROJ_CHUNK)
        s = slot0
        for i in range(i0, i1):
            if not keep[i]:
                continue
            x, y, z = _camera_point(means, i, Rw, tw)
            mxw, myw, mzw = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            if model == 0:
                depth = z
                sx = x / z
                sy = y / z
                u = fx * sx + cx
                v = fy * sy + cy
                sxc = min(max(sx, -lxn), lxp)
                syc = min(max(sy, -lyn), lyp)
                j00 = fx / z
                j01 = 0.0
                j02 = -fx * sxc / z
                j10 = 0.0
                j11 = fy / z
                j12 = -fy * syc / z
            elif model == 2:
                # opencv: J the lens's exact Jacobian at the mean (for cov2 = J Sigma J^T + low_pass I, whose det and
                # opacity compensation are the reference's); (u, v) the mean on the undistorted image plane, where
                # the raster measures each pixel's offset (lensmap.opencv_plane_footprint)
                depth = z
                _, _, _, j00, j01, j02, j10, j11, j12 = lens_project(model, lp, fx, fy, cx, cy, x, y, z)
                u = fx * (x / z) + cx
                v = fy * (y / z) + cy
            elif model >= 3:
                depth = math.sqrt(x * x + y * y + z * z)
                _, u, v, j00, j01, j02, j10, j11, j12 = lens_project(model, lp, fx, fy, cx, cy, x, y, z)
            else:
                r = math.sqrt(x * x + y * y + z * z)
                depth = r
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
            if model == 2:
                # the footprint on the plane (written first: its tiles are found from the stored float32 row, as the
                # binning finds them): an ellipse, the box of the tiles whose extent there meets it (_plane_tile_box);
                # or, unbounded, the pixels whose positions the box of its part in front can hold (_plane_span)
                ok, pa0, pa1, pb0, pb1 = opencv_plane_footprint(x, y, z, j00, j01, j02, j10, j11, j12, c00, c01, c11,
                                                                fx, fy)
                if not ok:
                    continue
                _write_mean(rows, s, u, v)
                rows[s, 5] = pa0
                rows[s, 6] = pa1
                rows[s, 7] = pb0
                rows[s, 9] = pmax
                rows[s, 14] = pb1
                ell = _plane_ellipse(rows, s, fx, fy, cx, cy)
                if ell[0]:
                    tx0, tx1, ty0, ty1 = _plane_tile_box(ell, ptab[2], ptab[3], ptab[4], ptab[5])
                    if tx1 < tx0:
                        continue
                    v_lo = ty0 * TILE
                    v_hi = min(height - 1, ty1 * TILE + TILE - 1)
                else:
                    ok, xlo, xhi, ylo, yhi = opencv_plane_box(x, y, z, j00, j01, j02, j10, j11, j12, c00, c01, c11, ext,
                                                              fx, fy, cx, cy)
                    v_lo, v_hi = _plane_span(ptab[1], ylo, yhi)
                    u_lo, u_hi = _plane_span(ptab[0], xlo, xhi)
                    if not ok or v_lo > v_hi or u_lo > u_hi:
                        continue
                    tx0 = u_lo // TILE
                    tx1 = u_hi // TILE
            else:
                v_lo = max(0, int(math.ceil(max(v - ry, -1e9))))
                v_hi = min(height - 1, int(math.floor(min(v + ry, 1e9))))
            if v_lo > v_hi:
                continue
            u_lo_f = math.ceil(max(u - rx, -1e9))
            u_hi_f = math.floor(min(u + rx, 1e9))
            if model == 2:
                pass            # tx0, tx1 found above
            elif model != 1:
                u_lo = max(0, int(u_lo_f))
                u_hi = min(width - 1, int(u_hi_f))
                if u_lo > u_hi:
                    continue
                tx0 = u_lo // TILE
                tx1 = u_hi // TILE
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
            ty0 = v_lo // TILE
            ty1 = v_hi // TILE
            _write_mean(rows, s, u, v)
            if model == 2:      # the plane layout (gather_row): first image row, a0 a1 b0, ..., b1, last row
                rows[s, 4] = v_lo
                rows[s, 5] = pa0
                rows[s, 6] = pa1
                rows[s, 7] = pb0
                rows[s, 14] = pb1
                rows[s, 15] = v_hi
            else:
                rows[s, 4] = ry
                rows[s, 5] = 0.5 * c11 / det
                rows[s, 6] = -c01 / det
                rows[s, 7] = 0.5 * c00 / det
                rows[s, 14] = 0.0
                rows[s, 15] = 0.0
            rows[s, 8] = opa
            rows[s, 9] = pmax
            vx, vy, vz = mxw - campos[0], myw - campos[1], mzw - campos[2]
            for c in range(3):
                rows[s, 10 + c] = _sh_colour(sh, i, c, vx, vy, vz)
            rows[s, 13] = depth
            trange[s, 0] = tx0 | (tx1 << 16)
            trange[s, 1] = ty0 | (ty1 << 16)
            depth_out[s] = depth
            gid[s] = i
            s += 1
        return s - slot0

    chunk_fn = njit(cache=True, nogil=True)
    return chunk_fn(per_model(precull_chunk, model)), chunk_fn(per_model(project_chunk, model))


def _precull_chunk_call(model, means, log_scales, cam, ptab, planes, sat, boxes, phase, ch, keep):
    """(numba only) the precull chunk function of `model` (a compile-time constant)."""
    raise NotImplementedError("called from numba kernels only")


@overload(_precull_chunk_call)
def _ol_precull_chunk_call(model, means, log_scales, cam, ptab, planes, sat, boxes, phase, ch, keep):
    if not isinstance(model, types.IntegerLiteral):
        return None
    fn = _chunk_functions(model.literal_value)[0]

    def impl(model, means, log_scales, cam, ptab, planes, sat, boxes, phase, ch, keep):
        return fn(means, log_scales, cam, ptab, planes, sat, boxes, phase, ch, keep)
    return per_model(impl, model.literal_value)


def _project_chunk_call(model, means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased,
                        opacity_mode, rows, trange, depth_out, gid, ch, slot0, ntx):
    """(numba only) the project chunk function of `model` (a compile-time constant)."""
    raise NotImplementedError("called from numba kernels only")


@overload(_project_chunk_call)
def _ol_project_chunk_call(model, means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased,
                           opacity_mode, rows, trange, depth_out, gid, ch, slot0, ntx):
    if not isinstance(model, types.IntegerLiteral):
        return None
    fn = _chunk_functions(model.literal_value)[1]

    def impl(model, means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased, opacity_mode,
             rows, trange, depth_out, gid, ch, slot0, ntx):
        return fn(means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased, opacity_mode,
                  rows, trange, depth_out, gid, ch, slot0, ntx)
    return per_model(impl, model.literal_value)


@functools.cache
def precull_counts(model: int):
    """The pre-cull kernel of one camera model (see above): kernel(means, log_scales, cam, ptab, planes, sat,
    boxes, phase, counts, keep): counts[c] = how many Gaussians of chunk c (PROJ_CHUNK Gaussians each) survive
    _precull (``sat``: its open tiles); 0 for a chunk whose bounding box lies wholly outside one of `planes`
    (chunk_planes), or (pinhole) falls wholly on covered tiles (_box_closed), without looking at its Gaussians;
    likewise (pinhole) each run of SUB_CHUNK Gaussians of a chunk whose own box falls on covered tiles alone. The
    boxes: ``boxes`` [., 7] float64 (sub_boxes of the set these Gaussians are rows ``phase`` .. of; precull_chunk),
    or [0, 7] (made here from the means). keep [N] uint8: 1 for
    each Gaussian that survives, 0 for each that does not (a chunk counted 0 without a look is left unwritten): the
    projection (project_kernel) visits only these. An upper bound of what project_kernel keeps, so its outputs can
    be allocated to fit."""
    model = int(model)

    def precull_counts_kernel(means, log_scales, cam, ptab, planes, sat, boxes, phase, counts, keep):
        nch = (means.shape[0] + PROJ_CHUNK - 1) // PROJ_CHUNK
        for k in prange(SPREAD * ((nch + SPREAD - 1) // SPREAD)):
            ch = _spread(k, nch)
            if ch < 0:
                continue
            counts[ch] = _precull_chunk_call(model, means, log_scales, cam, ptab, planes, sat, boxes, phase, ch,
                                             keep)

    return njit(cache=True, parallel=True, nogil=True)(per_model(precull_counts_kernel, model))


@functools.cache
def project_kernel(model: int):
    """The projection kernel of one camera model (see above): kernel(means, quats, log_scales, opacity_logits, sh,
    campos, cam, ptab, keep, antialiased, opacity_mode, pre, base, rows, trange, depth_out, gid, counts): project
    the Gaussians that precull_counts kept (keep, pre: its outputs for the same camera and tiles; the pre-cull is not
    done again), in float64, parallel over chunks of PROJ_CHUNK Gaussians. Chunk c (pre[c] > 0)
    writes its visible Gaussians, in index order, to slots base[c], base[c] + 1, ... (base: the exclusive prefix
    sum of pre) and their number (<= pre[c]) to counts[c]; per slot s: rows[s] = the 64-byte float32 row
    (layout: NCG), trange[s] [., 2] int32 = (tx0 | tx1 << 16, ty0 | ty1 << 16) the tiles its bounding box touches
    (tx1 < tx0: the range wraps around the azimuth seam, equirect), depth_out[s] float64 = depth, gid[s] int32 =
    the Gaussian's index. Slots past counts[c] are left unwritten (never read). Slots increase with the Gaussian
    index, so sorting slots is sorting indices."""
    model = int(model)

    def project_kernel_model(means, quats, log_scales, opacity_logits, sh, campos, cam, ptab, keep, antialiased,
                             opacity_mode, pre, base, rows, trange, depth_out, gid, counts):
        nch = (means.shape[0] + PROJ_CHUNK - 1) // PROJ_CHUNK
        ntx = (cam[11] + TILE - 1) // TILE
        for k in prange(SPREAD * ((nch + SPREAD - 1) // SPREAD)):
            ch = _spread(k, nch)
            if ch < 0:
                continue
            counts[ch] = 0
            if pre[ch] > 0:
                counts[ch] = _project_chunk_call(model, means, quats, log_scales, opacity_logits, sh, campos, cam,
                                                 ptab, keep, antialiased, opacity_mode, rows, trange, depth_out, gid,
                                                 ch, base[ch], ntx)

    return njit(cache=True, parallel=True, nogil=True)(per_model(project_kernel_model, model))


@njit(inline="always")
def _write_mean(rows, s, u, v):
    """Row s's mean (u, v) as float32 hi + lo pairs (float64 precision; NCG)."""
    hi = np.float32(u)
    rows[s, 0] = hi
    rows[s, 1] = np.float32(u - np.float64(hi))
    hi = np.float32(v)
    rows[s, 2] = hi
    rows[s, 3] = np.float32(v - np.float64(hi))


@njit(inline="always")
def _box_row(boxes, j):
    """Box j of sub_boxes' [., 7] array as _chunk_box's tuple."""
    return (boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3], boxes[j, 4], boxes[j, 5], boxes[j, 6])


@njit(inline="always")
def _boxes_union(boxes, j0, j1):
    """The box of sub_boxes' boxes j0 .. j1 - 1 (j1 > j0) as _chunk_box's tuple: the box of all their Gaussians,
    the same float64 values _chunk_box returns for them (min and max of the same float32 values)."""
    lo0, hi0, lo1, hi1, lo2, hi2, ls = _box_row(boxes, j0)
    for j in range(j0 + 1, j1):
        lo0 = min(lo0, boxes[j, 0])
        hi0 = max(hi0, boxes[j, 1])
        lo1 = min(lo1, boxes[j, 2])
        hi1 = max(hi1, boxes[j, 3])
        lo2 = min(lo2, boxes[j, 4])
        hi2 = max(hi2, boxes[j, 5])
        ls = max(ls, boxes[j, 6])
    return lo0, hi0, lo1, hi1, lo2, hi2, ls


@njit(cache=True, parallel=True, nogil=True)
def sub_boxes(means, log_scales):
    """[ceil(N / SUB_CHUNK), 7] float64: the box of each run of SUB_CHUNK Gaussians (rows j SUB_CHUNK ..), as
    _chunk_box gives it (lo0, hi0, lo1, hi1, lo2, hi2, largest log scale): precull_counts reads these instead of
    the means of a set drawn again and again (Gaussians.box_grid)."""
    n = means.shape[0]
    nb = (n + SUB_CHUNK - 1) // SUB_CHUNK
    out = np.empty((nb, 7), np.float64)
    for j in prange(nb):
        box = _chunk_box(means, log_scales, j * SUB_CHUNK, min(n, (j + 1) * SUB_CHUNK))
        for c in range(7):
            out[j, c] = box[c]
    return out


@njit(inline="always")
def _chunk_box(means, log_scales, i0, i1):
    """(lo0, hi0, lo1, hi1, lo2, hi2, largest log scale) of means[i0:i1] (float64; i1 > i0)."""
    # compared in the arrays' own dtype (a float32 scene: half the width; float64 of the extremes is the same)
    lo0 = hi0 = means[i0, 0]
    lo1 = hi1 = means[i0, 1]
    lo2 = hi2 = means[i0, 2]
    ls = log_scales[i0, 0]
    for i in range(i0, i1):
        m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
        lo0 = min(lo0, m0)
        hi0 = max(hi0, m0)
        lo1 = min(lo1, m1)
        hi1 = max(hi1, m1)
        lo2 = min(lo2, m2)
        hi2 = max(hi2, m2)
        ls = max(ls, max(log_scales[i, 0], max(log_scales[i, 1], log_scales[i, 2])))
    return (np.float64(lo0), np.float64(hi0), np.float64(lo1), np.float64(hi1), np.float64(lo2), np.float64(hi2),
            np.float64(ls))


@njit(cache=True, nogil=True)
def _chunk_outside(means, log_scales, planes, i0, i1):
    """True when the axis-aligned box of means[i0:i1] (world frame, float64) lies wholly on the outer side of
    one of planes [k, 5] float64 (a0, a1, a2, offset, kscale; see chunk_planes): max over the box of a.x + offset
    < -kscale * exp(max log scale of the chunk)."""
    return _box_outside(_chunk_box(means, log_scales, i0, i1), planes)


@njit(cache=True, nogil=True)
def _box_outside(box, planes):
    """_chunk_outside's test on the chunk's box (_chunk_box's tuple)."""
    lo0, hi0, lo1, hi1, lo2, hi2, ls = box
    smax = math.exp(ls)
    c0, c1, c2 = 0.5 * (lo0 + hi0), 0.5 * (lo1 + hi1), 0.5 * (lo2 + hi2)
    h0, h1, h2 = 0.5 * (hi0 - lo0), 0.5 * (hi1 - lo1), 0.5 * (hi2 - lo2)
    for k in range(planes.shape[0]):
        a0, a1, a2 = planes[k, 0], planes[k, 1], planes[k, 2]
        top = a0 * c0 + a1 * c1 + a2 * c2 + abs(a0) * h0 + abs(a1) * h1 + abs(a2) * h2 + planes[k, 3]
        if top < -planes[k, 4] * smax:
            return True
    return False


@njit(cache=True, nogil=True)
def _chunk_closed(means, log_scales, i0, i1, Rw, tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near,
                  low_pass, sat):
    """(pinhole) True when no Gaussian of means[i0:i1] can pass _precull's open-tile test: the box of their
    camera-frame means lies wholly in front of the near plane (a box that reaches behind it: False, not tested),
    and the pixels its eight corners project to (every mean of the box projects inside their range: the
    projection of a box in front of the camera is the hull of its corners'), widened by the largest pre-cull
    radius any of them can have (3.34 x the chunk's largest scale through the clamped Jacobian's row norm at the
    box's nearest depth, plus the low-pass), touch no tile counted in ``sat`` (summed-area table of the open
    tiles, see open_slots). A chunk of a later layer that falls wholly on tiles the layers before covered is then
    skipped without testing its Gaussians one by one."""
    return _box_closed(_chunk_box(means, log_scales, i0, i1), Rw, tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width,
                       height, near, low_pass, sat)


@njit(cache=True, nogil=True)
def _box_closed(box, Rw, tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp, width, height, near, low_pass, sat):
    """_chunk_closed's test on the chunk's box (_chunk_box's tuple)."""
    lo0, hi0, lo1, hi1, lo2, hi2, ls = box
    umin = vmin = np.inf
    umax = vmax = -np.inf
    zmin = np.inf
    for c in range(8):
        px = hi0 if c & 1 else lo0
        py = hi1 if c & 2 else lo1
        pz = hi2 if c & 4 else lo2
        x = Rw[0, 0] * px + Rw[0, 1] * py + Rw[0, 2] * pz + tw[0]
        y = Rw[1, 0] * px + Rw[1, 1] * py + Rw[1, 2] * pz + tw[1]
        z = Rw[2, 0] * px + Rw[2, 1] * py + Rw[2, 2] * pz + tw[2]
        if not z >= near:
            return False
        zmin = min(zmin, z)
        u = fx * (x / z) + cx
        v = fy * (y / z) + cy
        umin = min(umin, u)
        umax = max(umax, u)
        vmin = min(vmin, v)
        vmax = max(vmax, v)
    smax = math.exp(ls)
    # _precull's radii at depth z >= zmin, with (1 + sxc^2) <= 1 + max(lxn, lxp)^2 (sxc is clamped to the limits)
    kx = 1.0 + max(lxn, lxp) ** 2
    ky = 1.0 + max(lyn, lyp) ** 2
    ru = 3.34 * math.sqrt((fx / zmin) ** 2 * kx * smax * smax + low_pass) + 1.0    # +1 px: rounding
    rv = 3.34 * math.sqrt((fy / zmin) ** 2 * ky * smax * smax + low_pass) + 1.0
    umin -= ru
    umax += ru
    vmin -= rv
    vmax += rv
    if umin > width - 1 or umax < 0.0 or vmin > height - 1 or vmax < 0.0:
        return True
    tx0 = int(max(umin, 0.0)) // TILE
    tx1 = int(min(umax, width - 1.0)) // TILE
    ty0 = int(max(vmin, 0.0)) // TILE
    ty1 = int(min(vmax, height - 1.0)) // TILE
    return _rect_sum(sat, tx0, tx1, ty0, ty1) == 0


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
def visible_slots(counts, base):
    """The written slots of project_kernel, ascending: [sum(counts)] int32 (chunk c's are base[c] ..
    base[c] + counts[c] - 1)."""
    out = np.empty(counts.sum(), np.int32)
    k = 0
    for ch in range(counts.shape[0]):
        for j in range(counts[ch]):
            out[k] = base[ch] + j
            k += 1
    return out


@njit(cache=True, nogil=True)
def offset_slots(gid, counts, base, offset):
    """gid[s] += offset for the written slots of chunks (counts, base; as visible_slots lists them)."""
    for ch in range(counts.shape[0]):
        for j in range(counts[ch]):
            gid[base[ch] + j] += offset


@njit(cache=True, nogil=True)
def depth_keys(dep, visible):
    """[n] uint32: the bit patterns of float32(dep[visible]) (positive depths: they order like the values)."""
    out = np.empty(visible.shape[0], np.float32)
    for k in range(visible.shape[0]):
        out[k] = np.float32(dep[visible[k]])
    return out.view(np.uint32)


@njit(cache=True, nogil=True)
def depth_order(visible, keys):
    """Stable LSD radix sort of `visible` (slot ids, ascending) by keys [n] uint32 (the bit patterns of
    positive float32 depths, which order like the values): three passes of 11, 11 and 10 bits (2048-bin
    histograms, all counted in one read of the keys; the scatter's 2048 write streams stay cached where
    65536 did not: 35 -> 30 ms for 2 M keys), a pass where all keys share the digit skipped. Ties keep slot
    (= Gaussian index) order, as the reference's lexsort."""
    n = visible.shape[0]
    hist = np.zeros((3, 2049), np.int64)
    for k in range(n):
        key = keys[k]
        hist[0, (key & np.uint32(0x7FF)) + 1] += 1
        hist[1, ((key >> np.uint32(11)) & np.uint32(0x7FF)) + 1] += 1
        hist[2, (key >> np.uint32(22)) + 1] += 1
    src = visible.astype(np.int32)
    srck = keys
    dst = np.empty(n, np.int32)
    dstk = np.empty(n, np.uint32)
    for d in range(3):
        h = hist[d]
        if n == 0 or h.max() == n:
            continue
        for b in range(2048):
            h[b + 1] += h[b]
        sh_ = np.uint32(11 * d)
        for k in range(n):
            b = (srck[k] >> sh_) & np.uint32(0x7FF)
            pos = h[b]
            h[b] = pos + 1
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


_NO_K = np.zeros(4)
_NO_TX = np.zeros((0, 0, 2))


@njit(inline="always")
def gather_row(cg, k, x0, y0, width, wrap, plane, kk, tilex, rowy, out, j):
    """Per-instance features of compact Gaussian k seen from the tile at (x0, y0) -> out[j, :NFEAT] float32:
    tile-local mean (the copy nearest the tile for equirect), half conic A B C, opacity, pmax, r g b, depth,
    first and last tile-local rows the footprint can touch (first > last: it misses the tile). Forward and
    backward use this same code. plane (an opencv camera, kk = fx, fy, cx, cy): the mean on the undistorted
    image plane, a0 a1 b0 in place of A B C, then b1, n0, n1 (lensmap.opencv_plane_footprint's power; n0, n1
    from the mean, lensmap.plane_weights); the rows: the image rows the projection found (_plane_span), narrowed
    to those whose pixels' extent on the plane (rowy) can meet the footprint where the tile's columns lie (tilex;
    _plane_rows)."""
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
    if plane:
        n0, n1 = plane_weights(mx + x0, my + y0, kk[0], kk[1], kk[2], kk[3])
        out[j, 13] = cg[k, 14]
        out[j, 14] = n0
        out[j, 15] = n1
        r0, r1 = _plane_rows(cg, k, kk, x0, y0, tilex, rowy, max(0.0, np.float64(cg[k, 4]) - y0),
                             min(TILE - 1.0, np.float64(cg[k, 15]) - y0))
        out[j, 11] = r0
        out[j, 12] = r1
        return
    r0 = max(0.0, math.ceil(my - ry))         # the pixel rows y with |y - my| <= ry
    r1 = min(TILE - 1.0, math.floor(my + ry))
    if not wrap:
        r0, r1 = _ellipse_rows(np.float64(cg[k, 5]), np.float64(cg[k, 6]), np.float64(cg[k, 7]),
                               np.float64(cg[k, 9]), mx, my, r0, r1)
    out[j, 11] = r0
    out[j, 12] = r1


@njit(inline="always")
def _plane_ellipse(cg, k, fx, fy, cx, cy):
    """An opencv camera's footprint of compact Gaussian k (plane layout, lensmap.opencv_plane_footprint: power =
    ((a0 dx + a1 dy)^2 + (b0 dx + b1 dy)^2) / (1 + n0 dx + n1 dy)^2 <= pm about the mean (mx, my) on the
    undistorted image plane) as an ellipse there: (bounded, k00, k01, k11, rhs, ex, ey, hx, hy), the points d with
    (d - e)^T K' (d - e) <= rhs, K' = a a^T + b b^T - pm n n^T, e = (mx, my) + c, c = pm K'^-1 n, rhs = pm + pm n.c,
    half-extents hx, hy (float64). Not bounded (K' not positive definite): the footprint reaches the camera's
    z = 0 plane."""
    mx = np.float64(cg[k, 0]) + np.float64(cg[k, 1])
    my = np.float64(cg[k, 2]) + np.float64(cg[k, 3])
    a0 = np.float64(cg[k, 5])
    a1 = np.float64(cg[k, 6])
    b0 = np.float64(cg[k, 7])
    b1 = np.float64(cg[k, 14])
    pm = np.float64(cg[k, 9])
    n0, n1 = plane_weights(mx, my, fx, fy, cx, cy)
    k00 = a0 * a0 + b0 * b0 - pm * n0 * n0
    k01 = a0 * a1 + b0 * b1 - pm * n0 * n1
    k11 = a1 * a1 + b1 * b1 - pm * n1 * n1
    det = k00 * k11 - k01 * k01
    if not (k00 > 0.0 and det > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    ox = pm * (k11 * n0 - k01 * n1) / det
    oy = pm * (k00 * n1 - k01 * n0) / det
    rhs = pm + pm * (n0 * ox + n1 * oy)
    return True, k00, k01, k11, rhs, mx + ox, my + oy, math.sqrt(k11 * rhs / det), math.sqrt(k00 * rhs / det)


@njit(inline="always")
def _ell_range(kaa, kab, kbb, rhs, ha, hb, lo, hi):
    """(ok, lo, hi): the range of the second coordinate b over the centred ellipse kaa a^2 + 2 kab a b + kbb b^2
    <= rhs (half-extents ha, hb) where the first, a, lies in [lo, hi] (not ok: the ellipse misses that interval).
    The extremes of its upper (concave) and lower (convex) arcs over an interval lie at their clamped
    unconstrained extremes (as _ellipse_rows)."""
    lo = max(lo, -ha)
    hi = min(hi, ha)
    if lo > hi:
        return False, 0.0, 0.0
    if lo <= -ha and hi >= ha:
        return True, -hb, hb
    det = kaa * kbb - kab * kab
    at = min(max(-kab * hb / kaa, lo), hi)       # where the upper arc peaks
    al = min(max(kab * hb / kaa, lo), hi)        # where the lower arc bottoms out
    top = (-kab * at + math.sqrt(max(0.0, kbb * rhs - det * at * at))) / kbb
    bot = (-kab * al - math.sqrt(max(0.0, kbb * rhs - det * al * al))) / kbb
    return True, bot, top


@njit(inline="always")
def _plane_tile_box(ell, tyext, rowtx, tilex, tiley):
    """(tx0, tx1, ty0, ty1): the box of the tiles whose extent on the plane meets the bounded ellipse ell
    (_plane_ellipse; empty: tx1 < tx0). Row of tiles by row (those whose extent in Y, tyext, can meet its Y
    range; loose where the lens bends the pixel rows on the plane): the tiles whose extent in X meets its X range
    (rowtx's search table, followed from the previous row), trimmed from both ends to the first and last that
    meet the ellipse itself (_plane_tile_hit)."""
    ntx = rowtx.shape[1]
    xlo = ell[5] - ell[7] - ROW_PAD
    xhi = ell[5] + ell[7] + ROW_PAD
    tya, tyb = _plane_ellipse_rows(ell, tyext)
    tx0 = ntx
    tx1 = -1
    ty0 = tyb + 1
    ty1 = -1
    ta = 0
    tb = -1
    for ty in range(tya, tyb + 1):
        if ty == tya:
            ta, tb = _plane_span(rowtx[ty], xlo, xhi)
        else:                               # the first tile with rowtx[ty, t, 0] >= xlo, the last with [., 1] <= xhi
            ta = min(max(ta, 0), ntx - 1)
            while ta > 0 and rowtx[ty, ta - 1, 0] >= xlo:
                ta -= 1
            while ta < ntx and rowtx[ty, ta, 0] < xlo:
                ta += 1
            tb = min(max(tb, 0), ntx - 1)
            while tb < ntx - 1 and rowtx[ty, tb + 1, 1] <= xhi:
                tb += 1
            while tb >= 0 and rowtx[ty, tb, 1] > xhi:
                tb -= 1
        a = ta
        b = tb
        while a <= b and not _plane_tile_hit(ell, tilex, tiley, ty, a):
            a += 1
        while b >= a and not _plane_tile_hit(ell, tilex, tiley, ty, b):
            b -= 1
        if a <= b:
            tx0 = min(tx0, a)
            tx1 = max(tx1, b)
            ty0 = min(ty0, ty)
            ty1 = max(ty1, ty)
    return tx0, tx1, ty0, ty1


@njit(inline="always")
def _plane_ellipse_rows(ell, tyext):
    """(first, last): the rows of tiles whose extent in Y (tyext's search table) can meet the bounded ellipse."""
    ey = ell[6]
    hy = ell[8]
    return _plane_span(tyext, ey - hy - ROW_PAD, ey + hy + ROW_PAD)


@njit(inline="always")
def _plane_tile_hit(ell, tilex, tiley, ty, tx):
    """Whether tile (tx, ty)'s extent on the plane (tilex, tiley; lensmap.opencv_pixel_map) meets the ellipse ell
    (_plane_ellipse; widened by ROW_PAD): its Y range over the tile's X extent against the tile's Y extent."""
    bounded, k00, k01, k11, rhs, ex, ey, hx, hy = ell
    if not bounded:
        return True
    xa = tilex[ty, tx, 0] - ex - ROW_PAD
    xb = tilex[ty, tx, 1] - ex + ROW_PAD
    ya = tiley[ty, tx, 0] - ey - ROW_PAD
    yb = tiley[ty, tx, 1] - ey + ROW_PAD
    if xa > hx or xb < -hx or ya > hy or yb < -hy:      # the ellipse's box misses the tile's
        return False
    ok, bot, top = _ell_range(k00, k01, k11, rhs, hx, hy, xa, xb)
    return ok and bot <= yb and top >= ya


@njit(inline="always")
def _plane_rows(cg, k, kk, x0, y0, tilex, rowy, r0, r1):
    """Narrow the tile-local rows [r0, r1] of the tile at (x0, y0) to those where compact Gaussian k's footprint
    (an opencv camera, _plane_ellipse) can be: its Y range over the tile's X extent (tilex), against each row's
    Y extent (rowy; both widened by ROW_PAD). Returns r0 > r1 where it misses the tile; [r0, r1] unchanged for
    an unbounded footprint."""
    bounded, k00, k01, k11, rhs, ex, ey, hx, hy = _plane_ellipse(cg, k, kk[0], kk[1], kk[2], kk[3])
    if not bounded:
        return r0, r1
    tx = x0 // TILE
    ok, bot, top = _ell_range(k00, k01, k11, rhs, hx, hy, tilex[y0 // TILE, tx, 0] - ex - ROW_PAD,
                              tilex[y0 // TILE, tx, 1] - ex + ROW_PAD)
    if not ok:
        return 1.0, 0.0
    ylo = ey + bot - ROW_PAD
    yhi = ey + top + ROW_PAD
    while r0 <= r1 and rowy[y0 + int(r0), tx, 1] < ylo:
        r0 += 1.0
    while r1 >= r0 and rowy[y0 + int(r1), tx, 0] > yhi:
        r1 -= 1.0
    return r0, r1


@njit(inline="always")
def _ellipse_rows(A, B, C, pm, mx, my, r0, r1):
    """Narrow the tile-local rows [r0, r1] to those where the footprint ellipse A dx^2 + B dx dy + C dy^2 <= pm
    (dx = x - mx, dy = y - my, float64) meets the tile's pixel columns x in [0, TILE - 1]: a Gaussian binned
    to the tile by its bounding box but whose ellipse only passes the tile's corner region costs fewer rows,
    or none (returns r0 > r1). The extremes of the ellipse's upper (concave) and lower (convex) arcs over the
    column interval lie at the clamped unconstrained extremes. Widened by ROW_PAD px in x and y, far above the
    float32 rounding of the per-pixel power (~1e-6 relative), so no pixel the power test accepts is dropped."""
    D = 4.0 * A * C - B * B
    if not (A > 0.0 and C > 0.0 and D > 0.0):
        return r0, r1
    rx = math.sqrt(4.0 * C * pm / D)          # the ellipse's half-extents
    ry = math.sqrt(4.0 * A * pm / D)
    xa = max(-mx - ROW_PAD, -rx)              # the columns' dx range, within the ellipse's
    xb = min(TILE - 1.0 - mx + ROW_PAD, rx)
    if xa > xb:
        return 1.0, 0.0
    xt = min(max(-B * ry / (2.0 * A), xa), xb)   # where the upper arc peaks (clamped)
    xl = min(max(B * ry / (2.0 * A), xa), xb)    # where the lower arc bottoms out (clamped)
    top = (-B * xt + math.sqrt(max(0.0, 4.0 * C * pm - D * xt * xt))) / (2.0 * C)
    bot = (-B * xl - math.sqrt(max(0.0, 4.0 * C * pm - D * xl * xl))) / (2.0 * C)
    return max(r0, math.ceil(my + bot - ROW_PAD)), min(r1, math.floor(my + top + ROW_PAD))


@njit(cache=True, parallel=True, nogil=True)
def instance_features(start, ids, rows, ntx, width, wrap):
    """feat [n_inst, NFEAT] float32: every tile instance's features (gather_row), for the backward pass."""
    ntiles = start.shape[0] - 1
    feat = np.zeros((ids.shape[0], NFEAT), np.float32)
    for t in prange(ntiles):
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        for j in range(start[t], start[t + 1]):
            gather_row(rows, ids[j], x0, y0, width, wrap, False, _NO_K, _NO_TX, _NO_TX, feat, j)
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
def _blend_one(fb, j, jj, px, py, T, c0, c1, c2, dd, lst, wrap, plane, wf, inv_w, live):
    """Blend gathered instance fb[j] (global instance index jj) into the tile's pixel state, on the tile rows
    its bounding box touches, one SIMD vector (16 pixels, AVX-512) per row (the rows evaluated returned): a constant
    trip count, so no
    remainder loop. Unsigned pixel indices: numba then emits no negative-index wraparound, which would block
    SIMD. `wrap` and `plane` are passed as literals by the caller, so LLVM drops the seam code for pinhole
    cameras and keeps dy per row where the pixels' positions are a grid (plane: an opencv camera's pixels sit at
    their undistorted positions, px and py vary along a row). live [TILE] bool: a row whose pixels all stopped
    (as of the tile's last stop check) is skipped whole (its pixels would not change: a stopped pixel's T < 0)."""
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
    b1 = fb[j, 13]
    n0 = fb[j, 14]
    n1 = fb[j, 15]
    done = 0
    for row in range(np.uint64(fb[j, 11]), np.uint64(fb[j, 12]) + np.uint64(1)):
        if not live[row]:
            continue
        done += 1
        base = row * np.uint64(TILE)
        if plane:   # lensmap.opencv_plane_footprint: A, B, C hold a0, a1, b0
            for q in range(TILE):
                p = base + np.uint64(q)
                dx = px[p] - mx
                dy = py[p] - my
                w = F1 + n0 * dx + n1 * dy
                a = A * dx + B * dy
                b = C * dx + b1 * dy
                power = (a * a + b * b) / (w * w)
                power = power if w > F0 else P_FAR      # 90 degrees or more from the mean: none of it
                _blend_px(p, power, op, pm, cr, cg, cbl, z, jj, T, c0, c1, c2, dd, lst)
            continue
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
    return done


@njit(cache=True, parallel=True, nogil=True, fastmath=RASTER_MATH)
def raster_forward(start, ids, rows, ntx, width, height, wrap, plane, offsets, kk, tilex, rowy, bg, rgb, alpha, depth,
                   last, t_final, row_evals, resume, covered, done):
    """Front-to-back blend per tile. bg [H, W, 3] f32. Outputs rgb [H, W, 3], alpha, depth [H, W] f32,
    last [H, W] int32 (index of the last blended instance, -1 if none), t_final [H, W] f32, row_evals [ntiles]
    int64 (16-pixel tile rows evaluated: the work done, for benchmarks).
    wrap (equirect): dx is taken to the nearest copy of the Gaussian across the azimuth seam, per pixel.
    plane (an opencv lens, kk = fx, fy, cx, cy): pixel (x, y) is evaluated at its position on the undistorted
    image plane, (x, y) + offsets[y, x] (lensmap.opencv_pixel_map, with its tilex and rowy; NaN: no ray, no
    Gaussian blends there), with the tangent-plane power of lensmap.opencv_plane_footprint; else offsets, kk,
    tilex and rowy are unused.
    Each Gaussian is evaluated on the tile rows its bounding box touches, in one branch-free SIMD loop.
    A pixel that stopped (or lies outside the image) keeps -T in T: negative T means inactive.
    resume: rgb, alpha and depth hold on entry what was drawn in front of these Gaussians over black (an earlier
    render's outputs with no background), and the blend goes on from there, as if those Gaussians had come first
    in the sort: a pixel starts at T = 1 - alpha with its colour and alpha-weighted depth, and one already at or
    below T_RESUME starts stopped. covered [ntiles] bool (with resume; covered_tiles): a covered tile is finished as
    the earlier render drew it, each pixel's colour and alpha-weighted depth divided by its alpha (alpha 1), none of
    these Gaussians drawn there (_finish_tile; its last and t_final unwritten); done [ntiles] bool (or empty):
    covered tiles an earlier layer finished already (alpha 1 throughout: finishing them again would change nothing),
    left as they are, their last and t_final unwritten (a resumed render has no backward pass to read them)."""
    ntiles = start.shape[0] - 1
    for k in prange(SPREAD * ((ntiles + SPREAD - 1) // SPREAD)):
        t = _spread(k, ntiles)
        if t < 0:
            continue
        if resume and covered[t]:
            if not (done.shape[0] and done[t]):
                _finish_tile(t, ntx, rgb, alpha)
            row_evals[t] = 0
            continue
        px = np.empty(TILE_PIX, np.float32)
        py = np.empty(TILE_PIX, np.float32)
        T = np.empty(TILE_PIX, np.float32)
        c0 = np.empty(TILE_PIX, np.float32)
        c1 = np.empty(TILE_PIX, np.float32)
        c2 = np.empty(TILE_PIX, np.float32)
        dd = np.empty(TILE_PIX, np.float32)
        lst = np.empty(TILE_PIX, np.int32)
        fb = np.empty((GATHER, NFEAT), np.float32)
        live = np.empty(TILE, np.bool_)
        for p in range(TILE_PIX):
            px[p] = p % TILE
            py[p] = p // TILE
        if plane:
            x0 = (t % ntx) * TILE
            y0 = (t // ntx) * TILE
            for r in range(min(TILE, height - y0)):
                for q in range(min(TILE, width - x0)):
                    px[r * TILE + q] = np.float32(q) + offsets[y0 + r, x0 + q, 0]
                    py[r * TILE + q] = np.float32(r) + offsets[y0 + r, x0 + q, 1]
        _raster_tile(t, start, ids, rows, ntx, width, height, wrap, plane, kk, tilex, rowy, bg, rgb, alpha, depth,
                     last, t_final, row_evals, px, py, T, c0, c1, c2, dd, lst, fb, resume, live)


@njit(inline="always", fastmath=RASTER_MATH)
def _finish_tile(t, ntx, rgb, alpha):
    """A covered tile of raster_forward: each pixel's colour divided by its alpha, alpha 1 (its depth, the
    alpha-weighted mean, stays). Branch-free (selects: the loop is SIMD): a covered tile's alpha is above
    1 - cover > 0 everywhere (covered_tiles), and a pixel at alpha 1 is multiplied by exactly 1. Its last and
    t_final are not written: a resumed render has no backward pass to read them."""
    x0 = (t % ntx) * TILE
    y0 = (t // ntx) * TILE
    for yy in range(y0, min(y0 + TILE, alpha.shape[0])):
        for xx in range(x0, min(x0 + TILE, alpha.shape[1])):
            al = alpha[yy, xx]
            ok = al > F0
            inv = F1 / al if ok else F1
            rgb[yy, xx, 0] *= inv
            rgb[yy, xx, 1] *= inv
            rgb[yy, xx, 2] *= inv
            alpha[yy, xx] = F1 if ok else al


@njit(cache=True, parallel=True, nogil=True)
def covered_tiles(alpha, ntx, nty, cover, known):
    """[nty * ntx] bool: the 16x16 tiles (row-major) none of whose pixels (the image's part of the tile) has more
    than ``cover`` of its light left, 1 - alpha <= cover (cover 0: a tile whose alpha is 1 throughout). known
    [nty * ntx] bool (or empty): tiles known to have alpha 1 throughout (raster_forward's done), not read again."""
    out = np.empty(ntx * nty, np.bool_)
    for t in prange(ntx * nty):
        if known.shape[0] and known[t]:
            out[t] = True
            continue
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        ok = True
        for r in range(min(TILE, alpha.shape[0] - y0)):
            for q in range(min(TILE, alpha.shape[1] - x0)):
                ok &= F1 - alpha[y0 + r, x0 + q] <= cover
        out[t] = ok
    return out


@njit(inline="always")
def _rect_sum(sat, x0, x1, y0, y1):
    return sat[y1 + 1, x1 + 1] - sat[y0, x1 + 1] - sat[y1 + 1, x0] + sat[y0, x0]


@njit(cache=True, nogil=True)
def open_slots(visible, trange, sat, ntx):
    """The slots of ``visible`` (ascending, kept so) whose footprint's tile range (trange, see project_kernel; a
    range that wraps the equirect seam, tx1 < tx0, in its two pieces) touches a tile counted in ``sat``
    ([nty + 1, ntx + 1] summed-area table of the open tiles, sat[y, x] = the count in rows < y, columns < x)."""
    out = np.empty(visible.shape[0], np.int32)
    n = 0
    for k in range(visible.shape[0]):
        i = visible[k]
        tx0 = trange[i, 0] & 0xFFFF
        tx1 = trange[i, 0] >> 16
        ty0 = trange[i, 1] & 0xFFFF
        ty1 = trange[i, 1] >> 16
        if ty1 < ty0:               # no tile row (bin_kernel lists it nowhere)
            continue
        if tx1 >= tx0:
            c = _rect_sum(sat, tx0, tx1, ty0, ty1)
        else:
            c = _rect_sum(sat, tx0, ntx - 1, ty0, ty1) + _rect_sum(sat, 0, tx1, ty0, ty1)
        if c > 0:
            out[n] = i
            n += 1
    return out[:n]


@njit(inline="always", fastmath=RASTER_MATH)
def _raster_tile(t, start, ids, rows, ntx, width, height, wrap, plane, kk, tilex, rowy, bg, rgb, alpha, depth, last,
                 t_final, row_evals, px, py, T, c0, c1, c2, dd, lst, fb, resume, live):
    """Tile t of raster_forward: blend its instance list into the scratch arrays (pixel state), then write its
    pixels out; ``live`` [TILE]: which rows still have a blending pixel (updated at each stop check; _blend_one
    skips the others). (At most 30 arguments: CPython passes more as *args, which numba cannot inline.)"""
    wf = np.float32(width)
    inv_w = np.float32(1.0 / width)
    x0 = (t % ntx) * TILE
    y0 = (t // ntx) * TILE
    nq = min(TILE, width - x0)          # the tile's columns and rows inside the image
    nr = min(TILE, height - y0)
    for p in range(TILE_PIX):
        c0[p] = F0
        c1[p] = F0
        c2[p] = F0
        dd[p] = F0
        lst[p] = -1
        T[p] = -F1
    nact = 0
    for r in range(nr):
        for q in range(nq):
            p = r * TILE + q
            if resume:          # go on from the earlier render's pixel (raster_forward's resume)
                al = alpha[y0 + r, x0 + q]
                tb = F1 - al
                c0[p] = rgb[y0 + r, x0 + q, 0]
                c1[p] = rgb[y0 + r, x0 + q, 1]
                c2[p] = rgb[y0 + r, x0 + q, 2]
                dd[p] = depth[y0 + r, x0 + q] * al
                T[p] = tb if tb > T_RESUME else -tb
                nact += 1 if tb > T_RESUME else 0
            else:
                T[p] = F1
                nact += 1
    for r in range(TILE):
        lv = False
        for q in range(TILE):
            lv |= T[r * TILE + q] > F0
        live[r] = lv
    nrow = 0
    for b0 in range(start[t], start[t + 1], GATHER):
        if nact == 0:
            break
        nb = min(GATHER, start[t + 1] - b0)
        for jb in range(nb):  # gather this batch's features into a small contiguous buffer
            if jb + GATHER_AHEAD < nb:      # the rows are in depth order, all over the projected rows
                prefetch_row(rows, ids[b0 + jb + GATHER_AHEAD])
            gather_row(rows, ids[b0 + jb], x0, y0, width, wrap, plane, kk, tilex, rowy, fb, jb)
        for jb in range(nb):
            if wrap:
                nrow += _blend_one(fb, jb, np.int32(b0 + jb), px, py, T, c0, c1, c2, dd, lst, True, False, wf, inv_w,
                                   live)
            elif plane:
                nrow += _blend_one(fb, jb, np.int32(b0 + jb), px, py, T, c0, c1, c2, dd, lst, False, True, wf, inv_w,
                                   live)
            else:
                nrow += _blend_one(fb, jb, np.int32(b0 + jb), px, py, T, c0, c1, c2, dd, lst, False, False, wf,
                                   inv_w, live)
            if (jb & (STOP_CHECK - 1)) == STOP_CHECK - 1 or jb == nb - 1:
                # every STOP_CHECK instances: does any pixel still blend? (stopped pixels hold T < 0)
                tmax = -F1
                for r in range(TILE):
                    rmax = -F1
                    for q in range(TILE):
                        rmax = max(rmax, T[r * TILE + q])
                    live[r] = rmax > F0
                    tmax = max(tmax, rmax)
                if tmax <= F0:
                    nact = 0
                    break
    row_evals[t] = nrow
    for r in range(nr):
        yy = y0 + r
        for q in range(nq):
            p = r * TILE + q
            xx = x0 + q
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
def reduce_kernel(ids, gid, g_inst, n):
    """Sum instance gradients per Gaussian -> [n, 10] float64 (ids: the instances' slots, gid: slot ->
    Gaussian index, see project_kernel)."""
    out = np.zeros((n, g_inst.shape[1]), np.float64)
    for j in range(ids.shape[0]):
        i = gid[ids[j]]
        for k in range(g_inst.shape[1]):
            out[i, k] += g_inst[j, k]
    return out
