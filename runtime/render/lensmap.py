"""The fast renderer's lens maps (numba, float64): for a camera-frame point, its pixel through the camera's lens
(runtime.lenses, the float64 numpy definition) and the 2x3 Jacobian of that map, which the projection uses as
EWA's local linearisation; plus the image-circle test of the fisheye and f-theta models.

A camera is passed to the kernels as a model code and a float64 parameter array `lp` (`lens_params`):
- 0 pinhole, 1 equirectangular (no lens; lp unused);
- 2 opencv: lp = k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4, r2_valid (the squared normalised radius up to which the
  distortion is unfolded: `opencv_valid_r2`);
- 3 opencv_fisheye: lp = k1 k2 k3 k4, max_angle (rad), circle (theta_d at max_angle);
- 4 ftheta: lp = max_angle (rad), circle (px), c, d, e, ref (0: angle_to_pixeldist is the reference polynomial,
  1: pixeldist_to_angle), n, then the reference polynomial's n coefficients (constant term first); with ref 1 then
  M, h and the tables R(k h), R'(k h), k = 0..M (FTHETA_TABLE intervals over [0, max_angle], from
  runtime.lenses.poly_solve): R(theta) is the inverse of the reference polynomial, solved from the table's cubic
  Hermite interpolant (error ~ h^4 |R^(4)| / 384, ~1e-12 px for real lenses) with one Newton step (quadratic: to
  rounding), and by runtime.lenses.poly_solve's bracketed Newton iteration where that step's residual is not at
  rounding (a lens whose polynomial nearly turns within max_angle). Measured: 25 ns an inverse against 55-64 ns
  for the bracketed solve alone (one thread, the f-theta of benchmarks/lens_bench.py).

Jacobians (analytic): opencv: diag(fx, fy) . D(x', y') . P, with D the distortion's 2x2 Jacobian on the normalised
coordinates (x', y') = (x/z, y/z) and P = d(x', y')/d(x, y, z); as for the pinhole (gsplat's clamp), D and P's z
column are evaluated at (x', y') clamped to the clamp box (`opencv_limits`: the undistorted image plus 0.3 of its
half-extent beyond each side), so an opencv lens with zero coefficients gives exactly the pinhole's Jacobian.
Fisheye and f-theta: the pixel is (cx, cy) + A R(theta) n, n = (x, y)/rho the azimuth's unit vector, R the radial
pixel-distance function (fisheye: theta_d, A = diag(fx, fy); f-theta: the polynomial r(theta) or the inverse of
theta(r), A = [[c, d], [e, 1]]); with r2 = x^2 + y^2 + z^2,
    d(R n)/d(x, y) = R' z / r2 . n n^T + R / rho . (I - n n^T),   d(R n)/dz = -R' rho / r2 . n,
exact for every rho > 0 (no cancellation: R / rho is a ratio of two accurate numbers); on the axis (rho = 0, z > 0)
the limit R'(0) / z . I, z column 0.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from ..lenses import _opencv_with_jacobian

PINHOLE, EQUIRECT, OPENCV, FISHEYE, FTHETA = 0, 1, 2, 3, 4
MODEL_CODES = {"opencv": OPENCV, "opencv_fisheye": FISHEYE, "ftheta": FTHETA}
OPENCV_SCAN_MAX = 1.0e3   # normalised radius scanned for the opencv fold (89.94 degrees from the axis)
FTHETA_TABLE = 1024       # intervals of the f-theta inverse's Hermite table (2 x 8 KB)


@functools.lru_cache(maxsize=64)
def opencv_valid_r2(coeffs: tuple[float, ...]) -> float:
    """The squared normalised radius r^2 = (x/z)^2 + (y/z)^2 within which an opencv lens's distortion is
    unfolded: along 128 azimuths, the radius before the first of 6000 geometric samples in (0, OPENCV_SCAN_MAX]
    where the distortion's Jacobian determinant is <= 0 (runtime.lenses.opencv_undistort refuses pixels there:
    the map folds back, so points beyond would land on the image in the wrong place) or the rational term's
    denominator is <= 0; the smallest over the azimuths. Points beyond are culled."""
    r = np.geomspace(1e-4, OPENCV_SCAN_MAX, 6000)
    phi = np.linspace(0.0, 2 * np.pi, 128, endpoint=False)
    x, y = r[:, None] * np.cos(phi)[None], r[:, None] * np.sin(phi)[None]
    k4, k5, k6 = coeffs[5], coeffs[6], coeffs[7]
    with np.errstate(all="ignore"):
        _, _, j11, j12, j21, j22 = _opencv_with_jacobian(x, y, coeffs)
        r2 = x * x + y * y
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        bad = ~(j11 * j22 - j12 * j21 > 0) | ~(den > 0)
    first = np.where(bad.any(axis=0), bad.argmax(axis=0), len(r))   # per azimuth: the first bad sample
    k = int(first.min())
    return 0.0 if k == 0 else float(r[k - 1] ** 2)


def opencv_limits(camera) -> tuple[float, float, float, float]:
    """The Jacobian clamp box of an opencv lens on (x/z, y/z), as projection.pinhole_limits for the pinhole: the
    undistorted normalised coordinates of the image's border (u in [0, W], v in [0, H], 64 samples a side, where
    the lens unprojects them) plus 0.3 of the image's half-extent beyond each side. Returns (lim_x_neg, lim_x_pos,
    lim_y_neg, lim_y_pos)."""
    from ..lenses import opencv_undistort
    from .projection import pinhole_limits

    K, W, H = camera.K, camera.width, camera.height
    t = np.linspace(0.0, 1.0, 64)
    uv = np.concatenate([np.stack([t * W, np.zeros_like(t)], 1), np.stack([t * W, np.full_like(t, H)], 1),
                         np.stack([np.zeros_like(t), t * H], 1), np.stack([np.full_like(t, W), t * H], 1)])
    xy, ok = opencv_undistort(np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], 1),
                              camera.distortion.coeffs)
    if not ok.any():
        return pinhole_limits(camera)
    xs, ys = xy[ok, 0], xy[ok, 1]
    xn, xp, yn, yp = max(-xs.min(), 0.0), max(xs.max(), 0.0), max(-ys.min(), 0.0), max(ys.max(), 0.0)
    mx, my = 0.3 * 0.5 * (xn + xp), 0.3 * 0.5 * (yn + yp)
    return xn + mx, xp + mx, yn + my, yp + my


def lens_params(camera) -> tuple[int, np.ndarray]:
    """(model code, lp float64 array) of a runtime.camera.Camera for the kernels (module docstring)."""
    if camera.is_equirect:
        return EQUIRECT, np.zeros(1)
    lens = camera.distortion
    if lens is None:
        return PINHOLE, np.zeros(1)
    if lens.model == "opencv":
        return OPENCV, np.array([*lens.coeffs, opencv_valid_r2(tuple(lens.coeffs))], np.float64)
    if lens.model == "opencv_fisheye":
        return FISHEYE, np.array([*lens.coeffs, lens.max_angle, lens.circle_limit], np.float64)
    ref = 0 if lens.reference_poly == "angle_to_pixeldist" else 1
    poly = lens.angle_to_pixeldist_poly if ref == 0 else lens.pixeldist_to_angle_poly
    head = [lens.max_angle, lens.circle_limit, *lens.linear_cde, ref, len(poly), *poly]
    if ref == 0:
        return FTHETA, np.array(head, np.float64)
    return FTHETA, np.concatenate([head, _ftheta_table(lens)])


@functools.lru_cache(maxsize=64)
def _ftheta_table(lens) -> np.ndarray:
    """[M, h, R(k h) for k = 0..M, R'(k h) for k = 0..M] of a pixeldist_to_angle f-theta lens (lp's tail)."""
    from ..lenses import poly_derivative, poly_eval, poly_solve

    poly = lens.pixeldist_to_angle_poly
    M = FTHETA_TABLE
    theta = np.linspace(0.0, lens.max_angle, M + 1)
    R = poly_solve(poly, theta, lens.circle_limit)
    dR = 1.0 / poly_eval(poly_derivative(poly), R)
    return np.concatenate([[M, lens.max_angle / M], R, dR])


# ------------------------------------------------------------------------------------------------ polynomials
@njit(inline="always")
def _poly(lp, o, n, x):
    """sum_i lp[o + i] x^i (Horner, as runtime.lenses.poly_eval)."""
    y = lp[o + n - 1]
    for i in range(n - 2, -1, -1):
        y = y * x + lp[o + i]
    return y


@njit(inline="always")
def _dpoly(lp, o, n, x):
    """d/dx sum_i lp[o + i] x^i."""
    if n < 2:
        return 0.0
    y = (n - 1) * lp[o + n - 1]
    for i in range(n - 2, 0, -1):
        y = y * x + i * lp[o + i]
    return y


@njit(cache=True, nogil=True)
def poly_solve1(lp, o, n, y, x_max):
    """x in [0, x_max] with poly(x) = y for a polynomial increasing there: runtime.lenses.poly_solve for one
    value (Newton's method inside a shrinking bracket, bisection where a step leaves it; the same steps and stop
    rule, so both agree to rounding)."""
    lo = 0.0
    hi = x_max
    x = min(max(y / lp[o + 1], lo), hi)
    for _ in range(200):
        f = _poly(lp, o, n, x) - y
        if f <= 0.0:
            lo = x
        if f >= 0.0:
            hi = x
        step = x - f / _dpoly(lp, o, n, x)
        if not (step > lo and step < hi):
            step = 0.5 * (lo + hi)
        done = abs(step - x) <= 4e-16 * max(1.0, abs(x))
        x = step
        if done:
            break
    return x


@njit(inline="always")
def _radial(model, lp, theta):
    """(R, dR/dtheta): the radial pixel-distance function of a fisheye (theta_d, normalised) or f-theta (px)."""
    if model == FISHEYE:
        t2 = theta * theta
        R = theta * (1.0 + t2 * (lp[0] + t2 * (lp[1] + t2 * (lp[2] + t2 * lp[3]))))
        dR = 1.0 + t2 * (3.0 * lp[0] + t2 * (5.0 * lp[1] + t2 * (7.0 * lp[2] + t2 * 9.0 * lp[3])))
        return R, dR
    n = int(lp[6])
    if lp[5] == 0.0:
        return _poly(lp, 7, n, theta), _dpoly(lp, 7, n, theta)
    R = _ftheta_inverse(lp, n, theta)
    return R, 1.0 / _dpoly(lp, 7, n, R)


@njit(inline="always")
def _ftheta_inverse(lp, n, theta):
    """R with poly(R) = theta (pixeldist_to_angle f-theta, module docstring): the Hermite table's value, one
    Newton step, the bracketed solve where the residual is not at rounding."""
    o = 7 + n
    M = int(lp[o])
    h = lp[o + 1]
    t = theta / h
    k = min(max(int(t), 0), M - 1)
    s = t - k
    r0 = lp[o + 2 + k]
    r1 = lp[o + 3 + k]
    d0 = lp[o + 3 + M + k] * h
    d1 = lp[o + 4 + M + k] * h
    s2 = s * s
    s3 = s2 * s
    R = (2 * s3 - 3 * s2 + 1) * r0 + (s3 - 2 * s2 + s) * d0 + (3 * s2 - 2 * s3) * r1 + (s3 - s2) * d1
    R -= (_poly(lp, 7, n, R) - theta) / _dpoly(lp, 7, n, R)
    if abs(_poly(lp, 7, n, R) - theta) <= 1e-15 * max(1.0, theta) and R >= 0.0 and R <= lp[1]:
        return R
    return poly_solve1(lp, 7, n, theta, lp[1])


# ------------------------------------------------------------------------------------------------ the maps
@njit(cache=True, nogil=True)
def lens_project(model, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp, x, y, z):
    """Camera-frame point (x, y, z) -> (ok, u, v, j00, j01, j02, j10, j11, j12): its pixel through the lens
    (model 2, 3 or 4; runtime.lenses.Lens.project) and the Jacobian d(u, v)/d(x, y, z) (module docstring).
    Not ok: opencv: z <= 0 or beyond the fold radius (lp[12]); fisheye / f-theta: beyond max_angle, or on the
    axis behind the camera (theta = pi, no azimuth)."""
    if model == OPENCV:
        if not (z > 0.0):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        sx = x / z
        sy = y / z
        r2v = lp[12]
        if not (sx * sx + sy * sy <= r2v):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        xd, yd, _, _, _, _ = _opencv_distort(lp, sx, sy)
        sxc = min(max(sx, -lxn), lxp)
        syc = min(max(sy, -lyn), lyp)
        rc = sxc * sxc + syc * syc
        if rc > r2v:                               # keep the clamped point inside the unfolded disc too
            f = math.sqrt(r2v / rc)
            sxc *= f
            syc *= f
        _, _, d00, d01, d10, d11 = _opencv_distort(lp, sxc, syc)
        iz = 1.0 / z
        return (True, fx * xd + cx, fy * yd + cy,
                fx * d00 * iz, fx * d01 * iz, -fx * (d00 * sxc + d01 * syc) * iz,
                fy * d10 * iz, fy * d11 * iz, -fy * (d10 * sxc + d11 * syc) * iz)
    if model == FISHEYE:
        a00, a01, a10, a11 = fx, 0.0, 0.0, fy
        amax = lp[4]
    else:
        a00, a01, a10, a11 = lp[2], lp[3], lp[4], 1.0
        amax = lp[0]
    rho = math.sqrt(x * x + y * y)       # (not math.hypot: slower, and its overflow guard is not needed here)
    theta = math.atan2(rho, z)
    if not (theta <= amax):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if rho == 0.0:
        if not (z > 0.0):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        _, dR = _radial(model, lp, 0.0)
        s = dR / z
        return True, cx, cy, a00 * s, a01 * s, 0.0, a10 * s, a11 * s, 0.0
    R, dR = _radial(model, lp, theta)
    nx = x / rho
    ny = y / rho
    r2 = rho * rho + z * z
    a = dR * z / r2
    b = R / rho
    w00 = a * nx * nx + b * (1.0 - nx * nx)
    w01 = (a - b) * nx * ny
    w11 = a * ny * ny + b * (1.0 - ny * ny)
    c = -dR * rho / r2
    w02 = c * nx
    w12 = c * ny
    ox = R * nx
    oy = R * ny
    return (True, a00 * ox + a01 * oy + cx, a10 * ox + a11 * oy + cy,
            a00 * w00 + a01 * w01, a00 * w01 + a01 * w11, a00 * w02 + a01 * w12,
            a10 * w00 + a11 * w01, a10 * w01 + a11 * w11, a10 * w02 + a11 * w12)


@njit(inline="always")
def _opencv_distort(lp, x, y):
    """OpenCV's rational + tangential + thin-prism distortion of normalised (x, y) and its 2x2 Jacobian:
    (xd, yd, d00, d01, d10, d11), the expressions of runtime.lenses._opencv_with_jacobian."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (lp[0], lp[1], lp[2], lp[3], lp[4], lp[5], lp[6], lp[7],
                                                      lp[8], lp[9], lp[10], lp[11])
    xx = x * x
    yy = y * y
    xy = x * y
    r2 = xx + yy
    n = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = n / d
    dradial = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * d - n * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / (d * d)
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * xx) + r2 * (s1 + r2 * s2)
    yd = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy + r2 * (s3 + r2 * s4)
    sx = s1 + 2 * s2 * r2
    sy = s3 + 2 * s4 * r2
    cross = 2 * xy * dradial + 2 * p1 * x + 2 * p2 * y
    j11 = radial + 2 * xx * dradial + 2 * p1 * y + 6 * p2 * x + 2 * x * sx
    j22 = radial + 2 * yy * dradial + 6 * p1 * y + 2 * p2 * x + 2 * y * sy
    return xd, yd, j11, cross + 2 * y * sx, cross + 2 * x * sy, j22


