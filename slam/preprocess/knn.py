"""k-nearest-neighbour queries shared by SOR and the covariance curvature (small_gicp KdTree).

small_gicp's KdTree was the fastest option measured for a 28.8k-point 16-beam scan at k=10
(vs scipy cKDTree with workers=1/-1 and unbalanced builds; see benchmarks/bench_preprocess.py).
"""

from __future__ import annotations

import numpy as np
import small_gicp

KNN_THREADS = 2  # build + query threads (28 vs 41 ms for a 28.8k-point scan at k=10, quiet box)


def knn(
    points: np.ndarray, queries: np.ndarray, k: int, threads: int = KNN_THREADS
) -> tuple[np.ndarray, np.ndarray]:
    """(M, k) int64 indices into points and (M, k) distances (m) of each query's k nearest
    points, ascending (a query that is in points finds itself first). Needs k <= len(points)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = np.ascontiguousarray(queries, dtype=np.float64)
    if len(queries) == 0:
        return np.empty((0, k), dtype=np.int64), np.empty((0, k))
    tree = small_gicp.KdTree(points, num_threads=threads)
    idx, sq = tree.batch_knn_search(queries, k, num_threads=threads)
    return idx.astype(np.int64, copy=False), np.sqrt(sq)
