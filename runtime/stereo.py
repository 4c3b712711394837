"""Depth from the motion between a drive's frames, for keyframes without a LiDAR sweep (docs/inference.md, "Stereo
between frames").

A moving camera sees the same surface from two places: the baseline between a keyframe and a frame about
STEREO_BASELINE_M away (before and after it) makes a stereo pair with known poses. Each camera of the keyframe is
matched with the same camera of each partner frame (SIFT features on images resized to STEREO_WIDTH pixels, Lowe's
ratio test), and each match's two rays (Camera.pixel_rays: any lens) are triangulated at the midpoint of their
closest points. A point is kept when the rays meet (closest distance within MAX_RAY_GAP_PX pixels of the resized
image, seen from either camera), cross at MIN_PARALLAX_DEG or more (a smaller angle leaves the depth undetermined:
the error grows as the distance over the parallax) and lie in front of both cameras. What moves gives no points: no
feature is taken where a keyframe camera sees the box of a tracked object that moves (box_mask; a point triangulated
from a car that moved between the frames lands anywhere, not in its box) and no point inside one. A feature found
with both partners is kept when its two points lie within AGREE of its distance of each other (what moves without
a track parts); when the drive's tracks name what moves (``tracked``), a feature found with one partner only is kept
too if its rays cross at MIN_PARALLAX_ONE_DEG or more, else a keyframe without a partner on each side gets none.
The points, in the keyframe's ego frame, go
where a LiDAR sweep would (Reconstructor.keyframe's ``lidar``): the model's depth is scaled to them per camera
(runtime.lidar.fuse_depth), and detail cells sit on them, so a camera-only drive is not held back by single-image
depth. They are sparse and less exact than a LiDAR's, so they never carve another keyframe's cells
(runtime.drive._carve_pair), and they are no sweep (Reconstructor.keyframe's ``lidar_is_sweep``): the detail
layer's ground plane stays the model's and their cells are trusted as the model's (runtime.detail.camera_detail's
``sweep``). An ego that stands still has no partner frame and no stereo points."""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

from .boxes import inside_boxes
from .numba_cache import njit

STEREO_BASELINE_M = 1.0     # the partner frames: the nearest frames at least this far from the keyframe, each side
STEREO_WIDTH = 960          # features are found on images resized to this width (2x faster than 1920, enough texture)
MIN_PARALLAX_DEG = 2.0      # rays that cross at a smaller angle leave the depth undetermined (at 2 degrees and a
                            # pixel of matching error, the depth is good to ~6 % of the distance)
MIN_PARALLAX_ONE_DEG = 3.0  # a point seen with one partner only (no second one to agree): a wider angle (its depth
                            # good to ~4 % at a pixel of error). Measured on the synthetic drive, camera only: 2 degrees
                            # gave +1.19 dB over one frame alone but the front camera 0.02 dB below it, 4 degrees +1.00
MAX_RAY_GAP_PX = 1.5        # the rays' closest distance, as pixels of the resized image at the point's distance
RATIO = 0.75                # Lowe's ratio test: the best match clearly better than the second
AGREE = 0.03                # a feature matched with both partners: its two points within this fraction of its range
MAX_FEATURES = 8000         # per image
BOX_SAMPLES = 5             # box_mask: points a side on each face of a moving object's box, projected
BOX_GROW_PX = 4             # ... and its outline grown this many pixels of the resized image (the box's pose error)
CONTRAST = 0.01             # SIFT's contrast threshold (OpenCV's default 0.04 finds a few hundred features on a
                            # rendered street, 0.01 several thousand; the ratio test and the ray check keep the good)


def partner_frames(positions: np.ndarray, k: int, baseline_m: float | None = None) -> list[int]:
    """The frames paired with frame k (positions [F, 3] metres: the ego positions of the drive's frames, one frame):
    the nearest frame before k and the nearest after it that stand at least ``baseline_m`` (default
    STEREO_BASELINE_M) from frame k; none on a side where no frame does (stereo_points needs both)."""
    b = STEREO_BASELINE_M if baseline_m is None else baseline_m
    pos = np.asarray(positions, np.float64)
    far = np.linalg.norm(pos - pos[k], axis=1) >= b
    before = [j for j in range(k - 1, -1, -1) if far[j]][:1]
    after = [j for j in range(k + 1, len(pos)) if far[j]][:1]
    return before + after


