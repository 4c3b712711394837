"""Quaternions (wxyz) <-> rotation matrices: the one numpy implementation used across the runtime; and ORTHO_TOL,
the one tolerance on a pose's rotation that every validator uses (rig.Camera's cam_to_ego and lidar_to_ego, the
renderer's, in runtime/camera.py: one validator)."""

from __future__ import annotations

import numpy as np

# max |R^T R - I| entry accepted for a pose's rotation block (calibration files carry ~1e-7 noise, poses stored in
# float32 ~1e-7, rotations printed with 4 decimals ~1e-4). One constant for every check: a rig that rig.load_rig
# accepts must never be refused later by the renderer's camera (the rig took 1e-3 and the renderer 1e-4: such a
# rig's LiDAR reconstruction then failed with an internal error, issue 27).
ORTHO_TOL = 1e-3


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """q [..., 4] wxyz (any non-zero norm; normalised here) -> R [..., 3, 3] float64."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def rotmats_to_quats(R: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotations -> [N, 4] unit quaternions wxyz (rotmat_to_quat for many: each row takes the branch of
    its largest diagonal term / trace, so no division by a small number)."""
    R = np.asarray(R, np.float64)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = m00 + m11 + m22
    q = np.empty((len(R), 4))
    cases = np.stack([tr, m00, m11, m22], axis=1).argmax(axis=1)
    for c in range(4):
        i = np.flatnonzero(cases == c)
        if not i.size:
            continue
        r = R[i]
        if c == 0:
            s4 = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = np.stack([0.25 * s4, (r[:, 2, 1] - r[:, 1, 2]) / s4, (r[:, 0, 2] - r[:, 2, 0]) / s4,
                             (r[:, 1, 0] - r[:, 0, 1]) / s4], axis=1)
        elif c == 1:
            s4 = 2.0 * np.sqrt(np.maximum(1.0 + m00[i] - m11[i] - m22[i], 1e-12))
            q[i] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s4, 0.25 * s4, (r[:, 0, 1] + r[:, 1, 0]) / s4,
                             (r[:, 0, 2] + r[:, 2, 0]) / s4], axis=1)
        elif c == 2:
            s4 = 2.0 * np.sqrt(np.maximum(1.0 + m11[i] - m00[i] - m22[i], 1e-12))
            q[i] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s4, (r[:, 0, 1] + r[:, 1, 0]) / s4, 0.25 * s4,
                             (r[:, 1, 2] + r[:, 2, 1]) / s4], axis=1)
        else:
            s4 = 2.0 * np.sqrt(np.maximum(1.0 + m22[i] - m00[i] - m11[i], 1e-12))
            q[i] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s4, (r[:, 0, 2] + r[:, 2, 0]) / s4,
                             (r[:, 1, 2] + r[:, 2, 1]) / s4, 0.25 * s4], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> [4] unit quaternion wxyz with w >= 0 (rotmats_to_quats of one matrix)."""
    q = rotmats_to_quats(np.asarray(R, np.float64)[None])[0]
    return -q if q[0] < 0 else q
