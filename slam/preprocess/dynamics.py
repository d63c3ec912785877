"""Dynamic object removal by cluster motion (LeGO-LOAM-LPB, paper 001, 3.1.3).

Non-ground points are clustered with DBSCAN (scikit-learn); each cluster's centroid is
matched to the nearest centroid of the previous scan after motion compensation (the
previous centroids are moved into the current sensor frame with the odometry
``T_prev_curr``); a matched cluster whose centroid moved more than ``motion_threshold``
is a moving object and its points are removed.

What keeps this from eating the static world on data nobody tuned for:
- centroids and motion are horizontal (perpendicular to ``up``): which rings hit an
  object changes as the sensor approaches it and moves its vertical centroid, not the
  horizontal one; people and machines move horizontally;
- only object-sized clusters can be dynamic (``max_extent``): the visible part of a wall
  slides along with the sensor, and so does its centroid;
- a match needs a similar point count (``max_count_ratio``): a cluster that split or
  merged with a neighbour (occlusion, a person passing a pole) changed its centroid without
  moving; unmatched clusters (new, or moved farther than ``match_radius``) are kept.

Pure functions: the previous centroids are passed in and the new ones returned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from sklearn.cluster import DBSCAN

from slam.errors import ConfigError, InputError
from slam.mapping.local_map import voxel_hash
from slam.preprocess.dynamics_kernels import dbscan_labels


@dataclass
class DynamicsConfig:
    """eps (m) and min_samples (points) of DBSCAN; voxel (m): points are clustered as
    voxel centroids weighted by their point counts (0: every point; a 64-beam scan has
    100k). motion_threshold (m): horizontal centroid motion between consecutive scans that
    marks a cluster as moving (0.1 m = 1 m/s at 10 Hz; a walker does 1.2-1.5 m/s).
    match_radius (m): farther previous centroids do not match (10 m/s at 10 Hz).
    track_window (scans): the memory of a track's start point.
    max_extent (m): clusters wider than this are structure, never removed.
    max_count_ratio: matched clusters differ at most this much in point count.
    refine_motion: correct T_prev_curr (yaw and horizontal shift) by the motion of the
    static majority of the clusters, so that an odometry guess's error moves no cluster."""

    enabled: bool = True
    eps: float = 0.5
    min_samples: int = 5
    voxel: float = 0.15
    z_scale: float = 0.4
    motion_threshold: float = 0.08
    min_displacement: float = 0.3
    displacement_per_m: float = 0.015
    match_radius: float = 1.0
    max_extent: float = 5.0
    track_window: int = 10
    max_count_ratio: float = 2.0
    refine_motion: bool = True
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.eps <= 0 or self.min_samples < 1:
            raise ConfigError("dynamics eps must be > 0 and min_samples >= 1")
        if not 0 < self.z_scale <= 1:
            raise ConfigError(f"dynamics z_scale must be in (0, 1], got {self.z_scale}")
        if self.voxel < 0:
            raise ConfigError(f"dynamics voxel must be >= 0, got {self.voxel}")
        if not 0 < self.motion_threshold < self.match_radius:
            raise ConfigError(
                "dynamics needs 0 < motion_threshold < match_radius, got "
                f"{self.motion_threshold} and {self.match_radius}"
            )
        if self.track_window < 1:
            raise ConfigError(f"dynamics track_window must be >= 1, got {self.track_window}")
        if self.max_extent <= 0 or self.max_count_ratio < 1:
            raise ConfigError("dynamics max_extent must be > 0 and max_count_ratio >= 1")


