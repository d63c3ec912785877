"""Covariance-based curvature correction (improved FLOAM, paper 000, section 2.3)."""

from __future__ import annotations

import numpy as np
from numba import njit

from slam.errors import ConfigError, InputError
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


@njit(cache=True, nogil=True)
def _kappa_kernel(xyz, q, idx):
    """``kappa_from_neighbours`` per query point in one pass (same formulas)."""
    m_all, k = idx.shape
    out = np.empty(m_all)
    for m in range(m_all):
        c0, c1, c2 = xyz[q[m], 0], xyz[q[m], 1], xyz[q[m], 2]
        s0 = s1 = s2 = 0.0
        xx = yy = zz = xy = xz = yz = 0.0
        for j in range(k):
            n = idx[m, j]
            d0, d1, d2 = xyz[n, 0] - c0, xyz[n, 1] - c1, xyz[n, 2] - c2
            s0 += d0
            s1 += d1
            s2 += d2
            xx += d0 * d0
            yy += d1 * d1
            zz += d2 * d2
            xy += d0 * d1
            xz += d0 * d2
            yz += d1 * d2
        xx -= s0 * s0 / k
        yy -= s1 * s1 / k
        zz -= s2 * s2 / k
        xy -= s0 * s1 / k
        xz -= s0 * s2 / k
        yz -= s1 * s2 / k
        fro = np.sqrt(xx**2 + yy**2 + zz**2 + 2.0 * (xy**2 + xz**2 + yz**2))
        out[m] = (xx + yy + zz) / fro if fro > 0 else 1.0
    return out


def kappa_from_neighbours(
    xyz: np.ndarray, q: np.ndarray, idx: np.ndarray, *, backend: str = "numba"
) -> np.ndarray:
    """kappa of xyz[q] (M,) from its (M, k) neighbour indices into xyz (itself included),
    e.g. the neighbourhoods SOR already searched. backend: "numba" (default, one compiled
    pass) or "numpy" (the vectorised reference); they agree to rounding (~1e-15)."""
    if backend not in ("numba", "numpy"):
        raise ConfigError(f"kappa: backend must be 'numba' or 'numpy', got {backend!r}")
    if backend == "numba" and idx.ndim == 2 and idx.shape[1] > 0:
        return _kappa_kernel(
            np.ascontiguousarray(xyz, dtype=np.float64),
            np.ascontiguousarray(q, dtype=np.int64),
            np.ascontiguousarray(idx, dtype=np.int64),
        )
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
