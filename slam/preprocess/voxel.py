"""Voxel-grid downsampling that keeps real points (indices), so every per-point field follows."""

from __future__ import annotations

import numpy as np

from slam.errors import InputError


def voxel_keys(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(N,) int64 id of the voxel (edge ``voxel`` m) holding each point; equal id = same voxel."""
    cells = np.floor(xyz / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        raise InputError(f"voxel {voxel} m is too small for a cloud this large")
    return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]


def voxel_downsample(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """Sorted indices of kept points: per occupied voxel, the point nearest to its centroid.

    voxel: edge length in metres; <= 0 keeps every point. Vectorised (one sort, bincounts).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    if voxel <= 0 or n == 0:
        return np.arange(n)
    _, inverse, counts = np.unique(voxel_keys(xyz, voxel), return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    centroid = np.stack(
        [np.bincount(inverse, weights=xyz[:, a]) / counts for a in range(3)], axis=1
    )
    dist2 = np.sum((xyz - centroid[inverse]) ** 2, axis=1)
    order = np.lexsort((dist2, inverse))
    first = np.ones(n, dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    return np.sort(order[first])
