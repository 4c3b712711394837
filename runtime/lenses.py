"""The lenses of the runtime's one camera type: what a K-based camera's `distortion` describes, and the exact float64
maps between camera-frame points and pixels (docs/conventions.md "Lens models" is the full statement).

Models (`Lens.model`), all in the OpenCV camera frame (x right, y down, z forward) and OpenCV pixel coordinates (the
centre of pixel column u is at x = u):
- "opencv": OpenCV's pinhole with rational radial, tangential and thin-prism distortion of the normalised
  coordinates (x/z, y/z), exactly as cv2.projectPoints with distCoeffs k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4; K maps
  the distorted coordinates to pixels. A point projects when its camera z > IN_FRONT_EPS.
- "opencv_fisheye": OpenCV's fisheye (Kannala-Brandt, cv2.fisheye.projectPoints): the angle theta from the optical
  axis becomes theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), the distorted point is
  theta_d (cos phi, sin phi) (phi the azimuth about the axis), K maps it to pixels. Defined up to max_angle_deg,
  which may exceed 90 degrees (cv2 itself folds points behind the image plane back in front: x/z).
- "ftheta": NVIDIA's f-theta (NuRec / AlpaSim `FthetaCameraParam`): the pixel distance r from the principal point
  (K's cx, cy) and theta are related by a polynomial in ascending powers, `angle_to_pixeldist_poly` (r of theta,
  the "forward" one) or `pixeldist_to_angle_poly` (theta of r, the "backward" one); `reference_poly` names the exact
  one, the other is an approximation kept for the round trip. The pixel is (cx, cy) + A r (cos phi, sin phi) with
  the linear term A = [[c, d], [e, 1]] (`linear_cde`, default [1, 0, 0]). Defined up to max_angle_deg. K's fx, fy
  are not used.

Pure functions on arrays of any leading shape: `poly_eval` / `poly_solve` (an increasing polynomial and its
inverse), `opencv_distort` / `opencv_undistort` on normalised coordinates, `fisheye_theta_d` / `fisheye_theta` on
angles, and per camera `project(K, lens, q)` -> (uv, valid) / `unproject(K, lens, uv)` -> (unit directions, valid)
with lens None the ideal pinhole. `Lens` is the frozen, validated description a `runtime.camera.Camera` holds;
`Lens.from_json` / `to_json` are rig.json's `"distortion"`. Errors are `CameraError` whose field names the rig.json
field ("distortion.k1", "distortion[2]", "distortion.pixeldist_to_angle_poly[3]", "distortion.max_angle_deg").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .errors import CameraError, plain

LensModel = Literal["opencv", "opencv_fisheye", "ftheta"]
LENS_MODELS = ("opencv", "opencv_fisheye", "ftheta")
OPENCV_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")  # cv2 distCoeffs order
OPENCV_LENGTHS = (4, 5, 8, 12, 14)  # the list form = OpenCV's distCoeffs (14: + tauX tauY, which must be 0)
FISHEYE_NAMES = ("k1", "k2", "k3", "k4")
POLY_NAMES = ("pixeldist_to_angle_poly", "angle_to_pixeldist_poly")
REFERENCE_POLYS = ("pixeldist_to_angle", "angle_to_pixeldist")  # the proto's PIXELDIST_TO_ANGLE, ANGLE_TO_PIXELDIST
POLY_LENGTHS = (2, 16)  # f-theta polynomial coefficients, constant term first
POLY_ZERO_TOL = 1e-6  # |constant term| of the reference polynomial (radians or pixels) accepted as 0
MAX_ANGLE_DEG = 180.0  # max_angle_deg in (0, 180]: the largest angle from the optical axis a lens images
IN_FRONT_EPS = 1e-6  # metres: a point needs camera z (pinhole, opencv) / distance (fisheye, f-theta) above this
_KEYS = {"opencv": OPENCV_NAMES, "opencv_fisheye": (*FISHEYE_NAMES, "max_angle_deg"),
         "ftheta": ("reference_poly", *POLY_NAMES, "max_angle_deg", "linear_cde")}
_JSON_OPENCV = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "s1", "s2", "s3", "s4")  # dict form's key order


# -- polynomials -------------------------------------------------------------------------------------------------

def poly_eval(c: Sequence[float], x: np.ndarray) -> np.ndarray:
    """sum_i c[i] x^i (Horner), float64."""
    x = np.asarray(x, dtype=np.float64)
    y = np.full_like(x, float(c[-1]))
    for a in reversed(c[:-1]):
        y = y * x + a
    return y


def poly_derivative(c: Sequence[float]) -> tuple[float, ...]:
    """Coefficients of d/dx sum_i c[i] x^i (constant term first); (0.0,) for a constant."""
    return tuple(i * float(a) for i, a in enumerate(c) if i) or (0.0,)


def poly_solve(c: Sequence[float], y: np.ndarray, x_max: float, x0: np.ndarray | None = None) -> np.ndarray:
    """x in [0, x_max] with poly_eval(c, x) = y, for a polynomial increasing on [0, x_max]: Newton's method kept
    inside a shrinking bracket (bisection where a step leaves it). y outside [p(0), p(x_max)] gives 0 or x_max."""
    y = np.asarray(y, dtype=np.float64)
    dc = poly_derivative(c)
    lo, hi = np.zeros_like(y), np.full_like(y, float(x_max))
    x = np.clip(y / c[1] if x0 is None else np.asarray(x0, np.float64), lo, hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(200):
            f = poly_eval(c, x) - y
            lo = np.where(f <= 0, x, lo)
            hi = np.where(f >= 0, x, hi)
            step = x - f / poly_eval(dc, x)
            step = np.where((step > lo) & (step < hi), step, 0.5 * (lo + hi))
            done = np.abs(step - x) <= 4e-16 * np.maximum(1.0, np.abs(x))
            x = step
            if done.all():
                break
    return x


def _first_turn(c: Sequence[float]) -> float:
    """The smallest x > 0 where the derivative of the polynomial is 0 (inf if none): the polynomial increases on
    [0, that x) when its slope at 0 is positive. NaN when the roots cannot be computed."""
    dc = np.trim_zeros(np.array(poly_derivative(c)), "b")
    if len(dc) < 2:
        return math.inf
    try:
        with np.errstate(all="ignore"):
            roots = np.polynomial.polynomial.polyroots(dc / np.max(np.abs(dc)))
    except np.linalg.LinAlgError:
        return math.nan
    if not np.all(np.isfinite(roots)):
        return math.nan
    real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))) & (roots.real > 0)]
    return float(real.min()) if len(real) else math.inf


# -- OpenCV radial-tangential-thin-prism -----------------------------------------------------------------------

def opencv_distort(xy: np.ndarray, c: Sequence[float]) -> np.ndarray:
    """[..., 2] undistorted normalised coordinates (x/z, y/z) -> distorted, OpenCV's formula with the 12
    coefficients k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 (the same expression as cv2.projectPoints)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + r2 * s2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + r2 * s4)
    return np.stack([xd, yd], axis=-1)