def _check_xyz(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    return xyz


def dbscan(
    points: np.ndarray, eps: float, min_samples: int, *, reference: bool = False
) -> np.ndarray:
    """DBSCAN labels (N,) int64 of ``points`` (N, 3), equal to scikit-learn's
    ``DBSCAN(eps, min_samples).fit_predict`` (tested): core points have at least
    ``min_samples`` points (themselves included) within ``eps``; clusters are the connected
    components of the cores, numbered by their first core point; a border point takes the
    lowest-numbered cluster among its core neighbours; the rest is noise (-1).

    One C pass (``cKDTree.query_pairs``), then the compiled union-find labelling
    (``dynamics_kernels.dbscan_labels``); ``reference``: sparse connected components and
    sorts in numpy / scipy instead (the same labels, ~10x slower on 600k pairs)."""
    n = len(points)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    if not reference:
        return dbscan_labels(n, i, j, int(min_samples))
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    core = (1 + np.bincount(i, minlength=n) + np.bincount(j, minlength=n)) >= min_samples
    cores = np.flatnonzero(core)
    if len(cores) == 0:
        return labels
    both = core[i] & core[j]
    graph = coo_matrix((np.ones(int(both.sum())), (i[both], j[both])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    # components in the order of their first core point (cores ascend: first occurrence)
    comp_of_core = comp[cores]
    _, first = np.unique(comp_of_core, return_index=True)
    number = np.full(int(comp.max()) + 1, -1, dtype=np.int64)
    number[comp_of_core[np.sort(first)]] = np.arange(len(first))
    labels[cores] = number[comp_of_core]
    # border points: the lowest cluster number among their core neighbours
    a = np.concatenate([i, j])
    b = np.concatenate([j, i])
    m = core[b] & ~core[a]
    a, lab = a[m], labels[b[m]]
    if len(a):
        order = np.lexsort((lab, a))
        a, lab = a[order], lab[order]
        head = np.r_[True, a[1:] != a[:-1]]
        labels[a[head]] = lab[head]
    return labels


def cluster(
    xyz_nonground: np.ndarray, cfg: DynamicsConfig | None = None, *, reference: bool = False
) -> np.ndarray:
    """DBSCAN labels (N,) int: 0, 1, ... per cluster, -1 for noise (points in sparse space).

    With ``cfg.voxel`` > 0 the points of a voxel share its label (DBSCAN runs on the voxel
    centroids; min_samples then counts voxels). ``reference``: scikit-learn's DBSCAN
    instead of :func:`dbscan` (the same labels)."""
    cfg = cfg or DynamicsConfig()
    xyz = _check_xyz(xyz_nonground)
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    up = np.asarray(cfg.up, dtype=np.float64) / np.linalg.norm(cfg.up)
    scale = np.eye(3) - (1.0 - cfg.z_scale) * np.outer(up, up)  # shrinks along up
    if cfg.voxel > 0:
        _, inverse, counts = np.unique(
            voxel_hash(xyz, cfg.voxel), return_inverse=True, return_counts=True
        )
        inverse = inverse.reshape(-1)
        centres = np.column_stack(
            [np.bincount(inverse, weights=xyz[:, c], minlength=len(counts)) for c in range(3)]
        )
        centres /= counts[:, None]
        labels = _dbscan(centres @ scale, cfg, reference)
        return labels[inverse].astype(np.int64)
    return _dbscan(xyz @ scale, cfg, reference)


def _dbscan(points: np.ndarray, cfg: DynamicsConfig, reference: bool) -> np.ndarray:
    if reference:
        db = DBSCAN(eps=cfg.eps, min_samples=cfg.min_samples)
        return db.fit_predict(points).astype(np.int64)
    return dbscan(points, cfg.eps, cfg.min_samples)


def _horizontal_basis(up: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes perpendicular to ``up``."""
    up = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)])


def cluster_stats(
    xyz: np.ndarray, labels: np.ndarray, basis: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cluster 0..L-1: centroids (L, 3), point counts (L,), horizontal extents (L,) m
    (the larger side of the box along ``basis``)."""
    m = labels >= 0
    lab, pts = labels[m], xyz[m]
    n_lab = int(lab.max()) + 1 if len(lab) else 0
    counts = np.bincount(lab, minlength=n_lab).astype(np.float64)
    centroids = np.zeros((n_lab, 3))
    np.add.at(centroids, lab, pts)
    centroids /= np.maximum(counts, 1)[:, None]
    h = pts @ basis.T
    lo = np.full((n_lab, 2), np.inf)
    hi = np.full((n_lab, 2), -np.inf)
    np.minimum.at(lo, lab, h)
    np.maximum.at(hi, lab, h)
    extent = (hi - lo).max(axis=1) if n_lab else np.zeros(0)
    return centroids, counts, extent


STATE_COLUMNS = ("x", "y", "z", "count", "anchor_x", "anchor_y", "anchor_z", "age")


def _static_alignment(
    prev_c: np.ndarray,
    centroids: np.ndarray,
    counts: np.ndarray,
    extent: np.ndarray,
    basis: np.ndarray,
    cfg: DynamicsConfig,
) -> np.ndarray:
    """4x4 horizontal rigid correction (rotation about up, shift) that best maps the
    previous centroids onto their nearest current ones, over the static majority (trimmed
    least squares, weights = point counts). An error of the motion given (a front end's
    constant-velocity guess in a turn: 1 deg = 0.17 m at 10 m) would otherwise move every
    static cluster; the world's static majority defines the frame instead."""
    A = np.eye(4)
    h_prev, h_curr = prev_c @ basis.T, centroids @ basis.T
    dist, j = cKDTree(h_prev).query(h_curr, k=1)
    use = (dist <= cfg.match_radius) & (extent <= 4 * cfg.max_extent)
    if use.sum() < 4:
        return A
    p, q, w = h_prev[j[use]], h_curr[use], counts[use]
    keep = np.ones(len(p), dtype=bool)
    for _ in range(3):  # trimmed: the movers and mismatches drop out
        ww = w * keep
        if ww.sum() <= 0 or keep.sum() < 4:
            return A
        mp, mq = (ww @ p) / ww.sum(), (ww @ q) / ww.sum()
        H = ((p - mp) * ww[:, None]).T @ (q - mq)
        U, _, Vt = np.linalg.svd(H)
        R2 = Vt.T @ U.T
        if np.linalg.det(R2) < 0:
            Vt[-1] *= -1
            R2 = Vt.T @ U.T
        t2 = mq - R2 @ mp
        res = np.linalg.norm(p @ R2.T + t2 - q, axis=1)
        keep = res <= max(cfg.motion_threshold, 2.0 * float(np.median(res)))
    # lift the 2D transform (in the horizontal basis) to 3D: rotation about up
    up = np.cross(basis[0], basis[1])
    M = np.vstack([basis, up])  # rows: horizontal axes, up
    R3 = np.eye(3)
    R3[:2, :2] = R2
    A[:3, :3] = M.T @ R3 @ M
    A[:3, 3] = M.T @ np.r_[t2, 0.0]
    return A


def _checked_prev(prev_centroids: np.ndarray) -> np.ndarray:
    """(M, len(STATE_COLUMNS)) previous state; bare (M, 3) centroids become tracks of unknown
    count (0) starting at the centroid; InputError for any other shape."""
    prev = np.asarray(prev_centroids, dtype=np.float64)
    if prev.ndim != 2 or prev.shape[1] not in (3, len(STATE_COLUMNS)):
        raise InputError(
            f"prev_centroids must be (M, 3) or (M, {len(STATE_COLUMNS)}), got {prev.shape}"
        )
    if prev.shape[1] == 3:
        prev = np.column_stack([prev, np.zeros(len(prev)), prev, np.zeros(len(prev))])
    return prev


def _prev_in_current(
    prev: np.ndarray,
    T_prev_curr: np.ndarray,
    centroids: np.ndarray,
    counts: np.ndarray,
    extent: np.ndarray,
    basis: np.ndarray,
    cfg: DynamicsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(prev_c, prev_anchor): the previous centroids and track anchors (m) moved into this
    scan's frame by the odometry, refined by the static clusters' alignment when enabled."""
    T = np.asarray(T_prev_curr, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"T_prev_curr must be 4x4, got shape {T.shape}")
    T_curr_prev = np.linalg.inv(T)
    R, t = T_curr_prev[:3, :3], T_curr_prev[:3, 3]
    prev_c = prev[:, :3] @ R.T + t
    prev_anchor = prev[:, 4:7] @ R.T + t
    if cfg.refine_motion:
        A = _static_alignment(prev_c, centroids, counts, extent, basis, cfg)
        prev_c, prev_anchor = prev_c @ A[:3, :3].T + A[:3, 3], prev_anchor @ A[:3, :3].T + A[:3, 3]
    return prev_c, prev_anchor


def _match_tracks(
    prev: np.ndarray,
    prev_c: np.ndarray,
    centroids: np.ndarray,
    counts: np.ndarray,
    basis: np.ndarray,
    cfg: DynamicsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(matched, j): whether each cluster continues previous track j: horizontally within
    match_radius (m), of similar point count, and the nearest cluster to that track."""
    dist, j = cKDTree(prev_c @ basis.T).query(centroids @ basis.T, k=1)
    matched = dist <= cfg.match_radius
    prev_count = prev[j, 3]
    has_count = prev_count > 0
    ratio = counts / np.maximum(prev_count, 1.0)
    similar = (ratio <= cfg.max_count_ratio) & (ratio >= 1.0 / cfg.max_count_ratio)
    matched &= similar | ~has_count
    # one track per previous cluster: the nearest current cluster continues it
    best = np.full(len(prev), np.inf)
    np.minimum.at(best, j[matched], dist[matched])
    matched &= dist <= best[j]
    return matched, j


def _advance_tracks(
    state: np.ndarray,
    centroids: np.ndarray,
    extent: np.ndarray,
    matched: np.ndarray,
    basis: np.ndarray,
    cfg: DynamicsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(state, moving): the tracks' anchors forgotten past track_window scans, and which
    matched clusters moved far enough (m) and fast enough (m per scan) to be dynamic."""
    state = state.copy()
    age = state[:, 7].copy()
    reach = np.linalg.norm(centroids @ basis.T, axis=1)  # horizontal range (m)
    moved = np.linalg.norm((centroids - state[:, 4:7]) @ basis.T, axis=1)
    # the anchor forgets: past track_window scans it trails the centroid exponentially, so a
    # walker turning back is still measured over about the last window (lag v * window)
    old = age > cfg.track_window
    state[old, 4:7] += (centroids[old] - state[old, 4:7]) / cfg.track_window
    state[old, 7] = cfg.track_window
    age = np.minimum(age, cfg.track_window)
    moving = (
        matched
        & (moved >= np.maximum(cfg.min_displacement, cfg.displacement_per_m * reach))
        & (moved >= cfg.motion_threshold * np.maximum(age, 1))
        & (extent <= cfg.max_extent)
    )
    return state, moving


def remove_dynamic(
    xyz_nonground: np.ndarray,
    prev_centroids: np.ndarray | None,
    T_prev_curr: np.ndarray,
    cfg: DynamicsConfig | None = None,
    *,
    labels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Keep-mask (N,) of the non-ground points and this scan's cluster state (3.1.3).

    prev_centroids: the state returned for the previous scan (rows of STATE_COLUMNS: the
    centroid (m, previous sensor frame), point count, the track's first centroid and its
    age in scans), or (M, 3) bare centroids, or None for the first scan (all kept).
    T_prev_curr: 4x4 pose of this scan in the previous scan's frame (odometry). labels:
    DBSCAN labels if already computed (else clustered here).

    A cluster matched to a previous one continues its track; it is moving when the track
    has moved at least ``min_displacement`` from where it was first seen, at a mean speed of
    at least ``motion_threshold`` per scan. Sampling jitter of a static cluster does not
    grow with the track's age; the path of a walker does."""
    cfg = cfg or DynamicsConfig()
    xyz = _check_xyz(xyz_nonground)
    if labels is None:
        labels = cluster(xyz, cfg)
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(xyz):
        raise InputError(f"labels has {len(labels)} entries for {len(xyz)} points")
    basis = _horizontal_basis(np.asarray(cfg.up, dtype=np.float64))
    centroids, counts, extent = cluster_stats(xyz, labels, basis)
    state = np.column_stack([centroids, counts, centroids, np.zeros(len(counts))])
    keep = np.ones(len(xyz), dtype=bool)
    if prev_centroids is None or len(prev_centroids) == 0 or not len(state):
        return keep, state
    prev = _checked_prev(prev_centroids)
    prev_c, prev_anchor = _prev_in_current(prev, T_prev_curr, centroids, counts, extent, basis, cfg)
    matched, j = _match_tracks(prev, prev_c, centroids, counts, basis, cfg)
    state[matched, 4:7] = prev_anchor[j[matched]]
    state[matched, 7] = prev[j[matched], 7] + 1
    state, moving = _advance_tracks(state, centroids, extent, matched, basis, cfg)
    if cfg.enabled and moving.any():
        clustered = labels >= 0
        keep[clustered] = ~moving[labels[clustered]]
    return keep, state
