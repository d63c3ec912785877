"""Covariance-based curvature correction (improved FLOAM, paper 000, section 2.3)."""

from __future__ import annotations

import numpy as np

from slam.errors import InputError
from slam.preprocess.knn import knn

KAPPA_LINE = 1.0
KAPPA_PLANE = float(np.sqrt(2.0))
KAPPA_VOLUME = float(np.sqrt(3.0))


def _check(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    if len(xyz) < 2:
        raise InputError(f"need at least 2 points for local covariances, got {len(xyz)}")
    return xyz


def local_covariances(
    xyz: np.ndarray, k: int = 10, query_idx: np.ndarray | None = None
) -> np.ndarray:
    """(M, 3, 3) covariance (m^2) of the k nearest neighbours (itself included) of each point,
    or of xyz[query_idx] only (neighbours still searched in all of xyz)."""
    xyz = _check(xyz)
    k_eff = min(k, len(xyz))
    queries = xyz if query_idx is None else xyz[np.asarray(query_idx, dtype=np.int64)]
    idx, _ = knn(xyz, queries, k_eff)
    centred = xyz[idx]
    centred -= centred.mean(axis=1, keepdims=True)
    return np.einsum("mki,mkj->mij", centred, centred) / max(k_eff - 1, 1)


def covariance_curvature(
    xyz: np.ndarray, k: int = 10, query_idx: np.ndarray | None = None
) -> np.ndarray:
    """kappa_i = tr(Sigma_i) / ||Sigma_i||_F per point (paper 000, curvature correction).

    Sigma_i is the covariance of the k nearest neighbours. kappa = sum(l) / sqrt(sum(l^2)) of
    the eigenvalues l: 1 on a line, sqrt(2) on an isotropic plane, sqrt(3) for isotropic
    scatter (noise). Dimensionless; a degenerate neighbourhood (all points equal) gives 1.
    query_idx: optional (M,) indices; then kappa (M,) of those points only, equal to the full
    computation's value at those indices (one tree over all of xyz, M queries).
    """
    xyz = _check(xyz)
    k_eff = min(k, len(xyz))
    q = np.arange(len(xyz)) if query_idx is None else np.asarray(query_idx, dtype=np.int64)
    idx, _ = knn(xyz, xyz[q], k_eff)
    return kappa_from_neighbours(xyz, q, idx)


def kappa_from_neighbours(xyz: np.ndarray, q: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """kappa of xyz[q] (M,) from its (M, k) neighbour indices into xyz (itself included),
    e.g. the neighbourhoods SOR already searched."""
    k_eff = idx.shape[1]
    idx_t = np.ascontiguousarray(idx.T)  # (k, M): reductions over k become row adds
    cols = [np.ascontiguousarray(xyz[:, a]) for a in range(3)]
    # neighbour offsets from the query point, one (k, M) array per axis; the scatter matrix
    # is sum d d^T - (sum d)(sum d)^T / k (offsets are small: no cancellation)
    d = [c[idx_t] - c[q] for c in cols]
    s = [di.sum(axis=0) for di in d]

    def dot(a: int, b: int) -> np.ndarray:
        return np.einsum("km,km->m", d[a], d[b]) - s[a] * s[b] / k_eff

    sxx, syy, szz, sxy, sxz, syz = dot(0, 0), dot(1, 1), dot(2, 2), dot(0, 1), dot(0, 2), dot(1, 2)
    tr = sxx + syy + szz
    fro = np.sqrt(sxx**2 + syy**2 + szz**2 + 2.0 * (sxy**2 + sxz**2 + syz**2))
    return np.where(fro > 0, tr / np.where(fro > 0, fro, 1.0), 1.0)
