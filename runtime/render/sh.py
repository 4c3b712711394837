"""Real spherical harmonics up to degree 3 with the 3DGS constants and sign conventions.

colour = max(0, sum_k basis_k(dir) * sh[k] + 0.5), dir = unit vector from the camera centre to the Gaussian
mean, world frame. `sh_basis` also returns d basis / d dir for the backward pass.
"""

from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: np.ndarray, n_coeffs: int, with_grad: bool = False):
    """dirs [N, 3] unit vectors (float64) -> basis [N, n_coeffs] and, if with_grad, d basis/d dir [N, n_coeffs, 3]."""
    n = dirs.shape[0]
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    b = np.zeros((n, n_coeffs), np.float64)
    g = np.zeros((n, n_coeffs, 3), np.float64) if with_grad else None
    o, zero = np.ones(n), np.zeros(n)
    b[:, 0] = SH_C0
    if n_coeffs > 1:
        b[:, 1], b[:, 2], b[:, 3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
        if with_grad:
            g[:, 1, 1], g[:, 2, 2], g[:, 3, 0] = -SH_C1, SH_C1, -SH_C1
    if n_coeffs > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        b[:, 4] = SH_C2[0] * xy
        b[:, 5] = SH_C2[1] * yz
        b[:, 6] = SH_C2[2] * (2 * zz - xx - yy)
        b[:, 7] = SH_C2[3] * xz
        b[:, 8] = SH_C2[4] * (xx - yy)
        if with_grad:
            g[:, 4] = SH_C2[0] * np.stack([y, x, zero], 1)
            g[:, 5] = SH_C2[1] * np.stack([zero, z, y], 1)
            g[:, 6] = SH_C2[2] * np.stack([-2 * x, -2 * y, 4 * z], 1)
            g[:, 7] = SH_C2[3] * np.stack([z, zero, x], 1)
            g[:, 8] = SH_C2[4] * np.stack([2 * x, -2 * y, zero], 1)
    if n_coeffs > 9:
        b[:, 9] = SH_C3[0] * y * (3 * xx - yy)
        b[:, 10] = SH_C3[1] * xy * z
        b[:, 11] = SH_C3[2] * y * (4 * zz - xx - yy)
        b[:, 12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        b[:, 13] = SH_C3[4] * x * (4 * zz - xx - yy)
        b[:, 14] = SH_C3[5] * z * (xx - yy)
        b[:, 15] = SH_C3[6] * x * (xx - 3 * yy)
        if with_grad:
            g[:, 9] = SH_C3[0] * np.stack([6 * xy, 3 * xx - 3 * yy, zero], 1)
            g[:, 10] = SH_C3[1] * np.stack([yz, xz, xy], 1)
            g[:, 11] = SH_C3[2] * np.stack([-2 * xy, 4 * zz - xx - 3 * yy, 8 * yz], 1)
            g[:, 12] = SH_C3[3] * np.stack([-6 * xz, -6 * yz, 6 * zz - 3 * xx - 3 * yy], 1)
            g[:, 13] = SH_C3[4] * np.stack([4 * zz - 3 * xx - yy, -2 * xy, 8 * xz], 1)
            g[:, 14] = SH_C3[5] * np.stack([2 * xz, -2 * yz, xx - yy], 1)
            g[:, 15] = SH_C3[6] * np.stack([3 * xx - 3 * yy, -6 * xy, zero], 1)
    del o
    return (b, g) if with_grad else b


def sh_colours(means: np.ndarray, sh: np.ndarray, cam_centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour [N, 3] (float64, clamped >= 0) and the unclamped mask [N, 3] seen from cam_centre [3] (world)."""
    k = sh.shape[1]
    if k == 1:
        raw = SH_C0 * sh[:, 0, :].astype(np.float64) + 0.5
    else:
        v = means.astype(np.float64) - cam_centre[None, :]
        d = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        raw = np.einsum("nk,nkc->nc", sh_basis(d, k), sh.astype(np.float64)) + 0.5
    return np.maximum(raw, 0.0), raw > 0.0
