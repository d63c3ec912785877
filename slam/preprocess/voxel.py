"""Voxel-grid downsampling that keeps real points (indices), so every per-point field follows.

``voxel_downsample`` runs one numpy argsort of the packed voxel keys and a compiled (numba)
pass over the sorted segments; ``voxel_downsample_reference`` is the vectorised numpy
reference it replaces (same indices: same summation order, same tie rule).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from slam.errors import InputError


def voxel_keys(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(N,) int64 id of the voxel (edge ``voxel`` m) holding each point; equal id = same voxel."""
    # one contiguous row per axis: reductions along rows are several times faster than
    # axis-0 reductions over an (N, 3) array
    cells = np.floor(np.ascontiguousarray(xyz.T) / voxel).astype(np.int64)
    cells -= cells.min(axis=1, keepdims=True)
    dims = cells.max(axis=1) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        raise InputError(f"voxel {voxel} m is too small for a cloud this large")
    return (cells[0] * dims[1] + cells[1]) * dims[2] + cells[2]


@njit(cache=True, nogil=True)
def _nearest_to_centroid(xyz, order, ks, out):
    """Per run of equal keys in ``ks`` (sorted, rows ``order``): the row nearest to the
    run's centroid (first on ties); returns how many were written to ``out``."""
    n = len(order)
    m = 0
    a = 0
    while a < n:
        b = a + 1
        while b < n and ks[b] == ks[a]:
            b += 1
        sx = sy = sz = 0.0
        for i in range(a, b):
            r = order[i]
            sx += xyz[r, 0]
            sy += xyz[r, 1]
            sz += xyz[r, 2]
        cnt = b - a
        cx, cy, cz = sx / cnt, sy / cnt, sz / cnt
        best = np.inf
        pick = order[a]
        for i in range(a, b):
            r = order[i]
            d = (xyz[r, 0] - cx) ** 2
            d += (xyz[r, 1] - cy) ** 2
            d += (xyz[r, 2] - cz) ** 2
            if d < best:
                best = d
                pick = r
        out[m] = pick
        m += 1
        a = b
    return m


def voxel_downsample(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """Sorted indices of kept points: per occupied voxel, the point nearest to its centroid.

    voxel: edge length in metres; <= 0 keeps every point. Ties go to the lowest index.
    One stable argsort of the packed int64 voxel keys, then one compiled pass over the
    segments (equal to ``voxel_downsample_reference``).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    if voxel <= 0 or n == 0:
        return np.arange(n)
    keys = voxel_keys(xyz, voxel)
    order = np.argsort(keys, kind="stable")  # within a voxel: ascending index
    out = np.empty(n, dtype=np.int64)
    m = _nearest_to_centroid(np.ascontiguousarray(xyz), order, keys[order], out)
    return np.sort(out[:m])


def voxel_downsample_reference(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """The numpy reference of ``voxel_downsample`` (segment reductions, no compiled code)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    if voxel <= 0 or n == 0:
        return np.arange(n)
    keys = voxel_keys(xyz, voxel)
    order = np.argsort(keys, kind="stable")  # within a voxel: ascending index
    ks = keys[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[start, n])
    seg = np.repeat(np.arange(len(start)), counts)
    dist2 = np.zeros(n)
    for a in range(3):  # per axis: (x - cx)^2 + (y - cy)^2 + (z - cz)^2, summed in that order
        pa = xyz[order, a]
        ca = np.bincount(seg, weights=pa) / counts
        dist2 += (pa - ca[seg]) ** 2
    best = dist2 == np.minimum.reduceat(dist2, start)[seg]
    first = np.flatnonzero(best)
    first = first[np.r_[True, seg[first[1:]] != seg[first[:-1]]]]  # lowest index among ties
    return np.sort(order[first])
