"""The region-graph back end of DPCR-SLAM (paper 003, section 3.5): a planar pose graph
(gtsam ``Pose2`` vertices, ``BetweenFactorPose2`` edges) optimised with Gauss-Newton,
eq. (9), each time the robot leaves a region (every keyframe of the ``dpcr2d`` front end is
a region event).

Factor plugins stay generic: they give Pose3 factors (odometry, priors, region edges of
``slam.region_edges``), which this back end projects on the plane - measured (x, y, yaw)
and the matching 3x3 block of the covariance (robust kernels kept). The graph it reports
(``graph()``, for ``graph.g2o``) is the factors as given.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from slam.errors import ConfigError, SlamError
from slam.factors import key
from slam.graph2d_gate import disagreement, frontend_check, optimize_gated

OPTIMIZERS = ("gauss_newton", "levenberg_marquardt")
_PLANE = [3, 4, 2]  # (x, y, yaw) in gtsam's Pose3 tangent order (rx, ry, rz, tx, ty, tz)


@dataclass
class RegionGraphConfig:
    """optimizer: "gauss_newton" (the paper) or "levenberg_marquardt"; max_iterations and
    relative_error_tol of the optimiser; optimize_every: keyframes between optimisations
    (1 = every region event); gate_sigma: a loop edge whose residual exceeds this many of
    its claimed sigmas at the result is switched off and the graph re-optimised
    (``slam.graph2d_gate``, at most ``gate_rounds`` times; 0: robust kernel only);
    disagree_sigma: an odometry factor (the front end's relative pose) this many sigmas off
    at the final estimate marks the run in ``stats()`` (metrics.json ``backend_stats``);
    keep_frontend_sigma: at the end, when every loop edge kept lies within this many of
    its claimed sigmas of the front end's own poses, the front end's poses are the result
    (``slam.graph2d_gate.frontend_check``: the edges do not show it wrong; 0: never)."""

    optimizer: str = "gauss_newton"
    max_iterations: int = 30
    relative_error_tol: float = 1e-6
    optimize_every: int = 1
    gate_sigma: float = 4.0
    gate_rounds: int = 3
    disagree_sigma: float = 3.0
    keep_frontend_sigma: float = 3.0

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ConfigError(f"backend.optimizer must be one of {', '.join(OPTIMIZERS)}")
        if self.max_iterations < 1 or self.optimize_every < 1:
            raise ConfigError("backend.max_iterations and optimize_every must be >= 1")


def pose2_of(p: gtsam.Pose3) -> gtsam.Pose2:
    """The planar part (x, y, yaw) of a Pose3."""
    return gtsam.Pose2(p.x(), p.y(), p.rotation().yaw())


def pose3_of(p: gtsam.Pose2) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Yaw(p.theta()), gtsam.Point3(p.x(), p.y(), 0.0))


def planar_noise(model: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """The (x, y, yaw) block of a 6-D Pose3 noise model, robust kernel kept."""
    robust = None
    if isinstance(model, gtsam.noiseModel.Robust):
        robust, model = model.robust(), model.noise()
    cov = np.asarray(model.covariance())[np.ix_(_PLANE, _PLANE)]
    base = gtsam.noiseModel.Gaussian.Covariance(cov)
    return base if robust is None else gtsam.noiseModel.Robust.Create(robust, base)


def planar_factor(factor: Any) -> Any:
    """A Pose2 factor for a Pose3 between/prior factor (Pose2 factors pass through)."""
    if isinstance(factor, gtsam.BetweenFactorPose3):
        a, b = factor.keys()
        return gtsam.BetweenFactorPose2(
            a, b, pose2_of(factor.measured()), planar_noise(factor.noiseModel())
        )
    if isinstance(factor, gtsam.PriorFactorPose3):
        return gtsam.PriorFactorPose2(
            factor.keys()[0], pose2_of(factor.prior()), planar_noise(factor.noiseModel())
        )
    if isinstance(factor, (gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2)):
        return factor
    raise ConfigError(
        f"the region_graph back end is planar: it takes Pose3/Pose2 between and prior "
        f"factors, not {type(factor).__name__}; use backend isam2 for this factor plugin"
    )


class RegionGraphBackend:
    """Planar pose graph of region vertices, optimised in batch on region events."""

    Config = RegionGraphConfig

    def __init__(self, config: RegionGraphConfig | None = None):
        self.config = config or RegionGraphConfig()
        self._factors2: list[Any] = []
        self._graph3 = gtsam.NonlinearFactorGraph()
        self._values2 = gtsam.Values()
        self._values3 = gtsam.Values()
        self._ids: list[int] = []
        self._estimate: dict[int, gtsam.Pose2] = {}
        self._pending = 0
        self.optimize_ms: list[float] = []  # the paper's T_graph, one per optimisation
        self.failures: list[str] = []  # optimisations that fell back (GN -> LM) or failed
        self._gate = None  # the last gated optimisation (slam.graph2d_gate.GateResult)
        self._check = None  # the final front-end check (slam.graph2d_gate.FrontendCheck)

    def update(
        self, factors: list[Any], initial: dict[int, gtsam.Pose3], loop_closed: bool = False
    ) -> None:
        for factor in factors:
            self._graph3.add(factor)
            self._factors2.append(planar_factor(factor))
        for kf_id, pose in initial.items():
            if self._values2.exists(key(kf_id)):
                raise SlamError(f"keyframe {kf_id} already has a value in the region graph")
            self._values2.insert(key(kf_id), pose2_of(pose))
            self._values3.insert(key(kf_id), pose)
            self._ids.append(kf_id)
            # until the next optimisation a new vertex sits at its initial value
            self._estimate[kf_id] = pose2_of(pose)
        self._pending += 1
        if self._pending >= self.config.optimize_every or loop_closed:
            self._optimize()

    def _optimize(self) -> None:
        self._pending = 0
        if not self._ids:
            return
        t = time.perf_counter()
        start = gtsam.Values()
        for kf_id in self._ids:
            start.insert(key(kf_id), self._estimate[kf_id])
        result = None
        order = [self.config.optimizer] + [o for o in OPTIMIZERS if o != self.config.optimizer]
        for name in order:  # Gauss-Newton stops on an indeterminant system; LM damps it
            try:
                self._gate = optimize_gated(
                    self._factors2,
                    start,
                    lambda graph, values, name=name: self._run(name, graph, values),
                    self.config.gate_sigma,
                    self.config.gate_rounds,
                )
                result = self._gate.values
                break
            except RuntimeError as exc:
                self.failures.append(f"{name}: {str(exc).splitlines()[0] if str(exc) else exc}")
        if result is not None:  # else: keep the last estimate (counted in stats)
            self._estimate = {i: result.atPose2(key(i)) for i in self._ids}
        self.optimize_ms.append((time.perf_counter() - t) * 1e3)

    def _run(
        self, name: str, graph: gtsam.NonlinearFactorGraph, start: gtsam.Values
    ) -> gtsam.Values:
        cfg = self.config
        if name == "gauss_newton":
            params = gtsam.GaussNewtonParams()
            params.setMaxIterations(cfg.max_iterations)
            params.setRelativeErrorTol(cfg.relative_error_tol)
            return gtsam.GaussNewtonOptimizer(graph, start, params).optimize()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.max_iterations)
        params.setRelativeErrorTol(cfg.relative_error_tol)
        return gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize()

    def estimate(self) -> dict[int, gtsam.Pose3]:
        return {i: pose3_of(p) for i, p in self._estimate.items()}

    def pose(self, kf_id: int) -> gtsam.Pose3:
        if kf_id not in self._estimate:
            raise SlamError(f"no estimate for keyframe {kf_id}: it was never added")
        return pose3_of(self._estimate[kf_id])

    def finalize(self) -> dict[int, gtsam.Pose3]:
        if self._pending:
            self._optimize()
        if self._gate is not None:
            sigma = self.config.keep_frontend_sigma
            self._check = frontend_check(self._factors2, self._gate, sigma)
            if self._check.keep_frontend:
                self._estimate = {i: self._check.values.atPose2(key(i)) for i in self._ids}
        return self.estimate()

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """Every factor as given (Pose3), a copy."""
        return gtsam.NonlinearFactorGraph(self._graph3)

    def values(self) -> gtsam.Values:
        return gtsam.Values(self._values3)

    def stats(self) -> dict[str, float]:
        """Optimisations run and their time (ms): the paper's graph optimisation time; the
        last result's agreement with the front end (``slam.graph2d_gate.disagreement``)
        and ``disagrees_with_frontend`` (1.0 when an odometry factor lies more than
        ``disagree_sigma`` of its claimed sigmas off)."""
        ms = self.optimize_ms
        out = {
            "optimizations": float(len(ms)),
            "optimize_mean_ms": float(np.mean(ms)) if ms else 0.0,
            "optimize_max_ms": float(np.max(ms)) if ms else 0.0,
            "optimizer_fallbacks": float(len(self.failures)),
        }
        if self._gate is not None:
            d = disagreement(self._factors2, self._gate.sigmas, self._gate.off)
            d["disagrees_with_frontend"] = float(
                d["frontend_residual_max_sigma"] > self.config.disagree_sigma
            )
            out.update(d)
        if self._check is not None:
            out["frontend_loop_residual_max_sigma"] = self._check.max_sigma
            out["kept_frontend"] = float(self._check.keep_frontend)
        return out
