"""Incremental point map: insert, lazy delete, restore, k-NN and radius queries without a
global rebuild per insert (LeGO-LOAM-LPB, paper 001, 3.4: the ikd-tree's role).

Structure (ours) over static KD-trees (scipy's): a log-structured set of buckets, each a
cKDTree over a block of points. An insert adds a bucket; while the bucket before it holds
no more points than it, the two merge into one rebuilt tree (a binary counter): every point
is rebuilt O(log N) times over the map's life, and there are O(log N) buckets to query.
Deletion is lazy: an alive flag per point, the trees keep the points until a bucket is
more than ``compact_fraction`` dead, when it is rebuilt from its live points. Queries
skip dead points exactly (a bucket's search widens until it found k live neighbours), so
the answers equal those of one KD-tree rebuilt over the live points.

Points get stable integer ids in insertion order (``insert`` returns them); queries
answer ids, ``points(ids)`` gives their coordinates.

``index="merged"``: no buckets; one KD-tree over the live points, rebuilt at the first query
after a change (same answers). For the windowed maps of a front end (10^4 points, one
insert per frame, ~20 queries between inserts) one tree query instead of ~2 bucket queries
and their merge is 2.5x faster including the rebuild (lego_lpb on the building scene,
benchmarks/bench_incremental_map.py); the buckets pay off when inserts outnumber queries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError, InputError
from slam.registration.gicp import KnnTree


@dataclass
class IncrementalMapConfig:
    """leafsize of the KD-trees; compact_fraction: a bucket whose dead share exceeds it is
    rebuilt from its live points (lower: faster queries, more rebuilds). merge_ratio: a new
    bucket merges with the one before while that one holds at most merge_ratio times its
    points (1: a binary counter; 4, the default: fewer buckets to query, 0.60 -> 0.42 of the
    rebuild-per-scan time over 60 plaza scans in bench_incremental_map.py). index:
    "buckets" (the log-structured trees) or "merged" (one tree over the live points rebuilt
    at the first query after a change; see the module doc)."""

    leafsize: int = 16
    compact_fraction: float = 0.5
    merge_ratio: float = 4.0
    index: str = "buckets"

    def __post_init__(self) -> None:
        if self.index not in ("buckets", "merged"):
            raise ConfigError(f"index must be 'buckets' or 'merged', got {self.index!r}")
        if self.leafsize < 1:
            raise ConfigError(f"leafsize must be >= 1, got {self.leafsize}")
        if self.merge_ratio < 1:
            raise ConfigError(f"merge_ratio must be >= 1, got {self.merge_ratio}")
        if not 0 < self.compact_fraction < 1:
            raise ConfigError(f"compact_fraction must be in (0, 1), got {self.compact_fraction}")


class _Bucket:
    """A static KD-tree over the points ``ids`` (their coordinates ``xyz``)."""

    def __init__(self, ids: np.ndarray, xyz: np.ndarray, leafsize: int):
        self.ids = ids
        self.tree = cKDTree(xyz, leafsize=leafsize, balanced_tree=False, compact_nodes=False)
        self.n_dead = 0

    @property
    def size(self) -> int:
        return len(self.ids)

    @property
    def n_alive(self) -> int:
        return self.size - self.n_dead


def _check_points(xyz: np.ndarray, what: str = "points") -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim == 1 and xyz.shape == (3,):
        xyz = xyz[None, :]
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"{what} must be an (N, 3) array, got shape {xyz.shape}")
    if not np.all(np.isfinite(xyz)):
        raise InputError(f"{what} contain NaN or inf")
    return xyz


class IncrementalMap:
    """A growing, shrinking point map with exact k-NN and radius queries (see module doc).

    insert(xyz) -> ids; delete(mask | ids= | box=) lazily; restore(ids) brings deleted
    points back; knn(queries, k) -> (dist, ids); radius(queries, r) -> list of id arrays.
    """

    def __init__(self, config: IncrementalMapConfig | None = None):
        self.config = config or IncrementalMapConfig()
        self._buckets: list[_Bucket] = []
        self._xyz = np.zeros((1024, 3))
        self._alive = np.zeros(1024, dtype=bool)
        self._bucket_of = np.full(1024, -1, dtype=np.int64)  # bucket serial, -1: none
        self._n = 0
        self._serial = 0
        self.rebuilt_points = 0  # points put into trees so far (the amortised cost)
        self._merged = self.config.index == "merged"
        self._version = 0  # changes of the live set (the merged tree follows it)
        self._tree_version = -1
        self._tree: cKDTree | None = None
        self._tree_ids = np.zeros(0, dtype=np.int64)
        self._knn_version = -1
        self._knn_tree: KnnTree | None = None
        self._knn_ids = np.zeros(0, dtype=np.int64)

    # ------------------------------------------------------------------ state
    def __len__(self) -> int:
        return int(self._alive[: self._n].sum())

    @property
    def n_ids(self) -> int:
        """Ids handed out so far (live and deleted)."""
        return self._n

    @property
    def n_buckets(self) -> int:
        return len(self._buckets)

    def alive_ids(self) -> np.ndarray:
        return np.flatnonzero(self._alive[: self._n])

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) coordinates of the live points, in id order."""
        return self._xyz[self.alive_ids()]

    def points(self, ids: np.ndarray) -> np.ndarray:
        """Coordinates (..., 3) of ``ids`` (live or deleted); -1 gives NaN."""
        ids = np.asarray(ids, dtype=np.int64)
        out = np.full(ids.shape + (3,), np.nan)
        ok = (ids >= 0) & (ids < self._n)
        out[ok] = self._xyz[ids[ok]]
        return out

    # ------------------------------------------------------------------ updates
    def _grow(self, n: int) -> None:
        cap = len(self._alive)
        if n <= cap:
            return
        new = max(n, 2 * cap)
        self._xyz = np.concatenate([self._xyz, np.zeros((new - cap, 3))])
        self._alive = np.concatenate([self._alive, np.zeros(new - cap, dtype=bool)])
        self._bucket_of = np.concatenate([self._bucket_of, np.full(new - cap, -1, np.int64)])

    def _make_bucket(self, ids: np.ndarray) -> _Bucket:
        b = _Bucket(ids, self._xyz[ids], self.config.leafsize)
        b.serial = self._serial  # type: ignore[attr-defined]
        self._serial += 1
        self._bucket_of[ids] = b.serial  # type: ignore[attr-defined]
        self.rebuilt_points += len(ids)
        return b

    def _add_bucket(self, ids: np.ndarray) -> None:
        """Append a bucket of live ``ids`` and merge while the previous one is not larger."""
        if len(ids) == 0:
            return
        self._buckets.append(self._make_bucket(ids))
        ratio = self.config.merge_ratio
        while (
            len(self._buckets) >= 2
            and self._buckets[-2].n_alive <= ratio * self._buckets[-1].n_alive
        ):
            b2, b1 = self._buckets.pop(), self._buckets.pop()
            live = np.concatenate([b1.ids, b2.ids])
            live = live[self._alive[live]]
            self._bucket_of[np.concatenate([b1.ids, b2.ids])] = -1
            if len(live):
                self._buckets.append(self._make_bucket(np.sort(live)))

    def insert(self, xyz: np.ndarray) -> np.ndarray:
        """Add points (N, 3); returns their ids (N,) int64."""
        xyz = _check_points(xyz)
        ids = np.arange(self._n, self._n + len(xyz), dtype=np.int64)
        self._grow(self._n + len(xyz))
        self._xyz[ids] = xyz
        self._alive[ids] = True
        self._n += len(xyz)
        self._version += 1
        if not self._merged:
            self._add_bucket(ids)
        return ids

    def _select(
        self,
        mask: np.ndarray | None,
        ids: np.ndarray | None,
        box: tuple[np.ndarray, np.ndarray] | None,
        outside: bool,
    ) -> np.ndarray:
        given = sum(x is not None for x in (mask, ids, box))
        if given != 1:
            raise InputError("delete takes exactly one of mask, ids or box")
        if mask is not None:
            mask = np.asarray(mask, dtype=bool).reshape(-1)
            if len(mask) != self._n:
                raise InputError(f"delete mask has {len(mask)} entries for {self._n} ids")
            return np.flatnonzero(mask)
        if ids is not None:
            ids = np.unique(np.asarray(ids, dtype=np.int64).reshape(-1))
            if len(ids) and (ids.min() < 0 or ids.max() >= self._n):
                raise InputError(f"ids must be in 0..{self._n - 1}")
            return ids
        lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in box)  # type: ignore[union-attr]
        cand = self.alive_ids()
        p = self._xyz[cand]
        inside = np.all((p >= lo) & (p <= hi), axis=1)
        return cand[~inside if outside else inside]

    def delete(
        self,
        mask: np.ndarray | None = None,
        *,
        ids: np.ndarray | None = None,
        box: tuple[np.ndarray, np.ndarray] | None = None,
        outside: bool = False,
    ) -> int:
        """Lazily delete points: ``mask`` (n_ids,) bool over ids, or ``ids``, or ``box`` =
        (min (3,), max (3,)) m: the live points inside it (``outside``: those outside it, a
        sliding-window map). Returns the number of points deleted."""
        sel = self._select(mask, ids, box, outside)
        sel = sel[self._alive[sel]]
        if len(sel) == 0:
            return 0
        self._alive[sel] = False
        self._version += 1
        if self._merged:
            return int(len(sel))
        serials = self._bucket_of[sel]
        counts = dict(zip(*np.unique(serials[serials >= 0], return_counts=True), strict=True))
        rebuild = []
        for b in self._buckets:
            b.n_dead += int(counts.get(b.serial, 0))  # type: ignore[attr-defined]
            if b.n_dead > self.config.compact_fraction * b.size:
                rebuild.append(b)
        for b in rebuild:  # compaction: rebuild the bucket from its live points
            idx = self._buckets.index(b)
            live = b.ids[self._alive[b.ids]]
            self._bucket_of[b.ids] = -1
            if len(live):
                self._buckets[idx] = self._make_bucket(live)
            else:
                self._buckets.pop(idx)
        return int(len(sel))

    def restore(self, ids: np.ndarray) -> int:
        """Bring deleted points back (the paper's re-insertion); returns how many. Points
        still held by their tree are only flagged alive; compacted ones get a new bucket."""
        ids = np.unique(np.asarray(ids, dtype=np.int64).reshape(-1))
        if len(ids) and (ids.min() < 0 or ids.max() >= self._n):
            raise InputError(f"ids must be in 0..{self._n - 1}")
        ids = ids[~self._alive[ids]]
        if len(ids) == 0:
            return 0
        self._alive[ids] = True
        self._version += 1
        if self._merged:
            return int(len(ids))
        held = self._bucket_of[ids] >= 0
        counts = dict(zip(*np.unique(self._bucket_of[ids[held]], return_counts=True), strict=True))
        for b in self._buckets:
            b.n_dead -= int(counts.get(b.serial, 0))  # type: ignore[attr-defined]
        self._add_bucket(ids[~held])
        return int(len(ids))

    # ------------------------------------------------------------------ queries
    def _bucket_knn(
        self, b: _Bucket, q: np.ndarray, k: int, bound: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest live points of one bucket within ``bound`` m: (Q, k) distances and
        ids (inf / -1 where missing)."""
        want = min(k, b.n_alive)
        dist = np.full((len(q), k), np.inf)
        out = np.full((len(q), k), -1, dtype=np.int64)
        todo = np.arange(len(q))
        kk = min(b.size, want if b.n_dead == 0 else 2 * want)
        while len(todo):
            d, j = b.tree.query(q[todo], k=kk, distance_upper_bound=bound)
            d, j = d.reshape(len(todo), kk), j.reshape(len(todo), kk)
            ids = b.ids[np.minimum(j, b.size - 1)]
            live = (j < b.size) & self._alive[ids]
            # done: enough live hits, the whole bucket seen, or nothing more within bound
            done = (live.sum(axis=1) >= want) | (kk >= b.size) | ~np.isfinite(d[:, -1])
            rows = todo[done]
            ld, li, lv = d[done], ids[done], live[done]
            if lv.all():  # no dead point among the hits (the common case): as they are
                dist[rows, :want] = ld[:, :want]
                out[rows, :want] = li[:, :want]
            else:  # stable: live hits in distance order first
                order = np.argsort(~lv, axis=1, kind="stable")[:, :want]
                pick_d = np.take_along_axis(ld, order, axis=1)
                pick_i = np.take_along_axis(li, order, axis=1)
                pick_ok = np.take_along_axis(lv, order, axis=1)
                dist[rows, :want] = np.where(pick_ok, pick_d, np.inf)
                out[rows, :want] = np.where(pick_ok, pick_i, -1)
            todo = todo[~done]
            kk = min(b.size, 2 * kk)
        return dist, out

    def knn(
        self, queries: np.ndarray, k: int = 1, *, distance_upper_bound: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest live points of each query (Q, 3): distances (Q, k) m ascending and
        ids (Q, k); missing neighbours (fewer than k live points, or beyond
        ``distance_upper_bound`` m) are inf / -1."""
        q = _check_points(queries, "queries")
        if k < 1:
            raise InputError(f"k must be >= 1, got {k}")
        bound = float(distance_upper_bound)
        if self._merged:
            return self._merged_knn(q, k, bound)
        parts = [self._bucket_knn(b, q, k, bound) for b in self._buckets if b.n_alive]
        if not parts:
            return np.full((len(q), k), np.inf), np.full((len(q), k), -1, dtype=np.int64)
        if len(parts) == 1:
            return parts[0]
        d = np.concatenate([p[0] for p in parts], axis=1)
        i = np.concatenate([p[1] for p in parts], axis=1)
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        return np.take_along_axis(d, order, axis=1), np.take_along_axis(i, order, axis=1)

    def _merged_tree(self) -> tuple[cKDTree | None, np.ndarray]:
        """The one cKDTree over the live points (index="merged"), rebuilt after a change;
        radius queries use it."""
        if self._tree_version != self._version:
            ids = self.alive_ids()
            self._tree = (
                cKDTree(self._xyz[ids], leafsize=self.config.leafsize, balanced_tree=False)
                if len(ids)
                else None
            )
            self._tree_ids = ids
            self._tree_version = self._version
            self.rebuilt_points += len(ids)
        return self._tree, self._tree_ids

    def _merged_knn_tree(self) -> tuple[KnnTree | None, np.ndarray]:
        """small_gicp's KD-tree over the live points (index="merged") for k-NN queries: the
        same neighbours as the cKDTree at about half the query cost (a front end's maps
        answer ~20 queries per insert), rebuilt after a change."""
        if self._knn_version != self._version:
            ids = self.alive_ids()
            self._knn_tree = KnnTree(self._xyz[ids]) if len(ids) else None
            self._knn_ids = ids
            self._knn_version = self._version
            self.rebuilt_points += len(ids)
        return self._knn_tree, self._knn_ids

    def _merged_knn(self, q: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
        tree, ids = self._merged_knn_tree()
        if tree is None:
            return np.full((len(q), k), np.inf), np.full((len(q), k), -1, dtype=np.int64)
        d, j = tree.query(q, k=k, distance_upper_bound=bound)
        j = j.reshape(len(q), k)
        found = j < len(ids)
        out = np.where(found, ids[np.minimum(j, len(ids) - 1)], -1)
        # the distances as cKDTree rounds them (x, y, z squares summed in order), so that
        # the answers equal a rebuilt cKDTree's to the bit
        diff = q[:, None, :] - self._xyz[np.maximum(out, 0)]
        exact = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2 + diff[..., 2] ** 2)
        return np.where(found, exact, np.inf), out

    def radius(
        self, queries: np.ndarray, r: float, *, return_distances: bool = False
    ) -> list[np.ndarray] | tuple[list[np.ndarray], list[np.ndarray]]:
        """Ids of the live points within ``r`` m of each query (Q, 3), sorted by distance;
        a list of Q int64 arrays (and their distances with ``return_distances``)."""
        q = _check_points(queries, "queries")
        if not r >= 0:
            raise InputError(f"radius must be >= 0, got {r}")
        qt = cKDTree(q)
        rows, ids, dists = [], [], []
        if self._merged:
            tree, tree_ids = self._merged_tree()
            sources = [] if tree is None else [(tree, tree_ids)]
        else:
            sources = [(b.tree, b.ids) for b in self._buckets if b.n_alive]
        for tree, bucket_ids in sources:
            m = qt.sparse_distance_matrix(tree, r, output_type="ndarray")
            hit_ids = bucket_ids[m["j"]]
            live = self._alive[hit_ids]
            rows.append(m["i"][live])
            ids.append(hit_ids[live])
            dists.append(m["v"][live])
        if rows:
            row, idc, dst = np.concatenate(rows), np.concatenate(ids), np.concatenate(dists)
        else:
            row, idc, dst = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        order = np.lexsort((idc, dst, row))
        row, idc, dst = row[order], idc[order], dst[order]
        cuts = np.searchsorted(row, np.arange(1, len(q)))
        out_ids = [a.astype(np.int64) for a in np.split(idc, cuts)]
        if return_distances:
            return out_ids, np.split(dst, cuts)
        return out_ids
