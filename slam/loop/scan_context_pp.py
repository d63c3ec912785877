"""Scan Context++ (Kim, Choi & Kim, T-RO 2022): polar and Cartesian contexts of non-ground points.

Two descriptors of one keyframe, both grids of the maximum height above the ground:

- polar context PC (rings x sectors): Scan Context of the non-ground points; a yaw is a
  column shift (:func:`slam.loop.scan_context.column_shift_distance`), a lateral offset is
  not: two passes of a street a lane apart see the near rings differently;
- Cartesian context CC (rows x cols): rows are lateral bins (sensor y, ``cc_lateral`` m
  either side), columns longitudinal bins (sensor x, ``cc_longitudinal`` m ahead and
  behind). A lateral offset between two passes is a row shift, a longitudinal one a
  column shift, and the same street driven back the other way is the CC turned half a turn
  (rows and columns reversed). Retrieval is augmented (SC++ section IV): the query's
  lateral key (row means, which a longitudinal shift hardly changes) is searched in the
  KD-tree for each lateral shift of ``-lateral_shifts..lateral_shifts`` rows and for the
  flipped CC, and each hit is scored by the column cosine distance (SC eq. 5-6) over the
  longitudinal shifts within ``longitudinal_shifts`` columns. The best (flip, row shift,
  column shift) gives the initial pose of the verification: half a turn or none, and the
  translation of the shifts.

Ground cut: points more than ``ground_clearance`` m above the sensor's ground level
(``-lidar_height``), a simple height cut (the paper builds SC++ on non-ground points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.loop.scan_context import ScanContextParams, scan_context
from slam.loop.search import tree_is_stale
from slam.loop.verify import yaw_matrix


@dataclass(frozen=True)
class ScanContextPPParams:
    """Grid geometry (m, bins) and augmentation of SC++.

    rings / sectors / max_radius (m): the polar context; lidar_height (m): added to z, so
    bins hold heights above the ground; ground_clearance (m): points lower than this above
    the ground are ground and left out of both contexts. cc_rows x cc_cols bins over
    +-cc_lateral (m, sensor y) x +-cc_longitudinal (m, sensor x): the Cartesian context
    (default 0.5 m lateral, 4 m longitudinal bins: a facade's lateral position must match
    to a fraction of a metre for the column cosines, its position along the street need
    not). lateral_shifts / longitudinal_shifts (bins): the augmented lateral row shifts and
    the longitudinal column shifts searched (+-10 rows of 0.5 m: the opposite lane 4.4 m
    aside; +-5 columns: +-20 m along the street).
    """

    rings: int = 20
    sectors: int = 60
    max_radius: float = 80.0
    lidar_height: float = 2.0
    ground_clearance: float = 0.3
    cc_rows: int = 80
    cc_cols: int = 20
    cc_lateral: float = 20.0
    cc_longitudinal: float = 40.0
    lateral_shifts: int = 10
    longitudinal_shifts: int = 5

    def __post_init__(self) -> None:
        if self.cc_rows < 2 or self.cc_cols < 2:
            raise ValueError(f"need cc_rows, cc_cols >= 2, got {self.cc_rows}, {self.cc_cols}")
        if not (self.cc_lateral > 0 and self.cc_longitudinal > 0):
            raise ValueError("cc_lateral and cc_longitudinal must be > 0 m")
        if self.lateral_shifts < 0 or self.longitudinal_shifts < 0:
            raise ValueError("lateral_shifts and longitudinal_shifts must be >= 0")

    @property
    def polar(self) -> ScanContextParams:
        return ScanContextParams(self.rings, self.sectors, self.max_radius, self.lidar_height)

    @property
    def cell(self) -> tuple[float, float]:
        """(lateral, longitudinal) bin size in m."""
        return 2.0 * self.cc_lateral / self.cc_rows, 2.0 * self.cc_longitudinal / self.cc_cols


def non_ground(points: np.ndarray, lidar_height: float, clearance: float = 0.3) -> np.ndarray:
    """Sensor-frame points more than ``clearance`` m above the ground plane z = -lidar_height."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    return pts[pts[:, 2] + lidar_height > clearance]


def polar_context(points: np.ndarray, p: ScanContextPPParams) -> np.ndarray:
    """PC (rings, sectors): Scan Context of the non-ground points."""
    return scan_context(non_ground(points, p.lidar_height, p.ground_clearance), p.polar)


def cartesian_context(points: np.ndarray, p: ScanContextPPParams) -> np.ndarray:
    """CC (cc_rows, cc_cols): max height above the ground of the non-ground points per
    (lateral y, longitudinal x) bin; 0 marks an empty bin. Row 0 is y = -cc_lateral, column
    0 is x = -cc_longitudinal, so half a turn of the sensor reverses rows and columns."""
    pts = non_ground(points, p.lidar_height, p.ground_clearance)
    desc = np.zeros(p.cc_rows * p.cc_cols, dtype=np.float64)
    if len(pts) == 0:
        return desc.reshape(p.cc_rows, p.cc_cols)
    cy, cx = p.cell
    row = np.floor((pts[:, 1] + p.cc_lateral) / cy).astype(np.intp)
    col = np.floor((pts[:, 0] + p.cc_longitudinal) / cx).astype(np.intp)
    ok = (row >= 0) & (row < p.cc_rows) & (col >= 0) & (col < p.cc_cols)
    np.maximum.at(desc, row[ok] * p.cc_cols + col[ok], pts[ok, 2] + p.lidar_height)
    return desc.reshape(p.cc_rows, p.cc_cols)


