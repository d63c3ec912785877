"""Incremental smoothing with GTSAM's iSAM2 (Kaess et al. 2012), as in LIO-SAM.

Each keyframe makes one ``ISAM2.update`` with only the new factors and the new
keyframes' initial values; after a loop closure a few extra empty updates let the
relinearisation settle.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import gtsam

from slam.errors import ConfigError, SlamError
from slam.factors import key

FACTORIZATIONS = ("CHOLESKY", "QR")


@dataclass
class Isam2Config:
    """iSAM2 settings.

    relinearize_threshold: relinearise a variable when its delta exceeds this (tangent units:
    rad / m). relinearize_skip: check for relinearisation every N updates.
    extra_updates_after_loop: empty updates after an update with ``loop_closed`` (1: the
    following keyframes' updates relinearise too; on the 1000-keyframe bench 3 extra updates
    doubled the loop update's peak for the same final error).
    partial_relinearization_check: look for variables to relinearise only in the cliques the
    update touched (GTSAM's enablePartialRelinearizationCheck): -25 % CPU at 1000 keyframes
    on the synthetic bench, but the parking-garage graph ends 5 % above batch LM's error
    (0.668 vs 0.634 at threshold 0.1 / skip 10), so it is off by default.
    factorization: "CHOLESKY" (fast) or "QR" (more stable on ill-conditioned graphs).
    wildfire_threshold: back-substitution stops where the change is below this.
    """

    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    enable_relinearization: bool = True
    extra_updates_after_loop: int = 1
    partial_relinearization_check: bool = False
    factorization: str = "CHOLESKY"
    wildfire_threshold: float = 0.001
    cache_linearized_factors: bool = True

    def __post_init__(self) -> None:
        if self.factorization not in FACTORIZATIONS:
            raise ConfigError(
                f"backend.factorization must be one of {', '.join(FACTORIZATIONS)}, "
                f"got '{self.factorization}'"
            )
        if self.relinearize_threshold < 0 or self.wildfire_threshold < 0:
            raise ConfigError("backend thresholds must be >= 0")
        if self.relinearize_skip < 1:
            raise ConfigError(f"backend.relinearize_skip must be >= 1, got {self.relinearize_skip}")
        if self.extra_updates_after_loop < 0:
            raise ConfigError("backend.extra_updates_after_loop must be >= 0")


def isam2_params(config: Isam2Config) -> gtsam.ISAM2Params:
    """gtsam.ISAM2Params from the config."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(config.relinearize_threshold)
    params.relinearizeSkip = config.relinearize_skip
    params.enableRelinearization = config.enable_relinearization
    params.cacheLinearizedFactors = config.cache_linearized_factors
    params.enablePartialRelinearizationCheck = config.partial_relinearization_check
    params.setFactorization(config.factorization)
    params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(config.wildfire_threshold))
    return params


class Isam2Backend:
    """Backend that keeps an ISAM2 instance plus a copy of every factor and initial value."""

    Config = Isam2Config

    def __init__(self, config: Isam2Config | None = None):
        self.config = config or Isam2Config()
        self._isam = gtsam.ISAM2(isam2_params(self.config))
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._ids: list[int] = []
        self._cache: dict[int, gtsam.Pose3] | None = {}
        self.n_updates = 0
        self.loop_updates = 0  # updates with loop_closed
        self.loop_update_ms: list[float] = []  # their iSAM2 time (ms), extra updates included
        self.extra_update_ms = 0.0  # total time (ms) of the extra updates after loops
        self.extra_updates = 0

    def update(
        self, factors: list[Any], initial: dict[int, gtsam.Pose3], loop_closed: bool = False
    ) -> None:
        """One iSAM2 step with only the new factors and values (keyframe id -> Pose3)."""
        new_factors = gtsam.NonlinearFactorGraph()
        for factor in factors:
            new_factors.add(factor)
        new_values = gtsam.Values()
        for kf_id, pose in initial.items():
            if self._values.exists(key(kf_id)):
                raise SlamError(f"keyframe {kf_id} already has a value in the iSAM2 graph")
            new_values.insert(key(kf_id), pose)
        t0 = time.perf_counter()
        try:
            self._isam.update(new_factors, new_values)
            if loop_closed:
                t1 = time.perf_counter()
                for _ in range(self.config.extra_updates_after_loop):
                    self._isam.update()
                    self.extra_updates += 1
                self.extra_update_ms += 1e3 * (time.perf_counter() - t1)
        except (RuntimeError, ValueError, IndexError) as exc:
            raise SlamError(f"iSAM2 update failed: {exc}") from exc
        self._graph.push_back(new_factors)
        self._values.insert(new_values)
        self._ids.extend(sorted(initial))
        self._cache = None
        self.n_updates += 1
        if loop_closed:
            self.loop_updates += 1
            self.loop_update_ms.append(1e3 * (time.perf_counter() - t0))

    def stats(self) -> dict[str, float]:
        """Counts and timings (ms) for metrics.json: updates, loop updates (with their extra
        updates) and their mean / max ms, the extra updates' share."""
        loops = self.loop_update_ms
        return {
            "updates": self.n_updates,
            "loop_updates": self.loop_updates,
            "loop_update_ms_mean": round(sum(loops) / len(loops), 3) if loops else 0.0,
            "loop_update_ms_max": round(max(loops), 3) if loops else 0.0,
            "extra_updates": self.extra_updates,
            "extra_update_ms_total": round(self.extra_update_ms, 3),
        }

    def estimate(self) -> dict[int, gtsam.Pose3]:
        """Current estimate of every keyframe id (cached until the next update)."""
        if self._cache is None:
            values = self._isam.calculateEstimate()
            self._cache = {i: values.atPose3(key(i)) for i in self._ids}
        return dict(self._cache)

    def pose(self, kf_id: int) -> gtsam.Pose3:
        """Estimate of one keyframe without computing the whole estimate."""
        if not self._values.exists(key(kf_id)):
            raise SlamError(f"no estimate for keyframe {kf_id}: it was never added")
        if self._cache is not None:
            return self._cache[kf_id]
        return self._isam.calculateEstimatePose3(key(kf_id))

    def finalize(self) -> dict[int, gtsam.Pose3]:
        return self.estimate()

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """Every factor added so far (a copy)."""
        return gtsam.NonlinearFactorGraph(self._graph)

    def values(self) -> gtsam.Values:
        """Every initial value added so far (a copy)."""
        return gtsam.Values(self._values)
