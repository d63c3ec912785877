"""A visit graph for 2D laser SLAM: vertices per visit, not
per region (a submap of a fixed number of scans, as in Cartographer), edges only between
measurement-only clouds, a wide loop search, and the final poses of every scan from the
optimised visit poses.

A *visit* is ``visit_scans`` consecutive scans; its vertex sits at the pose of its last
scan and its cloud is the hit cells (sub-cell means, 5 cm) of its scans and ``pad`` scans
either side, drawn at the front end's own poses relative to that scan: a short stretch
of scan matching, never a map moved by the graph. Consecutive visits are linked by the
front end's relative pose (noise grows with the distance and the turn). For each new
visit, the earlier visits at least ``min_path`` m of path back whose estimated vertex lies
within ``radius`` m are loop candidates (nearest first, at most ``max_candidates``); each
is searched by the correlative matcher (``slam.registration.correlative2d``) over a window
of +- ``search_m`` m (growing with the path between the two, up to ``max_search_m``) and
+- ``search_deg``, then refined by PLICP. An edge is kept when the search is unique (second
peak / best <= ``max_uniqueness``: corridors are ambiguous), PLICP stays within two search
cells of it, and ``min_inliers`` of the overlapping target points lie on the reference.
A verified edge enters the graph only once an independent edge nearby agrees with it
through the front end's relative poses (``PairwiseCheck``: an aliased match rarely repeats
itself consistently). Loop edges carry a Cauchy kernel and are switched off beyond
``gate_sigma`` claimed sigmas at the result; the graph is optimised (Levenberg-Marquardt on
gtsam Pose2) after each visit that added one. At the end, when the front end lies within
``keep_frontend_sigma`` of every loop edge kept, its poses are the result (the edges do
not show it wrong; ``slam.graph2d_gate.frontend_check``).

``VisitGraph`` is the incremental core; ``VisitGraph.scan_poses`` gives every scan's pose
(its visit's optimised pose o its front-end pose relative to the visit's vertex).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from slam.cell_lines import line_reference
from slam.errors import ConfigError
from slam.graph2d_gate import frontend_check, optimize_gated
from slam.mapping.grid2d import (
    GridConfig,
    OccupancyGrid,
    compose2d,
    inverse2d,
    transform2d,
    wrap,
)
from slam.registration.correlative2d import CorrelativeConfig, correlative_search
from slam.registration.plicp import LineReference, PlicpConfig, plicp
from slam.visit_refine import refine_visits


@dataclass
class VisitGraphConfig:
    """visit_scans: scans per visit (vertex); pad: scans before it also drawn into a
    visit's cloud; ref_visits: a loop candidate's reference is its cloud and those of this
    many visits either side; resolution (m): its cells;
    odom_sigma_m + odom_sigma_per_m * distance and odom_sigma_deg + odom_sigma_deg_per_m *
    distance + odom_turn_fraction * turn: noise of the front end's relative pose between
    consecutive visits (the defaults are ``slam.mapping.grid2d.planar_information``'s, the
    odometry factors of a pipeline run); min_path (m): a loop candidate is at least this
    much path back; radius (m): its estimated vertex at most this far; max_candidates per
    visit (nearest first); search_m + search_fraction * path (at most max_search_m) and
    search_deg: the window of the correlative search; search: its other settings;
    max_uniqueness: second peak / best above this is ambiguous; min_inliers: share of the
    target's points near the reference (within ``overlap_m``) that lie within
    ``inlier_m`` after PLICP; min_overlap: fewest such points; loop_sigma_m /
    loop_sigma_deg: noise of a loop edge (Cauchy kernel, ``robust_param``);
    refine_rounds: rounds of the final multi-view refinement (``refine_visits``, 0: none);
    refine_radius (m) / refine_refs: a visit's reference there is the clouds of the other
    visits (at least ``min_path`` of path away) whose optimised vertex lies this close,
    the nearest ``refine_refs``; refine_max_m / refine_max_deg: a registration moving
    the visit farther is dropped; refine_min_inliers: share of the overlapping points
    within ``inlier_m`` after it; refine_sigma_m / refine_sigma_deg: noise of the
    registration, split over the reference visits (an edge to each, sigma * sqrt(n));
    gate_sigma / gate_rounds: loop edges beyond this many claimed sigmas at the result are
    switched off and the graph re-optimised (``slam.graph2d_gate``; 0: Cauchy only);
    pair_window (visits, 0: off): a verified loop edge enters the graph only once another
    one, independent of it (another new visit, or old visits whose references share no
    cloud), whose new visit lies within this many visits agrees with it through the front
    end's relative poses: the cycle of the two edges and the two stretches of front end
    between them closes within pair_m + pair_ratio * travelled (m) and pair_deg +
    pair_ratio_deg * travelled (deg), travelled the path of the two stretches (m), and
    no more confirmed edges nearby contradict it than agree (``PairwiseCheck``);
    keep_frontend_sigma: the front end's poses are the result when every loop edge kept
    lies within this many of its claimed sigmas of them (``slam.graph2d_gate.
    frontend_check``; 0: never)."""

    visit_scans: int = 30
    pad: int = 15
    ref_visits: int = 2
    resolution: float = 0.05
    odom_sigma_m: float = 0.02
    odom_sigma_per_m: float = 0.02
    odom_sigma_deg: float = 0.5
    odom_sigma_deg_per_m: float = 0.0
    odom_turn_fraction: float = 0.02
    min_path: float = 8.0
    radius: float = 6.0
    max_candidates: int = 6
    search_m: float = 1.5
    search_fraction: float = 0.05
    max_search_m: float = 4.0
    search_deg: float = 15.0
    search: CorrelativeConfig = field(default_factory=CorrelativeConfig)
    max_uniqueness: float = 0.8
    min_inliers: float = 0.6
    min_overlap: int = 100
    overlap_m: float = 0.3
    inlier_m: float = 0.08
    loop_sigma_m: float = 0.05
    loop_sigma_deg: float = 1.0
    robust_param: float = 1.0
    plicp: PlicpConfig = field(default_factory=lambda: PlicpConfig(max_distance=0.3))
    refine_rounds: int = 0
    refine_radius: float = 6.0
    refine_refs: int = 8
    refine_max_m: float = 0.3
    refine_max_deg: float = 3.0
    refine_min_inliers: float = 0.6
    refine_sigma_m: float = 0.05
    refine_sigma_deg: float = 1.0
    gate_sigma: float = 4.0
    gate_rounds: int = 3
    pair_window: int = 4
    pair_m: float = 0.2
    pair_ratio: float = 0.02
    pair_deg: float = 1.5
    pair_ratio_deg: float = 0.1
    keep_frontend_sigma: float = 3.0

    def __post_init__(self) -> None:
        if self.pair_window < 0 or min(self.pair_m, self.pair_deg) <= 0:
            raise ConfigError("visit_graph: pair_window >= 0, pair_m and pair_deg > 0")
        if self.visit_scans < 1 or self.pad < 0 or self.max_candidates < 0:
            raise ConfigError("visit_graph: visit_scans >= 1, pad >= 0, max_candidates >= 0")
        if self.refine_rounds < 0 or self.refine_refs < 1:
            raise ConfigError("visit_graph: refine_rounds >= 0 and refine_refs >= 1")


@dataclass
class LoopEvent:
    """One loop candidate examined: visits (new, old), search score and uniqueness,
    inlier share, the correction of the estimate it implies (m, deg), accepted or why not."""

    new: int
    old: int
    score: float
    uniqueness: float
    inliers: float
    correction_m: float
    correction_deg: float
    accepted: bool
    reason: str


def visit_cloud(
    poses: np.ndarray, scans: list[np.ndarray], anchor: np.ndarray, resolution: float
) -> np.ndarray:
    """Hit cells (sub-cell means, (M, 2)) of ``scans`` at ``poses`` (front end frame), in
    the frame of ``anchor``: a cell counts once hit by two scans (or one, for a single scan)."""
    grid = OccupancyGrid(GridConfig(resolution=resolution, hit=1.0, miss=-1.0, clamp=300.0,
                                    occupied=1.5 if len(scans) > 1 else 0.5))  # fmt: skip
    inv = inverse2d(anchor)
    for pose, pts in zip(poses, scans, strict=True):
        local = compose2d(inv, pose)
        if len(pts):
            grid.add_scan(transform2d(local, pts), local[:2], free_space=False)
    return grid.obstacle_points()


@dataclass(eq=False)
class VerifiedLoop:
    """A verified loop edge old -> new (z: new in old's frame), waiting for a partner."""

    old: int
    new: int
    z: np.ndarray
    confirmed: bool = False
    expired: bool = False


class PairwiseCheck:
    """Pairwise consistency of loop edges through the front end (Mangelson et al. 2018,
    eq. 5; the 2D form of ``slam.loop.consistency``): two edges (a1 -> b1, z1) and
    (a2 -> b2, z2) both give b2 in a1's frame, z1 o D_b and D_a o z2 with D the front end's
    relative pose between a1, a2 (old pass) and b1, b2 (new pass). A wrong edge (an
    aliased match) rarely agrees with an independent one; see ``VisitGraphConfig``."""

    def __init__(self, cfg: VisitGraphConfig, fe: dict, path: dict):
        self.cfg, self.fe, self.path = cfg, fe, path
        self.loops: list[VerifiedLoop] = []
        self.expired = 0

    def cycle(self, l1: VerifiedLoop, l2: VerifiedLoop) -> tuple[float, float, float]:
        """(translation m, rotation deg, travelled m) of the cycle of two edges."""
        fe = self.fe
        d_a = compose2d(inverse2d(fe[l1.old]), fe[l2.old])
        d_b = compose2d(inverse2d(fe[l1.new]), fe[l2.new])
        err = compose2d(inverse2d(compose2d(d_a, l2.z)), compose2d(l1.z, d_b))
        travelled = abs(self.path[l1.old] - self.path[l2.old]) + abs(
            self.path[l1.new] - self.path[l2.new]
        )
        return float(np.hypot(err[0], err[1])), float(abs(np.degrees(wrap(err[2])))), travelled

    def consistent(self, l1: VerifiedLoop, l2: VerifiedLoop) -> bool:
        c = self.cfg
        t, r, d = self.cycle(l1, l2)
        return t <= c.pair_m + c.pair_ratio * d and r <= c.pair_deg + c.pair_ratio_deg * d

    def independent(self, l1: VerifiedLoop, l2: VerifiedLoop) -> bool:
        """Another new visit, or old references that share no visit's cloud."""
        return l1.new != l2.new or abs(l1.old - l2.old) > 2 * self.cfg.ref_visits

    def add(self, loop: VerifiedLoop) -> list[VerifiedLoop]:
        """Take a verified edge; returns the edges it confirms (itself and / or waiting
        partners). Edges of new visits more than ``pair_window`` back expire unconfirmed."""
        w = self.cfg.pair_window
        if w <= 0:
            loop.confirmed = True
            return [loop]
        for m in self.loops:
            if not m.confirmed and not m.expired and m.new < loop.new - w:
                m.expired = True
                self.expired += 1
        near = [m for m in self.loops if not m.expired and abs(m.new - loop.new) <= w
                and self.independent(loop, m)]  # fmt: skip
        agree = [m for m in near if self.consistent(loop, m)]
        self.loops.append(loop)
        if not agree or not self._wins(near, agree):
            return []
        loop.confirmed = True
        out = [loop]
        for m in agree:
            if m.confirmed:
                continue
            m_near = [x for x in self.loops if x is not m and not x.expired
                      and abs(x.new - m.new) <= w and self.independent(m, x)]  # fmt: skip
            m_agree = [x for x in m_near if x is loop or self.consistent(m, x)]
            if self._wins(m_near, m_agree):
                m.confirmed = True
                out.append(m)
        return out

    @staticmethod
    def _wins(near: list[VerifiedLoop], agree: list[VerifiedLoop]) -> bool:
        ids = {id(m) for m in agree}
        against = sum(1 for m in near if m.confirmed and id(m) not in ids)
        return sum(1 for m in agree if m.confirmed) >= against


class VisitLoops:
    """The loop search over visits, apart from any graph: each visit's front-end pose,
    cloud and path length; ``search(i, estimate)`` examines the candidates of visit ``i``
    under the current pose estimates (``estimate(j)`` -> (x, y, theta)) and returns the
    accepted edges (j, i, measured pose of i in j's frame) with every event."""

    def __init__(self, cfg: VisitGraphConfig | None = None):
        self.cfg = cfg or VisitGraphConfig()
        self.fe: dict[int, np.ndarray] = {}
        self.clouds: dict[int, np.ndarray] = {}
        self.path: dict[int, float] = {}
        self._refs: dict[int, tuple[int, LineReference | None]] = {}
        self.order: list[int] = []
        self.events: list[LoopEvent] = []
        self.search_ms: list[float] = []
        self.pairs = PairwiseCheck(self.cfg, self.fe, self.path)

    def add(self, i: int, fe_pose: np.ndarray, cloud: np.ndarray) -> None:
        fe_pose = np.asarray(fe_pose, dtype=np.float64)
        last = self.order[-1] if self.order else None
        step = 0.0 if last is None else float(np.linalg.norm(fe_pose[:2] - self.fe[last][:2]))
        self.path[i] = (0.0 if last is None else self.path[last]) + step
        self.fe[i] = fe_pose
        self.clouds[i] = np.asarray(cloud, dtype=np.float64).reshape(-1, 2)[:, :2]
        self.order.append(i)

    def _ref(self, pos: int, newest: int) -> LineReference | None:
        """The reference of the candidate at ``pos`` (in ``order``): its cloud and those of
        ``ref_visits`` visits either side (up to position ``newest``), placed by the front
        end's relative poses (a short stretch of scan matching, not the graph's
        estimate); cached once complete."""
        r = self.cfg.ref_visits
        hi = min(pos + r, newest)
        j = self.order[pos]
        cached = self._refs.get(j)
        if cached is not None and cached[0] == hi:
            return cached[1]
        inv = inverse2d(self.fe[j])
        parts = [
            transform2d(compose2d(inv, self.fe[k]), self.clouds[k])
            for k in self.order[max(0, pos - r) : hi + 1]
        ]
        ref, _ = line_reference(np.vstack(parts), self.cfg.resolution)
        self._refs[j] = (hi, ref)
        return ref

    def search(self, i: int, estimate) -> tuple[list[tuple[int, int, np.ndarray]], list[LoopEvent]]:
        """The loop edges (old, new, z) confirmed by visit ``i``'s candidates (``pair_window``:
        edges of earlier visits a partner now confirms among them) and its events."""
        verified, events = self.verify(i, estimate)
        edges = []
        for j, k, z in verified:
            for m in self.pairs.add(VerifiedLoop(j, k, z)):
                edges.append((m.old, m.new, m.z))
        return edges, events

    def verify(self, i: int, estimate) -> tuple[list[tuple[int, int, np.ndarray]], list[LoopEvent]]:
        """Visit ``i``'s loop candidates searched and verified, before the pairwise check."""
        c = self.cfg
        X_i = np.asarray(estimate(i), dtype=np.float64)
        pos_i = len(self.order) - 1 if self.order[-1] == i else self.order.index(i)
        old = [p for p in range(pos_i) if self.path[i] - self.path[self.order[p]] >= c.min_path]
        target = self.clouds[i]
        edges: list[tuple[int, int, np.ndarray]] = []
        events: list[LoopEvent] = []
        if not old or len(target) < c.min_overlap:
            return edges, events
        newest = old[-1]  # a reference holds only visits min_path back
        cands = []
        for p in old:
            X_j = np.asarray(estimate(self.order[p]), dtype=np.float64)
            d = float(np.linalg.norm(X_j[:2] - X_i[:2]))
            if d <= c.radius:
                cands.append((d, p, X_j))
        for _, p, X_j in sorted(cands, key=lambda t: t[0])[: c.max_candidates]:
            j = self.order[p]
            ref = self._ref(p, newest)
            if ref is None:
                continue
            t = time.perf_counter()
            guess = compose2d(inverse2d(X_j), X_i)
            path = self.path[i] - self.path[j]
            window = min(c.max_search_m, c.search_m + c.search_fraction * path)
            scfg = replace(c.search, max_shift=window, max_angle_deg=c.search_deg)
            found = correlative_search(ref.points, target, guess, scfg)
            ev, z = self._verify(i, j, ref, target, guess, found)
            self.search_ms.append((time.perf_counter() - t) * 1e3)
            events.append(ev)
            if z is not None:
                edges.append((j, i, z))
        self.events.extend(events)
        return edges, events

    def _verify(self, i, j, ref, target, guess, found) -> tuple[LoopEvent, np.ndarray | None]:
        c = self.cfg

        def event(inl, z, ok, reason):
            corr = compose2d(inverse2d(guess), z)
            return LoopEvent(i, j, found.score, found.uniqueness, inl,
                             float(np.linalg.norm(corr[:2])), float(np.degrees(corr[2])),
                             ok, reason)  # fmt: skip

        if found.uniqueness > c.max_uniqueness:
            return event(0.0, found.pose, False, "ambiguous"), None
        res = plicp(target, ref, found.pose, c.plicp)
        refine = compose2d(inverse2d(found.pose), res.pose)
        if (
            np.linalg.norm(refine[:2]) > 2 * c.search.resolution
            or abs(np.degrees(refine[2])) > 2 * c.search.angle_step_deg
        ):
            return event(0.0, res.pose, False, "PLICP left the search's peak"), None
        dist, _ = ref.tree.query(transform2d(res.pose, target), distance_upper_bound=c.overlap_m)
        near = np.isfinite(dist)
        if near.sum() < c.min_overlap:
            return event(0.0, res.pose, False, "too little overlap"), None
        inl = float(np.mean(dist[near] < c.inlier_m))
        if inl < c.min_inliers:
            return event(inl, res.pose, False, "too few inliers"), None
        return event(inl, res.pose, True, "ok"), res.pose


def odometry_sigmas(cfg: VisitGraphConfig, rel: np.ndarray) -> np.ndarray:
    """(sigma_x, sigma_y, sigma_theta) of the front end's relative pose ``rel`` between
    two visits."""
    d = float(np.linalg.norm(rel[:2]))
    s_t = cfg.odom_sigma_m + cfg.odom_sigma_per_m * d
    s_r = np.radians(cfg.odom_sigma_deg + cfg.odom_sigma_deg_per_m * d)
    return np.array([s_t, s_t, s_r + cfg.odom_turn_fraction * abs(float(rel[2]))])


def loop_sigmas(cfg: VisitGraphConfig) -> np.ndarray:
    return np.array([cfg.loop_sigma_m, cfg.loop_sigma_m, np.radians(cfg.loop_sigma_deg)])


class VisitGraph:
    """The visit graph on its own (gtsam Pose2, Levenberg-Marquardt after each visit that
    closed a loop): ``add_visit`` per visit, ``estimates()`` at the end."""

    def __init__(self, cfg: VisitGraphConfig | None = None):
        self.cfg = cfg or VisitGraphConfig()
        self.loop_search = VisitLoops(self.cfg)
        self.factors: list = []
        self.gate = None  # the last gated optimisation (slam.graph2d_gate.GateResult)
        self.loops: list[tuple[int, int, np.ndarray]] = []
        self.optimize_ms: list[float] = []
        self._estimate: list[np.ndarray] = []
        self._fe: list[np.ndarray] = []
        self.refine_stats: list[dict] = []
        self.check = None  # the final front-end check (slam.graph2d_gate.FrontendCheck)

    @property
    def events(self) -> list[LoopEvent]:
        return self.loop_search.events

    @property
    def search_ms(self) -> list[float]:
        return self.loop_search.search_ms

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for f in self.factors:
            graph.add(f)
        return graph

    def _optimize(self, extra: list | None = None) -> None:
        """Levenberg-Marquardt on the odometry and loop edges (and ``extra`` ones), loop
        edges beyond ``gate_sigma`` switched off (``slam.graph2d_gate``)."""
        t = time.perf_counter()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        params.setRelativeErrorTol(1e-6)
        start = gtsam.Values()
        for i, p in enumerate(self._estimate):
            start.insert(i, gtsam.Pose2(*p))
        self.gate = optimize_gated(
            self.factors + list(extra or []),
            start,
            lambda g, v: gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize(),
            self.cfg.gate_sigma,
            self.cfg.gate_rounds,
        )
        result = self.gate.values
        self._estimate = [
            np.array([result.atPose2(i).x(), result.atPose2(i).y(), result.atPose2(i).theta()])
            for i in range(len(self._estimate))
        ]
        self.optimize_ms.append((time.perf_counter() - t) * 1e3)

    def add_visit(self, fe_pose: np.ndarray, cloud: np.ndarray) -> list[LoopEvent]:
        """A new vertex at front-end pose ``fe_pose`` (x, y, theta) with its ``cloud``
        ((M, 2), the vertex's frame); returns the loop candidates it examined."""
        i = len(self._fe)
        fe_pose = np.asarray(fe_pose, dtype=np.float64)
        if i == 0:
            prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 1e-4]))
            self.factors.append(gtsam.PriorFactorPose2(0, gtsam.Pose2(*fe_pose), prior))
            self._estimate.append(fe_pose.copy())
        else:
            rel = compose2d(inverse2d(self._fe[-1]), fe_pose)
            noise = gtsam.noiseModel.Diagonal.Sigmas(odometry_sigmas(self.cfg, rel))
            self.factors.append(gtsam.BetweenFactorPose2(i - 1, i, gtsam.Pose2(*rel), noise))
            self._estimate.append(compose2d(self._estimate[-1], rel))
        self._fe.append(fe_pose)
        self.loop_search.add(i, fe_pose, cloud)
        edges, events = self.loop_search.search(i, lambda k: self._estimate[k])
        loop_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self.cfg.robust_param),
            gtsam.noiseModel.Diagonal.Sigmas(loop_sigmas(self.cfg)),
        )
        for j, k, z in edges:
            self.factors.append(gtsam.BetweenFactorPose2(j, k, gtsam.Pose2(*z), loop_noise))
            self.loops.append((j, k, z))
        if edges:
            self._optimize()
        return events

    def finalize(self) -> None:
        if self.loops:
            self._optimize()
            self.check = frontend_check(self.factors, self.gate, self.cfg.keep_frontend_sigma)
            if self.check.keep_frontend:
                v = [self.check.values.atPose2(i) for i in range(len(self._fe))]
                self._estimate = [np.array([p.x(), p.y(), p.theta()]) for p in v]
        if self.cfg.refine_rounds:
            self.refine_stats = refine_visits(self)

    def estimates(self) -> np.ndarray:
        return np.array(self._estimate)

    @property
    def fe(self) -> list[np.ndarray]:
        return self._fe


