"""The visit graph's final multi-view refinement and its consistency measure
(``slam.visit_graph``): every visit's cloud registered on the other visits near it at
their current poses (``visit_offsets``), summarised (``offset_stats``), and optionally
turned into edges and re-optimised for a few rounds (``refine_visits``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from slam.cell_lines import line_reference
from slam.mapping.grid2d import compose2d, inverse2d, transform2d
from slam.registration.plicp import plicp

if TYPE_CHECKING:  # the visit graph calls this module; it is a type here only
    from slam.visit_graph import VisitGraph, VisitGraphConfig


@dataclass
class VisitOffset:
    """One visit registered on the others near it (``visit_offsets``): its correction
    (x, y, theta in its frame: where its cloud sits best on theirs), the reference visits
    its inliers fell on, and whether the registration was accepted."""

    visit: int
    correction: np.ndarray
    refs: np.ndarray
    accepted: bool


def visit_offsets(
    X: np.ndarray, clouds: list[np.ndarray], path: np.ndarray, cfg: VisitGraphConfig
) -> list[VisitOffset]:
    """Every visit's cloud (``clouds[i]``, its vertex frame) registered by PLICP, from
    where it is (vertex poses ``X`` (V, 3)), against the clouds of the other visits near
    it (vertex within ``refine_radius``, at least ``min_path`` of ``path`` away, the
    nearest ``refine_refs``) fused at their poses: how far each visit lies from the
    others where they see the same walls - a wall drawn twice 10 cm apart moves a visit
    by ~10 cm, however many hits are fused (the grid measures grow with them). Accepted
    when within ``refine_max_m`` / ``refine_max_deg`` and ``refine_min_inliers`` of its
    overlapping points (within ``overlap_m``) lie within ``inlier_m`` after it."""
    c = cfg
    X = np.asarray(X, dtype=np.float64)
    path = np.asarray(path, dtype=np.float64)
    world = [transform2d(X[i], clouds[i]) for i in range(len(X))]
    out: list[VisitOffset] = []
    for i in range(len(X)):
        target = clouds[i]
        if len(target) < c.min_overlap:
            continue
        d = np.linalg.norm(X[:, :2] - X[i, :2], axis=1)
        ok = (np.abs(path - path[i]) >= c.min_path) & (d <= c.refine_radius)
        refs = [j for j in np.argsort(d) if ok[j]][: c.refine_refs]
        if not refs:
            continue
        inv = inverse2d(X[i])
        pts = np.vstack([transform2d(inv, world[j]) for j in refs])
        owner = np.concatenate([np.full(len(world[j]), j) for j in refs])
        ref, first = line_reference(pts, c.resolution)
        if ref is None:
            continue
        corr = plicp(target, ref, np.zeros(3), c.plicp).pose
        none = np.zeros(0, dtype=np.int64)
        if np.hypot(corr[0], corr[1]) > c.refine_max_m or abs(np.degrees(corr[2])) > (
            c.refine_max_deg
        ):
            out.append(VisitOffset(i, corr, none, False))
            continue
        dist, near_idx = ref.tree.query(transform2d(corr, target), distance_upper_bound=c.overlap_m)
        near = np.isfinite(dist)
        if near.sum() < c.min_overlap or np.mean(dist[near] < c.inlier_m) < c.refine_min_inliers:
            out.append(VisitOffset(i, corr, none, False))
            continue
        # the reference visits the inliers fell on (a cell counts for its first point's)
        good = near & (dist < c.inlier_m)
        js, n = np.unique(owner[first][near_idx[good]], return_counts=True)
        out.append(VisitOffset(i, corr, js[n >= max(10, 0.1 * n.max())], True))
    return out


def offset_stats(offsets: list[VisitOffset]) -> dict:
    """Visits registered / accepted and the accepted corrections' median / p90 / max (m)
    and median (deg)."""
    acc = [o for o in offsets if o.accepted]
    m = np.array([np.hypot(*o.correction[:2]) for o in acc]) if acc else np.zeros(1)
    deg = np.array([abs(np.degrees(o.correction[2])) for o in acc]) if acc else np.zeros(1)
    return {"registered": len(offsets), "accepted": len(acc), "median_m": float(np.median(m)),
            "p90_m": float(np.percentile(m, 90)), "max_m": float(m.max()),
            "median_deg": float(np.median(deg))}  # fmt: skip


def refine_visits(vg: VisitGraph, rounds: int | None = None) -> list[dict]:
    """The final multi-view refinement (Cartographer's final optimisation in spirit): each
    round, every visit registered on the others near it at their current optimised poses
    (``visit_offsets``); an accepted registration becomes an edge to each reference visit
    its inliers fell on (Cauchy kernel, the registration's noise split over them, sigma *
    sqrt(n)), and the graph (odometry and loop edges, and this round's edges: the last
    round's are dropped, they measured the poses before) is re-optimised. Returns per
    round ``offset_stats`` of the registrations (before that round's optimisation)."""
    c = vg.cfg
    rounds = c.refine_rounds if rounds is None else rounds
    loops = vg.loop_search
    ids = range(len(vg.fe))
    path = np.array([loops.path[i] for i in ids])
    clouds = [loops.clouds[i] for i in ids]
    sig = np.array([c.refine_sigma_m, c.refine_sigma_m, np.radians(c.refine_sigma_deg)])
    stats: list[dict] = []
    for _ in range(rounds):
        X = vg.estimates()
        offsets = visit_offsets(X, clouds, path, c)
        extra = []
        for o in offsets:
            if not o.accepted or not len(o.refs):
                continue
            noise = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Cauchy.Create(c.robust_param),
                gtsam.noiseModel.Diagonal.Sigmas(sig * np.sqrt(len(o.refs))),
            )
            Xi = compose2d(X[o.visit], o.correction)
            for j in o.refs:
                z = compose2d(inverse2d(X[int(j)]), Xi)
                extra.append(gtsam.BetweenFactorPose2(int(j), o.visit, gtsam.Pose2(*z), noise))
        vg._optimize(extra)
        stats.append(offset_stats(offsets))
    return stats


__all__ = ["VisitOffset", "offset_stats", "refine_visits", "visit_offsets"]