def triangulate(o_a: np.ndarray, d_a: np.ndarray, o_b: np.ndarray, d_b: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints of rays a and b (origins [M, 3], unit directions [M, 3], one frame): (points [M, 3], the rays'
    closest distance [M] metres, the distances along a and b [M] (negative: behind), the angle between them [M]
    degrees). Parallel rays get NaN points."""
    w = o_a - o_b
    b = np.einsum("ij,ij->i", d_a, d_b)
    d = np.einsum("ij,ij->i", d_a, w)
    e = np.einsum("ij,ij->i", d_b, w)
    den = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - d) / den
        t = (e - b * d) / den
    pa = o_a + s[:, None] * d_a
    pb = o_b + t[:, None] * d_b
    ang = np.degrees(np.arccos(np.clip(b, -1.0, 1.0)))
    return 0.5 * (pa + pb), np.linalg.norm(pa - pb, axis=1), np.stack([s, t], axis=1), ang


def triangulate_reference(o_a, d_a, o_b, d_b) -> np.ndarray:
    """triangulate's points by least squares, one pair at a time (slow, obviously correct; for the tests): the
    (s, t) minimising |o_a + s d_a - o_b - t d_b|, then the midpoint."""
    out = np.full((len(o_a), 3), np.nan)
    for i in range(len(o_a)):
        A = np.stack([d_a[i], -d_b[i]], axis=1)
        st, *_ = np.linalg.lstsq(A, o_b[i] - o_a[i], rcond=None)
        out[i] = 0.5 * (o_a[i] + st[0] * d_a[i] + o_b[i] + st[1] * d_b[i])
    return out


def _features(img: np.ndarray, mask: np.ndarray | None, width: int):
    """(keypoints [M, 2] pixels of the full-size image, SIFT descriptors [M, 128]) of an [H, W, 3] 0..1 image."""
    import cv2

    h, w = img.shape[:2]
    scale = min(1.0, width / w)
    grey = cv2.cvtColor((np.clip(img, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    small = cv2.resize(grey, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA) if scale < 1 else grey
    m = None
    if mask is not None:
        m = (~_resized_mask(mask, small.shape)).astype(np.uint8) * 255      # features only off the mask
    kps, desc = cv2.SIFT_create(nfeatures=MAX_FEATURES, contrastThreshold=CONTRAST).detectAndCompute(small, m)
    if desc is None or not len(kps):
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    uv = (np.array([k.pt for k in kps], np.float64) + 0.5) / scale - 0.5     # pixel centres at integers
    return uv, desc


def match(fa, fb) -> tuple[np.ndarray, np.ndarray]:
    """(i [M], j [M]): the indices of the features ``fa`` and ``fb`` (_features) that pass the ratio test both ways
    (a's best in b, and b's best in a, is each other). The squared distances of every pair as |a|^2 + |b|^2 - 2 a.b
    (one float32 matrix product), each row's nearest two and each column's nearest in one parallel pass over it
    (match_reference is OpenCV's brute-force matcher, which took 0.15 s a pair of 3500-feature images, twice over
    every pair: a camera-only keyframe matches twelve; tested against it)."""
    (_, da), (_, db) = fa, fb
    if len(da) < 2 or len(db) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    da, db = np.ascontiguousarray(da, np.float32), np.ascontiguousarray(db, np.float32)
    g = da @ db.T                                       # [Na, Nb] float32
    best, d0, d1, col = _nearest(g, (da * da).sum(axis=1), (db * db).sum(axis=1))
    r = np.arange(len(da))
    # Lowe's ratio on the distances (not their squares); a distance below 0 is float32 rounding of 0
    ok = (np.sqrt(np.maximum(d0, 0)) < RATIO * np.sqrt(np.maximum(d1, 0))) & (col[best] == r)
    return r[ok].astype(np.int64), best[ok].astype(np.int64)


@njit(cache=True, parallel=True, nogil=True)
def _nearest(g, na, nb):
    """From g [Na, Nb] = a.b and the squared norms na [Na], nb [Nb]: each row's nearest column (the first of equals)
    and the two smallest squared distances, and each column's nearest row (the first of equals): rows in blocks,
    each block's column minima kept apart, then merged in block order."""
    n_a, n_b = g.shape
    blocks = min(n_a, 64)
    best = np.empty(n_a, np.int64)
    d0 = np.empty(n_a, np.float32)
    d1 = np.empty(n_a, np.float32)
    cmin = np.full((blocks, n_b), np.inf, np.float32)
    carg = np.zeros((blocks, n_b), np.int64)
    for b in numba.prange(blocks):
        for i in range(b * n_a // blocks, (b + 1) * n_a // blocks):
            m0, m1, j0 = np.float32(np.inf), np.float32(np.inf), 0
            for j in range(n_b):
                d = na[i] + nb[j] - np.float32(2.0) * g[i, j]
                if d < m0:
                    m1, m0, j0 = m0, d, j
                elif d < m1:
                    m1 = d
                if d < cmin[b, j]:
                    cmin[b, j], carg[b, j] = d, i
            best[i], d0[i], d1[i] = j0, m0, m1
    col = np.empty(n_b, np.int64)
    for j in numba.prange(n_b):
        m, a = cmin[0, j], carg[0, j]
        for b in range(1, blocks):
            if cmin[b, j] < m:
                m, a = cmin[b, j], carg[b, j]
        col[j] = a
    return best, d0, d1, col


def match_reference(fa, fb) -> tuple[np.ndarray, np.ndarray]:
    """match by OpenCV's brute-force matcher: a's two nearest in b (knnMatch), b's nearest in a."""
    import cv2

    (_, da), (_, db) = fa, fb
    if len(da) < 2 or len(db) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    ab = bf.knnMatch(da, db, k=2)
    best_ba = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(db, da, k=1) if m}
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in ab
             if len(m) == 2 and m[0].distance < RATIO * m[1].distance and best_ba.get(m[0].trainIdx) == m[0].queryIdx]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = np.array(pairs, np.int64).T
    return i, j