KEY_BINS = 20  # lateral key length: a KD-tree stays efficient in ~20 dimensions


def lateral_key(cc: np.ndarray, bins: int = KEY_BINS) -> np.ndarray:
    """Retrieval key of a CC, (..., <= bins): the mean height of each lateral band of rows
    (a longitudinal shift moves content along the rows and leaves their means nearly
    unchanged; bands of cc_rows / bins rows keep the key short for the KD-tree)."""
    rows = np.asarray(cc).mean(axis=-1)
    n = rows.shape[-1]
    edges = np.linspace(0, n, min(bins, n) + 1).astype(np.intp)
    sums = np.add.reduceat(rows, edges[:-1], axis=-1)
    return sums / np.diff(edges)


def shift_rows(a: np.ndarray, shift: int, axis: int = -2) -> np.ndarray:
    """``a`` moved by ``shift`` bins along ``axis`` (content at i goes to i + shift), 0-filled."""
    out = np.zeros_like(a)
    n = a.shape[axis]
    if abs(shift) >= n:
        return out
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    src[axis] = slice(max(0, -shift), n - max(0, shift))
    dst[axis] = slice(max(0, shift), n - max(0, -shift))
    out[tuple(dst)] = a[tuple(src)]
    return out


def flipped(cc: np.ndarray) -> np.ndarray:
    """The CC of the same scan turned half a turn about z (rows and columns reversed)."""
    return np.asarray(cc)[..., ::-1, ::-1]


def cc_distance(
    query: np.ndarray, candidates: np.ndarray, max_shift: int
) -> tuple[np.ndarray, np.ndarray]:
    """Column cosine distance (SC eq. 5-6 without wrap-around) of ``query`` (R, C) to
    ``candidates`` (K, R, C), minimised over longitudinal shifts ``-max_shift..max_shift``
    of the query. Returns (distance (K,) in [0, 2], best shift (K,))."""
    c = np.asarray(candidates, dtype=np.float64)
    if c.ndim == 2:
        c = c[None]
    shifts = np.arange(-max_shift, max_shift + 1)
    qs = np.stack([shift_rows(np.asarray(query, dtype=np.float64), int(s), axis=-1)
                   for s in shifts])  # fmt: skip
    qn = np.linalg.norm(qs, axis=1)  # (S, C)
    cn = np.linalg.norm(c, axis=1)  # (K, C)
    dots = np.einsum("src,krc->ksc", qs, c)  # (K, S, C)
    both = (qn[None] > 0) & (cn[:, None] > 0)
    cos = np.where(both, dots / np.maximum(qn[None] * cn[:, None], 1e-12), 0.0)
    count = both.sum(axis=2)
    dist = np.where(count > 0, 1.0 - cos.sum(axis=2) / np.maximum(count, 1), 1.0)  # (K, S)
    best = np.argmin(dist, axis=1)
    return dist[np.arange(len(c)), best], shifts[best]


def cc_pose(flip: bool, lateral: int, longitudinal: int, p: ScanContextPPParams) -> np.ndarray:
    """T_candidate_query implied by a CC match: the query turned half a turn (``flip``), then
    moved by ``lateral`` rows and ``longitudinal`` columns, matches the candidate."""
    cy, cx = p.cell
    return yaw_matrix(np.pi if flip else 0.0, np.array([longitudinal * cx, lateral * cy, 0.0]))


@dataclass
class CCMatch:
    """A scored CC database entry: row, distance, and the pose T_candidate_query it implies."""

    row: int
    distance: float
    T_candidate_query: np.ndarray