# ------------------------------------------------------------------------------------------------ image circle
@njit(inline="always")
def outside_circle(model, lp, fx, fy, cx, cy, u, v):
    """Pixel (u, v) lies outside a fisheye's / f-theta's image circle of max_angle (no ray reaches it: the test
    runtime.lenses.Lens.unproject makes, same expressions). False for the other models."""
    if model == FISHEYE:
        return not (math.hypot((u - cx) / fx, (v - cy) / fy) <= lp[5] * (1 + 1e-12))
    if model == FTHETA:
        c, d, e = lp[2], lp[3], lp[4]
        det = c - d * e
        ox = u - cx
        oy = v - cy
        return not (math.hypot((ox - d * oy) / det, (c * oy - e * ox) / det) <= lp[1] * (1 + 1e-12))
    return False


@njit(cache=True, parallel=True, nogil=True)
def circle_mask(model, lp, fx, fy, cx, cy, height, width):
    """[H, W] bool: the pixels inside the image circle (all True for the models without one)."""
    out = np.ones((height, width), np.bool_)
    for y in prange(height):
        for x in range(width):
            out[y, x] = not outside_circle(model, lp, fx, fy, cx, cy, np.float64(x), np.float64(y))
    return out


@njit(cache=True, parallel=True, nogil=True)
def clear_outside_circle(model, lp, fx, fy, cx, cy, bg, rgb, alpha, depth, last, t_final):
    """After the raster: the pixels outside the image circle show the background alone (alpha 0, depth 0, no
    Gaussian blended), as the reference, whose rays there are NaN, draws them. Rows that lie wholly inside the
    circle are skipped after testing their two ends (the circle is convex in each row)."""
    H, W = alpha.shape
    for y in prange(H):
        yf = np.float64(y)
        if not outside_circle(model, lp, fx, fy, cx, cy, 0.0, yf) and \
                not outside_circle(model, lp, fx, fy, cx, cy, np.float64(W - 1), yf):
            continue
        for x in range(W):
            if outside_circle(model, lp, fx, fy, cx, cy, np.float64(x), yf):
                rgb[y, x, 0] = bg[y, x, 0]
                rgb[y, x, 1] = bg[y, x, 1]
                rgb[y, x, 2] = bg[y, x, 2]
                alpha[y, x] = 0.0
                depth[y, x] = 0.0
                last[y, x] = -1
                t_final[y, x] = 1.0


def image_circle(camera) -> np.ndarray | None:
    """[H, W] bool of the pixels a fisheye / f-theta camera images (inside its circle of max_angle); None for
    the cameras without a circle (pinhole, opencv, equirectangular)."""
    model, lp = lens_params(camera)
    if model not in (FISHEYE, FTHETA):
        return None
    K = camera.K
    return circle_mask(model, lp, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), camera.height,
                       camera.width)
