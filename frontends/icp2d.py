"""Baseline 2D front end (paper 003's comparison): scan-to-submap ICP with a pose graph of
every Nth scan.

Per scan: predict the pose from the wheel odometry (``Scan.odom``; else constant
velocity), register the scan against the points of the last N scans (world frame, one
KD-tree per scan) with the CONVENTIONAL PLICP of Censi (2008): each scan point is matched
to the line through its two nearest reference points (``method="plicp"``), or
point-to-point ICP (``method="point"``); Gauss-Newton on (x, y, theta), Huber-weighted.
Every ``keyframe_every``-th scan is a keyframe (its scan is its cloud), so the back end
holds a pose graph of every Nth scan linked by odometry factors. Poses are planar 4x4
(z = 0, roll = pitch = 0). Unlike DPCR-SLAM (``frontends.dpcr2d``) there is no grid and no
line feature: the local line of two points is all the structure a match sees.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.mapping.grid2d import (
    compose2d,
    inverse2d,
    planar_information,
    planar_points,
    pose2_to_matrix,
    predict2d,
    transform2d,
    wrap,
)
from slam.registration.correlative2d import CorrelativeConfig, correlative_search
from slam.registration.local_lines2d import thin
from slam.types import FrameDiagnostics, Odometry, Scan, TrackingStatus


@dataclass
class Icp2dConfig:
    """submap_scans: N, the scans the reference holds; keyframe_every: a keyframe (graph
    vertex) every this many scans; method: "plicp" (point to the line through the two
    nearest reference points, Censi) or "point" (point to point); max_iterations;
    tolerance: stop when the update is below it (m and rad); max_distance (m): matches
    farther than this after the prediction are ignored; min_matches: fewest matches of a
    usable registration; robust_floor (m): smallest Huber threshold (3 robust sigmas of the
    residuals otherwise); voxel (m): the reference keeps one point per cell of this size;
    use_odometry: predict from ``Scan.odom`` when present; max_range (m); min_points:
    fewest points of a usable scan; max_step / max_step_deg (m, deg): a registration
    moving the pose further than this from the prediction is rejected; start_frames:
    without wheel odometry the first registrations of these frames start from a
    correlative search of the motion (``start``: +-0.5 m, +-20 deg around the
    constant-velocity prediction) instead of assuming rest."""

    submap_scans: int = 10
    keyframe_every: int = 5
    method: str = "plicp"
    max_iterations: int = 30
    tolerance: float = 1e-5
    max_distance: float = 0.5
    min_matches: int = 20
    robust_floor: float = 0.03
    voxel: float = 0.05
    use_odometry: bool = True
    max_range: float = 30.0
    min_points: int = 30
    max_step: float = 0.5
    max_step_deg: float = 20.0
    start_frames: int = 3
    start: CorrelativeConfig = field(
        default_factory=lambda: CorrelativeConfig(max_shift=0.5, max_angle_deg=20.0)
    )

    def __post_init__(self) -> None:
        if self.submap_scans < 1 or self.keyframe_every < 1 or self.max_iterations < 1:
            raise ConfigError("icp2d: submap_scans, keyframe_every, max_iterations >= 1")
        if self.method not in ("plicp", "point"):
            raise ConfigError(f"icp2d: method must be 'plicp' or 'point', got {self.method!r}")
        if not (self.max_distance > 0 and self.voxel >= 0):
            raise ConfigError("icp2d: max_distance > 0 and voxel >= 0 required")


@dataclass
class Icp2dResult:
    """pose (x, y, theta) mapping scan points into the reference frame; rmse (m) of the
    final residuals; matches; iterations; converged."""

    pose: np.ndarray
    rmse: float
    matches: int
    iterations: int
    converged: bool


def _matches(
    moved: np.ndarray, ref: np.ndarray, tree: cKDTree, method: str, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point index, normal rows (K, 2), anchor (K, 2)) of the matches of ``moved``: one
    row (the normal of the line through the two nearest points) per PLICP match, two
    rows (the axes) per point match or where the two neighbours coincide."""
    k = 2 if method == "plicp" else 1
    dist, j = tree.query(moved, k=k, distance_upper_bound=max_distance)
    if k == 1:
        dist, j = dist[:, None], j[:, None]
    ok = np.isfinite(dist[:, 0])
    i = np.flatnonzero(ok)
    q1 = ref[j[ok, 0]]
    line = np.zeros(len(i), dtype=bool)
    normals = np.zeros((len(i), 2))
    if k == 2:
        has2 = np.isfinite(dist[ok, 1])
        q2 = np.where(has2[:, None], ref[np.minimum(j[ok, 1], len(ref) - 1)], q1)
        d = q2 - q1
        length = np.linalg.norm(d, axis=1)
        line = length > 1e-6
        normals[line] = np.column_stack([-d[line, 1], d[line, 0]]) / length[line, None]
    pt = ~line
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    idx = np.concatenate([i[line], i[pt], i[pt]])
    n = np.concatenate(
        [normals[line], np.broadcast_to(ex, (pt.sum(), 2)), np.broadcast_to(ey, (pt.sum(), 2))]
    )
    q = np.concatenate([q1[line], q1[pt], q1[pt]])
    return idx, n, q