def _opencv_with_jacobian(x: np.ndarray, y: np.ndarray, c: Sequence[float]) -> tuple[np.ndarray, ...]:
    """opencv_distort and its Jacobian d(xd, yd)/d(x, y) in one pass: (xd, yd, j11, j12, j21, j22)."""
    return opencv_distortion_terms(x, y, *c)


def opencv_distortion_terms(x, y, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4):
    """The distortion and its Jacobian as plain arithmetic on scalars or arrays: the one copy of these expressions,
    which the renderer compiles with numba (runtime.render.lensmap._opencv_distort)."""
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    n = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = n / d
    dradial = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * d - n * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / (d * d)
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * xx) + r2 * (s1 + r2 * s2)
    yd = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy + r2 * (s3 + r2 * s4)
    sx, sy = s1 + 2 * s2 * r2, s3 + 2 * s4 * r2      # d (thin prism) / d r2
    cross = 2 * xy * dradial + 2 * p1 * x + 2 * p2 * y
    j11 = radial + 2 * xx * dradial + 2 * p1 * y + 6 * p2 * x + 2 * x * sx
    j22 = radial + 2 * yy * dradial + 6 * p1 * y + 2 * p2 * x + 2 * y * sy
    return xd, yd, j11, cross + 2 * y * sx, cross + 2 * x * sy, j22