def run_visit_graph(
    fe_poses: np.ndarray, scans: list[np.ndarray], cfg: VisitGraphConfig | None = None
) -> tuple[np.ndarray, VisitGraph]:
    """The visit graph over a whole run: front-end poses (K, 3) and scans (each (N, 2),
    sensor frame), as a pipeline would see them: a vertex at the last scan of every
    ``visit_scans`` (and at scan 0), its cloud the scans since the vertex before and the
    ``pad`` before those, each scan following the vertex at or before it. Returns every
    scan's optimised pose (K, 3) and the graph."""
    cfg = cfg or VisitGraphConfig()
    fe_poses = np.asarray(fe_poses, dtype=np.float64)
    n = len(fe_poses)
    vg = VisitGraph(cfg)
    anchors = vertex_scans(n, cfg.visit_scans)
    prev = 0
    for a in anchors:
        lo = max(0, prev + 1 - cfg.pad) if a else 0
        cloud = visit_cloud(fe_poses[lo : a + 1], scans[lo : a + 1], fe_poses[a], cfg.resolution)
        vg.add_visit(fe_poses[a], cloud)
        prev = a
    vg.finalize()
    of = np.searchsorted(anchors, np.arange(n), side="right") - 1
    return scan_poses(fe_poses, of, anchors, vg.estimates()), vg


def vertex_scans(n_scans: int, visit_scans: int) -> np.ndarray:
    """The scans that are vertices: 0, then the last scan of every ``visit_scans``."""
    return np.unique(np.r_[0, np.arange(visit_scans, n_scans + 1, visit_scans) - 1]).astype(int)


def scan_poses(
    fe_poses: np.ndarray, of: np.ndarray, anchors: np.ndarray, estimates: np.ndarray
) -> np.ndarray:
    """Every scan at its vertex's optimised pose o its front-end pose relative to the
    vertex (rigid between vertices; the pipeline's trajectory also spreads each change over
    the frames by their spreads, ``slam.spread``)."""
    out = np.zeros_like(fe_poses)
    for s, v in enumerate(of):
        rel = compose2d(inverse2d(fe_poses[anchors[v]]), fe_poses[s])
        out[s] = compose2d(estimates[v], rel)
    out[:, 2] = wrap(out[:, 2])
    return out


__all__ = [
    "PairwiseCheck",
    "VerifiedLoop",
    "VisitGraph",
    "VisitGraphConfig",
    "line_reference",
    "run_visit_graph",
    "vertex_scans",
    "visit_cloud",
]
