"""Column stride: thin a dense spinning-lidar scan in azimuth, every ring kept.

A 64-128 beam scan (120-260k points) is a range image of rings x azimuth columns, 2-4x
denser along the ring than the 16-beam sensor paper 000 was designed for. Keeping one point
per ``stride`` columns of each ring leaves a range image with all its rings: LOAM's
along-ring curvature and the ring labels still work, the vertical resolution is untouched,
the horizontal one is ``stride`` times coarser.

Columns come from the azimuth atan2(y, x) seen from the sensor origin, never from the storage
order (drivers store points beam by beam, firing by firing or shuffled; every k-th stored
point of a firing-order cloud would drop whole lasers): each ring's turn is cut into
``n_columns // stride`` equal azimuth bins and each bin keeps its point nearest the bin's
start. A bin then keeps one of about ``stride`` returns, whatever the point order and even
where the estimated column count is a little off (the kept spacing is the bin width).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam.errors import InputError

COLUMN_PERCENTILE = 90.0  # rings that see returns all around set the column count


def ring_columns(ring: np.ndarray) -> int:
    """Columns of the range image: the 90th percentile of the points per ring (rings looking
    into the sky have gaps, a full ring has one point per column). ring < 0: not counted."""
    ring = np.asarray(ring)
    counts = np.bincount(ring[ring >= 0].astype(np.int64))
    counts = counts[counts > 0]
    return int(np.percentile(counts, COLUMN_PERCENTILE)) if len(counts) else 0


COLUMN_DROPOUT = 1.05  # a full ring may miss up to 5 % of its returns (absorbing surfaces)


def column_stride(n_points: int, n_columns: int, max_points: int, min_columns: int) -> int:
    """Stride s = ceil(n_points / max_points) (1 = keep the scan; max_points 0 = never thin),
    at most 1.05 n_columns / min_columns so that each ring keeps about >= min_columns
    columns (n_columns, counted from the returns, may miss a few percent of the real ones)."""
    if max_points <= 0 or n_points <= max_points:
        return 1
    s = math.ceil(n_points / max_points)
    if min_columns > 0:
        s = min(s, int(COLUMN_DROPOUT * n_columns / min_columns))
    return max(s, 1)


def _bins(
    xyz: np.ndarray, ring: np.ndarray, n_bins: int, phase: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bin id, azimuth offset in the bin (rad), ok): bin = ring * n_bins + azimuth bin; the
    bins start ``phase`` (a fraction of a bin) later."""
    w = 2.0 * np.pi / n_bins
    a = (np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi - phase * w) % (2.0 * np.pi)  # [0, 2 pi]
    col = np.minimum(np.floor(a / w).astype(np.int64), n_bins - 1)
    ring = ring.astype(np.int64)
    return ring * n_bins + col, a - col * w, ring >= 0


def stride_columns_reference(
    xyz: np.ndarray, ring: np.ndarray, stride: int, n_columns: int, phase: float = 0.0
) -> np.ndarray:
    """Ascending indices of the points kept: per ring and azimuth bin (2 pi * stride /
    n_columns rad wide, starting ``phase`` bins after azimuth -pi) the point nearest the
    bin's start (ties: the first stored); points with ring < 0 are all kept. The readable
    numpy reference of ``stride_columns``."""
    n_bins = max(n_columns // stride, 1)
    b, off, ok = _bins(xyz, ring, n_bins, phase)
    idx = np.flatnonzero(ok)
    order = idx[np.lexsort((off[idx], b[idx]))]  # by bin, then by offset (stable)
    first = np.r_[True, b[order][1:] != b[order][:-1]]
    return np.sort(np.concatenate([order[first], np.flatnonzero(~ok)]))


@njit(cache=True, nogil=True)
def _first_in_bin(b: np.ndarray, off: np.ndarray, ok: np.ndarray, n: int) -> np.ndarray:
    """(M,) ascending indices: per bin id 0..n-1 the smallest offset (the first on ties),
    plus every index with ok False."""
    best = np.full(n, -1, np.int64)
    for i in range(b.size):
        if ok[i]:
            j = b[i]
            if best[j] < 0 or off[i] < off[best[j]]:
                best[j] = i
    keep = ~ok
    for j in range(n):
        if best[j] >= 0:
            keep[best[j]] = True
    return np.flatnonzero(keep)


def stride_columns(
    xyz: np.ndarray, ring: np.ndarray, stride: int, n_columns: int, phase: float = 0.0
) -> np.ndarray:
    """Ascending indices of the points kept by a column stride (see
    ``stride_columns_reference``; compiled, O(N), the same indices)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    ring = np.asarray(ring)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or ring.shape != (len(xyz),):
        raise InputError(f"column stride needs (N, 3) points and (N,) rings, got {xyz.shape}")
    if stride < 1 or n_columns < 1:
        raise InputError(f"column stride needs stride >= 1 and n_columns >= 1, got {stride}")
    n_bins = max(n_columns // stride, 1)
    b, off, ok = _bins(xyz, ring, n_bins, phase)
    n_rings = int(ring.max()) + 1 if len(ring) else 0
    return _first_in_bin(b, off, ok, max(n_rings, 0) * n_bins)


def thin_scan(
    xyz: np.ndarray, ring: np.ndarray, max_points: int, min_columns: int, frame: int = 0
) -> tuple[np.ndarray | None, int]:
    """(indices kept or None, stride): the column stride a scan needs to hold about
    max_points points (``column_stride``), applied (``stride_columns``); None = untouched.

    frame: the scan's number in the sequence; the kept columns advance by one column per
    frame (phase (frame mod stride) / stride), so that s consecutive scans together sample
    every column. A fixed choice would sample the world only at the same azimuths while the
    sensor stands still (scan points fall exactly on the map's: an artificially low residual
    that made the first moving frames look lost) and leave the map as sparse as one scan."""
    if max_points <= 0 or len(xyz) <= max_points:
        return None, 1
    n_columns = ring_columns(ring)
    s = column_stride(len(xyz), n_columns, max_points, min_columns)
    if s <= 1:
        return None, 1
    return stride_columns(xyz, ring, s, n_columns, (frame % s) / s), s
