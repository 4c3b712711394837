"""A plain numba peer renderer, and the benchmark that compares it with ours (`xyzcyl.runtime.render.render`).

What the peer is: a straightforward numba port of the forward pass of the original 3D Gaussian Splatting
rasteriser (Kerbl et al. 2023, `diff-gaussian-rasterization`) with gsplat's projection details, as a competent
person would write it without the optimisations of docs/renderer.md:

1. **project** (`_preprocess`, `prange` over Gaussians, float64): camera-frame mean, cull below `near`, pixel
   mean, EWA 2D covariance J W R S S^T R^T W^T J^T + 0.3 px^2 on the diagonal (gsplat's eps2d; gsplat's
   Jacobian clamp: x/z within the image plus 0.3 tan(fov/2) beyond each edge), conic, opacity =
   sigmoid(logit), SH degree 0 colour max(0, 0.5 + SH_C0 dc), the 3-sigma radius (`radius="circle"`:
   ceil(3 sqrt(largest eigenvalue)) as in 3DGS and gsplat <= 1.4; `"box"`: ceil(3 sqrt(cov_xx)) and
   ceil(3 sqrt(cov_yy)) per axis as in gsplat >= 1.5) and the 16x16 tiles that radius touches (gsplat's
   floor / ceil bounds; 3DGS's integer rounding of the upper bound can drop a pixel column at the 3-sigma
   edge).
2. **sort**: an exclusive prefix sum of the tile counts (`np.cumsum`), one key `tile id << 32 | float32 depth
   bits` per (tile, Gaussian) pair (`_duplicate_with_keys`, `prange` over Gaussians, 3DGS's
   duplicateWithKeys), `np.argsort(keys, kind="stable")` (3DGS / gsplat sort with CUB's radix sort; numpy's
   stable sort is what a port reaches for), then each tile's [start, end) in the sorted list (`_tile_ranges`,
   3DGS's identifyTileRanges).
3. **raster** (`_rasterise`, `prange` over tiles): for every pixel of the tile, the tile's Gaussians front to
   back: power = -1/2 d^T conic d, skipped if > 0; alpha = min(0.99, o exp(power)) with `math.exp`, skipped
   below 1/255; the pixel stops before blending a Gaussian that would bring T below 1e-4 (3DGS's
   `test_T < 0.0001`); C += c alpha T, D += z alpha T, T *= 1 - alpha. rgb = C + T background,
   alpha = 1 - T, depth = D / alpha (0 where alpha == 0), the same outputs as ours.

Why it is a fair peer: the same inputs (the raw parameters: log-scales, opacity logits, wxyz quaternions, SH
DC) and outputs, the same compiler (numba, `cache=True`, so no compile time is timed), the same thread count,
every stage parallel where 3DGS's is except numpy's single-threaded prefix sum and sort, float64 projection
and float32 per-Gaussian features as in 3DGS (the raster's arithmetic is float64 because numba promotes
float32 loads with float literals; scalar code costs the same either way). It leaves out exactly what our
renderer adds: the cut at the 3-sigma ellipse (the peer, like 3DGS, evaluates a Gaussian on every pixel of
every tile its radius touches, so its picture differs from ours by faint alphas of at most 0.99 exp(-4.5) ~
0.011 beyond 3 sigma), counting-sort binning of int32 ids, the per-tile gather into 64-byte rows, the
branch-free 16-pixel SIMD loop with a polynomial exp and the tile-level stop test.

Benchmark: `render_bench.scene(n)` (500k random Gaussians) seen by `render_bench.camera(w, h)` at 1600x900 and
800x450, `--threads` numba threads (default 2), both renderers warmed up first (compile / cache load), then
--repeats calls of each, interleaved (ours, peer, ours, ...) so machine load hits both alike; medians. One
JSON line per size: ours_s, peer_s, speedup = peer_s / ours_s, psnr_vs_ours (dB over rgb, peak 1),
mean_abs_rgb_diff, the peer's stage medians. Pinhole cameras and SH degree 0 only.

    .venv/bin/python benchmarks/peer_renderer.py [--sizes 1600x900 800x450] [--gaussians 500000] [--threads 2]
        [--repeats 5] [--radius circle|box]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numba
import numpy as np
import render_bench  # a sibling script: its folder is on the path (run as a script, or pytest's pythonpath)
from numba import njit, prange
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.render.projection import pinhole_limits
from xyzcyl.runtime.render.result import background_image

TILE = 16                    # tile edge, pixels (3DGS BLOCK_X / BLOCK_Y)
SH_C0 = 0.28209479177387814  # degree-0 SH basis constant (3DGS)
LOW_PASS = 0.3               # px^2 added to the 2D covariance diagonal (3DGS, gsplat eps2d)
ALPHA_MAX = 0.99             # alpha clamp
ALPHA_MIN = 1.0 / 255.0      # alphas below are skipped
T_MIN = 1e-4                 # a pixel stops before a Gaussian that would bring T below this
RADII = ("circle", "box")


# ---------------------------------------------------------------------------------------------------- project
@njit(parallel=True, cache=True)
def _preprocess(means, quats, log_scales, opacity_logits, sh_dc, Rw, tw, fx, fy, cx, cy, lxn, lxp, lyn, lyp,
                width, height, near, box_radius, xy, conic_opacity, colour, depth, rect, tiles_touched):
    """Project Gaussian i (float64 arithmetic) for every i in parallel.

    Inputs: means [N, 3] m, quats [N, 4] wxyz, log_scales [N, 3], opacity_logits [N], sh_dc [N, 3];
    Rw [3, 3], tw [3] world -> camera; fx, fy, cx, cy px; lxn .. lyp the Jacobian clamp on x/z, y/z.
    Outputs (written only where tiles_touched[i] > 0): xy [N, 2] f32 px, conic_opacity [N, 4] f32
    (a, b, c, o: power = -(a dx^2 + c dy^2) / 2 - b dx dy), colour [N, 3] f32, depth [N] f32 camera z (m),
    rect [N, 4] int32 tile bounds (tx0, ty0, tx1, ty1), upper bounds exclusive; tiles_touched [N] int64
    (0 = culled)."""
    n = means.shape[0]
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for i in prange(n):
        tiles_touched[i] = 0
        mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        x = Rw[0, 0] * mx + Rw[0, 1] * my + Rw[0, 2] * mz + tw[0]
        y = Rw[1, 0] * mx + Rw[1, 1] * my + Rw[1, 2] * mz + tw[1]
        z = Rw[2, 0] * mx + Rw[2, 1] * my + Rw[2, 2] * mz + tw[2]
        if z < near:
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        # rotation from the normalised quaternion, M = R S
        qw, qx, qy, qz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), \
            np.float64(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        s0 = math.exp(np.float64(log_scales[i, 0]))
        s1 = math.exp(np.float64(log_scales[i, 1]))
        s2 = math.exp(np.float64(log_scales[i, 2]))
        m00 = (1.0 - 2.0 * (qy * qy + qz * qz)) * s0
        m01 = 2.0 * (qx * qy - qw * qz) * s1
        m02 = 2.0 * (qx * qz + qw * qy) * s2
        m10 = 2.0 * (qx * qy + qw * qz) * s0
        m11 = (1.0 - 2.0 * (qx * qx + qz * qz)) * s1
        m12 = 2.0 * (qy * qz - qw * qx) * s2
        m20 = 2.0 * (qx * qz - qw * qy) * s0
        m21 = 2.0 * (qy * qz + qw * qx) * s1
        m22 = (1.0 - 2.0 * (qx * qx + qy * qy)) * s2
        # 3D covariance cov3 = M M^T (symmetric: 6 entries)
        v00 = m00 * m00 + m01 * m01 + m02 * m02
        v01 = m00 * m10 + m01 * m11 + m02 * m12
        v02 = m00 * m20 + m01 * m21 + m02 * m22
        v11 = m10 * m10 + m11 * m11 + m12 * m12
        v12 = m10 * m20 + m11 * m21 + m12 * m22
        v22 = m20 * m20 + m21 * m21 + m22 * m22
        # EWA: cov2 = T cov3 T^T with T = J Rw, J the (clamped) Jacobian of the projection at the camera-frame
        # mean: J = [[fx/z, 0, -fx x'/z], [0, fy/z, -fy y'/z]], x' = x/z and y' = y/z clamped
        txz = min(max(x / z, -lxn), lxp)
        tyz = min(max(y / z, -lyn), lyp)
        j00, j02 = fx / z, -fx * txz / z
        j11, j12 = fy / z, -fy * tyz / z
        t00 = j00 * Rw[0, 0] + j02 * Rw[2, 0]
        t01 = j00 * Rw[0, 1] + j02 * Rw[2, 1]
        t02 = j00 * Rw[0, 2] + j02 * Rw[2, 2]
        t10 = j11 * Rw[1, 0] + j12 * Rw[2, 0]
        t11 = j11 * Rw[1, 1] + j12 * Rw[2, 1]
        t12 = j11 * Rw[1, 2] + j12 * Rw[2, 2]
        # cov3 T^T, column by column
        a0 = v00 * t00 + v01 * t01 + v02 * t02
        a1 = v01 * t00 + v11 * t01 + v12 * t02
        a2 = v02 * t00 + v12 * t01 + v22 * t02
        b0 = v00 * t10 + v01 * t11 + v02 * t12
        b1 = v01 * t10 + v11 * t11 + v12 * t12
        b2 = v02 * t10 + v12 * t11 + v22 * t12
        c00 = t00 * a0 + t01 * a1 + t02 * a2 + LOW_PASS
        c01 = t00 * b0 + t01 * b1 + t02 * b2
        c11 = t10 * b0 + t11 * b1 + t12 * b2 + LOW_PASS
        det = c00 * c11 - c01 * c01
        if det <= 0.0:
            continue
        if box_radius:
            rx = math.ceil(3.0 * math.sqrt(c00))
            ry = math.ceil(3.0 * math.sqrt(c11))
        else:
            mid = 0.5 * (c00 + c11)
            lam = mid + math.sqrt(max(0.1, mid * mid - det))
            rx = math.ceil(3.0 * math.sqrt(lam))
            ry = rx
        tx0 = min(ntx, max(0, math.floor((u - rx) / TILE)))
        tx1 = min(ntx, max(0, math.ceil((u + rx) / TILE)))
        ty0 = min(nty, max(0, math.floor((v - ry) / TILE)))
        ty1 = min(nty, max(0, math.ceil((v + ry) / TILE)))
        if tx1 <= tx0 or ty1 <= ty0:
            continue
        xy[i, 0] = u
        xy[i, 1] = v
        conic_opacity[i, 0] = c11 / det
        conic_opacity[i, 1] = -c01 / det
        conic_opacity[i, 2] = c00 / det
        conic_opacity[i, 3] = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[i])))
        for c in range(3):
            colour[i, c] = max(0.0, 0.5 + SH_C0 * np.float64(sh_dc[i, c]))
        depth[i] = z
        rect[i, 0] = tx0
        rect[i, 1] = ty0
        rect[i, 2] = tx1
        rect[i, 3] = ty1
        tiles_touched[i] = (tx1 - tx0) * (ty1 - ty0)


# ------------------------------------------------------------------------------------------------------- sort
@njit(parallel=True, cache=True)
def _duplicate_with_keys(offsets, tiles_touched, rect, depth_bits, ntx, keys, gids):
    """For every (tile, Gaussian) pair, keys = tile id << 32 | the float32 depth's bit pattern (positive
    floats order like their bits) and gids = the Gaussian index, Gaussian i writing slots offsets[i] ..
    offsets[i] + tiles_touched[i] - 1. offsets [N] int64 (exclusive prefix sum), rect [N, 4] int32,
    depth_bits [N] uint32; keys [M] uint64, gids [M] int32 (M = total tiles touched)."""
    for i in prange(tiles_touched.shape[0]):
        if tiles_touched[i] == 0:
            continue
        k = offsets[i]
        lo = np.uint64(depth_bits[i])
        for ty in range(rect[i, 1], rect[i, 3]):
            for tx in range(rect[i, 0], rect[i, 2]):
                keys[k] = (np.uint64(ty * ntx + tx) << np.uint64(32)) | lo
                gids[k] = i
                k += 1


@njit(parallel=True, cache=True)
def _tile_ranges(sorted_keys, ranges):
    """ranges [n_tiles, 2] int64 (zeroed by the caller) <- each tile's [start, end) in sorted_keys [M]
    uint64."""
    m = sorted_keys.shape[0]
    for j in prange(m):
        tile = np.int64(sorted_keys[j] >> np.uint64(32))
        if j == 0:
            ranges[tile, 0] = 0
        else:
            prev = np.int64(sorted_keys[j - 1] >> np.uint64(32))
            if prev != tile:
                ranges[prev, 1] = j
                ranges[tile, 0] = j
        if j == m - 1:
            ranges[tile, 1] = m


# ----------------------------------------------------------------------------------------------------- raster
@njit(parallel=True, cache=True)
def _rasterise(ranges, point_list, xy, conic_opacity, colour, depth, bg, width, height, out_rgb, out_alpha,
               out_depth):
    """3DGS's forward blend, parallel over tiles: every pixel walks its tile's list
    [ranges[t, 0], ranges[t, 1]) of point_list [M] int32 front to back. bg [H, W, 3] f32; out_rgb [H, W, 3],
    out_alpha, out_depth [H, W] f32."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for t in prange(ntx * nty):
        x0 = (t % ntx) * TILE
        y0 = (t // ntx) * TILE
        j0 = ranges[t, 0]
        j1 = ranges[t, 1]
        for py in range(y0, min(y0 + TILE, height)):
            for px in range(x0, min(x0 + TILE, width)):
                T = 1.0
                c0 = 0.0
                c1 = 0.0
                c2 = 0.0
                d = 0.0
                for j in range(j0, j1):
                    g = point_list[j]
                    dx = xy[g, 0] - px
                    dy = xy[g, 1] - py
                    power = -0.5 * (conic_opacity[g, 0] * dx * dx + conic_opacity[g, 2] * dy * dy) \
                        - conic_opacity[g, 1] * dx * dy
                    if power > 0.0:
                        continue
                    alpha = min(ALPHA_MAX, conic_opacity[g, 3] * math.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    test_T = T * (1.0 - alpha)
                    if test_T < T_MIN:
                        break
                    w = alpha * T
                    c0 += colour[g, 0] * w
                    c1 += colour[g, 1] * w
                    c2 += colour[g, 2] * w
                    d += depth[g] * w
                    T = test_T
                a = 1.0 - T
                out_rgb[py, px, 0] = c0 + T * bg[py, px, 0]
                out_rgb[py, px, 1] = c1 + T * bg[py, px, 1]
                out_rgb[py, px, 2] = c2 + T * bg[py, px, 2]
                out_alpha[py, px] = a
                out_depth[py, px] = d / a if a > 0.0 else 0.0


# ----------------------------------------------------------------------------------------------------- driver
def render_peer(gaussians: Gaussians, camera: Camera, background=None, *, radius: str = "circle",
                near: float = 0.01, timings: dict[str, float] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render with the plain 3DGS-style peer (see the module docstring).

    gaussians: SH degree 0 (higher bands are refused rather than ignored). camera: Camera only.
    background: None (black), an RGB triple or an image [H, W, 3], as for `render`. radius: "circle" (3DGS) or
    "box" (gsplat >= 1.5). near: m, Gaussians with camera z below are culled (3DGS uses 0.2; 0.01 is ours).
    timings: if given, filled with seconds per stage: project, sort (prefix sum, keys, argsort, tile ranges),
    raster, and with instances, the number of (tile, Gaussian) pairs.
    Returns rgb [H, W, 3], alpha [H, W], depth [H, W] (camera z, m; 0 where alpha == 0), float32."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: the peer renderer supports Camera only, got {type(camera).__name__}")
    if gaussians.sh.shape[1] != 1:
        raise ValueError(f"sh: the peer renderer evaluates SH degree 0 only, got {gaussians.sh_degree}")
    if radius not in RADII:
        raise ValueError(f"radius: expected one of {RADII}, got {radius!r}")
    W, H = camera.width, camera.height
    ntx, nty = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    bg = background_image(background, H, W)
    n = len(gaussians)
    t0 = time.perf_counter()
    w2c = np.linalg.inv(camera.cam_to_ego)
    K = camera.K
    xy = np.empty((n, 2), np.float32)
    conic_opacity = np.empty((n, 4), np.float32)
    colour = np.empty((n, 3), np.float32)
    depth = np.zeros(n, np.float32)
    rect = np.empty((n, 4), np.int32)
    tiles_touched = np.empty(n, np.int64)
    c = np.ascontiguousarray
    _preprocess(c(gaussians.means), c(gaussians.quats), c(gaussians.log_scales), c(gaussians.opacity_logits),
                c(gaussians.sh[:, 0, :]), c(w2c[:3, :3]), c(w2c[:3, 3]), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                *pinhole_limits(camera), W, H, float(near), radius == "box", xy, conic_opacity, colour, depth,
                rect, tiles_touched)
    t1 = time.perf_counter()
    ends = np.cumsum(tiles_touched)
    m = int(ends[-1]) if n else 0
    keys = np.empty(m, np.uint64)
    gids = np.empty(m, np.int32)
    _duplicate_with_keys(ends - tiles_touched, tiles_touched, rect, depth.view(np.uint32), ntx, keys, gids)
    order = np.argsort(keys, kind="stable")
    point_list = gids[order]
    ranges = np.zeros((ntx * nty, 2), np.int64)
    _tile_ranges(keys[order], ranges)
    t2 = time.perf_counter()
    rgb = np.empty((H, W, 3), np.float32)
    alpha = np.empty((H, W), np.float32)
    out_depth = np.empty((H, W), np.float32)
    _rasterise(ranges, point_list, xy, conic_opacity, colour, depth, bg, W, H, rgb, alpha, out_depth)
    t3 = time.perf_counter()
    if timings is not None:
        timings.update(project=t1 - t0, sort=t2 - t1, raster=t3 - t2, instances=float(m))
    return rgb, alpha, out_depth


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images with peak value 1 (inf when equal)."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=_size, nargs="+", default=[(1600, 900), (800, 450)], help="WxH")
    ap.add_argument("--gaussians", type=int, default=500_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--radius", choices=RADII, default="circle")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    g = render_bench.scene(args.gaussians)
    small = render_bench.camera(64, 48)
    render(g, small)  # warm-up: compile or load the numba caches of both renderers
    render_peer(g, small, radius=args.radius)
    for width, height in args.sizes:
        cam = render_bench.camera(width, height)
        ours_res = render(g, cam)
        peer_rgb, _, _ = render_peer(g, cam, radius=args.radius)
        ours_t, peer_t, stages = [], [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            render(g, cam)
            ours_t.append(time.perf_counter() - t0)
            st: dict[str, float] = {}
            t0 = time.perf_counter()
            render_peer(g, cam, radius=args.radius, timings=st)
            peer_t.append(time.perf_counter() - t0)
            stages.append(st)
        ours_s, peer_s = float(np.median(ours_t)), float(np.median(peer_t))
        row = {
            "case": f"{args.gaussians}@{width}x{height}/t{args.threads}", "gaussians": args.gaussians,
            "width": width, "height": height, "threads": args.threads, "peer_radius": args.radius,
            "ours_s": round(ours_s, 4), "peer_s": round(peer_s, 4), "speedup": round(peer_s / ours_s, 2),
            "psnr_vs_ours": round(psnr(peer_rgb, ours_res.rgb), 2),
            "mean_abs_rgb_diff": float(f"{np.abs(peer_rgb - ours_res.rgb).mean():.3g}"),
            "peer_stages_s": {k: round(float(np.median([s[k] for s in stages])), 4)
                              for k in ("project", "sort", "raster")},
            "peer_instances": int(stages[0]["instances"]), "ours_instances": int(ours_res.state.ids.shape[0]),
            "load_avg_1m": round(os.getloadavg()[0], 2),
        }
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
