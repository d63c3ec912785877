"""k-nearest-neighbour queries shared by SOR and the covariance curvature (small_gicp KdTree).

small_gicp's KdTree was the fastest option measured for a 28.8k-point 16-beam scan at k=10
(vs scipy cKDTree with workers=1/-1 and unbalanced builds; see benchmarks/bench_preprocess.py).
"""

from __future__ import annotations

import numpy as np
import small_gicp
from scipy.spatial import cKDTree

from slam.errors import ConfigError

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


def fallback_tree(points: np.ndarray) -> cKDTree:
    """The KD-tree for the few queries the range image leaves (~0.3-1 % of a scan): scipy's
    unbalanced build is the cheapest to build (28.8k points: 2.6 ms CPU vs 5.1 for small_gicp
    and 1.9 for pykdtree, whose OpenMP query of a hundred points then cost 4 ms against
    0.5; benchmarks/bench_preprocess.py --knn)."""
    return cKDTree(points, leafsize=16, balanced_tree=False, compact_nodes=False)


def self_knn(
    xyz: np.ndarray,
    k: int,
    *,
    ring: np.ndarray | None = None,
    threads: int = KNN_THREADS,
    fallback: str = "boxes",
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's k nearest other points: (N, k+1) int64 indices, the point itself first,
    and (N, k) distances (m) to the k others, ascending. Needs 1 <= k <= N - 1.

    ring: (N,) beam index per point (``scan.ring``): the exact range-image search
    (``slam.preprocess.range_image``, same distances as the KD-tree, same index sets up to
    ties). fallback: how the points the window cannot certify are answered, "boxes" (the
    exact box search of ``range_image_knn(complete=True)``, default) or "kdtree" (a KD-tree
    over the whole scan, the earlier way, kept for benchmarks). Without ring: KD-tree.
    """
    if fallback not in ("boxes", "kdtree"):
        raise ConfigError(f"unknown k-NN fallback '{fallback}'; valid: boxes, kdtree")
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    if ring is None:
        idx, dist = knn(xyz, xyz, k + 1, threads)
        return idx, dist[:, 1:]
    from slam.preprocess.range_image import range_image_knn

    res = range_image_knn(xyz, ring, k, complete=fallback == "boxes")
    if res.complete:
        return res.idx, res.dist
    idx, dist = res.idx, res.dist
    bad = np.flatnonzero(~res.certified)
    if len(bad) > len(xyz) // 4:  # rings that are no beams: the whole scan to the KD-tree
        return self_knn(xyz, k, threads=threads)
    if len(bad):
        fb_dist, fb_idx = fallback_tree(xyz).query(xyz[bad], k + 1)
        others = fb_idx != bad[:, None]  # drop the point itself, or the (k+1)-th if absent
        others[others.all(axis=1), -1] = False
        idx[bad, 1:] = fb_idx[others].reshape(-1, k)
        dist[bad] = fb_dist[others].reshape(-1, k)
    return idx, dist
