"""Keyframe policy of a scan-to-map odometry: selection, the information of the
keyframe-to-keyframe motion, the keyframe's cloud and the slide (ambiguity) test."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from slam.features.thinning import voxel_thin
from slam.frontend import is_new_keyframe
from slam.odometry.config import CommonConfig
from slam.registration.ambiguity import (
    OdometryAmbiguity,
    loosened_information,
    odometry_ambiguity,
)
from slam.registration.information import Information, default_information


@dataclass
class KeyframeDecision:
    """One frame's keyframe outcome. relative: T_prevkf_current. info: its 6x6 information
    (registration covariance + drift, loosened along an ambiguous axis). cloud: (N, 3)
    float32 sensor-frame keyframe cloud, (0, 3) on other frames. ambiguity: the slide
    test's result when it ran, with ``info_before_ambiguity`` and ``ambiguity_ms``."""

    relative: np.ndarray
    info: np.ndarray
    is_keyframe: bool
    cloud: np.ndarray
    degenerate: bool
    ambiguity: OdometryAmbiguity | None = None
    info_before_ambiguity: np.ndarray | None = None
    ambiguity_ms: float = 0.0


class KeyframePolicy:
    """The last keyframe's pose, the number of keyframes, and the (pose, cloud) of the
    last keyframes (the slide test's target)."""

    def __init__(self, cfg: CommonConfig):
        self._c = cfg
        self.T_kf = np.eye(4)
        self.n_keyframes = 0
        self.clouds: deque[tuple[np.ndarray, np.ndarray]] = deque(
            maxlen=cfg.odometry_ambiguity.window
        )

    def decide(
        self,
        pose: np.ndarray,
        tracked: bool,
        information: Information | None,
        H: np.ndarray | None,
        filtered: np.ndarray | None,
        timings: dict[str, float],
    ) -> KeyframeDecision:
        """The keyframe decision at ``pose``; ``tracked``: the pose is a trusted estimate
        (only those become keyframes); ``information``: the registration's (None without
        one); ``filtered``: the filtered, deskewed scan (sensor frame)."""
        first = self.n_keyframes == 0
        relative = np.linalg.inv(self.T_kf) @ pose if not first else np.eye(4)
        if information is not None:
            info_reg, degenerate = information.info, information.degenerate
        else:
            info_reg, degenerate = default_information(self._c.information), not tracked
        is_kf = tracked and (first or is_new_keyframe(relative, self._c.keyframe))
        out = KeyframeDecision(
            relative,
            self.information(info_reg, relative),
            is_kf,
            np.zeros((0, 3), dtype=np.float32),
            bool(degenerate),
        )
        if not is_kf:
            return out
        if filtered is not None:
            t = time.perf_counter()
            kept = voxel_thin(filtered, self._c.cloud_voxel)
            out.cloud = np.ascontiguousarray(filtered[kept], dtype=np.float32)
            timings["cloud_ms"] = (time.perf_counter() - t) * 1e3
        if self._c.odometry_ambiguity.enabled:
            if not first and H is not None and len(self.clouds):
                self._slide_test(out, H, pose)
            if len(out.cloud):
                self.clouds.append((pose.copy(), np.asarray(out.cloud, dtype=np.float64)))
        self.T_kf = pose.copy()
        self.n_keyframes += 1
        return out

    def information(self, info_reg: np.ndarray, relative: np.ndarray) -> np.ndarray:
        """Information of T_prevkf_current: the registration's covariance plus drift
        proportional to the distance travelled."""
        dist = float(np.linalg.norm(relative[:3, 3]))
        cov = np.linalg.inv(info_reg)
        s_t = self._c.drift_translation * dist
        s_r = np.radians(self._c.drift_rotation_deg_per_m) * dist
        cov = cov + np.diag([s_r**2] * 3 + [s_t**2] * 3)
        info = np.linalg.inv(cov)
        return 0.5 * (info + info.T)

    def _slide_test(self, out: KeyframeDecision, H: np.ndarray, pose: np.ndarray) -> None:
        """The keyframe's cloud against the previous keyframes' (moved into its frame by the
        odometry); an alignment that is not unique along the registration's weakest
        horizontal direction loosens ``out.info`` along it."""
        c = self._c.odometry_ambiguity
        t = time.perf_counter()
        inv = np.linalg.inv(pose)
        parts = []
        for T_kf, pts in self.clouds:
            T = inv @ T_kf
            parts.append(pts @ T[:3, :3].T + T[:3, 3])
        target = np.concatenate(parts) if parts else np.zeros((0, 3))
        amb = odometry_ambiguity(out.cloud, target, H, c)
        out.ambiguity = amb
        if amb.ambiguous:
            out.info_before_ambiguity = out.info
            out.info = loosened_information(out.info, amb.axis, c.sigma)
        out.ambiguity_ms = (time.perf_counter() - t) * 1e3
