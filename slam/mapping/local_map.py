"""A bounded local map updated incrementally: voxel hashing with a per-voxel point cap and
exact nearest-neighbour queries through the hash (no KD-tree of the map on any hot path).

Like KISS-ICP's VoxelHashMap: points (in the odometry frame) are binned into voxels of
``voxel_size`` metres; a voxel accepts new points until it holds ``max_points_per_voxel``;
points farther than ``radius`` from the sensor are dropped every ``prune_distance`` of
travel. Optional per-point covariances (3x3, odometry frame) travel with the points, so a
GICP target needs no re-estimation.

Layout (kernels in ``local_map_kernels``): flat point / covariance arrays grown by doubling,
an open-addressing hash table voxel key -> voxel id with the rows of its points (at most the
cap), and a second table of coarse cells (``COARSE`` voxels a side) -> a linked list of their
voxels. Insertion appends (O(batch)); eviction by radius visits the coarse cells the sphere
cuts and fills each removed row with the last one (O(removed + boundary), no compaction or
rehash of the map), so the map work of a frame is bounded by what changed, not by the map.

``query`` has the signature and the results of ``scipy.spatial.cKDTree.query`` (k nearest,
ascending, missing neighbours as distance inf and index ``len(map)``), so the map itself can
stand in for a KD-tree (``GicpTarget(..., tree=map)``). It is exact: it scans the voxel
shells around a query outwards until the k-th neighbour found is closer than every point
of the unscanned voxels (or than ``distance_upper_bound``); a query not settled within
``MAX_SHELLS`` shells (an isolated point: sparse far returns) goes on over shells of coarse
cells, opening only the voxels nearer than its current k-th neighbour. Batches of at least
``PARALLEL_QUERIES`` queries (the map update's neighbour queries) are split over
``LocalMapConfig.threads`` numba threads; every query writes only its own rows, so the
answers do not depend on the threads or their timing (tests/test_local_map.py,
tests/test_same_run_twice.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from slam.deferred import numba_threads
from slam.errors import ConfigError, InputError
from slam.mapping import local_map_kernels as K

_OFFSET = np.int64(1 << 20)  # voxel coordinates are packed into 21 bits each
_EMPTY = np.int64(-1)
MAX_SHELLS = 2  # voxel shells scanned before a query goes on over coarse cells (or as many
# as a finite distance bound needs, up to MAX_BOUNDED_SHELLS)
MAX_BOUNDED_SHELLS = 4
_SHELLS = K.shell_offsets(max(MAX_SHELLS, MAX_BOUNDED_SHELLS))  # voxel visiting order
PARALLEL_QUERIES = 4000  # batches at least this large run on numba's threads (the map
# update's neighbour queries: 5-20k per frame on a car drive); smaller ones, e.g. one GICP
# iteration on a 16-beam indoor scan, stay serial (a parallel region's start-up and barrier)
COARSE = 8  # voxels per side of a coarse cell (4 m with the default 0.5 m voxels)


@dataclass
class LocalMapConfig:
    """voxel_size (m), max_points_per_voxel, radius (m) of the kept neighbourhood.

    prune_distance (m): points beyond ``radius`` are dropped once the sensor has moved this
    far since the last pruning (only the coarse cells the sphere cuts are visited): older
    points stay within ``radius + prune_distance``, newer scans reach as far as the sensor.
    threads: numba threads for query batches of at least ``PARALLEL_QUERIES`` points (same
    answers; a map refresh on a worker thread runs serial); 1 = always serial (the default:
    a second thread saves no wall time, docs/speed.md)."""

    voxel_size: float = 0.5
    max_points_per_voxel: int = 20
    radius: float = 60.0
    prune_distance: float = 3.0
    threads: int = 1

    def __post_init__(self) -> None:
        if self.voxel_size <= 0 or self.max_points_per_voxel < 1 or self.radius <= 0:
            raise ConfigError(
                "local map needs voxel_size > 0, max_points_per_voxel >= 1 and radius > 0"
            )
        if self.prune_distance < 0:
            raise ConfigError("local map prune_distance must be >= 0")
        if self.threads < 1:
            raise ConfigError(f"local map threads must be >= 1, got {self.threads}")


def voxel_hash(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N,) int64 key of each point's voxel (21 bits per axis, about +-1e6 voxels)."""
    c = np.floor(xyz / voxel_size).astype(np.int64) + _OFFSET
    if len(c) and (c.min() < 0 or c.max() >= 2 * _OFFSET):
        raise InputError(f"points too far from the origin for voxel size {voxel_size} m")
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


