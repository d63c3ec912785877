"""Edges between regional maps (paper 003, DPCR-SLAM, section 3.5): the factor plugin of
the region graph (plugin name ``region_edges``).

The ``dpcr2d`` front end makes a keyframe each time the robot enters another region; its
cloud is the obstacle map of the region just left, in that keyframe's frame, and its
``RegionTag`` names that region (``left``). For each new such keyframe this plugin looks
at the earlier ones whose regions' centres lie within ``S * alpha`` (eq. (10), RegDis),
registers the two regional maps with the improved PLICP (starting from the current
estimate), and adds an edge when their MatchRate, eq. (11):

    MatchRate = 2 * MatchNum / (TerNum1 + TerNum2),

passes ``min_match_rate`` and the correction agrees with the odometry within a gate that
grows with the distance travelled (the same physics as the 3D loop gate: drift is a few
per cent of the path). When that registration does not match (a revisit 15 deg / metres
off the estimate, beyond PLICP's basin), a wide correlative search around the estimate
(``slam.registration.correlative2d``) gives PLICP a start; such an edge must be unique
(no second peak close to the best: not a corridor) and passes the wider gate
``wide_gate_m`` / ``wide_gate_deg``. Edges are BetweenFactorPose3 (planar) with a robust
kernel, so any back end takes them; the ``region_graph`` back end projects them on the plane.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from slam.errors import ConfigError
from slam.factors import FactorConfig, GraphView, key, pose3, robust_noise
from slam.features.lines2d import LineConfig, extract_lines
from slam.mapping.grid2d import (
    RegionDivision,
    compose2d,
    inverse2d,
    matrix_to_pose2,
    pose2_to_matrix,
    transform2d,
)
from slam.registration.correlative2d import CorrelativeConfig, correlative_search
from slam.registration.plicp import LineReference, PlicpConfig, PlicpResult, plicp
from slam.types import Keyframe, RegionTag
from slam.visit_graph import VisitGraphConfig, VisitLoops, loop_sigmas

CSV_COLUMNS = ("source", "target", "region_source", "region_target", "match_rate", "rmse",
               "accepted", "reason")  # fmt: skip


@dataclass
class RegionEdgeConfig(FactorConfig):
    """region_width: S (m), the front end's; alpha: RegDis <= S * alpha (eq. (10), >= 1);
    min_match_rate: MatchRate threshold (eq. (11)); match_distance (m): a point pair
    closer than this after registration is a match; skip_recent: the last keyframes not
    linked (the odometry chain already is); gate_m + gate_fraction * path (m since the
    other keyframe): largest correction of the odometry an edge may make; gate_deg;
    resolution (m): the grid cells of the clouds (line extraction); wide_search: a
    candidate PLICP does not match from the estimate, or matches with a correction beyond
    the gate, is searched over the window ``wide``
    (at most ``wide_per_keyframe`` candidates per keyframe, nearest centres first),
    accepted when its second peak / best <= ``wide_max_uniqueness`` and its correction
    of the odometry is within ``wide_gate_m`` + gate_fraction * path and
    ``wide_gate_deg``; anchor_sigma_m / anchor_sigma_deg: the noise of a front end's
    re-anchor (its keyframe's ``RegionTag.anchor``: its pose on the map of that earlier
    keyframe), an edge too; anchor_robust: a visit's re-anchor edge is under the robust
    kernel and the visit graph's gate like its loop edges (the wide search can land on a
    second minimum along a corridor; False: Gaussian, never switched off).
    visits: the loop search of the visit graph (``slam.visit_graph``), used for the
    keyframes a front end marks as visits (``dpcr2d`` with ``visit_scans``:
    ``RegionTag.visit``) instead of the region pairs."""

    region_width: float = 4.0
    alpha: float = 1.5
    min_match_rate: float = 0.35
    match_distance: float = 0.1
    skip_recent: int = 1
    gate_m: float = 1.0
    gate_fraction: float = 0.05
    gate_deg: float = 15.0
    resolution: float = 0.05
    robust: str = "cauchy"
    robust_param: float = 1.0
    wide_search: bool = True
    wide: CorrelativeConfig = field(default_factory=CorrelativeConfig)
    wide_per_keyframe: int = 2
    wide_max_uniqueness: float = 0.8
    wide_gate_m: float = 3.0
    wide_gate_deg: float = 25.0
    anchor_sigma_m: float = 0.05
    anchor_sigma_deg: float = 1.0
    anchor_robust: bool = False
    visits: VisitGraphConfig = field(default_factory=VisitGraphConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.alpha < 1.0:
            raise ConfigError(f"region_edges.alpha must be >= 1 (paper 003), got {self.alpha}")
        if not 0.0 < self.min_match_rate <= 1.0:
            raise ConfigError("region_edges.min_match_rate must be in (0, 1]")


@dataclass
class RegionEdge:
    source: int
    target: int
    region_source: int
    region_target: int
    match_rate: float
    rmse: float
    accepted: bool
    reason: str
    wide: bool = False


class RegionEdgePlugin:
    """Links regional maps whose regions are close and whose maps match."""

    Config = RegionEdgeConfig
    is_loop = True
    takes_anchors = True  # a front end's re-anchors (``RegionTag.anchor``) become edges

    def __init__(self, config: RegionEdgeConfig | None = None):
        self.config = config or RegionEdgeConfig()
        self.division = RegionDivision.with_width(self.config.region_width, self.config.resolution)
        self._regions: dict[int, int] = {}  # keyframe id -> region its cloud maps
        self._refs: dict[int, LineReference] = {}
        self._path: list[float] = [0.0]  # odometry distance at each keyframe (m)
        self.events: list[RegionEdge] = []
        self.plicp = PlicpConfig(max_distance=0.4, max_iterations=40)
        self.visit_loops = VisitLoops(self.config.visits)

    # ------------------------------------------------------------------ helpers
    def _reference(self, graph: GraphView, kf_id: int) -> LineReference | None:
        if kf_id not in self._refs:
            pts = np.asarray(graph.cloud(kf_id), dtype=np.float64)[:, :2]
            if len(pts) < 20:
                return None
            lines = extract_lines(pts, self.config.resolution, LineConfig())
            self._refs[kf_id] = LineReference.from_lines(lines)
        return self._refs[kf_id]

    def match_rate(self, ref: LineReference, b: np.ndarray, T_ab: np.ndarray) -> float:
        """Eq. (11) for the reference's points and cloud ``b`` (N, 2) moved into the
        reference frame by T_ab (the reference's KD-tree, built once per keyframe)."""
        if len(ref) == 0 or len(b) == 0:
            return 0.0
        moved = transform2d(T_ab, b)
        dist, _ = ref.tree.query(moved, distance_upper_bound=self.config.match_distance)
        matches = int(np.isfinite(dist).sum())
        return 2.0 * matches / (len(ref) + len(b))

    # ------------------------------------------------------------------ contract
    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.BetweenFactorPose3]:
        cfg = self.config
        if kf.id > 0:
            step = float(np.linalg.norm(np.asarray(kf.relative)[:2, 3]))
            self._path.append(self._path[-1] + step)
        tag = kf.region or RegionTag()
        if tag.visit:  # a re-anchored visit also carries its front end's loop edge
            return self._anchor(kf, robust=cfg.anchor_robust) + self._visit(kf, graph)
        anchors = self._anchor(kf)
        region = tag.left
        cloud = graph.cloud(kf.id)
        if region < 0 or len(cloud) < 20:
            return anchors
        self._regions[kf.id] = region
        centre = self.division.centre(region)
        T_k = graph.estimate(kf.id)
        factors = []
        target = np.asarray(cloud, dtype=np.float64)[:, :2]
        candidates = self._candidates(kf.id, centre)
        wide_left = cfg.wide_per_keyframe if cfg.wide_search else 0
        for _, j, region_j in sorted(candidates):
            ref = self._reference(graph, j)
            if ref is None:
                continue
            T_j = graph.estimate(j)
            guess = matrix_to_pose2(np.linalg.solve(T_j, T_k))  # kf's frame in j's frame
            res = plicp(target, ref, guess, self.plicp)
            rate = self.match_rate(ref, target, res.pose)
            T_jk_odom = matrix_to_pose2(np.linalg.solve(graph.keyframes[j].pose_odom, kf.pose_odom))
            path = self._path[kf.id] - self._path[j]
            reason = self._reject(rate, compose2d(inverse2d(T_jk_odom), res.pose), path, False)
            wide = False
            if reason and wide_left > 0:  # no match, or a correction only a unique one may make
                wide_left -= 1
                found = self._wide(ref, target, guess)
                if found is not None:
                    wide_rate = self.match_rate(ref, target, found.pose)
                    corr = compose2d(inverse2d(T_jk_odom), found.pose)
                    wide_reason = self._reject(wide_rate, corr, path, True)
                    if not wide_reason or wide_rate > rate:
                        res, rate, wide, reason = found, wide_rate, True, wide_reason
            accepted = not reason
            self.events.append(
                RegionEdge(kf.id, j, region, region_j, rate, res.rmse, accepted,
                           reason or ("ok (wide search)" if wide else "ok"), wide)
            )  # fmt: skip
            if not accepted:
                continue
            factors.append(self._edge_factor(j, kf.id, res))
        return anchors + factors

    def _edge_factor(self, j: int, k: int, res: PlicpResult) -> gtsam.BetweenFactorPose3:
        """The planar edge j -> k of a registration (its information, robust kernel)."""
        cfg = self.config
        info = np.zeros((6, 6))
        idx = [3, 4, 2]  # gtsam Pose3 tangent: (rx, ry, rz, tx, ty, tz)
        info[np.ix_(idx, idx)] = res.info
        info[0, 0] = info[1, 1] = info[5, 5] = 1e6  # planar: z, roll, pitch held
        noise = robust_noise(
            gtsam.noiseModel.Gaussian.Information(0.5 * (info + info.T)),
            cfg.robust,
            cfg.robust_param,
        )
        return gtsam.BetweenFactorPose3(key(j), key(k), pose3(pose2_to_matrix(res.pose)), noise)

    def _candidates(self, kf_id: int, centre: np.ndarray) -> list[tuple[float, int, int]]:
        """(centre distance, keyframe, region) of the earlier region keyframes within
        RegDis <= S * alpha (eq. (10)), the last ``skip_recent`` left out."""
        cfg = self.config
        out = []
        for j, region_j in self._regions.items():
            if j >= kf_id - cfg.skip_recent:
                continue
            dist = float(np.linalg.norm(self.division.centre(region_j) - centre))
            if dist <= cfg.region_width * cfg.alpha:
                out.append((dist, j, region_j))
        return out

    def _visit(self, kf: Keyframe, graph: GraphView) -> list[gtsam.BetweenFactorPose3]:
        """Loop edges of a visit keyframe (``slam.visit_graph.VisitLoops``): its cloud
        searched on the clouds of earlier visits near its estimate."""
        cloud = np.asarray(graph.cloud(kf.id), dtype=np.float64)[:, :2]
        self.visit_loops.add(kf.id, matrix_to_pose2(kf.pose_odom), cloud)
        edges, events = self.visit_loops.search(kf.id, lambda j: matrix_to_pose2(graph.estimate(j)))
        for e in events:
            self.events.append(
                RegionEdge(e.new, e.old, -1, -1, e.inliers, e.score, e.accepted,
                           e.reason if not e.accepted else "ok (visit)", True)
            )  # fmt: skip
        s = loop_sigmas(self.config.visits)
        info = np.diag([1e6, 1e6, 1.0 / s[2] ** 2, 1.0 / s[0] ** 2, 1.0 / s[1] ** 2, 1e6])
        noise = robust_noise(gtsam.noiseModel.Gaussian.Information(info), "cauchy",
                             self.config.visits.robust_param)  # fmt: skip
        return [
            gtsam.BetweenFactorPose3(key(j), key(i), pose3(pose2_to_matrix(z)), noise)
            for j, i, z in edges
        ]

    def _anchor(self, kf: Keyframe, robust: bool = True) -> list[gtsam.BetweenFactorPose3]:
        """The edge of a front-end re-anchor (``dpcr2d``: the submap matched, by the wide
        search, on the old maps): keyframe ``anchor_kf`` -> this one. ``robust`` False:
        Gaussian, never switched off by the visit graph's gate (``slam.graph2d_gate``): the
        front end moved onto that map already, the graph only places the correction."""
        cfg = self.config
        anchor = None if kf.region is None else kf.region.anchor
        if anchor is None or not 0 <= anchor.keyframe < kf.id:
            return []
        j, z = anchor.keyframe, np.array(anchor.pose)
        s_t, s_r = cfg.anchor_sigma_m, np.radians(cfg.anchor_sigma_deg)
        info = np.diag([1e6, 1e6, 1.0 / s_r**2, 1.0 / s_t**2, 1.0 / s_t**2, 1e6])
        noise = gtsam.noiseModel.Gaussian.Information(info)
        if robust:
            noise = robust_noise(noise, cfg.robust, cfg.robust_param)
        region = -1 if kf.region.region is None else kf.region.region
        self.events.append(RegionEdge(kf.id, j, region, -1, 1.0, 0.0, True, "ok (re-anchor)"))
        return [gtsam.BetweenFactorPose3(key(j), key(kf.id), pose3(pose2_to_matrix(z)), noise)]

    def _reject(self, rate: float, corr: np.ndarray, path: float, wide: bool) -> str:
        """Why an edge of this match rate and correction of the odometry (x, y, theta),
        ``path`` m after the other keyframe, is rejected ("" = accepted)."""
        cfg = self.config
        gate_m = (cfg.wide_gate_m if wide else cfg.gate_m) + cfg.gate_fraction * path
        gate_deg = cfg.wide_gate_deg if wide else cfg.gate_deg
        if rate < cfg.min_match_rate:
            return f"match rate {rate:.2f} < {cfg.min_match_rate}"
        if np.linalg.norm(corr[:2]) > gate_m:
            return f"correction {np.linalg.norm(corr[:2]):.2f} m beyond the drift gate"
        if abs(np.degrees(corr[2])) > gate_deg:
            return f"correction {np.degrees(corr[2]):.1f} deg beyond the gate"
        return ""

    def _wide(
        self, ref: LineReference, target: np.ndarray, guess: np.ndarray
    ) -> PlicpResult | None:
        """The wide-basin registration of ``target`` on ``ref`` around ``guess``: the
        correlative search, then PLICP from its best; None when the search is ambiguous
        (second peak / best above ``wide_max_uniqueness``: a corridor, a symmetric room)."""
        found = correlative_search(ref.points, target, guess, self.config.wide)
        if found.uniqueness > self.config.wide_max_uniqueness:
            return None
        return plicp(target, ref, found.pose, self.plicp)

    def stats(self) -> dict[str, float]:
        return {
            "region_candidates": float(len(self.events)),
            "region_edges": float(sum(e.accepted for e in self.events)),
            "region_edges_wide": float(sum(e.accepted and e.wide for e in self.events)),
        }

    def write_csv(self, path: str | Path) -> None:
        """loops.csv: one row per region pair examined."""
        with Path(path).open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CSV_COLUMNS)
            for e in self.events:
                w.writerow(
                    [e.source, e.target, e.region_source, e.region_target,
                     f"{e.match_rate:.4f}", f"{e.rmse:.4f}", int(e.accepted), e.reason]
                )  # fmt: skip