def icp2d(
    target: np.ndarray,
    ref: np.ndarray,
    initial: np.ndarray | None = None,
    cfg: Icp2dConfig | None = None,
    tree: cKDTree | None = None,
) -> Icp2dResult:
    """Register ``target`` (N, 2, own frame) to reference points ``ref`` (M, 2) from the
    prediction ``initial`` (x, y, theta): Gauss-Newton on the point-to-line (Censi's PLICP)
    or point-to-point residuals r = n . (R p + t - q), Jacobian [n_x, n_y, n . (dR/dtheta)
    p], Huber weights; ``tree``: a KD-tree of ``ref`` already built."""
    cfg = cfg or Icp2dConfig()
    target = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    ref = np.asarray(ref, dtype=np.float64).reshape(-1, 2)
    pose = np.zeros(3) if initial is None else np.asarray(initial, dtype=np.float64).copy()
    if len(ref) < 2 or len(target) == 0:
        return Icp2dResult(pose, np.inf, 0, 0, False)
    tree = tree or cKDTree(ref)
    it, converged, rmse, matches = 0, False, np.inf, 0
    while it < cfg.max_iterations:
        it += 1
        moved = transform2d(pose, target)
        idx, n, q = _matches(moved, ref, tree, cfg.method, cfg.max_distance)
        matches = len(np.unique(idx))
        if matches < cfg.min_matches:
            break
        r = np.einsum("ij,ij->i", moved[idx] - q, n)
        # Huber at 3 robust sigmas (MAD), floored
        delta = max(cfg.robust_floor, 3 * 1.4826 * float(np.median(np.abs(r))))
        w = np.where(np.abs(r) <= delta, 1.0, delta / np.maximum(np.abs(r), 1e-12))
        rel = moved[idx] - pose[:2]  # R p, the lever arm of the rotation
        J = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]])
        H = J.T @ (J * w[:, None])
        b = J.T @ (w * r)
        try:
            step = -np.linalg.solve(H + 1e-9 * np.eye(3), b)
        except np.linalg.LinAlgError:
            break
        # the step rotates the moved points about the sensor position, then shifts them
        pose = pose + step
        pose[2] = float(wrap(pose[2]))
        rmse = float(np.sqrt(np.mean(r**2)))
        if np.linalg.norm(step[:2]) < cfg.tolerance and abs(step[2]) < cfg.tolerance:
            converged = True
            break
    return Icp2dResult(pose, rmse, matches, it, converged)