# --------------------------------------------------------------------------- the map


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with room for n rows (doubling), the first rows kept."""
    if len(a) >= n:
        return a
    out = np.empty((max(n, 2 * len(a), 64),) + a.shape[1:], dtype=a.dtype)
    out[: len(a)] = a
    return out


def _table(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Empty hash table (keys -1, values) for n entries at load factor <= 1/2."""
    size = max(64, 1 << int(np.ceil(np.log2(max(2 * n, 1)))))
    return np.full(size, _EMPTY), np.zeros(size, dtype=np.int64)


class VoxelHashMap:
    """Points (M, 3), optional covariances (M, 3, 3) and their voxel keys, bounded in size.

    ``points`` / ``covs`` are views of the first M rows of growing buffers (writable: the
    front end refreshes covariances in place); ``query`` is an exact k-NN through the hash
    (cKDTree's signature); ``tree()`` still builds a cKDTree on demand for callers that need
    one. Row order: ``add`` appends the accepted points as the last rows; ``remove_far``
    moves the last rows into the holes it leaves (rows are not kept in insertion order).
    """

    def __init__(self, cfg: LocalMapConfig | None = None, with_covariances: bool = False):
        self.cfg = cfg or LocalMapConfig()
        self.with_covariances = with_covariances
        cap = self.cfg.max_points_per_voxel
        self._state = np.zeros(9, dtype=np.int64)  # n, voxels, cells, box (see the kernels)
        self._pts = np.zeros((0, 3))
        self._covs = np.zeros((0, 3, 3)) if with_covariances else None
        self._pkeys = np.zeros(0, dtype=np.int64)
        self._pvox = np.zeros(0, dtype=np.int64)
        self._pslot = np.zeros(0, dtype=np.int64)
        self._vkey = np.zeros(0, dtype=np.int64)
        self._vcount = np.zeros(0, dtype=np.int64)
        self._vslots = np.zeros((0, cap), dtype=np.int64)
        self._vpts = np.zeros((0, cap, 3))  # copies of the points, by voxel and slot
        self._vcell = np.zeros(0, dtype=np.int64)
        self._vprev = np.zeros(0, dtype=np.int64)
        self._vnext = np.zeros(0, dtype=np.int64)
        self._tkeys, self._tvals = _table(0)
        self._ckey = np.zeros(0, dtype=np.int64)
        self._chead = np.zeros(0, dtype=np.int64)
        self._cnvox = np.zeros(0, dtype=np.int64)
        self._ctkeys, self._ctvals = _table(0)
        self.version = 0
        self._tree: cKDTree | None = None
        self._tree_version = -1
        self._pruned_at: np.ndarray | None = None  # sensor position at the last pruning
        self._last_accepted = np.zeros(0, dtype=np.int64)

    @property
    def _n(self) -> int:
        return int(self._state[K.N])

    def __len__(self) -> int:
        return self._n

    @property
    def points(self) -> np.ndarray:
        """(M, 3) map points, odometry frame (m); a view."""
        return self._pts[: self._n]

    @property
    def covs(self) -> np.ndarray | None:
        """(M, 3, 3) covariances (m^2) or None; a writable view."""
        return None if self._covs is None else self._covs[: self._n]

    @property
    def keys(self) -> np.ndarray:
        """(M,) voxel key of each point (``voxel_hash``); a read-only view."""
        out = self._pkeys[: self._n].view()
        out.flags.writeable = False
        return out

    @property
    def num_voxels(self) -> int:
        return int(self._state[K.NV])

    @property
    def num_cells(self) -> int:
        """Occupied coarse cells (``COARSE`` voxels a side)."""
        return int(self._state[K.NC])

    def clear(self) -> None:
        self.__init__(self.cfg, self.with_covariances)

    # ------------------------------------------------------------------ insertion
    def _reserve(self, n_more: int) -> None:
        """Room for n_more points, voxels and cells (upper bounds), tables at load <= 1/2."""
        n, nv, nc = (int(x) for x in self._state[:3])
        self._pts = _grown(self._pts, n + n_more)
        if self._covs is not None:
            self._covs = _grown(self._covs, n + n_more)
        self._pkeys = _grown(self._pkeys, n + n_more)
        self._pvox = _grown(self._pvox, n + n_more)
        self._pslot = _grown(self._pslot, n + n_more)
        if len(self._vkey) < nv + n_more:
            for name in ("_vkey", "_vcount", "_vslots", "_vpts", "_vcell", "_vprev", "_vnext"):
                setattr(self, name, _grown(getattr(self, name), nv + n_more))
        if len(self._tkeys) < 2 * (nv + n_more):
            self._tkeys, self._tvals = _table(nv + n_more)
            K.rehash(self._vkey, nv, self._tkeys, self._tvals)
        nc_more = n_more  # each new cell comes with a new voxel of the batch
        if len(self._ckey) < nc + nc_more:
            for name in ("_ckey", "_chead", "_cnvox"):
                setattr(self, name, _grown(getattr(self, name), nc + nc_more))
        if len(self._ctkeys) < 2 * (nc + nc_more):
            self._ctkeys, self._ctvals = _table(nc + nc_more)
            K.rehash(self._ckey, nc, self._ctkeys, self._ctvals)

    def _append(self, points: np.ndarray, covs: np.ndarray | None, keys: np.ndarray) -> int:
        self._reserve(len(keys))
        n0 = self._n
        accepted = np.empty(len(keys), dtype=np.int64)
        n_acc = K.insert(
            keys,
            points,
            COARSE,
            *self._voxel_tables(),
            self._pkeys,
            self._pvox,
            self._pslot,
            self._state,
            accepted,
        )
        self._last_accepted = accepted[:n_acc]
        if n_acc:
            keep = accepted[:n_acc]
            self._pts[n0 : n0 + n_acc] = points[keep]
            if self._covs is not None:
                self._covs[n0 : n0 + n_acc] = covs[keep]
        return int(n_acc)

    def add(
        self,
        points: np.ndarray,
        covs: np.ndarray | None = None,
        origin: np.ndarray | None = None,
    ) -> int:
        """Insert odometry-frame points (and covariances); returns how many were kept.

        If ``origin`` (sensor position) is given and it moved ``prune_distance`` since the last
        pruning, map points beyond ``radius`` from it are removed first. Then a voxel with c
        points accepts the first (cap - c) new points falling in it; the accepted points are
        appended, so they are the last ``added`` rows.
        """
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"map points must be (N, 3), got {points.shape}")
        if self.with_covariances:
            if covs is None or covs.shape != (len(points), 3, 3):
                raise InputError("this map stores covariances: pass covs of shape (N, 3, 3)")
        if origin is not None:
            origin = np.asarray(origin, dtype=np.float64)[:3]
            moved = np.inf if self._pruned_at is None else np.linalg.norm(origin - self._pruned_at)
            if moved >= self.cfg.prune_distance:
                self.remove_far(origin)
                self._pruned_at = origin.copy()
        added = 0
        self._last_accepted = np.zeros(0, dtype=np.int64)
        if len(points):
            added = self._append(points, covs, voxel_hash(points, self.cfg.voxel_size))
        if added:
            self.version += 1
        return added

    @property
    def last_accepted(self) -> np.ndarray:
        """Input positions of the points the last ``add`` kept, ascending (they became the
        last rows, in this order): e.g. to fill in the covariances of the new rows after an
        ``add`` with placeholders."""
        return self._last_accepted

    def remove_far(self, origin: np.ndarray) -> int:
        """Drop points farther than ``radius`` from ``origin`` (3,); returns how many.

        Only the coarse cells the sphere cuts are visited; each removed row is filled with
        the current last row (its covariance and hash entry follow)."""
        if not self._n:
            return 0
        covs = self._covs if self._covs is not None else np.zeros((0, 3, 3))
        n_removed = K.remove_far(
            np.ascontiguousarray(origin, dtype=np.float64)[:3],
            float(self.cfg.radius),
            float(self.cfg.voxel_size),
            COARSE,
            *self._voxel_tables(),
            self._pts,
            covs,
            self._pkeys,
            self._pvox,
            self._pslot,
            self._state,
        )
        if n_removed:
            self.version += 1
        return int(n_removed)

    # ------------------------------------------------------------------ queries
    def query(
        self,
        x: np.ndarray,
        k: int = 1,
        distance_upper_bound: float = np.inf,
        workers: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exact k nearest map points of each row of ``x`` (N, 3), as ``cKDTree.query``.

        Returns (distances m, indices), shape (N,) for k == 1 else (N, k), ascending;
        neighbours beyond ``distance_upper_bound`` (or missing) are inf / ``len(self)``.
        Batches of at least ``PARALLEL_QUERIES`` run on ``cfg.threads`` numba threads (same
        answers: every query writes only its own rows); smaller ones on one thread, whose
        start-up would cost more than it saves. ``workers`` is accepted for compatibility.
        """
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        k = int(k)
        if k < 1:
            raise InputError(f"k must be >= 1, got {k}")
        od = np.empty((len(x), k))
        oi = np.empty((len(x), k), dtype=np.int64)
        max_d2, shells = self._search_extent(float(distance_upper_bound))
        unresolved = np.zeros(len(x), dtype=np.bool_)
        # a caller that keeps its numba kernels to one thread (slam.deferred) stays serial
        parallel = (
            self.cfg.threads > 1 and numba.get_num_threads() > 1 and len(x) >= PARALLEL_QUERIES
        )
        kernel = K.query_parallel if parallel else K.query
        with numba_threads(self.cfg.threads if parallel else None):
            self._run_query(kernel, x, k, max_d2, shells, od, oi, unresolved)
        rows = np.flatnonzero(unresolved)
        if len(rows):  # isolated points (sparse far returns): on over the coarse cells
            K.query_coarse(
                x,
                rows,
                max_d2,
                float(self.cfg.voxel_size),
                shells,
                COARSE,
                self._ctkeys,
                self._ctvals,
                self._chead,
                self._vnext,
                self._vkey,
                self._vcount,
                self._vslots,
                self._vpts,
                self._state,
                od,
                oi,
            )
        d = np.sqrt(od)
        if k == 1:
            return d[:, 0], oi[:, 0]
        return d, oi

    def _search_extent(self, bound: float) -> tuple[float, int]:
        """(squared distance bound m^2, voxel shells to scan) for ``distance_upper_bound``."""
        if not np.isfinite(bound):
            return np.inf, MAX_SHELLS
        need = int(np.ceil(bound / self.cfg.voxel_size))
        return bound * bound, min(max(MAX_SHELLS, need), MAX_BOUNDED_SHELLS)

    def _run_query(self, kernel, x, k, max_d2, shells, od, oi, unresolved) -> None:
        """One call of a voxel-shell query kernel over the hash tables."""
        kernel(
            x,
            k,
            max_d2,
            float(self.cfg.voxel_size),
            shells,
            *_SHELLS,
            self._tkeys,
            self._tvals,
            self._vcount,
            self._vslots,
            self._vpts,
            self._state,
            od,
            oi,
            unresolved,
        )

    def _voxel_tables(self) -> tuple[np.ndarray, ...]:
        """The voxel hash, the per-voxel point copies and lists, and the coarse-cell hash,
        in the order the insertion and eviction kernels take them."""
        return (
            self._tkeys,
            self._tvals,
            self._vkey,
            self._vcount,
            self._vslots,
            self._vpts,
            self._vcell,
            self._vprev,
            self._vnext,
            self._ctkeys,
            self._ctvals,
            self._ckey,
            self._chead,
            self._cnvox,
        )

    def tree(self) -> cKDTree | None:
        """KD-tree over the current points, rebuilt only when the map changed."""
        if self._tree_version != self.version:
            self._tree = (
                cKDTree(self.points, balanced_tree=False, compact_nodes=False) if self._n else None
            )
            self._tree_version = self.version
        return self._tree
