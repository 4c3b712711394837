"""The fast renderer: `render` (forward) and `render_backward`, driving the numba kernels."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from ..camera import Camera, check_render_size
from . import kernels as K
from . import lensmap
from .gaussians import Gaussians
from .lensmap import lens_params, opencv_pixel_map
from .projection import RenderOptions, check_camera, equirect_jacobian, pinhole_limits, project_reference
from .result import GaussianGrads, RenderResult, background_image
from .sh import sh_basis


@dataclass(frozen=True)
class _State:
    """What the backward pass needs from a forward pass (kept in RenderResult.state)."""
    opts: RenderOptions
    ntx: int
    start: np.ndarray     # [ntiles + 1] int64 instance offsets per tile
    ids: np.ndarray       # [n_inst] int32 slot per tile instance, front to back per tile
    rows: np.ndarray      # [m, kernels.NCG] float32 64-byte projected row per slot (m: the pre-cull count)
    gid: np.ndarray       # [m] int32 slot -> Gaussian index (slots a chunk did not fill: unwritten)
    bg: np.ndarray        # [H, W, 3] float32
    last: np.ndarray      # [H, W] int32
    t_final: np.ndarray   # [H, W] float32
    timings: dict         # seconds per stage: project, sort_bin, raster
    row_evals: np.ndarray  # [ntiles] int64 16-pixel rows the raster evaluated per tile (16 Gaussian-pixel each)
    resumed: bool = False  # drawn behind an earlier result (render's behind): no backward pass
    # [ntiles] bool: the tiles a render drawn behind another with cover left finished (alpha 1 throughout: render's
    # cover), which a render behind this one leaves as they are; None: none finished
    finished: np.ndarray | None = None


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


# the placeholders of an opencv camera's plane tables (lensmap.PixelPlane, read-only) for the other cameras: read-only
# too, so every camera calls the same numba specialisation (numba types read-only arrays apart)
_NO_TABLE = _read_only(np.zeros((0, 2)))
_NO_TILES = _read_only(np.zeros((0, 0, 2)))
_NO_PTAB = (_NO_TABLE, _NO_TABLE, _NO_TABLE, _NO_TILES, _NO_TILES, _NO_TILES)
_NO_OFFSETS = _read_only(np.zeros((0, 0, 2), np.float32))


def _camera_args(camera):
    """(model, (Rw, tw, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, ptab)) for the kernels: the model code (which
    kernel variant: kernels.project_kernel(model)) and its arguments: world -> camera, the lens parameters
    (lensmap.lens_params), K, the Jacobian clamp box (pinhole_limits; unused with a lens) and, for an opencv lens,
    the tables of its pixels' positions on its undistorted image plane (ptab = cols, rows, tyext, rowtx, tilex,
    tiley of lensmap.opencv_pixel_map; else empty)."""
    check_camera(camera)
    w2c = np.linalg.inv(camera.cam_to_ego)
    Rw, tw = np.ascontiguousarray(w2c[:3, :3]), np.ascontiguousarray(w2c[:3, 3])
    model, lp = lens_params(camera)
    if camera.is_equirect:
        return model, (Rw, tw, lp, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, _NO_PTAB)
    k = camera.K
    if model == lensmap.OPENCV:     # (no clamp box: its footprint lives on the mean's tangent plane)
        pm = opencv_pixel_map(camera)
        return model, (Rw, tw, lp, k[0, 0], k[1, 1], k[0, 2], k[1, 2], 0.0, 0.0, 0.0, 0.0,
                       (pm.cols, pm.rows, pm.tyext, pm.rowtx, pm.tilex, pm.tiley))
    return model, (Rw, tw, lp, k[0, 0], k[1, 1], k[0, 2], k[1, 2], *pinhole_limits(camera), _NO_PTAB)


def _plane_args(camera):
    """(plane, offsets, kk, tilex, rowy) for the raster: plane = an opencv lens, whose pixels sit on its
    undistorted image plane (lensmap.opencv_pixel_map; kk = fx, fy, cx, cy); else unused."""
    if camera.distortion is None or camera.distortion.model != "opencv":
        return False, _NO_OFFSETS, np.zeros(4), _NO_TILES, _NO_TILES
    pm = opencv_pixel_map(camera)
    kk = np.array([camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]])
    return True, pm.offsets, kk, pm.tilex, pm.rowy


def chunk_planes(camera, opts: RenderOptions) -> np.ndarray:
    """[k, 5] float64 world-frame half-spaces (a0, a1, a2, offset, kscale) for the projection's chunk test
    (kernels._chunk_outside): every Gaussian with a.mean + offset < -kscale * (its largest scale) is culled by
    the per-Gaussian tests anyway, so a chunk whose box lies there is skipped. Pinhole: near, far and the four
    image sides; a camera-frame point p is in front of a side when (for z > 0) its pre-cull box can reach the
    image, i.e. x + z (cx + 3.34 sqrt(low_pass) + 1) / fx + 3.34 c smax >= 0 (left side; c = sqrt(1 + lim^2)
    bounds the clamped Jacobian's row norm, 3.34 is the pre-cull's radius in sigmas, the extra pixel absorbs
    rounding); the other sides alike. Equirect: none (returns [0, 5]). A lens: only the culls of the mean itself,
    which need no bound on the lens's Jacobian: opencv: near and far (camera z); opencv_fisheye and ftheta with
    max_angle <= 90 degrees: z >= 0 (every point within max_angle has it); else none."""
    if camera.is_equirect:
        return np.zeros((0, 5))
    w2c = np.linalg.inv(camera.cam_to_ego)
    Rw, tw = w2c[:3, :3], w2c[:3, 3]
    if camera.distortion is not None:
        eps = 1e-6
        if camera.distortion.model == "opencv":
            cam = [((0.0, 0.0, 1.0), -opts.near + eps, 0.0), ((0.0, 0.0, -1.0), opts.far + eps, 0.0)]
        elif camera.distortion.max_angle <= np.pi / 2:
            cam = [((0.0, 0.0, 1.0), eps, 0.0)]
        else:
            return np.zeros((0, 5))
        return _planes(Rw, tw, cam)
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    lxn, lxp, lyn, lyp = pinhole_limits(camera)
    kx = 3.34 * np.sqrt(1.0 + max(lxn, lxp) ** 2)
    ky = 3.34 * np.sqrt(1.0 + max(lyn, lyp) ** 2)
    pad = 3.34 * np.sqrt(opts.low_pass) + 1.0          # pixels
    W, H = camera.width, camera.height
    eps = 1e-6                                         # metres of slack on near / far against rounding
    cam = [((0.0, 0.0, 1.0), -opts.near + eps, 0.0),   # z >= near
           ((0.0, 0.0, -1.0), opts.far + eps, 0.0),    # z <= far
           ((1.0, 0.0, (cx + pad) / fx), 0.0, kx),     # left
           ((-1.0, 0.0, (W - 1 - cx + pad) / fx), 0.0, kx),   # right
           ((0.0, 1.0, (cy + pad) / fy), 0.0, ky),     # top
           ((0.0, -1.0, (H - 1 - cy + pad) / fy), 0.0, ky)]   # bottom
    return _planes(Rw, tw, cam)


def _planes(Rw: np.ndarray, tw: np.ndarray, cam: list) -> np.ndarray:
    """Camera-frame half-spaces (a, offset, kscale): a . p + offset >= -kscale smax -> world frame [k, 5]."""
    out = np.empty((len(cam), 5))
    for k, (a, off, ks) in enumerate(cam):
        a = np.asarray(a)
        out[k, :3] = Rw.T @ a                          # a . (Rw x + tw) = (Rw^T a) . x + a . tw
        out[k, 3] = a @ tw + off
        out[k, 4] = ks
    return out


def _c(a):
    return np.ascontiguousarray(a)


_POOL = threading.local()   # per thread: the last scratch buffer of each name (see _scratch)


_BLACK: dict[tuple[int, int], np.ndarray] = {}     # _black's images, by (H, W)


def _black(H: int, W: int) -> np.ndarray:
    """[H, W, 3] float32 zeros shared by every render of that size with no background (a drive's view draws its
    layers with none: a fresh image a layer, and each later layer's check of the one before, cost ~10 ms a 1920x1080
    view). Never written: the rasteriser and the backward pass only read the background. The last four sizes kept
    (untouched pages of zeros: no memory until read, then the kernel's one zero page)."""
    bg = _BLACK.get((H, W))
    if bg is None:
        if len(_BLACK) >= 4:
            _BLACK.clear()
        bg = _BLACK[(H, W)] = np.zeros((H, W, 3), np.float32)
    return bg


def _scratch(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialised C-contiguous array of `shape`, starting on a 64-byte (cache-line) boundary, taken from
    this thread's pool: the previous buffer of that name is reused when it is big enough and nothing outside
    the pool holds it any more (a RenderResult's state holds its buffers until it is dropped; every array made
    from a buffer references it as its base, so the reference count tells). Fresh memory is zeroed page by page
    by the kernel on first touch: at stride 1 (11.8 M Gaussians) that was ~0.1 s of each render for the 170 MB
    of projected rows. The pool keeps at most one buffer per name and thread, 1.25x the largest size asked."""
    item = np.dtype(dtype).itemsize
    count = int(np.prod(shape))
    need = count + 64 // item
    pool = _POOL.__dict__
    buf = pool.get(name)
    # free: the pool's reference, `buf` here and getrefcount's argument
    if buf is None or buf.dtype != np.dtype(dtype) or buf.size < need or sys.getrefcount(buf) > 3:
        buf = np.empty(need + need // 4, dtype)
        pool[name] = buf
    off = (-buf.ctypes.data % 64) // item
    return buf[off:off + count].reshape(shape)


def as_parts(gaussians: Gaussians | Sequence[Gaussians]) -> list[Gaussians]:
    """A render's Gaussians as a list of sets drawn as their concatenation (render: one set, or several)."""
    if isinstance(gaussians, Gaussians):
        return [gaussians]
    parts = list(gaussians)
    if not parts or not all(isinstance(p, Gaussians) for p in parts):
        raise TypeError("gaussians: a Gaussians or a non-empty sequence of Gaussians")
    return parts


def _prepare(g: Gaussians | Sequence[Gaussians], camera, opts: RenderOptions, cull_chunks: bool = True,
             covered: np.ndarray | None = None):
    """Project, sort and bin ``g`` (one set, or several drawn exactly as their concatenation in order, without
    copying them: each part is projected into its own run of slots, so slots still increase with the index in the
    concatenation and the depth order breaks ties the same way; gid holds that index). covered [ntiles] bool or
    None: tiles the raster will not draw (render's cover); a Gaussian that touches no other tile is not sorted or
    binned."""
    W, H = camera.width, camera.height
    ntx, nty = (W + K.TILE - 1) // K.TILE, (H + K.TILE - 1) // K.TILE
    if ntx > 0x7FFF or nty > 0x7FFF:  # tile ranges are packed as two 16-bit fields in an int32
        raise ValueError(f"camera: width and height must be at most {0x7FFF * K.TILE} px, got {W}x{H}")
    t0 = time.perf_counter()
    parts = as_parts(g)
    nchs = [(len(p) + K.PROJ_CHUNK - 1) // K.PROJ_CHUNK for p in parts]
    ch0 = np.concatenate([[0], np.cumsum(nchs)]).astype(np.int64)       # each part's first chunk
    nch = int(ch0[-1])
    model, (*cargs, ptab) = _camera_args(camera)
    cam = (*cargs, W, H, float(opts.near), float(opts.far), float(opts.low_pass))   # kernels: the camera tuple
    planes = chunk_planes(camera, opts) if cull_chunks else np.zeros((0, 5))
    sat = np.zeros((0, 0), np.int64)       # the open tiles' summed-area table (kernels.open_slots); empty: all open
    if covered is not None and covered.any():
        sat = np.zeros((nty + 1, ntx + 1), np.int64)
        sat[1:, 1:] = np.cumsum(np.cumsum(~covered.reshape(nty, ntx), axis=0), axis=1)
    pre = np.zeros(nch, np.int64)
    # each Gaussian's pre-cull verdict (precull_counts), read by the projection instead of testing it again
    keep = _scratch("keep", (sum(len(p) for p in parts),), np.uint8)
    offset = 0
    for p, a, b in zip(parts, ch0[:-1], ch0[1:]):
        if b > a:
            # pass 1: an upper bound of the visible Gaussians per chunk, so the outputs are allocated to fit (a
            # slot per Gaussian made the kernel zero up to 64 bytes x N of fresh huge pages per render)
            boxes, phase = p.box_grid()
            K.precull_counts(model)(_c(p.means), _c(p.log_scales), cam, ptab, planes, sat, boxes, phase, pre[a:b],
                                    keep[offset:offset + len(p)])
        offset += len(p)
    base = np.zeros(nch, np.int64)
    np.cumsum(pre[:-1], out=base[1:])
    m = int(pre.sum())
    rows = _scratch("rows", (m, K.NCG), np.float32)    # one 64-byte row = one cache line
    dep = _scratch("depth", (m,), np.float64)
    trange = _scratch("trange", (m, 2), np.int32)
    gid = _scratch("gid", (m,), np.int32)
    counts = np.zeros(nch, np.int64)
    campos = np.ascontiguousarray(camera.cam_to_ego[:3, 3])
    offset = 0
    for p, a, b in zip(parts, ch0[:-1], ch0[1:]):
        if b > a and pre[a:b].any():
            K.project_kernel(model)(_c(p.means), _c(p.quats), _c(p.log_scales), _c(p.opacity_logits), _c(p.sh),
                                    campos, cam, ptab, keep[offset:offset + len(p)], bool(opts.antialiased),
                                    opts.radius_mode == "opacity", pre[a:b], base[a:b], rows, trange, dep, gid,
                                    counts[a:b])
            if offset:                  # the part's own indices -> indices in the concatenation
                K.offset_slots(gid, counts[a:b], base[a:b], offset)
        offset += len(p)
    t1 = time.perf_counter()
    visible = K.visible_slots(counts, base)
    if sat.shape[0]:    # the exact test on each footprint's tile range (a pinhole's projection kept only a bound's)
        visible = K.open_slots(visible, trange, sat, ntx)
    # depth order: float32 depths (positive: near > 0, so their bit patterns order like the values), ties by
    # Gaussian index (slots increase with it); the reference sorts the same keys
    order = K.depth_order(visible, K.depth_keys(dep, visible))
    start, ids = K.bin_kernel(order, trange, ntx, nty, numba.get_num_threads())
    t2 = time.perf_counter()
    return ntx, start, ids, rows, gid, {"project": t1 - t0, "sort_bin": t2 - t1}


def render(gaussians: Gaussians | Sequence[Gaussians], camera, background=None, behind: RenderResult | None = None,
           behind_inplace: bool = False, cover: float = 0.0, **options) -> RenderResult:
    """Render Gaussians from a runtime.camera.Camera: pinhole or equirectangular, a pinhole with a lens
    (runtime.lenses: opencv, opencv_fisheye, ftheta) drawn through the lens.

    gaussians: one set, or a sequence of sets drawn exactly as their concatenation in order (no copy; the parts
    may have different SH degrees; render_backward needs one set).
    behind: an earlier result of the same camera rendered with no background: these Gaussians are drawn behind
    what it drew, I = I_behind + (1 - A_behind) I_these (alpha and the alpha-weighted depth alike), pixel by pixel
    in the raster, which skips the pixels the earlier one already covered (render_backward cannot follow it).
    behind_inplace: draw into ``behind``'s own arrays instead of copies of them (``behind`` is then this render's
    result too: for layers whose earlier results are not kept, runtime.scene; saves three image copies a layer).
    cover (with ``behind``): a 16x16 tile of the image where ``behind`` left no pixel more than this fraction of its
    light is finished as ``behind`` drew it, its colour and alpha-weighted depth divided by its alpha (alpha 1), and
    nothing of these Gaussians is drawn there (runtime.scene.composite_layers's ``cover``, its reference); 0: the
    exact composite, every tile drawn.

    background: None (black), an RGB triple, or an image [H, W, 3] (0..1). Options: see RenderOptions.
    Returns RenderResult(rgb [H, W, 3], alpha [H, W], depth [H, W]) float32; depth is the expected camera z
    (pinhole, opencv lens) or distance from the camera centre (equirect, fisheye and f-theta lenses),
    sum(w z) / alpha, 0 where alpha == 0. Pixels outside a fisheye's or f-theta's image circle show the
    background alone (alpha 0, depth 0)."""
    opts = RenderOptions.from_kwargs(options)
    W, H = camera.width, camera.height
    check_render_size(W, H)                   # before any allocation (a clear error, not numpy's MemoryError)
    if isinstance(cover, bool) or not isinstance(cover, (int, float)) or not 0.0 <= cover < 1.0:
        raise ValueError(f"cover: must be a number in [0, 1), got {cover!r}")
    if behind is not None and (behind.alpha.shape != (H, W) or not isinstance(behind.state, _State)
                               or (behind.state.bg is not _BLACK.get((H, W)) and behind.state.bg.any())):
        raise ValueError(f"behind: must be a render of this {W}x{H} camera with no background")
    bg = _black(H, W) if background is None else background_image(background, H, W)
    ntx, nty = (W + K.TILE - 1) // K.TILE, (H + K.TILE - 1) // K.TILE
    covered = np.zeros(ntx * nty, bool)
    done = np.zeros(0, bool)        # tiles the layer in front finished already (_State.finished): not again
    if behind is not None and cover > 0:
        if behind.state.finished is not None:
            done = behind.state.finished
        covered = K.covered_tiles(behind.alpha, ntx, nty, np.float32(cover), done)
    ntx, start, ids, rows, gid, timings = _prepare(gaussians, camera, opts, covered=covered)
    t0 = time.perf_counter()
    if behind is None:
        rgb = np.empty((H, W, 3), np.float32)
        alpha = np.empty((H, W), np.float32)
        depth = np.empty((H, W), np.float32)
    else:
        if behind_inplace:
            rgb, alpha, depth = behind.rgb, behind.alpha, behind.depth
        else:
            rgb, alpha, depth = behind.rgb.copy(), behind.alpha.copy(), behind.depth.copy()
    last = _scratch("last", (H, W), np.int32)          # kept for the backward pass only
    t_final = _scratch("t_final", (H, W), np.float32)
    row_evals = np.empty(start.shape[0] - 1, np.int64)
    model, lp = lens_params(camera)
    plane, offsets, kk, tilex, rowy = _plane_args(camera)
    K.raster_forward(start, ids, rows, ntx, W, H, camera.is_equirect, plane, offsets, kk, tilex, rowy, bg, rgb,
                     alpha, depth, last, t_final, row_evals, behind is not None, covered, done)
    if model in (lensmap.FISHEYE, lensmap.FTHETA):   # no ray reaches the pixels outside the image circle
        k = camera.K
        lensmap.clear_outside_circle(model, lp, k[0, 0], k[1, 1], k[0, 2], k[1, 2], bg, rgb, alpha, depth, last,
                                     t_final)
    timings["raster"] = time.perf_counter() - t0
    state = _State(opts, ntx, start, ids, rows, gid, bg, last, t_final, timings, row_evals, behind is not None,
                   covered if behind is not None and cover > 0 else None)
    return RenderResult(rgb, alpha, depth, state)


def _as_grad(arr, shape, name):
    a = np.zeros(shape, np.float32) if arr is None else np.asarray(arr, dtype=np.float32)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {list(shape)}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: {int(np.count_nonzero(~np.isfinite(a)))} non-finite values")
    return np.ascontiguousarray(a)


def render_backward(gaussians: Gaussians, camera, result: RenderResult, d_rgb, d_alpha=None, d_depth=None,
                    background=None, **options) -> GaussianGrads:
    """Gradients of a scalar loss w.r.t. the raw Gaussian parameters (and the background), given
    d_rgb [H, W, 3], d_alpha [H, W], d_depth [H, W] (None = zero) for `result = render(gaussians, camera,
    background, **options)` with the same arguments. Pinhole and equirectangular cameras."""
    opts = RenderOptions.from_kwargs(options)
    check_camera(camera, backward=True)
    W, H = camera.width, camera.height
    st = result.state
    if not isinstance(st, _State) or st.opts != opts or st.last.shape != (H, W) or st.resumed:
        result = render(gaussians, camera, background, **options)
        st = result.state
    g_rgb = _as_grad(d_rgb, (H, W, 3), "d_rgb")
    g_al = _as_grad(d_alpha, (H, W), "d_alpha")
    g_d = _as_grad(d_depth, (H, W), "d_depth")
    n = len(gaussians)
    wrap = camera.is_equirect
    feat = K.instance_features(st.start, st.ids, st.rows, st.ntx, W, wrap)
    ids = st.ids
    g_inst = np.zeros((ids.shape[0], 10), np.float64)
    g_bg = np.zeros((H, W, 3), np.float64)
    K.raster_backward(st.start, feat, st.ntx, W, H, wrap, st.bg, result.depth, st.last, st.t_final,
                      g_rgb, g_al, g_d, g_inst, g_bg)
    g2 = K.reduce_kernel(ids, st.gid, g_inst, n) if n else np.zeros((0, 10))
    grads = _chain(gaussians, camera, opts, g2)
    if background is None:
        gb = None
    elif np.asarray(background).shape == (3,):
        gb = g_bg.sum(axis=(0, 1))
    else:
        gb = g_bg
    return GaussianGrads(*grads, background=gb)


def _sym(a, b, c):
    """[N] entries -> symmetric [N, 2, 2] [[a, b], [b, c]]."""
    return np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)


def _adj(m):
    return _sym(m[:, 1, 1], -m[:, 0, 1], m[:, 0, 0])


def _chain(g: Gaussians, camera, opts: RenderOptions, g2: np.ndarray):
    """2D gradients per Gaussian [N, 10] (mean2d x y, conic a b c, opacity, colour rgb, depth) -> 3D."""
    pr = project_reference(g, camera, opts)
    g_mx, g_my, g_ca, g_cb, g_cc, g_op = (g2[:, k] for k in range(6))
    g_col, g_z = g2[:, 6:9], g2[:, 9].copy()
    conic = _sym(pr["conic"][:, 0], pr["conic"][:, 1], pr["conic"][:, 2])
    G = _sym(g_ca, 0.5 * g_cb, g_cc)
    GS = -conic @ G @ conic                                   # dL/dcov2 (symmetric-matrix gradient)
    opa, comp = pr["opa"], pr["comp"]
    g_logit = g_op * comp * opa * (1.0 - opa)
    if opts.antialiased:
        det = pr["det"]
        c2r = pr["cov2_raw"]
        det_raw = c2r[:, 0, 0] * c2r[:, 1, 1] - c2r[:, 0, 1] ** 2
        safe = comp > 0
        cs = np.where(safe, comp, 1.0)
        dcomp = (_adj(pr["cov2_raw"]) * det[:, None, None] - det_raw[:, None, None] * _adj(pr["cov2"])) \
            / (det ** 2 * 2 * cs)[:, None, None]
        GS = GS + np.where(safe, g_op * opa, 0.0)[:, None, None] * dcomp
    Rw, J, cov3 = pr["Rw"], pr["J"], pr["cov3"]
    T = J @ Rw[None]
    g_cov3 = T.transpose(0, 2, 1) @ GS @ T
    g_T = 2.0 * GS @ T @ cov3
    g_J = g_T @ Rw.T[None]
    if camera.is_equirect:
        gp = _equirect_point_grad(pr, camera, g_J, g_mx, g_my, g_z)
    else:
        gp = _pinhole_point_grad(pr, camera, g_J, g_mx, g_my, g_z)
    g_means = gp @ Rw
    # covariance -> scales, rotation
    R, s, M = pr["R"], pr["s"], pr["M"]
    g_M = 2.0 * g_cov3 @ M
    g_s = np.einsum("nki,nki->ni", g_M, R)
    g_log_scales = g_s * s
    gR = g_M * s[:, None, :]
    q = g.quats.astype(np.float64)
    qnorm = np.linalg.norm(q, axis=1, keepdims=True)
    qn = q / qnorm
    w, qx, qy, qz = qn[:, 0], qn[:, 1], qn[:, 2], qn[:, 3]
    G_ = gR
    g_qn = 2.0 * np.stack([
        -qz * G_[:, 0, 1] + qy * G_[:, 0, 2] + qz * G_[:, 1, 0] - qx * G_[:, 1, 2] - qy * G_[:, 2, 0]
        + qx * G_[:, 2, 1],
        qy * G_[:, 0, 1] + qz * G_[:, 0, 2] + qy * G_[:, 1, 0] - 2 * qx * G_[:, 1, 1] - w * G_[:, 1, 2]
        + qz * G_[:, 2, 0] + w * G_[:, 2, 1] - 2 * qx * G_[:, 2, 2],
        -2 * qy * G_[:, 0, 0] + qx * G_[:, 0, 1] + w * G_[:, 0, 2] + qx * G_[:, 1, 0] + qz * G_[:, 1, 2]
        - w * G_[:, 2, 0] + qz * G_[:, 2, 1] - 2 * qy * G_[:, 2, 2],
        -2 * qz * G_[:, 0, 0] - w * G_[:, 0, 1] + qx * G_[:, 0, 2] + w * G_[:, 1, 0] - 2 * qz * G_[:, 1, 1]
        + qy * G_[:, 1, 2] + qx * G_[:, 2, 0] + qy * G_[:, 2, 1]], 1)
    g_quats = (g_qn - qn * np.einsum("ni,ni->n", qn, g_qn)[:, None]) / qnorm
    # colour -> SH (and view direction -> means)
    kc = g.sh.shape[1]
    g_col = g_col * pr["colour_unclamped"]
    v = g.means.astype(np.float64) - camera.cam_to_ego[:3, 3][None]
    vn = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    d = v / vn
    basis, dbasis = sh_basis(d, kc, with_grad=True)
    g_sh = basis[:, :, None] * g_col[:, None, :]
    if kc > 1:
        coef = np.einsum("nkc,nc->nk", g.sh.astype(np.float64), g_col)
        g_dir = np.einsum("nk,nkj->nj", coef, dbasis)
        g_means = g_means + (g_dir - d * np.einsum("nj,nj->n", d, g_dir)[:, None]) / vn
    return g_means, g_quats, g_log_scales, g_logit, g_sh


def _pinhole_point_grad(pr, camera: Camera, g_J, g_mx, g_my, g_z):
    """dL/d(camera-frame point) [N, 3] through mean2d, depth z and the (clamped) EWA Jacobian."""
    n = g_J.shape[0]
    x, y, z = pr["p_cam"][:, 0], pr["p_cam"][:, 1], pr["p_cam"][:, 2]
    zs = np.where(z > 0, z, 1.0)
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    fr_x, fr_y = (~pr["clamp"][:, 0]).astype(np.float64), (~pr["clamp"][:, 1]).astype(np.float64)
    lxn, lxp, lyn, lyp = pinhole_limits(camera)
    sxc, syc = np.clip(x / zs, -lxn, lxp), np.clip(y / zs, -lyn, lyp)
    dsx_dx, dsx_dz = fr_x / zs, -fr_x * x / zs ** 2
    dsy_dy, dsy_dz = fr_y / zs, -fr_y * y / zs ** 2
    gp = np.zeros((n, 3))
    gp[:, 0] = g_mx * fx / zs + g_J[:, 0, 2] * (-fx / zs * dsx_dx)
    gp[:, 1] = g_my * fy / zs + g_J[:, 1, 2] * (-fy / zs * dsy_dy)
    gp[:, 2] = (g_z - g_mx * fx * x / zs ** 2 - g_my * fy * y / zs ** 2
                - g_J[:, 0, 0] * fx / zs ** 2 - g_J[:, 1, 1] * fy / zs ** 2
                + g_J[:, 0, 2] * (fx * sxc / zs ** 2 - fx / zs * dsx_dz)
                + g_J[:, 1, 2] * (fy * syc / zs ** 2 - fy / zs * dsy_dz))
    return gp


def _equirect_point_grad(pr, camera: Camera, g_J, g_mx, g_my, g_z):
    """dL/d(camera-frame point) [N, 3] for the equirect map: mean2d's derivative is the unclamped spherical
    Jacobian, depth r's is p / r, and the Jacobian's own derivative is taken by complex step (exact to
    rounding for this analytic map; the pole clamp is held fixed, as a max() is)."""
    p = pr["p_cam"]
    W, H = camera.width, camera.height
    r = np.linalg.norm(p, axis=1)
    J_mean = equirect_jacobian(p, W, H, np.zeros(p.shape[0], bool))
    gp = g_mx[:, None] * J_mean[:, 0, :] + g_my[:, None] * J_mean[:, 1, :]
    gp += g_z[:, None] * p / np.where(r > 0, r, 1.0)[:, None]
    h = 1e-20 * np.maximum(r, 1e-3)
    for k in range(3):
        pc = p.astype(np.complex128)
        pc[:, k] += 1j * h
        dJ = equirect_jacobian(pc, W, H, pr["clamp"][:, 0]).imag / h[:, None, None]
        gp[:, k] += np.einsum("nab,nab->n", g_J, dJ)
    return gp
