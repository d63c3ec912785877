"""Self-consistency relations for 2D laser logs without published ones: relative poses
between scans a short way apart, each made by registering the two scans alone and kept
only when the registration verifies - the way the Freiburg relations of Kuemmerle et al.
(2009) were made (scan matching between chosen pairs, checked), here checked by machine.

A relation starts at every ``every``-th scan; its second scan is the first one at least
``distance`` m (of wheel-odometry path) later, for each distance of ``distances``. The two
scans are registered with no trajectory estimate involved: a correlative search
(``slam.registration.correlative2d``) of the second scan on the first around the wheel
odometry's relative pose, then PLICP on the first scan's line features
(``slam.registration.plicp``) from the search's best. A relation is kept when

- the search is unique (second peak / best <= ``max_uniqueness``: not a corridor) and
  its peak is inside the window, not on its edge (the true one may lie beyond),
- PLICP constrains every direction (no degenerate direction left at the start),
- ``min_overlap`` of the second scan's points have a point of the first within
  ``overlap_m`` and ``min_inliers`` of those lie within ``inlier_m`` after PLICP,
- and the reverse registration (first scan on the second) agrees within ``agree_m`` /
  ``agree_deg`` (a registration that depends on its direction is not a measurement).

Scored with ``slam.eval.relations``, these relations say how well a trajectory keeps the
local geometry the scans show: a graph that bends or breaks the front end's trajectory
where no scan says so is caught on every log.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from slam.errors import ConfigError
from slam.eval.relations import Relations
from slam.features.lines2d import LineConfig, extract_lines
from slam.mapping.grid2d import compose2d, inverse2d, pose2_to_matrix, transform2d, wrap
from slam.registration.correlative2d import CorrelativeConfig, correlative_search
from slam.registration.plicp import LineReference, PlicpConfig, plicp


@dataclass
class SelfRelationConfig:
    """every: a relation starts at every this many scans; distances (m): the second scan
    is the first this much wheel-odometry path later (one relation per distance);
    max_range (m): scan points beyond are dropped; resolution (m): the cells the lines
    are fitted to; search_m / search_deg: the correlative search window around the wheel
    odometry; max_uniqueness, min_overlap, overlap_m, inlier_m, min_inliers, agree_m,
    agree_deg: the checks (module docstring)."""

    every: int = 10
    distances: tuple[float, ...] = (0.5, 1.0, 2.0)
    max_range: float = 30.0
    resolution: float = 0.05
    search_m: float = 0.5
    search_deg: float = 10.0
    search: CorrelativeConfig = field(
        default_factory=lambda: CorrelativeConfig(resolution=0.05, angle_step_deg=0.5)
    )
    max_uniqueness: float = 0.8
    min_overlap: float = 0.5
    overlap_m: float = 0.3
    inlier_m: float = 0.1
    min_inliers: float = 0.85
    agree_m: float = 0.03
    agree_deg: float = 0.3
    plicp: PlicpConfig = field(default_factory=lambda: PlicpConfig(max_distance=0.3))

    def __post_init__(self) -> None:
        if self.every < 1 or not self.distances or min(self.distances) <= 0:
            raise ConfigError("self relations: every >= 1 and distances > 0 required")


@dataclass
class SelfRelationStats:
    """Pairs examined and why the rejected ones were rejected (counts)."""

    pairs: int = 0
    kept: int = 0
    rejected: dict = field(default_factory=dict)

    def reject(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1


def scan_reference(pts: np.ndarray, resolution: float) -> LineReference | None:
    """Line features of one scan's cell means (hits weighted), as a PLICP reference."""
    if len(pts) < 20:
        return None
    cells = np.floor(pts / resolution).astype(np.int64)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    count = np.bincount(inverse)
    mean = np.column_stack([np.bincount(inverse, pts[:, d]) / count for d in range(2)])
    return LineReference.from_lines(extract_lines(mean, resolution, LineConfig(), count * 1.0))


