"""Batch Levenberg-Marquardt over the whole graph, once, in ``finalize``.

The reference optimum for the incremental back end and the named baseline of the
pose-graph benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam

from slam.errors import ConfigError, SlamError
from slam.factors import key


@dataclass
class BatchConfig:
    """LM stopping criteria; errors are GTSAM's 0.5 * sum of squared whitened residuals."""

    max_iterations: int = 100
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    lambda_initial: float = 1e-5

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ConfigError(f"backend.max_iterations must be >= 1, got {self.max_iterations}")
        if min(self.relative_error_tol, self.absolute_error_tol, self.lambda_initial) < 0:
            raise ConfigError("backend tolerances and lambda_initial must be >= 0")


def lm_params(config: BatchConfig) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(config.absolute_error_tol)
    params.setlambdaInitial(config.lambda_initial)
    return params


class BatchBackend:
    """Collects factors and values; ``estimate`` is the initial guess until ``finalize``."""

    Config = BatchConfig

    def __init__(self, config: BatchConfig | None = None):
        self.config = config or BatchConfig()
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._ids: list[int] = []
        self._result: gtsam.Values | None = None
        self.iterations = 0

    def update(
        self, factors: list[Any], initial: dict[int, gtsam.Pose3], loop_closed: bool = False
    ) -> None:
        """Store new factors and initial values (keyframe id -> Pose3); no optimisation."""
        for kf_id, pose in initial.items():
            if self._values.exists(key(kf_id)):
                raise SlamError(f"keyframe {kf_id} already has a value in the batch graph")
            self._values.insert(key(kf_id), pose)
        self._ids.extend(sorted(initial))
        for factor in factors:
            self._graph.add(factor)
        self._result = None

    def estimate(self) -> dict[int, gtsam.Pose3]:
        """The optimum after ``finalize``; before, the initial values (odometry poses)."""
        values = self._result if self._result is not None else self._values
        return {i: values.atPose3(key(i)) for i in self._ids}

    def pose(self, kf_id: int) -> gtsam.Pose3:
        """Estimate of one keyframe (initial guess until ``finalize``)."""
        if not self._values.exists(key(kf_id)):
            raise SlamError(f"no estimate for keyframe {kf_id}: it was never added")
        values = self._result if self._result is not None else self._values
        return values.atPose3(key(kf_id))

    def finalize(self) -> dict[int, gtsam.Pose3]:
        """Run LM over the whole graph (again only if something was added since)."""
        if self._result is None and self._ids:
            try:
                optimizer = gtsam.LevenbergMarquardtOptimizer(
                    self._graph, self._values, lm_params(self.config)
                )
                self._result = optimizer.optimize()
            except (RuntimeError, ValueError, IndexError) as exc:
                raise SlamError(f"batch optimisation failed: {exc}") from exc
            self.iterations = optimizer.iterations()
        return self.estimate()

    def graph(self) -> gtsam.NonlinearFactorGraph:
        return gtsam.NonlinearFactorGraph(self._graph)

    def values(self) -> gtsam.Values:
        return gtsam.Values(self._values)
