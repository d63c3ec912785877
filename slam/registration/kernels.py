"""Compiled (numba) kernels of the registration solvers; each equals a numpy reference.

- ``linearise`` / ``cost``: H = sum w J^T W J, b = sum w J^T W e, cost = sum w e^T W e with
  e = R p + t - q and J = R [-[p]x, I] (rotation first, right perturbation) -- the numpy
  reference is ``slam.registration.solver._linearise`` / ``_cost``.
- ``gicp_information``: W_i = (R Sigma_p,i R^T + Sigma_q,j(i))^-1, eqs. (3) and (5) of paper
  000 -- the numpy reference is the einsum + ``np.linalg.inv`` of ``gicp_align``'s association.

One pass over the correspondences, no (N, 3, 6) temporaries; serial (a few thousand
correspondences per frame: threads would cost more than they save on 2 cores).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _accumulate(T, p, q, W, w, H, b, with_jacobian):
    R = T[:3, :3]
    t = T[:3, 3]
    cost = 0.0
    e = np.empty(3)
    J = np.empty((3, 6))
    WJ = np.empty((3, 6))
    for n in range(len(p)):
        px, py, pz = p[n, 0], p[n, 1], p[n, 2]
        for i in range(3):
            e[i] = R[i, 0] * px + R[i, 1] * py + R[i, 2] * pz + t[i] - q[n, i]
        We0 = W[n, 0, 0] * e[0] + W[n, 0, 1] * e[1] + W[n, 0, 2] * e[2]
        We1 = W[n, 1, 0] * e[0] + W[n, 1, 1] * e[1] + W[n, 1, 2] * e[2]
        We2 = W[n, 2, 0] * e[0] + W[n, 2, 1] * e[1] + W[n, 2, 2] * e[2]
        wn = w[n]
        cost += wn * (e[0] * We0 + e[1] * We1 + e[2] * We2)
        if not with_jacobian:
            continue
        # J = R [-[p]x, I]; -[p]x = [[0, pz, -py], [-pz, 0, px], [py, -px, 0]]
        for i in range(3):
            J[i, 0] = -R[i, 1] * pz + R[i, 2] * py
            J[i, 1] = R[i, 0] * pz - R[i, 2] * px
            J[i, 2] = -R[i, 0] * py + R[i, 1] * px
            J[i, 3] = R[i, 0]
            J[i, 4] = R[i, 1]
            J[i, 5] = R[i, 2]
        for i in range(3):
            for c in range(6):
                WJ[i, c] = wn * (W[n, i, 0] * J[0, c] + W[n, i, 1] * J[1, c] + W[n, i, 2] * J[2, c])
        for r in range(6):
            b[r] += wn * (J[0, r] * We0 + J[1, r] * We1 + J[2, r] * We2)
            for c in range(r, 6):
                H[r, c] += J[0, r] * WJ[0, c] + J[1, r] * WJ[1, c] + J[2, r] * WJ[2, c]
    if with_jacobian:
        for r in range(6):
            for c in range(r):
                H[r, c] = H[c, r]
    return cost


def _weights(w, n):
    return np.ones(n) if w is None else np.ascontiguousarray(w, dtype=np.float64)


def _c(a):
    return np.ascontiguousarray(a, dtype=np.float64)


def linearise(T, p, q, W, w):
    """(H 6x6, b 6, cost) of sum w e^T W e; same as ``solver._linearise``."""
    H = np.zeros((6, 6))
    b = np.zeros(6)
    cost = _accumulate(_c(T), _c(p), _c(q), _c(W), _weights(w, len(p)), H, b, True)
    return H, b, float(cost)


def cost(T, p, q, W, w) -> float:
    """sum w e^T W e; same as ``solver._cost``."""
    H = np.zeros((1, 1))
    b = np.zeros(1)
    return float(_accumulate(_c(T), _c(p), _c(q), _c(W), _weights(w, len(p)), H, b, False))


@njit(cache=True, nogil=True)
def _information(R, src_covs, ok_idx, tgt_covs, j, out):
    C = np.empty((3, 3))
    RS = np.empty((3, 3))
    for n in range(len(ok_idx)):
        S = src_covs[ok_idx[n]]
        Q = tgt_covs[j[n]]
        for r in range(3):
            for c in range(3):
                RS[r, c] = R[r, 0] * S[0, c] + R[r, 1] * S[1, c] + R[r, 2] * S[2, c]
        for r in range(3):
            for c in range(3):
                C[r, c] = RS[r, 0] * R[c, 0] + RS[r, 1] * R[c, 1] + RS[r, 2] * R[c, 2] + Q[r, c]
        # symmetric 3x3 inverse by cofactors
        a00 = C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]
        a01 = C[0, 2] * C[2, 1] - C[0, 1] * C[2, 2]
        a02 = C[0, 1] * C[1, 2] - C[0, 2] * C[1, 1]
        det = C[0, 0] * a00 + C[1, 0] * a01 + C[2, 0] * a02
        inv = 1.0 / det
        out[n, 0, 0] = a00 * inv
        out[n, 0, 1] = a01 * inv
        out[n, 0, 2] = a02 * inv
        out[n, 1, 0] = (C[1, 2] * C[2, 0] - C[1, 0] * C[2, 2]) * inv
        out[n, 1, 1] = (C[0, 0] * C[2, 2] - C[0, 2] * C[2, 0]) * inv
        out[n, 1, 2] = (C[0, 2] * C[1, 0] - C[0, 0] * C[1, 2]) * inv
        out[n, 2, 0] = (C[1, 0] * C[2, 1] - C[1, 1] * C[2, 0]) * inv
        out[n, 2, 1] = (C[0, 1] * C[2, 0] - C[0, 0] * C[2, 1]) * inv
        out[n, 2, 2] = (C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]) * inv


def gicp_information(
    R: np.ndarray, src_covs: np.ndarray, ok_idx: np.ndarray, tgt_covs: np.ndarray, j: np.ndarray
) -> np.ndarray:
    """(n, 3, 3) (R Sigma_p[ok_idx] R^T + Sigma_q[j])^-1 (eqs. (3), (5)), 1/m^2."""
    out = np.empty((len(ok_idx), 3, 3))
    _information(
        _c(R),
        _c(src_covs),
        np.ascontiguousarray(ok_idx, dtype=np.int64),
        _c(tgt_covs),
        np.ascontiguousarray(j, dtype=np.int64),
        out,
    )
    return out


@njit(cache=True, nogil=True)
def _neighbour_covariances(xyz, idx, out):
    k = idx.shape[1]
    for n in range(len(idx)):
        mx = my = mz = 0.0
        for c in range(k):
            j = idx[n, c]
            mx += xyz[j, 0]
            my += xyz[j, 1]
            mz += xyz[j, 2]
        mx /= k
        my /= k
        mz /= k
        sxx = sxy = sxz = syy = syz = szz = 0.0
        for c in range(k):
            j = idx[n, c]
            dx = xyz[j, 0] - mx
            dy = xyz[j, 1] - my
            dz = xyz[j, 2] - mz
            sxx += dx * dx
            sxy += dx * dy
            sxz += dx * dz
            syy += dy * dy
            syz += dy * dz
            szz += dz * dz
        f = 1.0 / (k - 1)
        out[n, 0, 0] = sxx * f
        out[n, 0, 1] = out[n, 1, 0] = sxy * f
        out[n, 0, 2] = out[n, 2, 0] = sxz * f
        out[n, 1, 1] = syy * f
        out[n, 1, 2] = out[n, 2, 1] = syz * f
        out[n, 2, 2] = szz * f


def neighbour_covariances(xyz: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(n, 3, 3) sample covariances 1/(k-1) sum (p - mean)(p - mean)^T of the neighbour sets
    ``xyz[idx]`` (idx (n, k), k >= 2), m^2: eq. (1) of paper 000 without the lambda I; the
    numpy reference is the einsum in ``covariances._sample_covariances``."""
    out = np.empty((len(idx), 3, 3))
    _neighbour_covariances(_c(xyz), np.ascontiguousarray(idx, dtype=np.int64), out)
    return out


