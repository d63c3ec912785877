"""Exact k-NN of a spinning-lidar scan through its range image (ring x azimuth).

A scan is searched ring by ring outward from each point's ring and, within a ring, outward
in azimuth, with a certificate that makes the answer exact: a point q on a ray at angle
theta from p's ray is at least |p| sin(theta) from p (theta <= 90 deg), and the spherical
law of haversines bounds theta from below by the elevation gap to the rings not searched
(their measured per-point elevations, not the nominal beam table) and by the azimuth gap
to the columns not searched. Once the k-th distance found is below that bound for every
unsearched point, the window answer is the true k-NN (same distances as a KD-tree, same
index sets up to ties). Points the window cannot certify within
``max_visits`` distance evaluations (isolated returns, points near the sensor axis) are
reported; with ``complete=True`` (as ``slam.preprocess.knn.self_knn`` asks) they are answered
by an exact search over the bounding boxes of short range-image arcs (``box_knn``) instead of
a KD-tree over the whole scan. All points are left to the caller's KD-tree when the ring
labels do not look like beams (``MAX_RING_SPREAD``).

The ring only steers the search; a wrong or coarse ring costs speed, never exactness.

What it costs against a KD-tree on each sensor: ``benchmarks/bench_preprocess.py --scans``
and docs/speed.md.
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass

import numba
import numpy as np

from slam.errors import InputError
from slam.preprocess.range_image_kernels import (
    box_knn,
    gather_rows,
    range_image_into,
    ring_ranks,
    window_knn,
)

__all__ = ["RangeImage", "RangeImageKnn", "range_image_knn", "range_image_of", "ring_ranks"]

MAX_VISITS = 400  # distance evaluations per point before it is left to the KD-tree
# Rings whose points deviate more than this (rad, mean absolute) from their ring's mean
# elevation are no beams (a ring field of zeros, random labels): every point is then left to
# the KD-tree. Real rings: 0 (simulated), 0.002 (KITTI-raw, rings inferred); one ring for a
# 30 deg field of view: ~0.13; the window search measured 2-4x slower than the KD-tree there.
MAX_RING_SPREAD = np.radians(1.0)
# Above this share of uncertified points the box search is left to the caller's KD-tree
MAX_UNCERTIFIED = 0.25


class _Buffers(threading.local):
    """Per-thread scratch arrays of ``range_image_knn``, grown as needed and reused from scan
    to scan: freshly mapped pages cost a third of a 16-beam scan's SOR time (page faults and
    zeroing, measured with perf). Holds ~60 bytes per point, plus 170 for scans that are not
    stored ring by ring; never returned to callers."""

    def __init__(self) -> None:
        self.store: dict[str, np.ndarray] = {}
        self.results: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: int | tuple[int, ...], dtype=np.float64) -> np.ndarray:
        size = int(np.prod(shape))
        a = self.store.get(name)
        if a is None or a.size < size:
            a = np.empty(size + size // 8, dtype=dtype)
            self.store[name] = a
        return a[:size].reshape(shape)

    def result(self, name: str, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        """An array to hand to the caller: a view of the block handed out last time under
        this name once nothing refers to that block any more (no array, view or object of
        the caller's can see it change), else of a new block, kept for next time."""
        size = int(np.prod(shape))
        a = self.results.get(name)
        # references to a free block: the dict entry, the name a, getrefcount's argument
        if a is None or a.size < size or sys.getrefcount(a) > 3:
            a = np.empty(size + size // 8, dtype=dtype)
            self.results[name] = a
        return a[:size].reshape(shape)


_BUFFERS = _Buffers()


@dataclass(frozen=True)
class RangeImageKnn:
    """idx (N, k+1) int64 indices: each point itself, then its k nearest other points;
    dist (N, k) the distances to those k (m), ascending; certified (N,) True where the
    window answer is proven exact (rows where it is False are not valid unless
    ``complete``); visits (N,) distance evaluations per point of the window search;
    complete: True when the uncertified rows were answered by the exact box search
    (``range_image_knn(..., complete=True)``), so that every row is valid; exited (N,)
    bool or None: rows of a search with early exits (``RangeImage.knn(exit_below=)``) that
    stopped early (their k points are real, each distance an upper bound of the true one at
    its rank; not valid k-NN rows, whatever ``complete`` says)."""

    idx: np.ndarray
    dist: np.ndarray
    certified: np.ndarray
    visits: np.ndarray
    complete: bool = False
    exited: np.ndarray | None = None

    @property
    def certified_rate(self) -> float:
        """Share of the points answered by the window search."""
        return float(self.certified.mean()) if len(self.certified) else 1.0


@dataclass
class RangeImage:
    """A scan sorted into its range image (``range_image_into``): order (N,) sorted
    position -> input index, start ring offsets, the sorted points xyz (N, 3) m, their
    range, elevation, pseudo-azimuth and unit azimuth direction (cx, cy), per-ring
    elevation bounds lo/hi (rad), spread (rad, see MAX_RING_SPREAD), in_place: stored ring
    by ring (rows are written in input order). Arrays are blocks no later scan reuses while
    this object lives (``_Buffers.result``), so it can answer more queries later."""

    order: np.ndarray
    start: np.ndarray
    xyz: np.ndarray
    rng: np.ndarray
    el: np.ndarray
    az: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    spread: float
    in_place: bool

    @property
    def beams(self) -> bool:
        """False when the ring labels do not look like beams (every query to a KD-tree)."""
        return self.spread <= MAX_RING_SPREAD

    def _search(self, k, max_visits, rows, job, exit2, exited) -> None:
        window_knn(
            self.xyz, self.rng, self.el, self.cx, self.cy, self.az, self.order, self.start,
            self.lo, self.hi, k, max_visits, *rows, self.in_place, job, exit2, exited,
        )  # fmt: skip

    def knn(
        self,
        k: int,
        *,
        max_visits: int = MAX_VISITS,
        complete: bool = False,
        job: np.ndarray | None = None,
        exit_below: float = -1.0,
        into: RangeImageKnn | None = None,
    ) -> RangeImageKnn:
        """The window search of every point (see ``range_image_knn``). job (N,) int8 per
        input point, with exit_below (m): 0 = not searched (row not written), 1 = in full,
        2 = stop once the k-th distance found is <= exit_below (``RangeImageKnn.exited``;
        such rows are neither certified nor completed by the box search). into: a result of
        this image (with job) whose rows the searched points overwrite, the others kept."""
        n = len(self.order)
        idx, dist, certified, visits, exited = self._outputs(k, job, into)
        if not self.beams:  # not beams: the window would be slow, not wrong
            idx[:] = -1
            dist[:] = np.inf
            certified[:] = False
            visits[:] = 0
            if exited is not None:
                exited[:] = False
            return RangeImageKnn(idx, dist, certified, visits, exited=exited)
        buf = _BUFFERS
        if self.in_place:
            rows = idx, dist, certified, visits
            ex_rows = exited
        else:  # rows in sorted order into scratch, gathered to the input order at the end
            rows = (
                buf.get("idx_s", (n, k + 1), np.int64),
                buf.get("dist_s", (n, k)),
                buf.get("cert_s", n, np.bool_),
                buf.get("visits_s", n, np.int64),
            )
            ex_rows = None if job is None else buf.get("exited_s", n, np.bool_)
        job_s = _NO_JOB if job is None else self._sorted_job(job)
        exit2 = exit_below * exit_below if exit_below >= 0.0 else -1.0
        # rings (and uncertified points) handed to the threads one at a time: rings differ
        # in work (sky, ground), and an equal split of them left one of 2 threads 7-26 %
        # longer
        with numba.parallel_chunksize(1):
            self._search(k, max_visits, rows, job_s, exit2, _NO_EXIT if job is None else ex_rows)
            done = complete and self._complete(k, rows, certified, job, job_s, exited, ex_rows)
            if not self.in_place and job is None:
                gather_rows(self.order, *rows, idx, dist, certified, visits)
            elif not self.in_place:  # only the rows searched (the others are not written)
                sel = np.flatnonzero(job_s)
                src = self.order[sel]
                idx[src], dist[src] = rows[0][sel], rows[1][sel]
                certified[src], visits[src] = rows[2][sel], rows[3][sel]
                exited[src] = ex_rows[sel]
        return RangeImageKnn(idx, dist, certified, visits, done, exited)

    def _outputs(self, k: int, job: np.ndarray | None, into: RangeImageKnn | None) -> tuple:
        """(idx, dist, certified, visits, exited) arrays the search writes: ``into``'s, or
        blocks returned to the caller (last scan's again once the caller has dropped them)."""
        if into is not None:
            return into.idx, into.dist, into.certified, into.visits, into.exited
        n, buf = len(self.order), _BUFFERS
        exited = None if job is None else buf.result("exited", (n,), np.bool_)
        if exited is not None:
            exited[:] = False
        return (
            buf.result("idx", (n, k + 1), np.int64),
            buf.result("dist", (n, k)),
            buf.result("certified", (n,), np.bool_),
            buf.result("visits", (n,), np.int64),
            exited,
        )

    def _complete(self, k, rows, certified, job, job_s, exited, ex_rows) -> bool:
        """The exact box search of the rows the window did not certify (searched rows only,
        not exited), unless they are more than MAX_UNCERTIFIED of the scan; True when done."""
        ok = certified[self.order] if self.in_place else rows[2]
        if job is not None:  # rows not searched, or exited: not to complete
            ok = ok | (job_s == 0) | (exited[self.order] if self.in_place else ex_rows)
        bad = np.flatnonzero(~ok)  # sorted rows
        if len(bad) > MAX_UNCERTIFIED * len(self.order):
            return False
        box_knn(self.xyz, self.order, bad, k, rows[0], rows[1], self.in_place)
        return True

    def _sorted_job(self, job: np.ndarray) -> np.ndarray:
        job_s = _BUFFERS.get("job_s", len(self.order), np.int8)
        np.take(np.asarray(job, dtype=np.int8), self.order, out=job_s)
        return job_s

    def exact_rows(
        self, res: RangeImageKnn, points: np.ndarray, *, max_visits: int = MAX_VISITS
    ) -> np.ndarray:
        """Overwrite the rows of the input points ``points`` (M,) in ``res`` (a
        ``knn(job=...)`` result over this image) with their exact k-NN: the full window
        search of those points alone (the rows it gives for all points), the box search for
        the ones it cannot certify. Returns the points whose rows the box search could not
        complete (KD-tree fallback: more than MAX_UNCERTIFIED of the scan, or no beams)."""
        n = len(self.order)
        k = res.dist.shape[1]
        points = np.asarray(points, dtype=np.int64)
        if len(points) == 0 or not self.beams:
            return points
        job = np.zeros(n, dtype=np.int8)
        job[points] = 1
        job_s = self._sorted_job(job)
        inv = np.empty(n, dtype=np.int64)
        inv[self.order] = np.arange(n)
        pos = np.sort(inv[points])  # sorted positions of the points
        buf = _BUFFERS
        if self.in_place:
            rows = res.idx, res.dist, res.certified, res.visits
        else:
            rows = (
                buf.get("idx_s", (n, k + 1), np.int64),
                buf.get("dist_s", (n, k)),
                buf.get("cert_s", n, np.bool_),
                buf.get("visits_s", n, np.int64),
            )
        with numba.parallel_chunksize(1):
            self._search(k, max_visits, rows, job_s, -1.0, buf.get("exited_x", n, np.bool_))
            cert = rows[2][self.order[pos]] if self.in_place else rows[2][pos]
            bad = pos[~cert]
            left = np.empty(0, dtype=np.int64)
            if len(bad) <= MAX_UNCERTIFIED * n:
                box_knn(self.xyz, self.order, bad, k, rows[0], rows[1], self.in_place)
            else:
                left = self.order[bad]
        if not self.in_place:
            src = self.order[pos]
            res.idx[src] = rows[0][pos]
            res.dist[src] = rows[1][pos]
            res.certified[src] = rows[2][pos]
            res.visits[src] = rows[3][pos]
        if res.exited is not None:
            res.exited[points] = False
        return left


_NO_JOB = np.empty(0, dtype=np.int8)
_NO_EXIT = np.empty(0, dtype=np.bool_)


def range_image_of(xyz: np.ndarray, ring: np.ndarray, k: int = 1) -> RangeImage:
    """The range image of a scan (N, 3) m with beam index ring (N,); checks 1 <= k <= N - 1
    for the k-NN asked of it later."""
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    ring = np.asarray(ring)
    n = len(xyz)
    if ring.shape != (n,):
        raise InputError(f"ring must have one entry per point ({n}), got shape {ring.shape}")
    if not 1 <= k <= n - 1:
        raise InputError(f"k-NN needs 1 <= k <= N - 1, got k={k} for {n} points")
    ring = ring.astype(np.int64, copy=False)
    if int(ring.max()) - int(ring.min()) > 1 << 16:  # sparse labels: compact them first
        ring = np.unique(ring, return_inverse=True)[1].astype(np.int64)
    buf = _BUFFERS
    order = buf.result("order", (n,), np.int64)
    xyz_s = buf.result("xyz", (n, 3))
    rng, el_s, az_s = buf.result("rng", (n,)), buf.result("el_s", (n,)), buf.result("az_s", (n,))
    cx, cy = buf.result("cx", (n,)), buf.result("cy", (n,))
    start, lo, hi, spread = range_image_into(
        xyz, ring, buf.get("az", n), buf.get("el", n), buf.get("rank", n, np.int64), order,
        xyz_s, rng, el_s, az_s, cx, cy,
    )  # fmt: skip
    # stored ring by ring (most steps of the order +-1): rows written in place, else sorted
    in_place = n < 2 or np.count_nonzero(np.abs(np.diff(order)) == 1) > n // 2
    return RangeImage(order, start, xyz_s, rng, el_s, az_s, cx, cy, lo, hi, spread, in_place)


def range_image_knn(
    xyz: np.ndarray,
    ring: np.ndarray,
    k: int,
    *,
    max_visits: int = MAX_VISITS,
    complete: bool = False,
) -> RangeImageKnn:
    """k nearest other points of each point of a scan (N, 3) m with beam index ring (N,),
    searched in the range image with the exactness certificate (module doc). Needs
    1 <= k <= N - 1.

    complete: answer the points the window cannot certify by an exact search over bounding
    boxes of short range-image arcs (``box_knn``; no KD-tree over the whole scan), unless
    they are more than MAX_UNCERTIFIED of the scan (labels that are no beams: the caller's
    KD-tree is then cheaper); the result's ``complete`` says whether it was done."""
    return range_image_of(xyz, ring, k).knn(k, max_visits=max_visits, complete=complete)