class Icp2d:
    """The baseline scan-to-submap ICP front end (plugin ``icp2d``)."""

    Config = Icp2dConfig

    def __init__(self, cfg: Icp2dConfig | None = None):
        self.cfg = cfg or Icp2dConfig()
        self.pose = np.zeros(3)
        self.motion = np.zeros(3)
        self.frame = 0
        self.window: deque[np.ndarray] = deque()  # world-frame points of the last N scans
        self.pose_kf = np.zeros(3)
        self.keyframe_bytes = 0
        self.counts = {"rejected": 0}
        self._odom: np.ndarray | None = None
        self._lost = False  # the last registered frame was rejected

    def storage_bytes(self) -> dict[str, int]:
        """Bytes of the stored map: the submap's points and the keyframe clouds the pose
        graph keeps (float32 x, y, z: the map of this baseline is its keyframe scans)."""
        return {
            "submap": int(sum(w.nbytes for w in self.window)),
            "keyframe_clouds": self.keyframe_bytes,
        }

    def _points(self, scan: Scan) -> np.ndarray:
        return planar_points(scan.xyz, self.cfg.max_range)

    def _plausible(self, res: Icp2dResult, start: np.ndarray) -> bool:
        step = compose2d(inverse2d(start), res.pose)
        return (
            res.matches >= self.cfg.min_matches
            and np.linalg.norm(step[:2]) <= self.cfg.max_step
            and abs(np.degrees(step[2])) <= self.cfg.max_step_deg
        )

    def _start(self, ref: np.ndarray, pts: np.ndarray, predicted: np.ndarray, blind: bool):
        """Where the registration starts: the prediction, or without wheels (``blind``) on
        the first ``start_frames`` a correlative search of the motion around it."""
        if blind and self.frame <= self.cfg.start_frames:
            return correlative_search(ref, pts, predicted, self.cfg.start).pose
        return predicted

    def process(self, scan: Scan) -> Odometry:
        cfg = self.cfg
        t0 = time.perf_counter()
        diag = FrameDiagnostics()
        pts = self._points(scan)
        odom = None if scan.odom is None else np.asarray(scan.odom, dtype=np.float64)
        use = cfg.use_odometry
        predicted = (
            predict2d(self.pose, self.motion, self._odom if use else None, odom)
            if self.frame
            else self.pose.copy()
        )
        self._odom = odom
        pose = predicted
        status = TrackingStatus.TRACKED if self.frame == 0 else TrackingStatus.PREDICTED
        if len(pts) < cfg.min_points:
            diag.skipped = f"too few points ({len(pts)} < {cfg.min_points})"
            status = TrackingStatus.PREDICTED
        elif self.window:
            t = time.perf_counter()
            ref = np.concatenate(list(self.window))
            res = icp2d(pts, ref, self._start(ref, pts, predicted, odom is None or not use), cfg)
            diag.timings_ms["icp_ms"] = (time.perf_counter() - t) * 1e3
            diag.counts.update(rmse=res.rmse, matches=res.matches, iterations=res.iterations)
            if self._plausible(res, predicted):
                pose = res.pose
                status = TrackingStatus.RECOVERED if self._lost else TrackingStatus.TRACKED
                self._lost = False
            else:
                self.counts["rejected"] += 1
                diag.rejected = True
                status = TrackingStatus.LOST
                self._lost = True
        previous = self.pose
        self.pose = pose
        if len(pts) >= cfg.min_points:
            self.window.append(thin(transform2d(pose, pts), cfg.voxel))
            if len(self.window) > cfg.submap_scans:
                self.window.popleft()
        is_kf = self.frame % cfg.keyframe_every == 0
        T = pose2_to_matrix(self.pose)
        relative = np.linalg.inv(pose2_to_matrix(self.pose_kf)) @ T
        cloud = None
        if is_kf:
            cloud = np.column_stack([pts, np.zeros(len(pts))]).astype(np.float32)
            self.keyframe_bytes += cloud.nbytes
            self.pose_kf = self.pose.copy()
        self.motion = compose2d(inverse2d(previous), self.pose) if self.frame else np.zeros(3)
        self.motion[2] = float(wrap(self.motion[2]))
        self.frame += 1
        diag.timings_ms["total_ms"] = (time.perf_counter() - t0) * 1e3
        diag.counts.update(self.storage_bytes())
        return Odometry(
            stamp=scan.stamp,
            pose=T,
            is_keyframe=is_kf,
            relative=relative,
            info=planar_information(relative),
            cloud=cloud,
            status=status,
            diagnostics=diag,
        )
