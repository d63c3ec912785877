"""Ground factor plugin: z, roll and pitch of keyframes from the ground plane they see
(LeGO-LOAM-LPB, paper 001, 3.1.2 / 3.3: the ground constraint on the z axis).

A keyframe that sees the ground plane (n_b, d_b) in its sensor frame b, which a reference
frame a sees as (n_a, d_a), fixes three of the six degrees of freedom of T_ab:

    R_ab n_b = n_a                  (tilt: 2 dof; the rotation about the normal is free)
    n_a . t_ab = d_b - d_a          (height along the normal: 1 dof)

We add this as a native GTSAM factor, no Python Jacobians: the "measurement" is the current
guess of T_ab with the smallest correction that satisfies both equations, and its noise
model is a 6x6 information that is 1/sigma^2 along the three constrained directions (in
the tangent space at b: rotations perpendicular to n_b, translation along n_b) and ~0 along
x, y and yaw, which stay with the other factors.

mode "chain" (default): the ground is one plane over ``segment_length`` metres of travel.
Each keyframe is tied (BetweenFactorPose3) to the anchor keyframe of its segment, which saw
the same ground; the keyframe that ends a segment anchors the next one. Within a segment
the constraints share the anchor's measurement, so a front end's slow tilt bias cannot
hide in per-step noise (a factor between consecutive keyframes only would be outweighed
by the odometry's tight relative rotation); across segments the ground may bend, so
slopes are followed. A keyframe whose plane disagrees beyond the gates (a ramp begins, a
kerb) adds nothing and anchors a new segment. mode "global": every keyframe sees the first
keyframe's ground (a PriorFactorPose3): one flat floor, as in the paper's building.

The plane comes from the front end when it provides one (``Keyframe.ground_plane``,
[nx, ny, nz, d]); else from fit_ground(kf.cloud).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from slam.errors import ConfigError, InputError
from slam.factors import FactorConfig, GraphView, key, pose3, robust_noise
from slam.preprocess.ground import GroundPlane, RansacGroundConfig, fit_ground
from slam.types import Keyframe

GROUND_MODES = ("chain", "global")
_FREE_SIGMA = 1e3  # x, y, yaw: left to the other factors (rad / m)


@dataclass
class GroundFactorConfig(FactorConfig):
    """mode: "chain" or "global" (module doc). segment_length (m of travel): in chain mode
    the keyframes within it are tied to one anchor keyframe's ground. sigma_height (m) and
    sigma_tilt_deg: noise of the plane's height and normal. gate_height (m) and
    gate_tilt_deg: a keyframe whose plane disagrees more with the current pose guess is not
    constrained (slope change, kerb, wrong plane); in chain mode the tilt's height error
    over the distance to the anchor counts against gate_height (curved terrain). max_rmse
    (m): planes fitted with larger residuals are not used; rmse_ref (m): a fitted plane's
    sigmas grow by its rmse / rmse_ref above 1 (a sweep distorted by the sensor's wobble,
    uneven ground). Defaults are cautious: planes of
    real 16-beam scans scatter by 0.3-1 deg (beam calibration, kerbs, the car pitching),
    and hills bend within 10 m; on a known flat floor 0.2 deg and 20 m correct more.
    up, max_tilt_deg, min_depth, max_range, inlier_band, min_inliers: the RANSAC ground fit
    (slam.preprocess.ground.RansacGroundConfig) when the front end gives no plane."""

    mode: str = "chain"
    segment_length: float = 10.0
    sigma_height: float = 0.05
    sigma_tilt_deg: float = 0.5
    gate_height: float = 0.1
    gate_tilt_deg: float = 0.7
    max_rmse: float = 0.06
    rmse_ref: float = 0.015
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    max_tilt_deg: float = 15.0
    min_depth: float = 0.3
    max_range: float = 30.0
    inlier_band: float = 0.08
    min_inliers: int = 100

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mode not in GROUND_MODES:
            raise ConfigError(
                f"ground mode must be one of {', '.join(GROUND_MODES)}, got {self.mode!r}"
            )
        for name in (
            "segment_length",
            "sigma_height",
            "sigma_tilt_deg",
            "gate_height",
            "gate_tilt_deg",
            "max_rmse",
        ):
            if not getattr(self, name) > 0:
                raise ConfigError(f"ground {name} must be > 0, got {getattr(self, name)}")
        self.ransac()  # validates the fit settings

    def ransac(self) -> RansacGroundConfig:
        return RansacGroundConfig(
            inlier_band=self.inlier_band,
            max_tilt_deg=self.max_tilt_deg,
            min_depth=self.min_depth,
            max_range=self.max_range,
            min_inliers=self.min_inliers,
            up=tuple(self.up),
        )


def plane_of(value: Any) -> tuple[np.ndarray, float]:
    """(unit normal (3,), d) from a GroundPlane, (normal, d), {"normal", "d"} or [a, b, c, d]."""
    if isinstance(value, GroundPlane):
        n, d = value.normal, value.d
    elif isinstance(value, dict):
        n, d = value["normal"], value["d"]
    elif isinstance(value, (tuple, list)) and len(value) == 2:
        n, d = value
    else:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        if arr.shape != (4,):
            raise InputError(f"ground_plane must be (normal, d) or [a, b, c, d], got {value!r}")
        n, d = arr[:3], arr[3]
    n = np.asarray(n, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(n)
    if not (np.isfinite(norm) and norm > 0 and np.isfinite(d)):
        raise InputError(f"ground_plane normal must be finite and non-zero, got {n}, d={d}")
    return n / norm, float(d) / norm


def transform_plane(T_ab: np.ndarray, n_b: np.ndarray, d_b: float) -> tuple[np.ndarray, float]:
    """The plane (n_b, d_b) of frame b expressed in frame a (x_a = R x_b + t)."""
    n_a = T_ab[:3, :3] @ n_b
    return n_a, float(d_b - n_a @ T_ab[:3, 3])


def _rotation_onto(m: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector m onto unit vector n."""
    axis = np.cross(m, n)
    s, c = np.linalg.norm(axis), float(np.clip(m @ n, -1.0, 1.0))
    if s < 1e-12:
        return np.eye(3)
    return gtsam.Rot3.AxisAngle(gtsam.Unit3(axis / s).point3(), float(np.arctan2(s, c))).matrix()


