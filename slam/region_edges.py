"""Edges between regional maps (paper 003, DPCR-SLAM, section 3.5): the factor plugin of
the region graph (plugin name ``region_edges``).

The ``dpcr2d`` front end makes a keyframe each time the robot enters another region; its
cloud is the obstacle map of the region just left, in that keyframe's frame, and its
extras name that region (``region_left``). For each new such keyframe this plugin looks
at the earlier ones whose regions' centres lie within ``S * alpha`` (eq. (10), RegDis),
registers the two regional maps with the improved PLICP (starting from the current
estimate), and adds an edge when their MatchRate, eq. (11):

    MatchRate = 2 * MatchNum / (TerNum1 + TerNum2),

passes ``min_match_rate`` and the correction agrees with the odometry within a gate that
grows with the distance travelled (the same physics as the 3D loop gate: drift is a few
per cent of the path). Edges are BetweenFactorPose3 (planar) with a robust kernel, so any
back end takes them; the ``region_graph`` back end projects them on the plane.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
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
from slam.registration.plicp import LineReference, PlicpConfig, plicp
from slam.types import Keyframe

CSV_COLUMNS = ("source", "target", "region_source", "region_target", "match_rate", "rmse",
               "accepted", "reason")  # fmt: skip


@dataclass
class RegionEdgeConfig(FactorConfig):
    """region_width: S (m), the front end's; alpha: RegDis <= S * alpha (eq. (10), >= 1);
    min_match_rate: MatchRate threshold (eq. (11)); match_distance (m): a point pair
    closer than this after registration is a match; skip_recent: the last keyframes not
    linked (the odometry chain already is); gate_m + gate_fraction * path (m since the
    other keyframe): largest correction of the odometry an edge may make; gate_deg;
    resolution (m): the grid cells of the clouds (line extraction)."""

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


class RegionEdgePlugin:
    """Links regional maps whose regions are close and whose maps match."""

    Config = RegionEdgeConfig
    is_loop = True

    def __init__(self, config: RegionEdgeConfig | None = None):
        self.config = config or RegionEdgeConfig()
        self.division = RegionDivision.with_width(self.config.region_width, self.config.resolution)
        self._regions: dict[int, int] = {}  # keyframe id -> region its cloud maps
        self._refs: dict[int, LineReference] = {}
        self._path: list[float] = [0.0]  # odometry distance at each keyframe (m)
        self.events: list[RegionEdge] = []
        self.plicp = PlicpConfig(max_distance=0.4, max_iterations=40)

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
        region = int(kf.extras.get("region_left", -1))
        cloud = graph.cloud(kf.id)
        if region < 0 or len(cloud) < 20:
            return []
        self._regions[kf.id] = region
        centre = self.division.centre(region)
        T_k = graph.estimate(kf.id)
        factors = []
        target = np.asarray(cloud, dtype=np.float64)[:, :2]
        for j, region_j in self._regions.items():
            if j >= kf.id - cfg.skip_recent:
                continue
            if (
                np.linalg.norm(self.division.centre(region_j) - centre)
                > cfg.region_width * cfg.alpha
            ):
                continue
            ref = self._reference(graph, j)
            if ref is None:
                continue
            T_j = graph.estimate(j)
            guess = matrix_to_pose2(np.linalg.solve(T_j, T_k))  # kf's frame in j's frame
            res = plicp(target, ref, guess, self.plicp)
            rate = self.match_rate(ref, target, res.pose)
            T_jk_odom = matrix_to_pose2(np.linalg.solve(graph.keyframes[j].pose_odom, kf.pose_odom))
            corr = compose2d(inverse2d(T_jk_odom), res.pose)
            path = self._path[kf.id] - self._path[j]
            reason = ""
            if rate < cfg.min_match_rate:
                reason = f"match rate {rate:.2f} < {cfg.min_match_rate}"
            elif np.linalg.norm(corr[:2]) > cfg.gate_m + cfg.gate_fraction * path:
                reason = f"correction {np.linalg.norm(corr[:2]):.2f} m beyond the drift gate"
            elif abs(np.degrees(corr[2])) > cfg.gate_deg:
                reason = f"correction {np.degrees(corr[2]):.1f} deg beyond the gate"
            accepted = not reason
            self.events.append(
                RegionEdge(kf.id, j, region, region_j, rate, res.rmse, accepted, reason or "ok")
            )
            if not accepted:
                continue
            info = np.zeros((6, 6))
            idx = [3, 4, 2]  # gtsam Pose3 tangent: (rx, ry, rz, tx, ty, tz)
            info[np.ix_(idx, idx)] = res.info
            info[0, 0] = info[1, 1] = info[5, 5] = 1e6  # planar: z, roll, pitch held
            noise = robust_noise(
                gtsam.noiseModel.Gaussian.Information(0.5 * (info + info.T)),
                cfg.robust,
                cfg.robust_param,
            )
            factors.append(
                gtsam.BetweenFactorPose3(
                    key(j), key(kf.id), pose3(pose2_to_matrix(res.pose)), noise
                )
            )
        return factors

    def stats(self) -> dict[str, float]:
        return {
            "region_candidates": float(len(self.events)),
            "region_edges": float(sum(e.accepted for e in self.events)),
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
