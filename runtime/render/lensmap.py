"""The fast renderer's lens maps (numba, float64): for a camera-frame point, its pixel through the camera's lens
(runtime.lenses, the float64 numpy definition) and the 2x3 Jacobian of that map, which the projection uses as
EWA's local linearisation (fisheye, f-theta) or for the low-pass's shape (opencv); the image-circle test of the
fisheye and f-theta models; and an opencv camera's undistorted image plane (`opencv_pixel_map`), on which the
raster measures each pixel's ray against each Gaussian's tangent plane (`opencv_plane_footprint`).

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
coordinates (x', y') = (x/z, y/z) and P = d(x', y')/d(x, y, z), at the point itself (no clamp: an opencv footprint
is not linearised through the lens, see opencv_plane_footprint; the clamp box of gsplat's pinhole, carried through
a strong lens, evaluated D where it magnifies many times more than anywhere on the image).
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
from typing import NamedTuple

import numpy as np
from numba import prange

from ..lenses import _opencv_with_jacobian, opencv_distortion_terms
from ..numba_cache import njit

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
def lens_project(model, lp, fx, fy, cx, cy, x, y, z):
    """Camera-frame point (x, y, z) -> (ok, u, v, j00, j01, j02, j10, j11, j12): its pixel through the lens
    (model 2, 3 or 4; runtime.lenses.Lens.project) and the Jacobian d(u, v)/d(x, y, z) at the point (module
    docstring). Not ok: opencv: z <= 0 or beyond the fold radius (lp[12]); fisheye / f-theta: beyond max_angle,
    or on the axis behind the camera (theta = pi, no azimuth). The renderer splats fisheye and f-theta
    Gaussians with this Jacobian; for opencv it gives the low-pass's shape (opencv_plane_footprint)."""
    if model == OPENCV:
        if not (z > 0.0):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        sx = x / z
        sy = y / z
        if not (sx * sx + sy * sy <= lp[12]):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        xd, yd, d00, d01, d10, d11 = _opencv_distort(lp, sx, sy)
        iz = 1.0 / z
        return (True, fx * xd + cx, fy * yd + cy,
                fx * d00 * iz, fx * d01 * iz, -fx * (d00 * sx + d01 * sy) * iz,
                fy * d10 * iz, fy * d11 * iz, -fy * (d10 * sx + d11 * sy) * iz)
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
def _tangent_frame(x, y, z):
    """(r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z): the distance of a camera-frame point with z > 0, its unit
    direction m and an orthonormal frame e1 = (m_z, 0, -m_x) / |.|, e2 = m x e1 of the plane tangent to the unit
    sphere there (any frame gives the same footprint; this one needs no case for the axis)."""
    r = math.sqrt(x * x + y * y + z * z)
    mx = x / r
    my = y / r
    mz = z / r
    h = math.sqrt(mx * mx + mz * mz)
    return r, mx, my, mz, mz / h, 0.0, -mx / h, -mx * my / h, h, -my * mz / h


@njit(inline="always")
def _ratio_range(mx, mz, a0, a1, c0, c1):
    """(lo, hi): the range of f(w) = (mx + a.w) / (mz + c.w) over the points of the unit disc |w| <= 1 with
    mz + c.w > 0 (mz > 0): the plane coordinate x/z of the points m + N w in front of the camera of an ellipse on a
    tangent plane (a and c two rows of N). A finite bound is where a level line {f = t} touches the circle: a root
    of q(t) = |a - t c|^2 - (t mz - mx)^2 = -(al t^2 - 2 be t + ga). Where the disc stays in front (al =
    mz^2 - |c|^2 > 0) both roots; else f is unbounded next to the chord c.w = -mz where the numerator is > 0
    (above) or < 0 (below) somewhere on it, and the remaining bound (if any) is the root beyond (q <= 0 outside
    the roots there)."""
    cc = c0 * c0 + c1 * c1
    al = mz * mz - cc
    be = mx * mz - (a0 * c0 + a1 * c1)
    ga = mx * mx - (a0 * a0 + a1 * a1)
    disc = be * be - al * ga
    if al > 0.0:
        sq = math.sqrt(max(disc, 0.0))
        return (be - sq) / al, (be + sq) / al
    if not (al < 0.0 and disc >= 0.0):
        return -math.inf, math.inf
    k = -mz / cc                          # the chord: w0 = k c, half-length h along u = (-c1, c0) / |c|
    h = math.sqrt(max(1.0 - mz * mz / cc, 0.0))
    mid = mx + k * (a0 * c0 + a1 * c1)
    half = abs(h * (a1 * c0 - a0 * c1) / math.sqrt(cc))
    above = mid + half >= 0.0
    below = mid - half <= 0.0
    if above and below:
        return -math.inf, math.inf
    sq = math.sqrt(disc)
    if above:
        return (be - sq) / al, math.inf
    return -math.inf, (be + sq) / al