@njit(cache=True, nogil=True)
def _gicp_terms(T, src, src_covs, tgt_pts, tgt_covs, j, n_tgt, p, q, W, H, b):
    """``_information`` then ``_accumulate`` (unit weights) fused in one pass over the source
    points that have a correspondence (j < n_tgt), in their order: the same arithmetic in
    the same order, so the same W, H, b and cost to the bit; p, q, W get the inlier rows."""
    R = T[:3, :3]
    t = T[:3, 3]
    C = np.empty((3, 3))
    RS = np.empty((3, 3))
    e = np.empty(3)
    J = np.empty((3, 6))
    WJ = np.empty((3, 6))
    cost = 0.0
    m = 0
    for i in range(len(src)):
        jj = j[i]
        if jj >= n_tgt:
            continue
        S = src_covs[i]
        Q = tgt_covs[jj]
        for r in range(3):
            for c in range(3):
                RS[r, c] = R[r, 0] * S[0, c] + R[r, 1] * S[1, c] + R[r, 2] * S[2, c]
        for r in range(3):
            for c in range(3):
                C[r, c] = RS[r, 0] * R[c, 0] + RS[r, 1] * R[c, 1] + RS[r, 2] * R[c, 2] + Q[r, c]
        a00 = C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]
        a01 = C[0, 2] * C[2, 1] - C[0, 1] * C[2, 2]
        a02 = C[0, 1] * C[1, 2] - C[0, 2] * C[1, 1]
        det = C[0, 0] * a00 + C[1, 0] * a01 + C[2, 0] * a02
        inv = 1.0 / det
        Wm = W[m]
        Wm[0, 0] = a00 * inv
        Wm[0, 1] = a01 * inv
        Wm[0, 2] = a02 * inv
        Wm[1, 0] = (C[1, 2] * C[2, 0] - C[1, 0] * C[2, 2]) * inv
        Wm[1, 1] = (C[0, 0] * C[2, 2] - C[0, 2] * C[2, 0]) * inv
        Wm[1, 2] = (C[0, 2] * C[1, 0] - C[0, 0] * C[1, 2]) * inv
        Wm[2, 0] = (C[1, 0] * C[2, 1] - C[1, 1] * C[2, 0]) * inv
        Wm[2, 1] = (C[0, 1] * C[2, 0] - C[0, 0] * C[2, 1]) * inv
        Wm[2, 2] = (C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]) * inv
        px, py, pz = src[i, 0], src[i, 1], src[i, 2]
        p[m, 0], p[m, 1], p[m, 2] = px, py, pz
        q[m, 0], q[m, 1], q[m, 2] = tgt_pts[jj, 0], tgt_pts[jj, 1], tgt_pts[jj, 2]
        for r in range(3):
            e[r] = R[r, 0] * px + R[r, 1] * py + R[r, 2] * pz + t[r] - q[m, r]
        We0 = Wm[0, 0] * e[0] + Wm[0, 1] * e[1] + Wm[0, 2] * e[2]
        We1 = Wm[1, 0] * e[0] + Wm[1, 1] * e[1] + Wm[1, 2] * e[2]
        We2 = Wm[2, 0] * e[0] + Wm[2, 1] * e[1] + Wm[2, 2] * e[2]
        cost += e[0] * We0 + e[1] * We1 + e[2] * We2
        for r in range(3):
            J[r, 0] = -R[r, 1] * pz + R[r, 2] * py
            J[r, 1] = R[r, 0] * pz - R[r, 2] * px
            J[r, 2] = -R[r, 0] * py + R[r, 1] * px
            J[r, 3] = R[r, 0]
            J[r, 4] = R[r, 1]
            J[r, 5] = R[r, 2]
        for r in range(3):
            for c in range(6):
                WJ[r, c] = Wm[r, 0] * J[0, c] + Wm[r, 1] * J[1, c] + Wm[r, 2] * J[2, c]
        for r in range(6):
            b[r] += J[0, r] * We0 + J[1, r] * We1 + J[2, r] * We2
            for c in range(r, 6):
                H[r, c] += J[0, r] * WJ[0, c] + J[1, r] * WJ[1, c] + J[2, r] * WJ[2, c]
        m += 1
    for r in range(6):
        for c in range(r):
            H[r, c] = H[c, r]
    return cost, m


def gicp_terms(T, src, src_covs, tgt_pts, tgt_covs, j):
    """GICP association terms at T in one pass: (p, q, W, H, b, cost) of the source points
    with a correspondence (``j[i] < len(tgt_pts)``; cKDTree's "missing" index), in source
    order; equal to ``gicp_information`` on them followed by ``linearise`` (unit weights)."""
    n_tgt = len(tgt_pts)
    n = len(src)
    p, q, W = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    H, b = np.zeros((6, 6)), np.zeros(6)
    cost, m = _gicp_terms(
        _c(T), _c(src), _c(src_covs), _c(tgt_pts), _c(tgt_covs),
        np.ascontiguousarray(j, dtype=np.int64), n_tgt, p, q, W, H, b,
    )  # fmt: skip
    return p[:m], q[:m], W[:m], H, b, float(cost)
