"""SE(3) helpers of the registration solvers, GTSAM's conventions: rotation first in the
tangent, perturbation on the right (``T <- T exp(xi)``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 exp of a twist xi = (omega, v), rotation first (GTSAM Pose3.Expmap ordering)."""
    omega, v = np.asarray(xi[:3], float), np.asarray(xi[3:], float)
    theta = float(np.linalg.norm(omega))
    K = skew(omega)
    if theta < 1e-9:
        V = np.eye(3) + 0.5 * K
    else:
        V = (
            np.eye(3)
            + (1 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * (K @ K)
        )
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(omega).as_matrix()
    T[:3, 3] = V @ v
    return T


def transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to (N, 3) points."""
    return xyz @ T[:3, :3].T + T[:3, 3]
