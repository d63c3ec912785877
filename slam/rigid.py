"""Keeping 4x4 rigid transforms rigid.

A pose that is chained frame after frame (T_last @ T_motion, T @ exp(xi), inv(T_kf) @ T)
accumulates rounding in its rotation block, and a constant-velocity motion model feeds
that rounding back into the next prediction: on the 4412-scan building route LeGO-LOAM's
|R^T R - I| grew from 1e-12 to 0.17 over 410 keyframes (x4 every ~100 frames), the
"rotation" then scaled the map by 1.0003 and GTSAM's iSAM2 failed on the odometry factor
(indeterminate system). Projecting the rotation back onto SO(3) once it is off by more
than ``TOLERANCE`` stops it; below that the matrix is left bit for bit as it is (rounding
of ~1e-12 over a few hundred frames changes nothing a user can see).
"""

from __future__ import annotations

import numpy as np

TOLERANCE = 1e-9  # max |R^T R - I| kept as it is


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``R`` (3x3) in the Frobenius norm: U V^T of its SVD,
    with the sign of the last singular direction flipped if needed so that det = +1."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.ones(3)
    D[2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return (U * D) @ Vt


def orthonormalized(T: np.ndarray) -> np.ndarray:
    """A copy of the 4x4 transform ``T`` with its rotation block projected onto SO(3) and
    the bottom row set to (0, 0, 0, 1); the translation is kept."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(T[:3, :3])
    out[:3, 3] = T[:3, 3]
    return out


def kept_rigid(T: np.ndarray, tolerance: float = TOLERANCE) -> np.ndarray:
    """``T`` itself while its rotation is within ``tolerance`` of SO(3), else
    :func:`orthonormalized` (T)."""
    if rotation_error(T) <= tolerance:
        return T
    return orthonormalized(T)


def rotation_error(T: np.ndarray) -> float:
    """max |R^T R - I| of the rotation block of a 4x4 (or 3x3) matrix: 0 for a rotation."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    return float(np.abs(R.T @ R - np.eye(3)).max())
