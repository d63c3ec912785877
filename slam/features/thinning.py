"""Voxel thinning of a point subset in one hashed pass: the points ``voxel_downsample`` keeps.

The front ends thin three sets per frame: the edge and plane features (paper 000 registers
a few thousand of them) and, on keyframes, the whole filtered scan for the stored cloud.
``slam.preprocess.voxel.voxel_downsample`` sorts the packed voxel keys (a stable argsort,
most of its cost: ~6 ms CPU for the 108k plane candidates of a 64-beam scan); this kernel
bins the points through an open-addressing hash of their voxel cells instead, in input
order, so that every voxel sums its points in the same order as the sorted pass and keeps
the same point (nearest to the centroid, lowest index on ties): identical indices
(tests/test_thinning.py), without the sort and without gathering the subset first.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from slam.errors import InputError

_CELL_LIMIT = 2.0**60  # |coordinate / voxel| beyond this: the cell index would overflow


@njit(cache=True, nogil=True)
def _thin(xyz, idx, voxel, table_bits, keep):
    """Mark in ``keep`` (len(idx),) the position of each voxel's point nearest to its
    centroid; returns the number of voxels, or -1 when a cell index would overflow."""
    n = len(idx)
    size = 1 << table_bits
    mask = size - 1
    table = np.full(size, -1, dtype=np.int64)  # slot -> voxel id
    cells = np.empty((n, 3), dtype=np.int64)  # voxel id -> cell
    sums = np.zeros((n, 3))
    counts = np.zeros(n, dtype=np.int64)
    vid = np.empty(n, dtype=np.int64)  # position -> voxel id
    m = 0
    for a in range(n):
        i = idx[a]
        fx = np.floor(xyz[i, 0] / voxel)
        fy = np.floor(xyz[i, 1] / voxel)
        fz = np.floor(xyz[i, 2] / voxel)
        if abs(fx) > _CELL_LIMIT or abs(fy) > _CELL_LIMIT or abs(fz) > _CELL_LIMIT:
            return -1
        cx, cy, cz = np.int64(fx), np.int64(fy), np.int64(fz)
        h = ((cx * 73856093) ^ (cy * 19349663) ^ (cz * 83492791)) & mask
        while True:
            v = table[h]
            if v < 0:
                v = m
                table[h] = v
                cells[v, 0], cells[v, 1], cells[v, 2] = cx, cy, cz
                m += 1
                break
            if cells[v, 0] == cx and cells[v, 1] == cy and cells[v, 2] == cz:
                break
            h = (h + 1) & mask
        vid[a] = v
        # the sorted pass sums a voxel's points in ascending position: so does this loop
        sums[v, 0] += xyz[i, 0]
        sums[v, 1] += xyz[i, 1]
        sums[v, 2] += xyz[i, 2]
        counts[v] += 1
    for v in range(m):
        c = counts[v]
        sums[v, 0] = sums[v, 0] / c
        sums[v, 1] = sums[v, 1] / c
        sums[v, 2] = sums[v, 2] / c
    best = np.full(m, np.inf)
    pick = np.empty(m, dtype=np.int64)
    for a in range(n):
        i = idx[a]
        v = vid[a]
        d = (xyz[i, 0] - sums[v, 0]) ** 2
        d += (xyz[i, 1] - sums[v, 1]) ** 2
        d += (xyz[i, 2] - sums[v, 2]) ** 2
        if d < best[v]:  # strict: the lowest position wins ties
            best[v] = d
            pick[v] = a
    for v in range(m):
        keep[pick[v]] = True
    return m


def voxel_thin(xyz: np.ndarray, voxel: float, idx: np.ndarray | None = None) -> np.ndarray:
    """Sorted positions kept by voxel thinning of ``xyz[idx]`` (all of ``xyz`` without idx):
    per occupied voxel (edge ``voxel`` m) the point nearest to its centroid, lowest position
    on ties; equal to ``voxel_downsample(xyz[idx], voxel)``. voxel <= 0 keeps every point.
    ``idx`` must be ascending for that equality (feature index arrays are)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    idx = np.arange(len(xyz)) if idx is None else np.asarray(idx, dtype=np.int64)
    n = len(idx)
    if voxel <= 0 or n == 0:
        return np.arange(n)
    keep = np.zeros(n, dtype=np.bool_)
    bits = max(int(np.ceil(np.log2(2 * n))), 4)  # load factor <= 1/2
    m = _thin(np.ascontiguousarray(xyz), np.ascontiguousarray(idx), float(voxel), bits, keep)
    if m < 0:
        raise InputError(f"voxel {voxel} m is too small for a cloud this large")
    return np.flatnonzero(keep)


def thin_to_count(
    parts: list[np.ndarray], voxels: list[float], max_points: int, growth: float = 1.1
) -> list[np.ndarray]:
    """Sorted positions of at most ``max_points`` points of the clouds ``parts`` together,
    spread evenly in space: each part voxel-thinned at ``voxels[i] * s``, with s the first
    of sqrt(n / max_points) * growth**m (m = 0, 1, ...; n the points of all parts; surface
    samples thin as 1/s^2) that leaves no more than that; every point when there are few
    enough. A density-aware cap that keeps the parts' proportions (edge and plane features
    grow coarser together): dense regions lose points first, sparse ones keep theirs."""
    if max_points < 1:
        raise InputError(f"max_points must be >= 1, got {max_points}")
    if len(parts) != len(voxels) or not all(v > 0 for v in voxels) or not growth > 1:
        raise InputError(f"need one voxel > 0 m per part and growth > 1, got {voxels}, {growth}")
    keep = [np.arange(len(x)) for x in parts]
    n = sum(len(k) for k in keep)
    if n <= max_points:
        return keep
    scale = float(np.sqrt(n / max_points)) / growth
    while sum(len(k) for k in keep) > max_points:
        scale *= growth
        keep = [voxel_thin(x, v * scale) for x, v in zip(parts, voxels, strict=True)]
    return keep
