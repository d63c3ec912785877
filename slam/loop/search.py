"""Loop candidate search: ring-key KD-tree retrieval, then the Scan Context distance.

Keyframes enter a growing database (amortised arrays). A query only sees keyframes
older than the exclusion window (the last ``exclude_recent`` keyframes and the last
``exclude_seconds`` seconds). The KD-tree over their ring keys is rebuilt lazily,
every ``rebuild_every`` newly eligible keyframes; the few eligible keyframes not yet in
the tree are compared by brute force, so results are exact without a rebuild per
keyframe. Once the tree is large the rebuild waits for REBUILD_GROWTH x its size new rows
(the brute-force tail stays a small share), so at 1000 keyframes it is rebuilt every ~125.
The ``top_k`` nearest ring keys are re-ranked by the column-shift distance (optionally
only around the sector-key pre-alignment shift).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.loop.scan_context import (
    column_shift_distance,
    ring_key,
    sector_key,
    sector_key_shift,
    shift_to_yaw,
)

REBUILD_GROWTH = 0.125  # rebuild the KD-tree after max(rebuild_every, this x its size) rows


def tree_is_stale(n_eligible: int, tree_size: int, rebuild_every: int) -> bool:
    """Rebuild the key tree now? When rows left it (the window moved back) or enough
    rows were added since: rebuild_every, or REBUILD_GROWTH of the tree once it is large."""
    grown = n_eligible - tree_size
    return n_eligible < tree_size or grown >= max(rebuild_every, int(REBUILD_GROWTH * tree_size))


@dataclass(frozen=True)
class SearchParams:
    """exclude_recent: newest keyframes never searched (>= 1: the query itself).
    exclude_seconds: also skip keyframes newer than this many seconds. threshold: accept a
    Scan Context distance below this (0.2-0.4). shift_window: 0 searches all column shifts;
    w > 0 only shifts within +-w of the sector-key pre-alignment."""

    exclude_recent: int = 30
    exclude_seconds: float = 0.0
    top_k: int = 10
    threshold: float = 0.25
    rebuild_every: int = 10
    shift_window: int = 0

    def __post_init__(self) -> None:
        if self.exclude_recent < 1:
            raise ValueError(f"exclude_recent must be >= 1, got {self.exclude_recent}")
        if self.top_k < 1 or self.rebuild_every < 1:
            raise ValueError("top_k and rebuild_every must be >= 1")


@dataclass
class Candidate:
    """A scored database entry: row in the database, keyframe id, Scan Context distance,
    column shift and the yaw (radians) of T_candidate_query it implies; init: a full initial
    pose (e.g. from a Scan Context++ Cartesian match), None = the yaw alone."""

    row: int
    kf_id: int
    distance: float
    shift: int
    yaw: float
    key_distance: float = float("nan")
    init: np.ndarray | None = None  # T_candidate_query to start verification from, if known


class ScanContextDatabase:
    """Descriptors, ring/sector keys, stamps and positions of all keyframes, in arrival order."""

    def __init__(self, rings: int, sectors: int, params: SearchParams = SearchParams()):
        self.rings, self.sectors, self.params = rings, sectors, params
        self._n = 0
        cap = 64
        self._desc = np.zeros((cap, rings, sectors), dtype=np.float32)
        self._rkey = np.zeros((cap, rings), dtype=np.float64)
        self._skey = np.zeros((cap, sectors), dtype=np.float64)
        self._ids = np.zeros(cap, dtype=np.int64)
        self._stamps = np.zeros(cap, dtype=np.float64)
        self._pos = np.full((cap, 3), np.nan, dtype=np.float64)
        self._tree: cKDTree | None = None
        self._tree_size = 0
        self.tree_builds = 0

    def __len__(self) -> int:
        return self._n

    # ------------------------------------------------------------------ storage
    def _grow(self) -> None:
        cap = 2 * self._desc.shape[0]
        for name in ("_desc", "_rkey", "_skey", "_ids", "_stamps", "_pos"):
            old = getattr(self, name)
            new = np.full((cap, *old.shape[1:]), np.nan if name == "_pos" else 0, dtype=old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, kf_id: int, stamp: float, desc: np.ndarray, position=None) -> int:
        """Append a keyframe's descriptor (rings, sectors); returns its row."""
        if self._n == self._desc.shape[0]:
            self._grow()
        row = self._n
        self._desc[row] = desc
        self._rkey[row] = ring_key(desc)
        self._skey[row] = sector_key(desc)
        self._ids[row] = kf_id
        self._stamps[row] = stamp
        if position is not None:
            self._pos[row] = position
        self._n += 1
        return row

    def kf_id(self, row: int) -> int:
        return int(self._ids[row])

    def stamp(self, row: int) -> float:
        return float(self._stamps[row])

    def descriptor(self, row: int) -> np.ndarray:
        return self._desc[row].astype(np.float64)

    def set_positions(self, rows: np.ndarray, positions: np.ndarray) -> None:
        """Refresh the (estimated) world positions used by the proximity search."""
        self._pos[np.asarray(rows, dtype=np.intp)] = positions

    def eligible(self, stamp: float) -> int:
        """Number of leading rows a query at ``stamp`` may match (rows are in time order)."""
        n = self._n - self.params.exclude_recent
        if self.params.exclude_seconds > 0.0:
            n = min(
                n,
                int(
                    np.searchsorted(
                        self._stamps[: self._n], stamp - self.params.exclude_seconds, "right"
                    )
                ),
            )
        return max(n, 0)

    # ------------------------------------------------------------------ search
    def _nearest_keys(self, key: np.ndarray, n_eligible: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the top_k nearest ring keys among the first ``n_eligible`` rows."""
        p = self.params
        if tree_is_stale(n_eligible, self._tree_size, p.rebuild_every):
            self._tree = cKDTree(self._rkey[:n_eligible])
            self._tree_size = n_eligible
            self.tree_builds += 1
        rows, dists = [], []
        if self._tree is not None and self._tree_size > 0:
            d, i = self._tree.query(key, k=min(p.top_k, self._tree_size))
            rows.append(np.atleast_1d(i))
            dists.append(np.atleast_1d(d))
        if n_eligible > self._tree_size:  # not yet in the tree: brute force (a small tail)
            tail = np.arange(self._tree_size, n_eligible)
            rows.append(tail)
            dists.append(np.linalg.norm(self._rkey[tail] - key, axis=1))
        if not rows:
            return np.zeros(0, dtype=np.intp), np.zeros(0)
        rows_a, dists_a = np.concatenate(rows), np.concatenate(dists)
        order = np.argsort(dists_a, kind="stable")[: p.top_k]
        return rows_a[order].astype(np.intp), dists_a[order]

    def score(self, desc: np.ndarray, rows: np.ndarray) -> list[Candidate]:
        """Column-shift distance of ``desc`` to the given rows, best first."""
        rows = np.asarray(rows, dtype=np.intp)
        if rows.size == 0:
            return []
        cands = self._desc[rows]
        shifts = None
        if self.params.shift_window > 0:
            s0 = sector_key_shift(sector_key(desc), self._skey[rows])
            w = np.arange(-self.params.shift_window, self.params.shift_window + 1)
            shifts = (s0[:, None] + w[None, :]) % self.sectors
        dist, best = column_shift_distance(desc, cands, shifts)
        yaws = shift_to_yaw(best, self.sectors)
        out = [
            Candidate(row=int(r), kf_id=int(self._ids[r]), distance=float(d), shift=int(s),
                      yaw=float(y))
            for r, d, s, y in zip(rows, dist, best, np.atleast_1d(yaws), strict=True)
        ]  # fmt: skip
        out.sort(key=lambda c: c.distance)
        return out

    def query(self, desc: np.ndarray, stamp: float) -> list[Candidate]:
        """Top-k ring-key neighbours among eligible rows, scored by Scan Context distance."""
        n_e = self.eligible(stamp)
        if n_e == 0:
            return []
        key = ring_key(desc)
        rows, kd = self._nearest_keys(key, n_e)
        scored = self.score(desc, rows)
        key_of = dict(zip(rows.tolist(), kd.tolist(), strict=True))
        for c in scored:
            c.key_distance = key_of[c.row]
        return scored

    def detect(self, desc: np.ndarray, stamp: float) -> Candidate | None:
        """The best candidate if its distance is below the threshold, else None."""
        scored = self.query(desc, stamp)
        if scored and scored[0].distance < self.params.threshold:
            return scored[0]
        return None

    def near(self, position: np.ndarray, radius: float, stamp: float) -> np.ndarray:
        """Eligible rows whose stored position lies within ``radius`` m, nearest first
        (LeGO-LOAM's proximity search); at most top_k rows."""
        n_e = self.eligible(stamp)
        if n_e == 0 or radius <= 0.0:
            return np.zeros(0, dtype=np.intp)
        d = np.linalg.norm(self._pos[:n_e] - np.asarray(position, dtype=np.float64), axis=1)
        inside = np.flatnonzero(d < radius)  # NaN positions compare False
        return inside[np.argsort(d[inside], kind="stable")][: self.params.top_k]
