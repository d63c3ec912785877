"""Verification jobs of a keyframe's candidates, made from the estimates at that keyframe:
initial guesses, the odometry gates and the clouds (:mod:`slam.loop.background` runs them)."""

from __future__ import annotations

import numpy as np

from slam.factors import GraphView
from slam.loop.angles import wrap_angle, yaw_matrix, yaw_of
from slam.loop.background import CandidateJob, KeyframeJob, OdometryGate
from slam.loop.config import LoopConfig
from slam.loop.estimates import current_estimate, estimate_of, local_cloud
from slam.loop.search import Candidate
from slam.types import Keyframe


class JobMaker:
    """Makes :class:`KeyframeJob` s; keeps each keyframe's odometric distance from the start
    (``travel``, m), which the gates scale with."""

    def __init__(self, cfg: LoopConfig):
        self.cfg = cfg
        self.travel: dict[int, float] = {}  # kf id -> odometric distance since the start (m)

    def note(self, kf: Keyframe) -> None:
        """Record ``kf``'s odometric distance from the start."""
        step = float(np.linalg.norm(np.asarray(kf.relative)[:3, 3])) if kf.id > 0 else 0.0
        self.travel[kf.id] = self.travel.get(kf.id - 1, 0.0) + step

    def make(self, kf: Keyframe, candidates: list[Candidate], graph: GraphView) -> KeyframeJob:
        """Everything verifying ``kf``'s first max_verify candidates needs, from the estimates
        now: initial guesses, the gates, and the clouds of the candidates the odometry does
        not already rule out (:meth:`unreachable`; the source cloud only if one remains)."""
        cfg, n = self.cfg, self.cfg.verify.neighbours
        jobs = []
        for cand in candidates[: cfg.search.max_verify]:
            if cand.shift < 0:  # proximity candidate: the estimate is the initial guess
                init = np.linalg.inv(estimate_of(graph, cand.kf_id)) @ current_estimate(graph, kf)
            elif cand.init is not None:
                init = np.asarray(cand.init, dtype=np.float64)
            else:
                init = yaw_matrix(cand.yaw)
            cj = CandidateJob(cand, init, self.gate(graph, kf, cand.kf_id))
            cj.T_odom = np.asarray(graph.keyframes[cand.kf_id].pose_odom, dtype=np.float64)
            cj.travel = self.travel.get(cand.kf_id, 0.0)
            cj.skip = self.unreachable(graph, kf, cand.kf_id, init)
            if not cj.skip:
                T_w_cand = estimate_of(graph, cand.kf_id) if n > 0 else np.eye(4)
                cj.target = local_cloud(graph, cand.kf_id, T_w_cand, n)
            jobs.append(cj)
        source = None
        if any(not cj.skip for cj in jobs):
            T_w_cur = current_estimate(graph, kf) if n > 0 else np.eye(4)
            source = local_cloud(graph, kf.id, T_w_cur, n)
        return KeyframeJob(
            kf.id, kf.stamp, jobs, source, kf.id + cfg.workers.lag, None,
            np.asarray(kf.pose_odom, dtype=np.float64), self.travel.get(kf.id, 0.0),
        )  # fmt: skip

    def _relative(self, graph: GraphView, kf: Keyframe, cand_id: int) -> tuple[np.ndarray, float]:
        """(T_candidate_current of the estimates, odometric distance between them in m)."""
        T_est = np.linalg.inv(estimate_of(graph, cand_id)) @ current_estimate(graph, kf)
        travelled = abs(self.travel.get(kf.id, 0.0) - self.travel.get(cand_id, 0.0))
        return T_est, travelled

    def gate(self, graph: GraphView, kf: Keyframe, cand_id: int) -> OdometryGate:
        """The odometry-consistency gate of candidate ``cand_id`` from the estimates now."""
        g = self.cfg.consistency.odometry
        T_est, travelled = self._relative(graph, kf, cand_id)
        return OdometryGate(T_est, g.allowed(travelled), travelled, g.yaw_deg, g.enabled)

    def unreachable(self, graph: GraphView, kf: Keyframe, cand_id: int, init: np.ndarray) -> str:
        """Why no registration from ``init`` could pass both the verification's and the
        odometry-consistency gates (empty string when one could): a cheap test before GICP.

        Exact consequence of the gates, so it rejects nothing they would accept: a result
        must lie within max_offset (m) of the candidate and within the gate's allowance of
        the estimate; its yaw within yaw_tolerance_deg of the guess or of the guess turned
        half a turn (try_flip, whose start also searches the BEV yaw offsets) and within the
        gate's yaw_deg of the estimate's yaw.
        """
        g, p = self.cfg.consistency.odometry, self.cfg.verify
        if not g.enabled:
            return ""
        T_est, travelled = self._relative(graph, kf, cand_id)
        allowed = g.allowed(travelled)
        dist = float(np.linalg.norm(T_est[:3, 3]))
        if dist > p.max_offset + allowed:
            return (
                f"inconsistent with odometry: the estimate is {dist:.1f} m away "
                f"(> max_offset {p.max_offset:.0f} m + allowed {allowed:.1f} m), not registered"
            )
        guess, est = yaw_of(init), yaw_of(T_est)
        margin = g.yaw_deg + p.yaw_tolerance_deg
        offs = max((abs(o) for o in p.bev_yaw_offsets_deg), default=0.0)
        turns = [abs(np.degrees(wrap_angle(guess - est)))]
        if p.try_flip:
            turns.append(abs(np.degrees(wrap_angle(guess + np.pi - est))) - offs)
        if min(turns) > margin:
            return (
                f"inconsistent with odometry: guess turns {min(turns):.0f} deg from the "
                f"estimate (> {margin:.0f} deg), not registered"
            )
        return ""