@njit(inline="always")
def _plane_dl(x, y, z, j00, j01, j02, j10, j11, j12):
    """(r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z, d00, d01, d10, d11): _tangent_frame and the lens's
    differential DL = d(pixel)/dg = |p| J [e1 e2] (J: lens_project's exact Jacobian at p)."""
    r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z = _tangent_frame(x, y, z)
    return (r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z,
            r * (j00 * e1x + j01 * e1y + j02 * e1z), r * (j00 * e2x + j01 * e2y + j02 * e2z),
            r * (j10 * e1x + j11 * e1y + j12 * e1z), r * (j10 * e2x + j11 * e2y + j12 * e2z))


@njit(inline="always")
def opencv_plane_footprint(x, y, z, j00, j01, j02, j10, j11, j12, c00, c01, c11, fx, fy):
    """An opencv camera's footprint of a Gaussian with camera-frame mean (x, y, z) (z > 0), as the reference
    (reference.py) defines it: on the plane tangent to the unit sphere at the mean's direction m (frame e1, e2), a
    ray d has gnomonic coordinates g = (d.e1, d.e2) / (d.m), and power = 1/2 (DL g)^T cov2^-1 (DL g), DL = d(pixel)
    / dg = |mean| J [e1 e2] the lens's differential (J: lens_project's exact Jacobian at the mean), cov2 (c00, c01,
    c11) = J Sigma J^T + low_pass I. With 1/2 DL^T cov2^-1 DL = L^T L (Cholesky) and A = L00 e1 + L01 e2, B = L11 e2:
    power = ((A.d)^2 + (B.d)^2) / (m.d)^2. For a pixel at (X, Y) on the undistorted image plane (pixels: fx x/z
    + cx, fy y/z + cy), offset (dx, dy) from the mean's (fx x/z + cx, fy y/z + cy), d = (x/z + dx/fx, y/z +
    dy/fy, 1) and A.m = B.m = 0, so
        power = ((a0 dx + a1 dy)^2 + (b0 dx + b1 dy)^2) / (1 + n0 dx + n1 dy)^2,
    a0 = A_x / (fx c), a1 = A_y / (fy c), b0, b1 alike, c = m.(x/z, y/z, 1) = |mean| / z, n0 = m_x / (fx c) =
    (x/z) / (1 + (x/z)^2 + (y/z)^2) / fx, n1 alike (plane_weights; rays with 1 + n.d <= 0 lie 90 degrees or more
    from the mean and see none of it). Returns (ok, a0, a1, b0, b1), not ok where DL or cov2 is singular."""
    r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z, d00, d01, d10, d11 = _plane_dl(x, y, z, j00, j01, j02, j10, j11,
                                                                                j12)
    det = c00 * c11 - c01 * c01
    if not (d00 * d11 - d01 * d10 != 0.0 and det > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0
    q00 = c11 / det
    q01 = -c01 / det
    q11 = c00 / det
    t00 = q00 * d00 + q01 * d10          # cov2^-1 DL
    t01 = q00 * d01 + q01 * d11
    t10 = q01 * d00 + q11 * d10
    t11 = q01 * d01 + q11 * d11
    h00 = 0.5 * (d00 * t00 + d10 * t10)  # 1/2 DL^T cov2^-1 DL
    h01 = 0.5 * (d00 * t01 + d10 * t11)
    h11 = 0.5 * (d01 * t01 + d11 * t11)
    l00 = math.sqrt(h00)
    l01 = h01 / l00
    l11 = math.sqrt(max(h11 - l01 * l01, 0.0))
    c = r / z
    return (True, (l00 * e1x + l01 * e2x) / (fx * c), (l00 * e1y + l01 * e2y) / (fy * c), l11 * e2x / (fx * c),
            l11 * e2y / (fy * c))


@njit(inline="always")
def opencv_plane_box(x, y, z, j00, j01, j02, j10, j11, j12, c00, c01, c11, ext, fx, fy, cx, cy):
    """(ok, X_lo, X_hi, Y_lo, Y_hi): the box on the undistorted image plane (pixels) of opencv_plane_footprint's
    footprint power <= ext^2 / 2, exact: on the tangent plane it is the ellipse g = ext F w, |w| <= 1, F F^T =
    (DL^T cov2^-1 DL)^-1 = DL^-1 cov2 DL^-T, whose points in front of the camera project to the box
    (_ratio_range; infinite on a side where it reaches the camera's z = 0 plane). Not ok where DL is singular."""
    r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z, d00, d01, d10, d11 = _plane_dl(x, y, z, j00, j01, j02, j10, j11,
                                                                                j12)
    ddet = d00 * d11 - d01 * d10
    if not (ddet != 0.0):
        return False, 0.0, 0.0, 0.0, 0.0
    i00 = d11 / ddet                     # DL^-1
    i01 = -d01 / ddet
    i10 = -d10 / ddet
    i11 = d00 / ddet
    s00 = i00 * (i00 * c00 + i01 * c01) + i01 * (i00 * c01 + i01 * c11)     # DL^-1 cov2 DL^-T
    s01 = i10 * (i00 * c00 + i01 * c01) + i11 * (i00 * c01 + i01 * c11)
    s11 = i10 * (i10 * c00 + i11 * c01) + i11 * (i10 * c01 + i11 * c11)
    f00 = math.sqrt(s00)
    f10 = s01 / f00
    f11 = math.sqrt(max(s11 - f10 * f10, 0.0))
    n00 = ext * (e1x * f00 + e2x * f10)  # N = ext [e1 e2] F, rows x, y, z
    n01 = ext * e2x * f11
    n10 = ext * (e1y * f00 + e2y * f10)
    n11 = ext * e2y * f11
    n20 = ext * (e1z * f00 + e2z * f10)
    n21 = ext * e2z * f11
    xlo, xhi = _ratio_range(mx, mz, n00, n01, n20, n21)
    ylo, yhi = _ratio_range(my, mz, n10, n11, n20, n21)
    return True, fx * xlo + cx, fx * xhi + cx, fy * ylo + cy, fy * yhi + cy


@njit(inline="always")
def opencv_plane_reach(x, y, z, j00, j01, j02, j10, j11, j12, s2, low_pass, k, fx, fy, cx, cy):
    """(ok, X_lo, X_hi, Y_lo, Y_hi): a bound of opencv_plane_box for any Gaussian with this mean and
    largest scale^2 s2 and any extent <= k sigmas: the disc g = k rho w on the tangent plane, rho^2 = s2 / |mean|^2
    + low_pass / sigma_min(DL)^2 >= the largest eigenvalue of DL^-1 cov2 DL^-T (DL^-1 J Sigma J^T DL^-T is the
    covariance on the tangent plane, <= s2 / |mean|^2). Not ok where DL is singular."""
    r, mx, my, mz, e1x, e1y, e1z, e2x, e2y, e2z, d00, d01, d10, d11 = _plane_dl(x, y, z, j00, j01, j02, j10, j11,
                                                                                j12)
    ddet = d00 * d11 - d01 * d10
    if not (ddet != 0.0):
        return False, 0.0, 0.0, 0.0, 0.0
    tr = d00 * d00 + d01 * d01 + d10 * d10 + d11 * d11     # DL^T DL: trace, determinant ddet^2
    lmax = 0.5 * (tr + math.sqrt(max(tr * tr - 4.0 * ddet * ddet, 0.0)))
    rho = k * math.sqrt(s2 / (r * r) + low_pass * lmax / (ddet * ddet))    # 1 / lmin = lmax / ddet^2
    xlo, xhi = _ratio_range(mx, mz, rho * e1x, rho * e2x, rho * e1z, rho * e2z)
    ylo, yhi = _ratio_range(my, mz, rho * e1y, rho * e2y, rho * e1z, rho * e2z)
    return True, fx * xlo + cx, fx * xhi + cx, fy * ylo + cy, fy * yhi + cy


@njit(inline="always")
def plane_weights(X, Y, fx, fy, cx, cy):
    """(n0, n1) of opencv_plane_footprint for a mean at (X, Y) on the undistorted image plane (pixels)."""
    sx = (X - cx) / fx
    sy = (Y - cy) / fy
    q = 1.0 / (1.0 + sx * sx + sy * sy)
    return sx * q / fx, sy * q / fy


_opencv_terms = njit(inline="always")(opencv_distortion_terms)


@njit(inline="always")
def _opencv_distort(lp, x, y):
    """OpenCV's rational + tangential + thin-prism distortion of normalised (x, y) and its 2x2 Jacobian:
    (xd, yd, d00, d01, d10, d11), runtime.lenses.opencv_distortion_terms compiled."""
    return _opencv_terms(x, y, lp[0], lp[1], lp[2], lp[3], lp[4], lp[5], lp[6], lp[7], lp[8], lp[9], lp[10], lp[11])


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


# ------------------------------------------------------------------------------------------------ opencv: the plane
@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _opencv_undistort_grid(lp, fx, fy, cx, cy, height, width, out):
    """out [H, W, 2] float64 = each pixel's undistorted position in the undistorted image plane (pixels: fx x' + cx,
    fy y' + cy), NaN where runtime.lenses.opencv_undistort refuses it: the same Newton iteration from the
    distorted point (steps at most 0.5 long, stop when a step is below 1e-15 (1 + |x| + |y|)), the same test
    (residual at most 1e-12 (1 + |xy_d|), Jacobian determinant > 0)."""
    for v in prange(height):
        for u in range(width):
            tx = (u - cx) / fx
            ty = (v - cy) / fy
            x = tx
            y = ty
            for _ in range(100):
                xd, yd, j11, j12, j21, j22 = _opencv_distort(lp, x, y)
                rx = xd - tx
                ry = yd - ty
                det = j11 * j22 - j12 * j21
                dx = (j22 * rx - j12 * ry) / det
                dy = (j11 * ry - j21 * rx) / det
                if not (abs(dx) < math.inf and abs(dy) < math.inf):
                    x = math.nan
                    break
                big = max(abs(dx), abs(dy))
                scale = 0.5 / big if big > 0.5 else 1.0
                keep = big > 1e-15 * (1.0 + abs(x) + abs(y))
                x -= scale * dx
                y -= scale * dy
                if not keep:
                    break
            xd, yd, j11, j12, j21, j22 = _opencv_distort(lp, x, y)
            ok = math.hypot(xd - tx, yd - ty) <= 1e-12 * (1.0 + math.hypot(tx, ty)) and j11 * j22 - j12 * j21 > 0
            out[v, u, 0] = fx * x + cx if ok else math.nan
            out[v, u, 1] = fy * y + cy if ok else math.nan


PLANE_PAD = 1e-3   # px: the search tables' slack for the float32 rounding of the raster's pixel positions


@functools.lru_cache(maxsize=8)
def _opencv_plane(coeffs, fx, fy, cx, cy, W, H):
    lp = np.array([*coeffs, 0.0], np.float64)
    grid = np.empty((H, W, 2))
    _opencv_undistort_grid(lp, fx, fy, cx, cy, H, W, grid)
    with np.errstate(invalid="ignore"):     # beyond the unfolded disc (a lens folding within the image): no ray
        grid[((grid[..., 0] - cx) / fx) ** 2 + ((grid[..., 1] - cy) / fy) ** 2 > opencv_valid_r2(coeffs)] = np.nan
    vv, uu = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    offsets = np.empty((H, W, 2), np.float32)
    offsets[..., 0] = grid[..., 0] - uu
    offsets[..., 1] = grid[..., 1] - vv
    valid = ~np.isnan(grid[..., 0])
    lo = np.where(valid[..., None], grid, np.inf)                 # no ray: outside every extent
    hi = np.where(valid[..., None], grid, -np.inf)
    cols = _tables(hi[..., 0].max(axis=0), lo[..., 0].min(axis=0))
    rows = _tables(hi[..., 1].max(axis=1), lo[..., 1].min(axis=1))
    T = 16                                                        # kernels.TILE
    ntx, nty = -(-W // T), -(-H // T)
    lo = np.pad(lo, ((0, nty * T - H), (0, ntx * T - W), (0, 0)), constant_values=np.inf)
    hi = np.pad(hi, ((0, nty * T - H), (0, ntx * T - W), (0, 0)), constant_values=-np.inf)
    tilex = np.stack([lo[..., 0].reshape(nty, T, ntx, T).min(axis=(1, 3)) - PLANE_PAD,
                      hi[..., 0].reshape(nty, T, ntx, T).max(axis=(1, 3)) + PLANE_PAD], -1)
    tiley = np.stack([lo[..., 1].reshape(nty, T, ntx, T).min(axis=(1, 3)) - PLANE_PAD,
                      hi[..., 1].reshape(nty, T, ntx, T).max(axis=(1, 3)) + PLANE_PAD], -1)
    rowy = np.stack([lo[:H, :, 1].reshape(H, ntx, T).min(axis=2) - PLANE_PAD,
                     hi[:H, :, 1].reshape(H, ntx, T).max(axis=2) + PLANE_PAD], -1)
    tyext = _tables(tiley[..., 1].max(axis=1), tiley[..., 0].min(axis=1)) - [PLANE_PAD, -PLANE_PAD]  # (widened)
    rowtx = np.stack([np.maximum.accumulate(tilex[..., 1], axis=1),
                      np.minimum.accumulate(tilex[:, ::-1, 0], axis=1)[:, ::-1]], -1)
    planes = PixelPlane(offsets, cols, rows, *(np.ascontiguousarray(a) for a in (tilex, tiley, rowy, tyext, rowtx)))
    for a in planes:
        a.setflags(write=False)
    return planes


class PixelPlane(NamedTuple):
    """opencv_pixel_map's arrays (see there)."""
    offsets: np.ndarray   # [H, W, 2] float32
    cols: np.ndarray      # [W, 2] float64 search table of the pixel columns' extents in X
    rows: np.ndarray      # [H, 2] float64, the pixel rows' in Y
    tilex: np.ndarray     # [nty, ntx, 2] float64: each tile's extent in X
    tiley: np.ndarray     # [nty, ntx, 2] float64: and in Y
    rowy: np.ndarray      # [H, ntx, 2] float64: each tile row's (16 pixels of an image row) extent in Y
    tyext: np.ndarray     # [nty, 2] float64: the search table (_tables) of each row of tiles' extent in Y
    rowtx: np.ndarray     # [nty, ntx, 2] float64: per row of tiles, the search table of the tiles' extents in X


def _tables(hi: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """[n, 2]: the running maximum of hi from the start, the running minimum of lo from the end (both
    non-decreasing), each widened by PLANE_PAD: a footprint whose box is [a, b] on the plane's coordinate can
    touch line k (a column or row of pixels) only if table[k, 0] >= a and table[k, 1] <= b."""
    return np.stack([np.maximum.accumulate(hi) + PLANE_PAD, np.minimum.accumulate(lo[::-1])[::-1] - PLANE_PAD], 1)


def opencv_pixel_map(camera) -> PixelPlane:
    """An opencv camera's undistorted image plane (the pinhole of its K), where a pixel's position (X, Y) = (fx x'
    + cx, fy y' + cy) is its ray (x', y', 1): PixelPlane(offsets [H, W, 2] float32 = each pixel's (X, Y) minus the
    pixel, NaN where no ray reaches it (runtime.lenses.opencv_undistort refuses it, or it lies beyond the unfolded
    disc); cols [W, 2], rows [H, 2], the search tables (_tables) of the pixel columns' extents in X and the pixel
    rows' in Y, from which the projection finds the pixels a footprint's box on the plane can touch; tilex, tiley,
    rowy: each 16x16 tile's extent in X and in Y, each tile row's in Y (widened by PLANE_PAD), from which the
    projection keeps the tiles a footprint meets and the raster narrows its rows in a tile; tyext, rowtx: the
    search tables of the rows of tiles' extents in Y and, per row, of its tiles' extents in X, from which the
    projection finds a footprint's tiles row by row). Cached per lens, K and size (8 cameras; ~20 MB and ~0.5 s
    at 1920x1080: the undistortion is opencv_undistort's Newton iteration per pixel, in numba). Read-only."""
    K = camera.K
    return _opencv_plane(tuple(camera.distortion.coeffs), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                         float(K[1, 2]), camera.width, camera.height)
