"""Render options and the float64 numpy projection (EWA splatting) used by the reference renderer and by the
backward pass. The numba projection in kernels.py implements the same formulas for the fast path."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..camera import Camera, CameraError
from ..rotations import quat_to_rotmat
from .gaussians import Gaussians
from .sh import sh_colours

ALPHA_MIN = 1.0 / 255.0      # alphas below are skipped; opacities below are culled
ALPHA_MAX = 0.99             # alpha clamp
T_MIN = 1e-4                 # stop when T * (1 - alpha) <= T_MIN; that Gaussian is not blended
TILE = 16                    # tile edge, pixels
OPACITY_EXTENT_MAX = 3.33    # gsplat's cap on the opacity-aware extent (sigmas)


@dataclass(frozen=True)
class RenderOptions:
    near: float = 0.01             # metres; Gaussians closer (camera z, or distance for equirect) are culled
    far: float = 1.0e4             # metres; farther ones are culled
    low_pass: float = 0.3          # pixels^2 added to the 2D covariance diagonal (3DGS / gsplat eps2d)
    antialiased: bool = False      # gsplat "antialiased": opacity *= sqrt(det(cov2d) / det(cov2d + low_pass I))
    radius_mode: str = "3sigma"    # "3sigma": footprint = 3-sigma ellipse; "opacity": gsplat's opacity-aware
    #                                extent min(3.33, sqrt(2 ln(255 o))) sigmas

    def __post_init__(self) -> None:
        if not (np.isfinite(self.near) and self.near > 0):
            raise ValueError(f"near: must be > 0, got {self.near!r}")
        if not (self.far > self.near):
            raise ValueError(f"far: must be > near, got {self.far!r}")
        if not (np.isfinite(self.low_pass) and self.low_pass >= 0):
            raise ValueError(f"low_pass: must be >= 0, got {self.low_pass!r}")
        if self.radius_mode not in ("3sigma", "opacity"):
            raise ValueError(f"radius_mode: must be '3sigma' or 'opacity', got {self.radius_mode!r}")

    @classmethod
    def from_kwargs(cls, options: dict) -> RenderOptions:
        names = {f.name for f in fields(cls)}
        for key in options:
            if key not in names:
                raise ValueError(f"{key}: unknown render option (known: {', '.join(sorted(names))})")
        return cls(**options)


def check_camera(camera, backward: bool = False) -> None:
    """The renderer draws a runtime.camera.Camera: pinhole (with or without a lens) or equirectangular; TypeError
    for anything else. The backward pass (backward=True) draws ideal cameras only: CameraError (field
    "distortion") for a camera with a lens."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a runtime.camera.Camera, got {type(camera).__name__}")
    if backward and camera.distortion is not None:
        raise CameraError("distortion", f"render_backward draws pinhole and equirectangular cameras only, not a "
                          f"{camera.distortion.model} lens (training uses ideal pinholes: drop the distortion)",
                          camera.where)


REF_STEP = 1e-5   # radians: the tangent-plane step of the reference's central differences of Lens.project


