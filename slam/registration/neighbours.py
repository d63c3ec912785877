"""Exact k-nearest-neighbour queries of the registration modules (small_gicp's KdTree behind
``cKDTree.query``'s interface) and the thread count per batch."""

from __future__ import annotations

import numpy as np
import small_gicp

SERIAL_QUERIES = 20000  # below this many queries cKDTree runs on one thread (docs/speed.md)


def _workers(n_queries: int, threads: int) -> int:
    """cKDTree ``workers`` for a batch of ``n_queries``: ``threads`` for large batches only."""
    return threads if n_queries >= SERIAL_QUERIES else 1


class KnnTree:
    """Exact k-NN over fixed points with ``cKDTree.query``'s interface and results (k
    nearest, ascending; beyond ``distance_upper_bound`` or missing: inf and ``len(points)``),
    answered by small_gicp's KdTree: the same neighbours as a cKDTree at about half the cost
    (docs/speed.md)."""

    def __init__(self, points: np.ndarray):
        self.n = len(points)
        self._tree = small_gicp.KdTree(np.ascontiguousarray(points, dtype=np.float64), 1)

    def query(
        self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        k_found = min(int(k), self.n)
        if len(x) == 0 or k_found == 0:
            d, j = np.full((len(x), k), np.inf), np.full((len(x), k), self.n, dtype=np.int64)
        else:
            j, sq = self._tree.batch_knn_search(x, k_found, num_threads=max(int(workers), 1))
            j, d = j.astype(np.int64), np.sqrt(sq)
            far = ~(d < distance_upper_bound)  # cKDTree: neighbours closer than the bound
            d[far], j[far] = np.inf, self.n
            if k_found < k:
                d = np.pad(d, ((0, 0), (0, k - k_found)), constant_values=np.inf)
                j = np.pad(j, ((0, 0), (0, k - k_found)), constant_values=self.n)
        return (d[:, 0], j[:, 0]) if k == 1 else (d, j)