def ground_corrected(
    T_ab: np.ndarray, n_a: np.ndarray, d_a: float, n_b: np.ndarray, d_b: float
) -> tuple[np.ndarray, float, float]:
    """T_ab with the smallest change that makes frame b's plane (n_b, d_b) coincide with
    frame a's (n_a, d_a); also the tilt (rad) and height (m) it had to change."""
    R, t = T_ab[:3, :3], T_ab[:3, 3]
    m = R @ n_b
    tilt = float(np.arccos(np.clip(m @ n_a, -1.0, 1.0)))
    step = float(d_b - d_a - n_a @ t)
    out = np.eye(4)
    out[:3, :3] = _rotation_onto(m, n_a) @ R
    out[:3, 3] = t + step * n_a
    return out, tilt, step


def ground_information(n_b: np.ndarray, sigma_tilt: float, sigma_height: float) -> np.ndarray:
    """6x6 information (rotation first, GTSAM's tangent order) in frame b: tilts
    perpendicular to n_b and the translation along n_b are constrained, the rest free."""
    P = np.outer(n_b, n_b)
    I3 = np.eye(3)
    free = 1.0 / _FREE_SIGMA**2
    info = np.zeros((6, 6))
    info[:3, :3] = (I3 - P) / sigma_tilt**2 + P * free
    info[3:, 3:] = P / sigma_height**2 + (I3 - P) * free
    return info