def lens_reference(camera: Camera, p: np.ndarray, near: float, far: float) -> dict:
    """The float64 reference's view of camera-frame points p [N, 3] through the camera's lens (runtime.lenses):
    mean2d = Lens.project; depth (camera z for opencv, distance for opencv_fisheye and ftheta); geo = the culls of
    the mean (depth in [near, far]; opencv: z > 0 and (x/z)^2 + (y/z)^2 <= the unfolded radius
    lensmap.opencv_valid_r2; fisheye / f-theta: angle from the axis <= max_angle and not on the axis behind);
    the tangent frame of each mean, m = p / |p| and e1, e2 spanning the plane orthogonal to it (e1 towards larger
    angles from the axis); DL [N, 2, 2] = d(pixel)/d(g) of L(g) = Lens.project(m + g1 e1 + g2 e2) at g = 0, by
    central differences with step h = REF_STEP (error ~ h^2 |L^(3)| / 6 + 1e-16 |uv| / h, ~1e-10 relative for
    these lenses; a backward second-order stencil where m + h e1 would leave max_angle); and the 2x3 Jacobian
    J = DL [e1; e2] / |p| (the projection is constant along rays, so d(pixel)/dp has p in its null space)."""
    from .lensmap import opencv_valid_r2

    lens, K = camera.distortion, camera.K
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    dist = np.linalg.norm(p, axis=1)
    uv, _ = lens.project(K, p)
    rho = np.hypot(x, y)
    theta = np.arctan2(rho, z)
    if lens.model == "opencv":
        depth = z
        zs = np.where(z > 0, z, 1.0)
        geo = (z > 0) & ((x / zs) ** 2 + (y / zs) ** 2 <= opencv_valid_r2(tuple(lens.coeffs)))
    else:
        depth = dist
        geo = (theta <= lens.max_angle) & ((rho > 0) | (z > 0))
    geo &= (depth >= near) & (depth <= far)
    m = p / np.where(dist > 0, dist, 1.0)[:, None]
    s = np.sin(theta)
    e1 = (m * np.cos(theta)[:, None] - np.array([0.0, 0.0, 1.0])) / np.where(s > 1e-9, s, 1.0)[:, None]
    e1 = np.where((s > 1e-9)[:, None], e1, np.array([1.0, 0.0, 0.0]))
    e1 -= m * np.einsum("ni,ni->n", e1, m)[:, None]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(m, e1)
    h = REF_STEP

    def at(g1: float, g2: float) -> np.ndarray:
        return lens.project(K, m + g1 * e1 + g2 * e2)[0]

    d1 = (at(h, 0.0) - at(-h, 0.0)) / (2 * h)
    if lens.model != "opencv":
        edge = theta + 1.01 * h > lens.max_angle            # m + h e1 lies beyond max_angle: backward stencil
        if edge.any():
            d1b = (3 * at(0.0, 0.0) - 4 * at(-h, 0.0) + at(-2 * h, 0.0)) / (2 * h)
            d1 = np.where(edge[:, None], d1b, d1)
    d2 = (at(0.0, h) - at(0.0, -h)) / (2 * h)
    DL = np.stack([d1, d2], axis=2)                          # [N, 2 (u, v), 2 (g1, g2)]
    J = DL @ np.stack([e1, e2], axis=1) / np.where(dist > 0, dist, 1.0)[:, None, None]
    return dict(mean2d=uv, depth=depth, geo=geo, J=J, DL=DL, frame=np.stack([m, e1, e2], axis=1))


def pinhole_limits(camera: Camera) -> tuple[float, float, float, float]:
    """Jacobian clamp on x/z and y/z (as gsplat): the image plus 0.3 * tan(half fov) beyond each edge.
    Returns (lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos), all >= 0, x/z is clamped to [-lim_x_neg, lim_x_pos]."""
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    tan_x, tan_y = 0.5 * camera.width / fx, 0.5 * camera.height / fy
    return (cx / fx + 0.3 * tan_x, (camera.width - cx) / fx + 0.3 * tan_x,
            cy / fy + 0.3 * tan_y, (camera.height - cy) / fy + 0.3 * tan_y)


