"""Depth from the motion between a drive's frames, for keyframes without a LiDAR sweep (docs/inference.md, "Stereo
between frames").

A moving camera sees the same surface from two places: the baseline between a keyframe and a frame about
STEREO_BASELINE_M away (before and after it) makes a stereo pair with known poses. Each camera of the keyframe is
matched with the same camera of each partner frame (SIFT features on images resized to STEREO_WIDTH pixels, Lowe's
ratio test), and each match's two rays (Camera.pixel_rays: any lens) are triangulated at the midpoint of their
closest points. A point is kept when the rays meet (closest distance within MAX_RAY_GAP_PX pixels of the resized
image, seen from either camera), cross at MIN_PARALLAX_DEG or more (a smaller angle leaves the depth undetermined:
the error grows as the distance over the parallax), lie in front of both cameras and outside the boxes of the
tracked objects that move (whose features moved between the frames), and a feature must be found with both
partners, its two points within AGREE of its distance (what moves without a track parts): a keyframe without a
partner on each side (the drive's ends) gets no stereo points. The points, in the keyframe's ego frame, go
where a LiDAR sweep would (Reconstructor.keyframe's ``lidar``): the model's depth is scaled to them per camera
(runtime.lidar.fuse_depth), and detail cells sit on them, so a camera-only drive is not held back by single-image
depth. They are sparse and less exact than a LiDAR's, so they never carve another keyframe's cells
(runtime.drive._carve_pair). An ego that stands still has no partner frame and no stereo points."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

STEREO_BASELINE_M = 1.0     # the partner frames: the nearest frames at least this far from the keyframe, each side
STEREO_WIDTH = 960          # features are found on images resized to this width (2x faster than 1920, enough texture)
MIN_PARALLAX_DEG = 2.0      # rays that cross at a smaller angle leave the depth undetermined (at 2 degrees and a
                            # pixel of matching error, the depth is good to ~6 % of the distance)
MAX_RAY_GAP_PX = 1.5        # the rays' closest distance, as pixels of the resized image at the point's distance
RATIO = 0.75                # Lowe's ratio test: the best match clearly better than the second
AGREE = 0.03                # a feature matched with both partners: its two points within this fraction of its range
MAX_FEATURES = 8000         # per image
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
        m = (cv2.resize(mask.astype(np.uint8), small.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0)
        m = (~m).astype(np.uint8) * 255                     # features only off the ego's body
    kps, desc = cv2.SIFT_create(nfeatures=MAX_FEATURES, contrastThreshold=CONTRAST).detectAndCompute(small, m)
    if desc is None or not len(kps):
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    uv = (np.array([k.pt for k in kps], np.float64) + 0.5) / scale - 0.5     # pixel centres at integers
    return uv, desc


def match(fa, fb) -> tuple[np.ndarray, np.ndarray]:
    """(i [M], j [M]): the indices of the features ``fa`` and ``fb`` (_features) that pass the ratio test both ways
    (a's best in b, and b's best in a, is each other)."""
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


def _pair_points(cam, T, fa, p_cam, p_T, fb, pix: float) -> dict[int, np.ndarray]:
    """{feature index in a: its point [3] in the scene's frame} of the matches between a keyframe camera (cam, pose
    T, features fa) and a partner frame's (p_cam, p_T, fb) that pass the ray checks (module docstring)."""
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
    return dict(zip(i[good].tolist(), pts[good]))


def stereo_points(cameras: Sequence, images: Sequence[np.ndarray], T: np.ndarray, partners: Sequence[tuple],
                  masks: Sequence[np.ndarray | None] | None = None,
                  moving: Callable[[np.ndarray], np.ndarray] | None = None, width: int | None = None) -> np.ndarray:
    """[P, 3] metres, the keyframe's ego frame: points triangulated between the keyframe's cameras (runtime.camera
    Camera, ego frame), their ``images`` ([H, W, 3] 0..1) and its pose ``T`` (ego -> the scene's frame), and each
    partner frame's (cameras, images, pose) in ``partners`` (module docstring); ``masks`` each keyframe camera's ego
    body (True: the ego's own, no features there) or None; ``moving`` maps points [P, 3] (the scene's frame) to [P]
    bool, True inside a moving object at the keyframe (runtime.drive.inside_boxes of its moving_boxes): those are
    dropped."""

    width = STEREO_WIDTH if width is None else width
    masks = list(masks) if masks is not None else [None] * len(cameras)
    out = []
    for c, (cam, img, mask) in enumerate(zip(cameras, images, masks)):
        fa = _features(img, mask, width)
        pix = 1.0 / max(1e-9, float(cam.K[0][0]) * min(1.0, width / cam.width))    # radians a resized pixel
        found = [_pair_points(cam, T, fa, p_cams[c], p_T, _features(p_imgs[c], mask, width), pix)
                 for p_cams, p_imgs, p_T in partners]
        if len(found) < 2:              # one partner: nothing tells a still surface from one that moved
            continue
        # a feature found with both partners: the two points agree for a still surface; a moving one (a car
        # without a track) moved between the three frames, and its two points part
        for i in found[0].keys() & found[1].keys():
            p, q = found[0][i], found[1][i]
            dist = np.linalg.norm(0.5 * (p + q) - T[:3, 3])
            if np.linalg.norm(p - q) <= AGREE * dist:
                out.append(0.5 * (p + q))
    pts = np.array(out, np.float64).reshape(-1, 3)
    if moving is not None and len(pts):
        pts = pts[~moving(pts)]
    Ti = np.linalg.inv(T)
    return (pts @ Ti[:3, :3].T + Ti[:3, 3]).astype(np.float64)


__all__ = ["MIN_PARALLAX_DEG", "STEREO_BASELINE_M", "STEREO_WIDTH", "match", "partner_frames", "stereo_points",
           "triangulate", "triangulate_reference"]