class GroundFactorPlugin:
    """Factors on z / roll / pitch of each keyframe from its ground plane (module doc)."""

    Config = GroundFactorConfig

    def __init__(self, config: GroundFactorConfig | None = None):
        self.config = config or GroundFactorConfig()
        self._anchor: tuple[int, np.ndarray, float] | None = None  # kf id, n, d (sensor)
        self._travelled = 0.0  # m since the anchor keyframe
        self._odo_since_anchor = np.eye(4)  # T_anchor_current from the odometry alone
        self._world: tuple[np.ndarray, float] | None = None  # global mode: the ground
        self._roughness = 1.0  # the current plane's sigma scale (fit rmse / rmse_ref)
        self.added = 0
        self.skipped: dict[str, int] = {}
        # per keyframe with a plane: (kf id, reference id (-1: world), tilt deg, step m,
        # lever m, factor added)
        self.history: list[tuple[int, int, float, float, float, bool]] = []

    def _new_anchor(self, kf_id: int, n: np.ndarray, d: float) -> None:
        self._anchor, self._travelled, self._odo_since_anchor = (kf_id, n, d), 0.0, np.eye(4)

    def _skip(self, reason: str) -> list[gtsam.NonlinearFactor]:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        return []

    def plane(self, kf: Keyframe) -> tuple[np.ndarray, float] | None:
        """The keyframe's ground (n, d) in its sensor frame, or None (counted in skipped)."""
        self._roughness = 1.0
        if kf.ground_plane is not None:
            return plane_of(kf.ground_plane)
        cloud = np.asarray(kf.cloud, dtype=np.float64)
        if cloud.ndim != 2 or len(cloud) < self.config.min_inliers:
            self._skip("no cloud")
            return None
        try:
            fit = fit_ground(cloud, self.config.ransac(), seed=kf.id)
        except InputError:
            self._skip("no ground")
            return None
        if fit.rmse > self.config.max_rmse:
            self._skip("rough ground")
            return None
        self._roughness = max(1.0, fit.rmse / self.config.rmse_ref)
        return fit.normal, fit.d

    def _noise(self, n_b: np.ndarray, lever: float = 0.0) -> gtsam.noiseModel.Base:
        """Noise of a plane measurement; the height ``lever`` m away from where the plane was
        measured is uncertain by the normal's error times the lever too."""
        c = self.config
        tilt = np.radians(c.sigma_tilt_deg) * self._roughness
        height = c.sigma_height * self._roughness
        info = ground_information(n_b, tilt, float(np.hypot(height, lever * tilt)))
        return robust_noise(gtsam.noiseModel.Gaussian.Information(info), c.robust, c.robust_param)

    def _gated(self, tilt: float, step: float, lever: float = 0.0) -> bool:
        """The plane agrees with the pose guess: tilt (rad) within gate_tilt_deg, and the
        height step plus the tilt's effect over the lever (m) within gate_height."""
        c = self.config
        return tilt <= np.radians(c.gate_tilt_deg) and abs(step) + tilt * lever <= c.gate_height

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        if not self.config.enabled:
            return []
        if kf.id > 0:
            rel = np.asarray(kf.relative, dtype=np.float64)
            self._travelled += float(np.linalg.norm(rel[:3, 3]))
            self._odo_since_anchor = self._odo_since_anchor @ rel
        plane = self.plane(kf)
        if plane is None:
            return []
        n_b, d_b = plane
        if self.config.mode == "global":
            T_wb = np.asarray(graph.estimate(kf.id), dtype=np.float64)
            if self._world is None:
                self._world = transform_plane(T_wb, n_b, d_b)
                return []  # the first keyframe defines the ground (the prior fixes it)
            n_w, d_w = self._world
            T_meas, tilt, step = ground_corrected(T_wb, n_w, d_w, n_b, d_b)
            ok = self._gated(tilt, step)
            self.history.append((kf.id, -1, float(np.degrees(tilt)), step, 0.0, ok))
            if not ok:
                return self._skip("gate")
            self.added += 1
            return [gtsam.PriorFactorPose3(key(kf.id), pose3(T_meas), self._noise(n_b))]
        anchor = self._anchor
        if anchor is None or kf.id == 0:
            self._new_anchor(kf.id, n_b, d_b)
            return []
        a_id, n_a, d_a = anchor
        # the odometry alone since the anchor, not the graph's estimate: once ground factors
        # pulled the estimate onto a plane, every later guess would agree with that plane
        T_ab = self._odo_since_anchor
        T_meas, tilt, step = ground_corrected(T_ab, n_a, d_a, n_b, d_b)
        lever = float(np.linalg.norm(T_ab[:3, 3] - (n_a @ T_ab[:3, 3]) * n_a))  # along the plane
        ok = self._gated(tilt, step, lever)
        self.history.append((kf.id, a_id, float(np.degrees(tilt)), step, lever, ok))
        if not ok:  # another ground (a slope change): start anew
            self._new_anchor(kf.id, n_b, d_b)
            return self._skip("gate")
        if self._travelled >= self.config.segment_length:
            self._new_anchor(kf.id, n_b, d_b)
        self.added += 1
        noise = self._noise(n_b, lever)
        return [gtsam.BetweenFactorPose3(key(a_id), key(kf.id), pose3(T_meas), noise)]