def register_pair(
    a: np.ndarray, b: np.ndarray, guess: np.ndarray, cfg: SelfRelationConfig
) -> tuple[np.ndarray | None, str]:
    """Scan ``b`` (N, 2) registered on scan ``a`` (M, 2) around ``guess`` (b in a's frame):
    (pose of b in a's frame, "") when every check passes, else (None, why not)."""
    ref_a, ref_b = scan_reference(a, cfg.resolution), scan_reference(b, cfg.resolution)
    if ref_a is None or ref_b is None:
        return None, "too few points"
    scfg = replace(cfg.search, max_shift=cfg.search_m, max_angle_deg=cfg.search_deg)
    found = correlative_search(a, b, guess, scfg)
    if found.uniqueness > cfg.max_uniqueness:
        return None, "ambiguous"
    shift = np.abs(found.pose[:2] - guess[:2]).max()
    turn = abs(np.degrees(wrap(found.pose[2] - guess[2])))
    if shift > cfg.search_m - 2 * scfg.resolution or turn > cfg.search_deg - 2 * (
        scfg.angle_step_deg
    ):
        return None, "peak at the window's edge"
    res = plicp(b, ref_a, found.pose, cfg.plicp)
    if res.degenerate or not res.converged:
        return None, "degenerate"
    dist, _ = ref_a.tree.query(transform2d(res.pose, b), distance_upper_bound=cfg.overlap_m)
    near = np.isfinite(dist)
    if near.mean() < cfg.min_overlap:
        return None, "too little overlap"
    if np.mean(dist[near] < cfg.inlier_m) < cfg.min_inliers:
        return None, "too few inliers"
    back = plicp(a, ref_b, inverse2d(res.pose), cfg.plicp)
    diff = compose2d(res.pose, back.pose)
    if np.hypot(diff[0], diff[1]) > cfg.agree_m or abs(np.degrees(wrap(diff[2]))) > cfg.agree_deg:
        return None, "directions disagree"
    return res.pose, ""


def pair_indices(odom: np.ndarray, cfg: SelfRelationConfig) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j): i every ``every``-th scan, j the first scan at least each
    distance of wheel-odometry path after i (pairs past the end left out)."""
    step = np.linalg.norm(np.diff(odom[:, :2], axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(step)])
    pi, pj = [], []
    for i in range(0, len(odom), cfg.every):
        for d in cfg.distances:
            j = int(np.searchsorted(path, path[i] + d))
            if j < len(odom):
                pi.append(i)
                pj.append(j)
    return np.array(pi, dtype=np.int64), np.array(pj, dtype=np.int64)


def self_relations(
    stamps: np.ndarray,
    scans: list[np.ndarray],
    odom: np.ndarray,
    cfg: SelfRelationConfig | None = None,
) -> tuple[Relations, SelfRelationStats]:
    """The verified relations of a log: ``stamps`` (K,), ``scans`` (each (N, 2), laser
    frame), wheel odometry ``odom`` (K, 3). Returns the relations (planar 4x4) and the
    counts of pairs examined, kept and rejected by reason."""
    cfg = cfg or SelfRelationConfig()
    odom = np.asarray(odom, dtype=np.float64)
    pairs = [
        (i, j, compose2d(inverse2d(odom[i]), odom[j]))
        for i, j in zip(*pair_indices(odom, cfg), strict=True)
    ]
    return _registered(stamps, scans, pairs, cfg)


def _registered(
    stamps: np.ndarray, scans: list[np.ndarray], pairs: list, cfg
) -> tuple[Relations, SelfRelationStats]:
    """The pairs (i, j, guess) that ``register_pair`` verifies, as relations, with the
    counts of pairs examined, kept and rejected by reason."""
    stats = SelfRelationStats()
    ti, tj, rel = [], [], []
    for i, j, guess in pairs:
        stats.pairs += 1
        a, b = _clip(scans[i], cfg.max_range), _clip(scans[j], cfg.max_range)
        pose, why = register_pair(a, b, guess, cfg)
        if pose is None:
            stats.reject(why)
            continue
        stats.kept += 1
        ti.append(stamps[i])
        tj.append(stamps[j])
        rel.append(pose2_to_matrix(pose))
    poses = np.array(rel).reshape(-1, 4, 4)
    return Relations(np.array(ti), np.array(tj), poses), stats


@dataclass
class RevisitRelationConfig:
    """Long-range relations between a scan and the same place seen again later.

    every: a relation may start at every this many scans; min_path (m): the second scan
    is at least this much wheel-odometry path later (a revisit, not the next metres);
    radius (m) / max_turn_deg: a proposing trajectory puts the two scans this close and
    this alike in heading; per_scan: revisits kept per first scan (nearest first, one
    scan per revisit: revisits are told apart by ``min_path`` of path between them);
    pair: the registration and its checks (``register_pair``), here over a window of
    ``pair.search_m`` / ``pair.search_deg`` around the proposing trajectory's guess."""

    every: int = 10
    min_path: float = 10.0
    radius: float = 2.0
    max_turn_deg: float = 60.0
    per_scan: int = 2
    pair: SelfRelationConfig = field(
        default_factory=lambda: SelfRelationConfig(search_m=1.0, search_deg=15.0)
    )

    def __post_init__(self) -> None:
        if self.every < 1 or self.per_scan < 1 or self.min_path <= 0 or self.radius <= 0:
            raise ConfigError("revisit relations: every, per_scan >= 1; min_path, radius > 0")


