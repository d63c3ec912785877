"""Map covariances recomputed when first used instead of when a neighbour arrives.

Inserting a scan changes the eq. (1) neighbourhood of the old map points near it. Recomputing
all of them at once (about five old points per new one on a car drive) is most of the map
work of a frame, while the next registration reaches only a few thousand map points. Here
such rows are marked stale (a NaN in their covariance) and recomputed, from the map as it is
then, the first time a correspondence search returns them. A row used by the next
registration gets the value the eager refresh would have given (the map has not changed in
between); one used later sees the map of that time.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam.mapping.local_map import VoxelHashMap

# rows (int64) -> their (n, 3, 3) covariances from the current map
Recompute = Callable[[np.ndarray], np.ndarray]


def mark_stale(covs: np.ndarray, rows: np.ndarray) -> None:
    """Flag ``rows`` of the map's (M, 3, 3) covariances for recomputation on first use."""
    covs[rows, 0, 0] = np.nan


def stale_rows(covs: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """The rows among ``rows`` (all when None) whose covariance is flagged stale."""
    if rows is None:
        return np.flatnonzero(np.isnan(covs[:, 0, 0]))
    return rows[np.isnan(covs[rows, 0, 0])]


class FreshCovarianceMap:
    """The local map as a GICP target's neighbour index (``cKDTree.query``'s signature) that
    recomputes the stale covariances of the rows each query returns before handing them on."""

    def __init__(self, voxel_map: VoxelHashMap, recompute: Recompute):
        self._map = voxel_map
        self._recompute = recompute
        self.recomputed = 0  # rows recomputed through this object

    def __len__(self) -> int:
        return len(self._map)

    def query(self, x, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1):
        d, j = self._map.query(x, k=k, distance_upper_bound=distance_upper_bound, workers=workers)
        used = j[j < len(self._map)]
        if used.size:
            self.refresh(np.unique(used))
        return d, j

    def refresh(self, rows: np.ndarray | None = None) -> None:
        """Recompute the stale covariances among ``rows`` (every stale row when None)."""
        covs = self._map.covs
        stale = stale_rows(covs, rows)
        if stale.size:
            covs[stale] = self._recompute(stale)
            self.recomputed += int(stale.size)
