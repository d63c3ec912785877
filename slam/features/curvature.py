"""Covariance-based curvature correction (improved FLOAM, paper 000, section 2.3)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import InputError

KAPPA_LINE = 1.0
KAPPA_PLANE = float(np.sqrt(2.0))
KAPPA_VOLUME = float(np.sqrt(3.0))


def local_covariances(xyz: np.ndarray, k: int = 10) -> np.ndarray:
    """(N, 3, 3) covariance (m^2) of each point's k nearest neighbours (itself included)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    if n < 2:
        raise InputError(f"need at least 2 points for local covariances, got {n}")
    k_eff = min(k, n)
    _, idx = cKDTree(xyz).query(xyz, k=k_eff, workers=-1)
    nb = xyz[idx.reshape(n, k_eff)]
    centred = nb - nb.mean(axis=1, keepdims=True)
    return np.matmul(centred.transpose(0, 2, 1), centred) / max(k_eff - 1, 1)


def covariance_curvature(xyz: np.ndarray, k: int = 10) -> np.ndarray:
    """kappa_i = tr(Sigma_i) / ||Sigma_i||_F per point (paper 000, curvature correction).

    Sigma_i is the covariance of the k nearest neighbours. kappa = sum(l) / sqrt(sum(l^2)) of
    the eigenvalues l: 1 on a line, sqrt(2) on an isotropic plane, sqrt(3) for isotropic
    scatter (noise). Dimensionless; a degenerate neighbourhood (all points equal) gives 1.
    """
    cov = local_covariances(xyz, k)
    tr = np.trace(cov, axis1=1, axis2=2)
    fro = np.sqrt(np.einsum("nij,nij->n", cov, cov))
    return np.where(fro > 0, tr / np.where(fro > 0, fro, 1.0), 1.0)