def revisit_pairs(
    odom: np.ndarray, trajectories: list[np.ndarray], cfg: RevisitRelationConfig
) -> list[tuple[int, int, np.ndarray]]:
    """Candidate revisits (i, j, guess of j in i's frame): for every ``every``-th scan i,
    the scans j at least ``min_path`` of wheel path later that one of ``trajectories``
    (each (K, 3), x y theta per scan) places within ``radius`` and ``max_turn_deg``; per
    trajectory the nearest scan of each revisit, the nearest ``per_scan`` revisits."""
    step = np.linalg.norm(np.diff(np.asarray(odom)[:, :2], axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(step)])
    out: dict[tuple[int, int], np.ndarray] = {}
    for traj in trajectories:
        traj = np.asarray(traj, dtype=np.float64)
        for i in range(0, len(traj), cfg.every):
            later = np.flatnonzero(path >= path[i] + cfg.min_path)
            if not len(later):
                break
            d = np.linalg.norm(traj[later, :2] - traj[i, :2], axis=1)
            turn = np.abs(np.degrees(wrap(traj[later, 2] - traj[i, 2])))
            near = later[(d <= cfg.radius) & (turn <= cfg.max_turn_deg)]
            if not len(near):
                continue
            # revisits: runs of near scans split where the path between exceeds min_path
            cut = np.flatnonzero(np.diff(path[near]) > cfg.min_path) + 1
            best = []
            for run in np.split(near, cut):
                dr = np.linalg.norm(traj[run, :2] - traj[i, :2], axis=1)
                best.append((float(dr.min()), int(run[np.argmin(dr)])))
            for _, j in sorted(best)[: cfg.per_scan]:
                out.setdefault((i, j), compose2d(inverse2d(traj[i]), traj[j]))
    return [(i, j, g) for (i, j), g in sorted(out.items())]


def revisit_relations(
    stamps: np.ndarray,
    scans: list[np.ndarray],
    odom: np.ndarray,
    trajectories: list[np.ndarray],
    cfg: RevisitRelationConfig | None = None,
) -> tuple[Relations, SelfRelationStats]:
    """Long-range verified relations of a log: revisits proposed by ``trajectories`` (any
    estimates, each (K, 3) per scan; their union, so that no one of them chooses the
    places it is scored on), each registered from its scans alone and checked as the
    short relations are (``register_pair``: unique in the window, peak inside it, overlap,
    inliers, both directions agree). A trajectory that a wrong loop edge bends or that
    drifts over a loop is caught where the place is seen again."""
    cfg = cfg or RevisitRelationConfig()
    return _registered(stamps, scans, revisit_pairs(odom, trajectories, cfg), cfg.pair)


def _clip(pts: np.ndarray, max_range: float) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)[:, :2]
    return pts[np.linalg.norm(pts, axis=1) <= max_range]


__all__ = ["RevisitRelationConfig", "SelfRelationConfig", "SelfRelationStats", "pair_indices",
           "register_pair", "revisit_pairs", "revisit_relations", "self_relations"]  # fmt: skip