class CartesianIndex:
    """CCs and their lateral keys in arrival order, with a KD-tree over the keys rebuilt
    like the Scan Context database's (:func:`slam.loop.search.tree_is_stale`; rows added
    since are searched by brute force)."""

    def __init__(self, p: ScanContextPPParams, top_k: int = 10, rebuild_every: int = 10):
        self.p, self.top_k, self.rebuild_every = p, top_k, rebuild_every
        self._cc = np.zeros((64, p.cc_rows, p.cc_cols), dtype=np.float32)
        self._key = np.zeros((64, min(KEY_BINS, p.cc_rows)), dtype=np.float64)
        self._n = 0
        self._tree: cKDTree | None = None
        self._tree_size = 0
        self.tree_builds = 0

    def __len__(self) -> int:
        return self._n

    def add(self, cc: np.ndarray) -> int:
        if self._n == len(self._cc):
            self._cc = np.concatenate([self._cc, np.zeros_like(self._cc)])
            self._key = np.concatenate([self._key, np.zeros_like(self._key)])
        self._cc[self._n] = cc
        self._key[self._n] = lateral_key(cc)
        self._n += 1
        return self._n - 1

    def _nearest(self, keys: np.ndarray, n_eligible: int) -> tuple[np.ndarray, np.ndarray]:
        """(Q, <= top_k) rows of the nearest keys per query key among the first n_eligible,
        and their key distances."""
        if tree_is_stale(n_eligible, self._tree_size, self.rebuild_every):
            self._tree = cKDTree(self._key[:n_eligible])
            self._tree_size = n_eligible
            self.tree_builds += 1
        k = self.top_k
        rows, dists = [], []
        if self._tree is not None and self._tree_size > 0:
            d, i = self._tree.query(keys, k=min(k, self._tree_size))
            rows.append(np.asarray(i).reshape(len(keys), -1))
            dists.append(np.asarray(d).reshape(len(keys), -1))
        if n_eligible > self._tree_size:
            tail = np.arange(self._tree_size, n_eligible)
            rows.append(np.broadcast_to(tail, (len(keys), len(tail))))
            dists.append(np.linalg.norm(self._key[tail][None] - keys[:, None], axis=2))
        r, d = np.concatenate(rows, axis=1), np.concatenate(dists, axis=1)
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        return np.take_along_axis(r, order, axis=1), np.take_along_axis(d, order, axis=1)

    def query(self, cc: np.ndarray, n_eligible: int) -> list[CCMatch]:
        """Best match per row, best first.

        Augmented queries: the CC and its half-turned copy, each shifted by every lateral
        row shift; the KD-tree gives each one's top-k rows by lateral key, and the 2 x top_k
        (augmented query, row) pairs of the smallest key distances overall are scored by
        :func:`cc_distance` over the longitudinal shifts (one batched product)."""
        p = self.p
        if n_eligible <= 0:
            return []
        q = np.asarray(cc, dtype=np.float64)
        flips = np.repeat([False, True], 2 * p.lateral_shifts + 1)
        lats = np.tile(np.arange(-p.lateral_shifts, p.lateral_shifts + 1), 2)
        aug = _lateral_shifts(np.stack([q, flipped(q)]), p.lateral_shifts).reshape(-1, *q.shape)
        rows, kd = self._nearest(lateral_key(aug), n_eligible)  # (A, K)
        pick = np.argsort(kd, axis=None, kind="stable")[: 2 * self.top_k]
        ai, ki = np.divmod(pick, rows.shape[1])
        cand = rows[ai, ki]
        dist, dc = _paired_cc_distance(
            aug[ai], self._cc[cand].astype(np.float64), p.longitudinal_shifts
        )
        best: dict[int, CCMatch] = {}
        for j in np.argsort(dist, kind="stable").tolist():
            r = int(cand[j])
            if r not in best:
                T = cc_pose(bool(flips[ai[j]]), int(lats[ai[j]]), int(dc[j]), p)
                best[r] = CCMatch(r, float(dist[j]), T)
        return sorted(best.values(), key=lambda m: m.distance)


def _lateral_shifts(ccs: np.ndarray, n: int) -> np.ndarray:
    """(F, R, C) -> (F, 2n + 1, R, C): each CC moved by -n..n rows (:func:`shift_rows`)."""
    f, r, c = ccs.shape
    pad = np.zeros((f, r + 2 * n, c))
    pad[:, n : n + r] = ccs
    # shift d: out[i] = cc[i - d] = pad[i - d + n], i.e. the window starting at n - d
    win = np.lib.stride_tricks.sliding_window_view(pad, r, axis=1)  # (F, 2n + 1, C, R)
    return np.ascontiguousarray(win[:, ::-1].transpose(0, 1, 3, 2))


def _paired_cc_distance(
    queries: np.ndarray, candidates: np.ndarray, max_shift: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cc_distance` of query i (N, R, C) to candidate i (N, R, C), pair by pair:
    (distance (N,), best longitudinal shift (N,))."""
    n, _, c = queries.shape
    qn = np.linalg.norm(queries, axis=1)  # (N, C)
    cn = np.linalg.norm(candidates, axis=1)
    shifts = np.arange(-max_shift, max_shift + 1)
    dist = np.ones((n, len(shifts)))
    for k, sh in enumerate(shifts.tolist()):
        # query column j - sh lands on column j: overlapping columns only (zero filled)
        qa, ca = slice(max(0, -sh), c - max(0, sh)), slice(max(0, sh), c - max(0, -sh))
        dots = np.einsum("nrc,nrc->nc", queries[:, :, qa], candidates[:, :, ca])
        norms = qn[:, qa] * cn[:, ca]
        both = norms > 0.0
        count = both.sum(axis=1)
        cos = np.where(both, dots / np.where(both, norms, 1.0), 0.0).sum(axis=1)
        dist[:, k] = np.where(count > 0, 1.0 - cos / np.maximum(count, 1), 1.0)
    best = np.argmin(dist, axis=1)
    return dist[np.arange(n), best], shifts[best]