def _pair_points(cam, T, fa, p_cam, p_T, fb, pix: float) -> dict[int, tuple[np.ndarray, float]]:
    """{feature index in a: (its point [3] in the scene's frame, the rays' angle in degrees)} of the matches between
    a keyframe camera (cam, pose T, features fa) and a partner frame's (p_cam, p_T, fb) that pass the ray checks
    (module docstring)."""
    i, j = match(fa, fb)
    if not len(i):
        return {}
    oa, da = cam.pixel_rays(fa[0][i])
    ob, db = p_cam.pixel_rays(fb[0][j])
    oa, da = oa @ T[:3, :3].T + T[:3, 3], da @ T[:3, :3].T
    ob, db = ob @ p_T[:3, :3].T + p_T[:3, 3], db @ p_T[:3, :3].T
    ok = np.isfinite(da).all(axis=1) & np.isfinite(db).all(axis=1)
    i, oa, da, ob, db = i[ok], oa[ok], da[ok], ob[ok], db[ok]
    pts, gap, st, ang = triangulate(oa, da, ob, db)
    good = ((ang >= MIN_PARALLAX_DEG) & (st > 0.5).all(axis=1)
            & (gap <= MAX_RAY_GAP_PX * pix * st.min(axis=1)) & np.isfinite(pts).all(axis=1))
    return {int(a): (p, float(g)) for a, p, g in zip(i[good], pts[good], ang[good])}


def box_mask(cam, T: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray]], size: tuple[int, int],
             grow_px: int = BOX_GROW_PX) -> np.ndarray:
    """[h, w] bool at ``size`` (w, h: the camera's image resized): the pixels where camera ``cam`` (ego frame; the
    ego at pose ``T``, ego -> the scene's frame) sees one of ``boxes`` (each (scene frame -> box [4, 4], half-sizes
    [3] metres): the convex hull of the box's projected surface points (BOX_SAMPLES a side; those behind the
    camera left out), grown by ``grow_px``."""
    import cv2

    w, h = size
    out = np.zeros((h, w), np.uint8)
    t = np.linspace(-1.0, 1.0, BOX_SAMPLES)
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[np.abs(grid).max(axis=1) == 1.0]                 # the box's surface
    sx, sy = w / cam.width, h / cam.height
    Ti = np.linalg.inv(T)
    for inv, half in boxes:
        box_to_scene = np.linalg.inv(np.asarray(inv, np.float64))
        pts = grid * np.asarray(half, np.float64)
        pts = pts @ box_to_scene[:3, :3].T + box_to_scene[:3, 3]
        pts = pts @ Ti[:3, :3].T + Ti[:3, 3]                       # the keyframe's ego frame
        uv, _, front = cam.project(pts)
        uv = uv[front & np.isfinite(uv).all(axis=1)]
        if len(uv) < 3:
            continue
        uv = np.clip(uv * (sx, sy), -4 * w, 4 * w).astype(np.float32)
        cv2.fillConvexPoly(out, cv2.convexHull(uv).astype(np.int32), 1)
    if grow_px > 0 and out.any():
        out = cv2.dilate(out, np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8))
    return out > 0