def opencv_undistort(xy_d: np.ndarray, c: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of opencv_distort: [..., 2] distorted normalised coordinates -> (undistorted [..., 2], ok [...]).
    Newton's method from the distorted point with the exact Jacobian (steps at most 0.5 long); ok where it converged
    (residual at most 1e-12 (1 + |xy_d|)) to a point where the map is not folded (Jacobian determinant > 0). Not
    ok: NaN."""
    xy_d = np.asarray(xy_d, dtype=np.float64)
    target = xy_d.reshape(-1, 2)
    xy = target.copy()
    active = np.arange(len(xy))
    with np.errstate(all="ignore"):
        for _ in range(100):
            whole = len(active) == len(xy)
            x, y = (xy[:, 0], xy[:, 1]) if whole else (xy[active, 0], xy[active, 1])
            t = target if whole else target[active]
            xd, yd, j11, j12, j21, j22 = _opencv_with_jacobian(x, y, c)
            fx, fy = xd - t[:, 0], yd - t[:, 1]
            det = j11 * j22 - j12 * j21
            dx, dy = (j22 * fx - j12 * fy) / det, (j11 * fy - j21 * fx) / det
            big = np.maximum(np.abs(dx), np.abs(dy))
            scale = np.where(big > 0.5, 0.5 / np.where(big > 0.5, big, 1.0), 1.0)
            keep = big > 1e-15 * (1.0 + np.abs(x) + np.abs(y))   # NaN steps leave too (ok is False)
            xy[active, 0], xy[active, 1] = x - scale * dx, y - scale * dy
            active = active[keep]
            if not len(active):
                break
        xd, yd, j11, j12, j21, j22 = _opencv_with_jacobian(xy[:, 0], xy[:, 1], c)
        ok = (np.hypot(xd - target[:, 0], yd - target[:, 1]) <= 1e-12 * (1.0 + np.hypot(target[:, 0], target[:, 1]))) \
            & (j11 * j22 - j12 * j21 > 0)
    xy[~ok] = np.nan
    return xy.reshape(xy_d.shape), ok.reshape(xy_d.shape[:-1])


# -- OpenCV fisheye ----------------------------------------------------------------------------------------------

def _fisheye_poly(k: Sequence[float]) -> tuple[float, ...]:
    """theta_d as a polynomial in theta: theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9."""
    k1, k2, k3, k4 = k
    return (0.0, 1.0, 0.0, k1, 0.0, k2, 0.0, k3, 0.0, k4)


def fisheye_max_angle_deg(k: Sequence[float], limit_deg: float = 180.0) -> float:
    """The widest ``max_angle_deg`` an opencv_fisheye lens of coefficients ``k`` (k1..k4) allows: where theta_d(theta)
    stops increasing (less 0.1 %, so the validator's strict check holds), capped at ``limit_deg``. For formats that
    carry no max angle (nerfstudio's OPENCV_FISHEYE)."""
    turn = _first_turn(_fisheye_poly(tuple(float(v) for v in k)))
    if not math.isfinite(turn):
        return float(limit_deg)
    return float(min(limit_deg, math.degrees(turn) * 0.999))


def fisheye_theta_d(theta: np.ndarray, k: Sequence[float]) -> np.ndarray:
    """OpenCV fisheye: theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), theta in radians."""
    theta = np.asarray(theta, dtype=np.float64)
    t2 = theta * theta
    k1, k2, k3, k4 = k
    return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def fisheye_theta(theta_d: np.ndarray, k: Sequence[float], max_angle: float) -> np.ndarray:
    """Inverse of fisheye_theta_d on [0, max_angle] radians (theta_d increasing there: Lens validates it)."""
    return poly_solve(_fisheye_poly(k), theta_d, max_angle, x0=theta_d)


# -- angles ------------------------------------------------------------------------------------------------------

def _angles(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points [..., 3] -> (theta from the optical axis in [0, pi], cos phi, sin phi, distance); phi the
    azimuth about the axis (0 = camera +x, towards +y); (1, 0) on the axis."""
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    rho = np.hypot(x, y)
    safe = np.where(rho > 0, rho, 1.0)
    return np.arctan2(rho, z), np.where(rho > 0, x / safe, 1.0), np.where(rho > 0, y / safe, 0.0), \
        np.sqrt(rho * rho + z * z)


def _ray(theta: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """Unit camera-frame directions at angle theta from the axis towards the image-plane offset (ox, oy)."""
    r = np.hypot(ox, oy)
    safe = np.where(r > 0, r, 1.0)
    s = np.sin(theta)
    return np.stack([np.where(r > 0, s * ox / safe, 0.0), np.where(r > 0, s * oy / safe, 0.0), np.cos(theta)],
                    axis=-1)


# -- the lens ----------------------------------------------------------------------------------------------------

def _number(v: Any, name: str) -> float:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise CameraError(name, f"must be a number (got {plain(v)!r:.60})")
    if not math.isfinite(float(v)):
        raise CameraError(name, "is not finite")
    return float(v)


def _is_list(v: Any) -> bool:
    """A list, tuple or 1-D array (its entries are checked one by one)."""
    return isinstance(v, (list, tuple)) or (isinstance(v, np.ndarray) and v.ndim == 1)


def _unset(v: Any, default: Any) -> bool:
    """Whether a Lens field holds its default (a parameter the model does not have must)."""
    if default is None or not _is_list(v):
        return v is default
    return len(v) == len(default) and all(a == b for a, b in zip(v, default))


def _numbers(v: Any, names: Sequence[str] | str) -> tuple[float, ...]:
    """A list of finite numbers; names: one per entry, or the field whose entries are named field[i]."""
    field_name = names if isinstance(names, str) else "distortion"
    if not _is_list(v):
        raise CameraError(field_name, f"must be a list of numbers (got {plain(v)!r:.60})")
    v = list(v)
    if not isinstance(names, str) and len(v) > len(names):
        raise CameraError(field_name, f"has {len(v)} coefficients, at most {len(names)}")
    return tuple(_number(a, f"{names}[{i}]" if isinstance(names, str) else names[i]) for i, a in enumerate(v))


@dataclass(frozen=True)
class Lens:
    """A camera lens (docs/conventions.md "Lens models"); frozen and validated on construction.

    model: "opencv" | "opencv_fisheye" | "ftheta";
    coeffs: opencv: OpenCV's distCoeffs k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tauX tauY]]]] (4, 5, 8, 12 or 14
      values, tauX = tauY = 0), stored as the 12 of OPENCV_NAMES; opencv_fisheye: k1 k2 k3 k4; ftheta: ();
    max_angle_deg: opencv_fisheye and ftheta, in (0, 180]: the largest angle from the optical axis imaged;
    pixeldist_to_angle_poly / angle_to_pixeldist_poly / reference_poly / linear_cde: ftheta (module docstring);
    list_length: how many coefficients the rig.json list form had (None: the dict form), for the round trip only.
    """

    model: LensModel
    coeffs: tuple[float, ...] = ()
    max_angle_deg: float | None = None
    pixeldist_to_angle_poly: tuple[float, ...] = ()
    angle_to_pixeldist_poly: tuple[float, ...] = ()
    reference_poly: str | None = None
    linear_cde: tuple[float, float, float] = (1.0, 0.0, 0.0)
    list_length: int | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        m = self.model
        if not isinstance(m, str) or m not in LENS_MODELS:
            raise CameraError("distortion.model", f"must be one of {LENS_MODELS} (got {plain(m)!r:.60})")
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        used = {"opencv": ("coeffs",), "opencv_fisheye": ("coeffs", "max_angle_deg"),
                "ftheta": ("max_angle_deg", *POLY_NAMES, "reference_poly", "linear_cde")}[m]
        for name in ("coeffs", "max_angle_deg", *POLY_NAMES, "reference_poly", "linear_cde"):
            if name not in used and not _unset(getattr(self, name), defaults[name]):
                raise CameraError(f"distortion.{name}", f"is not a parameter of the {m} model")
        getattr(self, f"_check_{m}")()

    def _set(self, **kw: Any) -> None:
        for k, v in kw.items():
            object.__setattr__(self, k, v)

    def _check_max_angle(self) -> float:
        if self.max_angle_deg is None:
            raise CameraError("distortion.max_angle_deg", "is missing (the largest angle from the optical axis the "
                              "lens images, degrees, e.g. 95 for a 190-degree fisheye)")
        a = _number(self.max_angle_deg, "distortion.max_angle_deg")
        if not 0 < a <= MAX_ANGLE_DEG:
            raise CameraError("distortion.max_angle_deg", f"must be in (0, {MAX_ANGLE_DEG:g}] degrees (got {a!r})")
        self._set(max_angle_deg=a)
        return math.radians(a)

    def _check_opencv(self) -> None:
        n = len(self.coeffs) if _is_list(self.coeffs) else 0
        names = [f"distortion[{i}]" for i in range(max(n, 14))] if self.list_length is not None else \
            [f"distortion.{k}" for k in (*OPENCV_NAMES, "tauX", "tauY")]
        c = _numbers(self.coeffs, names)
        if len(c) not in OPENCV_LENGTHS:
            raise CameraError("distortion", f"must have {OPENCV_LENGTHS} coefficients (got {len(c)})")
        for i in (12, 13):
            if len(c) > i and c[i] != 0:
                raise CameraError(names[i], "the tilted-sensor terms tauX, tauY are not supported: must be 0")
        self._set(coeffs=(c + (0.0,) * 12)[:12])

    def _check_opencv_fisheye(self) -> None:
        c = _numbers(self.coeffs, [f"distortion.{k}" for k in FISHEYE_NAMES])
        c = c + (0.0,) * (4 - len(c))
        self._set(coeffs=c)
        amax = self._check_max_angle()
        turn = _first_turn(_fisheye_poly(c))
        if not turn > amax:
            where = "cannot be checked" if math.isnan(turn) else f"stops increasing at {math.degrees(turn):.4g} deg"
            raise CameraError("distortion.max_angle_deg", f"theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8) "
                              f"{where}: max_angle_deg ({self.max_angle_deg:g}) must be below that")
        object.__setattr__(self, "_limit", float(fisheye_theta_d(amax, c)))  # theta_d at max_angle

    def _check_ftheta(self) -> None:
        polys = {}
        for name in POLY_NAMES:
            p = _numbers(getattr(self, name), f"distortion.{name}")
            if p and not POLY_LENGTHS[0] <= len(p) <= POLY_LENGTHS[1]:
                raise CameraError(f"distortion.{name}", f"must have {POLY_LENGTHS[0]}..{POLY_LENGTHS[1]} "
                                  f"coefficients, constant term first (got {len(p)})")
            polys[name] = p
        ref = self.reference_poly
        given = [n for n in POLY_NAMES if polys[n]]
        if not given:
            raise CameraError("distortion.pixeldist_to_angle_poly", "is missing (give pixeldist_to_angle_poly or "
                              "angle_to_pixeldist_poly)")
        if ref is None:
            if len(given) > 1:
                raise CameraError("distortion.reference_poly", f"is required when both polynomials are given (one "
                                  f"of {REFERENCE_POLYS})")
            ref = given[0][:-len("_poly")]
        elif not isinstance(ref, str) or ref not in REFERENCE_POLYS:
            raise CameraError("distortion.reference_poly", f"must be one of {REFERENCE_POLYS} (got "
                              f"{plain(ref)!r:.60})")
        name = f"{ref}_poly"
        p = polys[name]
        if not p:
            raise CameraError(f"distortion.{name}", f"is missing (reference_poly is {ref!r})")
        if abs(p[0]) > POLY_ZERO_TOL:
            raise CameraError(f"distortion.{name}[0]", f"must be 0: the principal point is the optical axis (got "
                              f"{p[0]!r})")
        if not p[1] > 0:
            raise CameraError(f"distortion.{name}[1]", f"must be > 0: the polynomial increases away from the axis "
                              f"(got {p[1]!r})")
        cde = _numbers(self.linear_cde, "distortion.linear_cde")
        if len(cde) != 3:
            raise CameraError("distortion.linear_cde", f"must be [c, d, e] (got {len(cde)} values)")
        if not cde[0] - cde[1] * cde[2] > 0:
            raise CameraError("distortion.linear_cde", f"[[c, d], [e, 1]] must have a positive determinant "
                              f"c - d e (got {cde[0] - cde[1] * cde[2]!r})")
        self._set(reference_poly=ref, linear_cde=cde, **polys)
        amax = self._check_max_angle()
        turn = _first_turn(p)
        if ref == "angle_to_pixeldist":
            if not turn > amax:
                raise CameraError(f"distortion.{name}", self._turn_message(turn, "theta") +
                                  f" before max_angle_deg ({self.max_angle_deg:g})")
            limit = float(poly_eval(p, amax))         # the image circle's radius, pixels
        else:
            top = math.inf if turn == math.inf else float(poly_eval(p, turn))
            if math.isnan(turn) or not top >= amax:
                raise CameraError(f"distortion.{name}", self._turn_message(turn, "r") + f" at theta = "
                                  f"{math.degrees(top):.4g} deg, below max_angle_deg ({self.max_angle_deg:g})")
            limit = float(poly_solve(p, np.float64(amax), turn if turn < math.inf else _reach(p, amax)))
        object.__setattr__(self, "_limit", limit)

    @staticmethod
    def _turn_message(turn: float, var: str) -> str:
        if math.isnan(turn):
            return "cannot be checked for monotonicity"
        shown = f"{math.degrees(turn):.4g} deg" if var == "theta" else f"{turn:.6g} px"
        return f"is not increasing: its slope is 0 at {var} = {shown}"

    # -- derived ---------------------------------------------------------------------------------------------
    @property
    def max_angle(self) -> float:
        """Radians; pi/2 for opencv (a point needs z > 0)."""
        return math.pi / 2 if self.max_angle_deg is None else math.radians(self.max_angle_deg)

    @property
    def circle_limit(self) -> float | None:
        """The image circle of max_angle: opencv_fisheye: theta_d there (normalised by fx, fy); ftheta: its pixel
        radius (after the linear term's inverse); opencv: None. `unproject` refuses the pixels beyond it."""
        return getattr(self, "_limit", None)

    def opencv_coefficients(self) -> tuple[float, ...]:
        """An opencv lens as cv2's distCoeffs: the list form's length, else the shortest of 4, 5, 8, 12 holding
        every non-zero coefficient."""
        if self.model != "opencv":
            raise ValueError(f"a {self.model} lens has no OpenCV distCoeffs")
        if self.list_length is not None:
            return (self.coeffs + (0.0, 0.0))[:self.list_length]
        n = next(n for n in (4, 5, 8, 12) if not any(self.coeffs[n:]))
        return self.coeffs[:n]

    @property
    def images_beyond_90(self) -> bool:
        """Whether the model can image points at or beyond 90 degrees from the optical axis (fisheye, f-theta);
        such a camera's depth is the distance from its centre, not camera z (docs/conventions.md "Depth")."""
        return self.model != "opencv"

    def paraxial_focal(self, K: np.ndarray) -> tuple[float, float]:
        """(fx, fy) pixels per radian on the optical axis: the focal of the pinhole that matches the lens there.
        opencv and opencv_fisheye: K's fx, fy (their maps have slope 1 at the axis); ftheta: the reference
        polynomial's slope at the axis (angle_to_pixeldist_poly[1], or 1 / pixeldist_to_angle_poly[1]), times c
        of linear_cde for x (K's fx, fy are not used by that lens)."""
        if self.model != "ftheta":
            return float(K[0, 0]), float(K[1, 1])
        if self.reference_poly == "angle_to_pixeldist":
            f = float(self.angle_to_pixeldist_poly[1])
        else:
            f = 1.0 / float(self.pixeldist_to_angle_poly[1])
        return self.linear_cde[0] * f, f

    def resized(self, sx: float, sy: float) -> Lens:
        """The lens of the image resampled by sx, sy (runtime.camera.Camera.resized scales K): opencv and fisheye act
        on normalised coordinates and stay; f-theta's pixel distances scale (as NVIDIA's ncore does): the forward
        polynomial by sy, the backward one's argument by 1/sy, c and d by sx/sy."""
        if self.model != "ftheta":
            return self
        fw = tuple(a * sy for a in self.angle_to_pixeldist_poly)
        bw = tuple(a / sy ** i for i, a in enumerate(self.pixeldist_to_angle_poly))
        c, d, e = self.linear_cde
        return dataclasses.replace(self, angle_to_pixeldist_poly=fw, pixeldist_to_angle_poly=bw,
                                   linear_cde=(c * sx / sy, d * sx / sy, e))

    # -- maps ------------------------------------------------------------------------------------------------
    def project(self, K: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points [..., 3] -> (uv [..., 2] pixels, valid [...]): opencv: z > IN_FRONT_EPS; fisheye
        and f-theta: distance > IN_FRONT_EPS and the angle from the axis <= max_angle. uv of points not valid is
        finite but meaningless."""
        if self.model == "opencv":
            z = q[..., 2]
            valid = z > IN_FRONT_EPS
            zs = np.where(valid, z, 1.0)
            xy = opencv_distort(np.stack([q[..., 0] / zs, q[..., 1] / zs], axis=-1), self.coeffs)
            return np.stack([K[0, 0] * xy[..., 0] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]], axis=-1), valid
        theta, cphi, sphi, dist = _angles(q)
        amax = self.max_angle
        valid = (dist > IN_FRONT_EPS) & (theta <= amax)
        theta = np.minimum(theta, amax)
        if self.model == "opencv_fisheye":
            td = fisheye_theta_d(theta, self.coeffs)
            return np.stack([K[0, 0] * td * cphi + K[0, 2], K[1, 1] * td * sphi + K[1, 2]], axis=-1), valid
        r = self._ftheta_radius(theta)
        ox, oy = r * cphi, r * sphi
        c, d, e = self.linear_cde
        return np.stack([c * ox + d * oy + K[0, 2], e * ox + oy + K[1, 2]], axis=-1), valid

    def unproject(self, K: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels [..., 2] -> (unit camera-frame directions [..., 3], valid [...]), the inverse of `project`. Not
        valid (NaN): pixels outside the image circle of max_angle (fisheye, f-theta), or where the opencv
        distortion cannot be inverted (beyond its fold)."""
        ox, oy = uv[..., 0] - K[0, 2], uv[..., 1] - K[1, 2]
        if self.model == "ftheta":
            c, d, e = self.linear_cde
            det = c - d * e
            ox, oy = (ox - d * oy) / det, (c * oy - e * ox) / det
            r = np.hypot(ox, oy)
            valid = r <= self._limit * (1 + 1e-12)
            theta = self._ftheta_angle(np.minimum(r, self._limit))
            out = _ray(theta, ox, oy)
        else:
            xd, yd = ox / K[0, 0], oy / K[1, 1]
            if self.model == "opencv":
                xy, valid = opencv_undistort(np.stack([xd, yd], axis=-1), self.coeffs)
                out = np.concatenate([xy, np.ones_like(xy[..., :1])], axis=-1)
                out /= np.linalg.norm(out, axis=-1, keepdims=True)
            else:
                td = np.hypot(xd, yd)
                valid = td <= self._limit * (1 + 1e-12)
                out = _ray(fisheye_theta(np.minimum(td, self._limit), self.coeffs, self.max_angle), xd, yd)
        out[~valid] = np.nan
        return out, valid

    def _ftheta_radius(self, theta: np.ndarray) -> np.ndarray:
        """f-theta: pixel distance of angle theta in [0, max_angle] (the reference polynomial or its inverse)."""
        if self.reference_poly == "angle_to_pixeldist":
            return poly_eval(self.angle_to_pixeldist_poly, theta)
        return poly_solve(self.pixeldist_to_angle_poly, theta, self._limit)

    def _ftheta_angle(self, r: np.ndarray) -> np.ndarray:
        """f-theta: angle of pixel distance r in [0, the image circle's radius]."""
        if self.reference_poly == "pixeldist_to_angle":
            return poly_eval(self.pixeldist_to_angle_poly, r)
        return poly_solve(self.angle_to_pixeldist_poly, r, self.max_angle)

    # -- rig.json ----------------------------------------------------------------------------------------------
    @classmethod
    def from_json(cls, value: Any) -> Lens | None:
        """rig.json's `"distortion"`: null, OpenCV's distCoeffs list (4, 5, 8, 12 or 14 values; all zero = null)
        or {"model": ..., named parameters} (docs/conventions.md "Lens models"); a Lens passes through."""
        if value is None or isinstance(value, Lens):
            return value
        if isinstance(value, Mapping):
            model = value.get("model")
            if "model" not in value:
                raise CameraError("distortion.model", f"is missing (one of {LENS_MODELS})")
            if not isinstance(model, str) or model not in LENS_MODELS:
                raise CameraError("distortion.model", f"must be one of {LENS_MODELS} (got {plain(model)!r:.60})")
            for key in value:
                if key != "model" and key not in _KEYS[model]:
                    raise CameraError(f"distortion.{key}", f"is not a parameter of the {model} model (those are "
                                      f"{', '.join(_KEYS[model])})")
            if model == "opencv":
                return cls("opencv", tuple(value.get(k, 0.0) for k in OPENCV_NAMES))
            if model == "opencv_fisheye":
                return cls(model, tuple(value.get(k, 0.0) for k in FISHEYE_NAMES),
                           max_angle_deg=value.get("max_angle_deg"))
            return cls(model, max_angle_deg=value.get("max_angle_deg"),
                       pixeldist_to_angle_poly=value.get("pixeldist_to_angle_poly", ()),
                       angle_to_pixeldist_poly=value.get("angle_to_pixeldist_poly", ()),
                       reference_poly=value.get("reference_poly"), linear_cde=value.get("linear_cde", (1.0, 0.0, 0.0)))
        if not _is_list(value):
            raise CameraError("distortion", f"must be null, OpenCV's coefficient list or an object with a \"model\" "
                              f"(got {plain(value)!r:.60})")
        lens = cls("opencv", tuple(value), list_length=len(value))
        return lens if any(lens.coeffs) else None

    def to_json(self) -> list[float] | dict[str, Any]:
        """rig.json's `"distortion"`: the list form where the lens came from one (byte-identical round trip), else
        {"model": ..., every parameter of the model}."""
        if self.model == "opencv":
            if self.list_length is not None:
                return list(self.opencv_coefficients())
            named = dict(zip(OPENCV_NAMES, self.coeffs))
            return {"model": "opencv", **{k: named[k] for k in _JSON_OPENCV}}
        if self.model == "opencv_fisheye":
            return {"model": self.model, **dict(zip(FISHEYE_NAMES, self.coeffs)), "max_angle_deg": self.max_angle_deg}
        out: dict[str, Any] = {"model": self.model, "reference_poly": self.reference_poly}
        out.update({n: list(getattr(self, n)) for n in POLY_NAMES if getattr(self, n)})
        out.update(max_angle_deg=self.max_angle_deg, linear_cde=list(self.linear_cde))
        return out


def _reach(p: Sequence[float], y: float) -> float:
    """An x > 0 with p(x) >= y for a polynomial increasing on [0, inf) (doubling from 1/p'(0))."""
    x = max(y / p[1], 1e-12)
    while float(poly_eval(p, x)) < y:
        x *= 2.0
    return x


# -- per camera ----------------------------------------------------------------------------------------------------

def project(K: np.ndarray, lens: Lens | None, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [..., 3] -> (uv [..., 2] pixels, valid [...]) through K and the lens (None: the ideal
    pinhole, valid = z > IN_FRONT_EPS). See Lens.project."""
    if lens is not None:
        return lens.project(K, q)
    z = q[..., 2]
    valid = z > IN_FRONT_EPS
    zs = np.where(valid, z, 1.0)
    return np.stack([K[0, 0] * (q[..., 0] / zs) + K[0, 2], K[1, 1] * (q[..., 1] / zs) + K[1, 2]], axis=-1), valid


def unproject(K: np.ndarray, lens: Lens | None, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [..., 2] -> (unit camera-frame directions [..., 3], valid [...]); NaN where not valid. See
    Lens.unproject; the ideal pinhole: normalise(inv(K) [u, v, 1]), always valid."""
    uv = np.asarray(uv, dtype=np.float64)
    if lens is not None:
        return lens.unproject(K, uv)
    d = np.stack([(uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1], np.ones(uv.shape[:-1])],
                 axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True), np.ones(uv.shape[:-1], bool)


__all__ = [
    "FISHEYE_NAMES",
    "IN_FRONT_EPS",
    "LENS_MODELS",
    "MAX_ANGLE_DEG",
    "OPENCV_LENGTHS",
    "OPENCV_NAMES",
    "POLY_LENGTHS",
    "POLY_NAMES",
    "REFERENCE_POLYS",
    "Lens",
    "LensModel",
    "fisheye_theta",
    "fisheye_theta_d",
    "opencv_distort",
    "opencv_undistort",
    "poly_derivative",
    "poly_eval",
    "poly_solve",
    "project",
    "unproject",
]