def equirect_jacobian(p: np.ndarray, width: int, height: int, pole_clamp: np.ndarray) -> np.ndarray:
    """d(u, v)/d(camera-frame point) [N, 2, 3] of the equirect map, with 1/rho clamped near the poles
    (rho >= r sin(pi / 2H), where pole_clamp is True). Works on complex p too (complex-step derivatives)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r2 = x * x + y * y + z * z
    r = np.sqrt(r2)
    rho = np.sqrt(x * x + z * z)
    rho_j = np.where(pole_clamp, r * np.sin(np.pi / (2 * height)), rho)
    r2 = np.where(r2 == 0, 1.0, r2)
    rho_j = np.where(rho_j == 0, 1.0, rho_j)
    ku, kv = width / (2 * np.pi), height / np.pi
    J = np.zeros((p.shape[0], 2, 3), dtype=p.dtype)
    J[:, 0, 0] = ku * z / rho_j ** 2
    J[:, 0, 2] = -ku * x / rho_j ** 2
    J[:, 1, 0] = -kv * y * x / (r2 * rho_j)
    J[:, 1, 1] = kv * rho / r2
    J[:, 1, 2] = -kv * y * z / (r2 * rho_j)
    return J


def project_reference(g: Gaussians, camera, opts: RenderOptions) -> dict:
    """Project every Gaussian (float64). Returns arrays over all N (invalid ones flagged):
    valid [N] bool; mean2d [N, 2] px; conic [N, 3] (a, b, c) with power = 0.5 a dx^2 + b dx dy + 0.5 c dy^2;
    opacity [N] (after the optional antialiasing compensation); pmax [N] (power cutoff of the footprint);
    depth [N] (camera z for pinhole and an opencv lens, distance for equirect, fisheye and f-theta); colour
    [N, 3]; plus intermediates for backward, and `lens` (lens_reference's dict, None without a lens). With a lens
    the Jacobian is lens_reference's (central differences of Lens.project, not clamped)."""
    n = len(g)
    check_camera(camera)
    w2c = np.linalg.inv(camera.cam_to_ego)
    Rw, tw = w2c[:3, :3], w2c[:3, 3]
    means = g.means.astype(np.float64)
    p = means @ Rw.T + tw                                   # [N, 3] camera frame
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    J = np.zeros((n, 2, 3))
    clamp = np.zeros((n, 2), bool)
    geo = np.ones(n, bool)
    lens = None
    if camera.distortion is not None:
        lens = lens_reference(camera, p, opts.near, opts.far)
        mean2d, depth, J, geo = lens["mean2d"], lens["depth"], lens["J"], lens["geo"]
    elif not camera.is_equirect:
        fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
        depth = z
        zs = np.where(z > 0, z, 1.0)
        lxn, lxp, lyn, lyp = pinhole_limits(camera)
        sx, sy = x / zs, y / zs
        sxc, syc = np.clip(sx, -lxn, lxp), np.clip(sy, -lyn, lyp)
        clamp[:, 0], clamp[:, 1] = sxc != sx, syc != sy
        mean2d = np.stack([fx * sx + cx, fy * sy + cy], 1)
        J[:, 0, 0] = fx / zs
        J[:, 0, 2] = -fx * sxc / zs
        J[:, 1, 1] = fy / zs
        J[:, 1, 2] = -fy * syc / zs
    else:
        W, H = camera.width, camera.height
        r = np.linalg.norm(p, axis=1)
        depth = r
        rho = np.hypot(x, z)
        phi, theta = np.arctan2(x, z), np.arctan2(rho, -y)
        mean2d = np.stack([W * (phi + np.pi) / (2 * np.pi) - 0.5, H * theta / np.pi - 0.5], 1)
        clamp[:, 0] = rho < r * np.sin(np.pi / (2 * H))
        J = equirect_jacobian(p, W, H, clamp[:, 0])

    R = quat_to_rotmat(g.quats)
    s = np.exp(g.log_scales.astype(np.float64))
    M = R * s[:, None, :]                                   # R S
    cov3 = M @ M.transpose(0, 2, 1)
    T = J @ Rw[None]                                        # [N, 2, 3]
    cov2_raw = T @ cov3 @ T.transpose(0, 2, 1)
    cov2 = cov2_raw + opts.low_pass * np.eye(2)[None]
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    dets = np.where(det > 0, det, 1.0)
    conic = np.stack([cov2[:, 1, 1] / dets, -cov2[:, 0, 1] / dets, cov2[:, 0, 0] / dets], 1)
    opa = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    if opts.antialiased:
        det_raw = cov2_raw[:, 0, 0] * cov2_raw[:, 1, 1] - cov2_raw[:, 0, 1] ** 2
        comp = np.sqrt(np.maximum(det_raw / dets, 0.0))
    else:
        comp = np.ones(n)
    opa_eff = opa * comp
    if opts.radius_mode == "3sigma":
        pmax = np.full(n, 4.5)
    else:
        ext = np.minimum(OPACITY_EXTENT_MAX, np.sqrt(2 * np.log(np.maximum(opa_eff, ALPHA_MIN) / ALPHA_MIN)))
        pmax = 0.5 * ext * ext
    valid = geo & (depth >= opts.near) & (depth <= opts.far) & (det > 0) & (opa_eff >= ALPHA_MIN)
    colour, unclamped = sh_colours(g.means, g.sh, camera.cam_to_ego[:3, 3])
    return dict(valid=valid, mean2d=mean2d, conic=conic, opacity=opa_eff, pmax=pmax, depth=depth,
                colour=colour, colour_unclamped=unclamped, p_cam=p, J=J, clamp=clamp, Rw=Rw, R=R, s=s, M=M,
                cov3=cov3, cov2_raw=cov2_raw, cov2=cov2, det=det, opa=opa, comp=comp, lens=lens)
