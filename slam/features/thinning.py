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


@njit(cache=True)
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
    xyz: np.ndarray, voxel: float, max_points: int, growth: float = 1.25
) -> np.ndarray:
    """Sorted positions of at most ``max_points`` of ``xyz``, spread evenly in space: voxel
    thinning at ``voxel * growth**m`` (m), m the smallest that leaves no more than that
    (m = 0: every point when there are few enough). A density-aware cap: dense regions lose
    points first, sparse ones keep theirs."""
    if max_points < 1:
        raise InputError(f"max_points must be >= 1, got {max_points}")
    if not (voxel > 0 and growth > 1):
        raise InputError(f"need voxel > 0 m and growth > 1, got {voxel}, {growth}")
    keep = np.arange(len(xyz))
    size = float(voxel)
    while len(keep) > max_points:
        size *= growth
        keep = voxel_thin(xyz, size)
    return keep