def stereo_points(cameras: Sequence, images: Sequence[np.ndarray], T: np.ndarray, partners: Sequence[tuple],
                  masks: Sequence[np.ndarray | None] | None = None,
                  boxes: Sequence[tuple[np.ndarray, np.ndarray]] | None = None, width: int | None = None,
                  tracked: bool = False) -> np.ndarray:
    """[P, 3] metres, the keyframe's ego frame: points triangulated between the keyframe's cameras (runtime.camera
    Camera, ego frame), their ``images`` ([H, W, 3] 0..1) and its pose ``T`` (ego -> the scene's frame), and each
    partner frame's (cameras, images, pose) in ``partners`` (module docstring); ``masks`` each keyframe camera's ego
    body (True: the ego's own, no features there) or None; ``boxes``: the objects that move, at the keyframe (each
    (scene frame -> box [4, 4], half-sizes [3]), runtime.drive.moving_boxes): no features where a camera sees one,
    and no point inside one. ``tracked``: the drive's tracks name every object that moves, so a feature matched
    with one partner only is kept too (else it must be found with both, its two points agreeing: what moves without
    a track parts)."""
    width = STEREO_WIDTH if width is None else width
    masks = list(masks) if masks is not None else [None] * len(cameras)
    boxes = list(boxes or [])
    out = []
    for c, (cam, img, body) in enumerate(zip(cameras, images, masks)):
        mask = body
        if boxes:
            scale = min(1.0, width / cam.width)
            mask = box_mask(cam, T, boxes, (round(cam.width * scale), round(cam.height * scale)))
            if body is not None:
                mask |= _resized_mask(body, mask.shape)
        fa = _features(img, mask, width)
        pix = 1.0 / max(1e-9, float(cam.K[0][0]) * min(1.0, width / cam.width))    # radians a resized pixel
        found = [_pair_points(cam, T, fa, p_cams[c], p_T, _features(p_imgs[c], body, width), pix)
                 for p_cams, p_imgs, p_T in partners]
        if len(found) < 2 and not tracked:      # one partner: nothing tells a still surface from one that moved
            continue
        both = found[0].keys() & found[1].keys() if len(found) == 2 else set()
        # a feature found with both partners: the two points agree for a still surface; a moving one (a car
        # without a track) moved between the three frames, and its two points part
        for i in both:
            p, q = found[0][i][0], found[1][i][0]
            dist = np.linalg.norm(0.5 * (p + q) - T[:3, 3])
            if np.linalg.norm(p - q) <= AGREE * dist:
                out.append(0.5 * (p + q))
        if tracked:
            out.extend(p for f in found for i, (p, ang) in f.items() if i not in both and ang >= MIN_PARALLAX_ONE_DEG)
    pts = np.array(out, np.float64).reshape(-1, 3)
    if boxes and len(pts):
        pts = pts[~inside_boxes(pts, boxes)]
    Ti = np.linalg.inv(T)
    return (pts @ Ti[:3, :3].T + Ti[:3, 3]).astype(np.float64)


def _resized_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[h, w] bool: ``mask`` resized to ``shape`` (h, w), nearest."""
    import cv2

    if mask.shape == tuple(shape):
        return mask.astype(bool)
    return cv2.resize(mask.astype(np.uint8), shape[::-1], interpolation=cv2.INTER_NEAREST) > 0


__all__ = ["MIN_PARALLAX_DEG", "STEREO_BASELINE_M", "STEREO_WIDTH", "match", "partner_frames", "stereo_points",
           "triangulate", "triangulate_reference"]
