"""Scan Context loop closure as a factor plugin (two layers: descriptor proposes, GICP verifies).

On each keyframe: describe it (:mod:`slam.loop.describe`) -> candidates older than the
exclusion window (:mod:`slam.loop.propose`) -> a verification job from the estimates now
(:mod:`slam.loop.jobs`), run here or in a worker (:mod:`slam.loop.background`) -> the
verified loop waits for a consistent partner (:mod:`slam.loop.record`) ->
``BetweenFactorPose3(key(candidate), key(current), T_candidate_current)`` with a robust
noise model. Every verified candidate is an event of ``loops.csv``.

Cost: the plugin keeps descriptors and keys only; verification reads the pipeline's
``Keyframe.cloud`` through the GraphView.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gtsam

from slam.factors import GraphView
from slam.loop.background import KeyframeJob, VerifyPool, run_job
from slam.loop.config import LoopConfig
from slam.loop.describe import Describer, auto_descriptor_params
from slam.loop.jobs import JobMaker
from slam.loop.propose import Proposer
from slam.loop.record import CSV_COLUMNS, LoopRecord
from slam.loop.scan_context import ScanContextParams
from slam.loop.search import ScanContextDatabase
from slam.loop.timing import LoopTimes
from slam.types import Keyframe, LoopConstraint

__all__ = ["CSV_COLUMNS", "LoopClosurePlugin", "auto_descriptor_params"]

# keyframes of head start for the verification workers before the first keyframe that can
# have a candidate: a spawned worker takes 1-2.5 s to import (1 s CPU), a 16-beam front end
# makes 4-12 keyframes a second
WORKER_LEAD = 15


class LoopClosurePlugin:
    """Loop closure factors from Scan Context + GICP (LeGO-LOAM-LPB's two-layer scheme)."""

    is_loop = True
    Config = LoopConfig

    def __init__(self, config: LoopConfig | None = None):
        self.config = cfg = config or LoopConfig()
        search = cfg.search
        if search.proposer == "radius":  # LeGO-LOAM: only keyframes this much older
            search = dataclasses.replace(
                search, exclude_seconds=max(search.exclude_seconds, search.radius_min_seconds)
            )
        self.db = ScanContextDatabase(cfg.descriptor.rings, cfg.descriptor.sectors, search)
        self.describer = Describer(cfg.descriptor, cfg.search, self.db)
        self.proposer = Proposer(cfg.search, self.db, self.describer)
        self.jobs = JobMaker(cfg)
        self.record = LoopRecord(cfg, self.db)
        self.times = LoopTimes()
        processes = cfg.workers.processes
        self.pool = VerifyPool(processes, cfg.verify) if processes else None
        # the workers start this many keyframes before the first one that can have a
        # candidate (the database must hold more than exclude_recent keyframes), not at the
        # first keyframe: a run too short for any candidate spawns none
        self._start_at = max(search.exclude_recent + 1 - WORKER_LEAD, 0)
        self._submitted: list[KeyframeJob] = []  # in the pool, oldest first

    @property
    def sc_params(self) -> ScanContextParams | None:
        """The Scan Context geometry (None until the auto geometry is fixed)."""
        return self.describer.sc_params

    @property
    def events(self) -> list[LoopConstraint]:
        return self.record.events

    @property
    def accepted(self) -> list[LoopConstraint]:
        return self.record.accepted

    # ------------------------------------------------------------------ plugin interface
    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.BetweenFactorPose3]:
        """Detect and verify a loop for ``kf``; returns the loop factors confirmed now."""
        cfg = self.config
        if not cfg.enabled:
            return []
        self.times.start()
        described = self.describer.add(kf)
        self.jobs.note(kf)
        candidates = [] if described is None else self.proposer.candidates(kf, *described, graph)
        self.times.detected()
        factors = []
        if self.pool is not None:
            if len(self.db) >= self._start_at:
                self.pool.start()
            factors = self._collect(kf.id)
        if not candidates or kf.id - self.record.last_accepted < cfg.search.min_keyframe_gap:
            self.times.verified(False)
            return factors
        try:
            job = self.jobs.make(kf, candidates, graph)
            if self.pool is None:
                factors += self.record.finish(job, run_job(job, cfg.verify))
            else:  # the loop enters the graph at keyframe job.due
                self.pool.submit(job)
                self._submitted.append(job)
            return factors
        finally:
            self.times.verified(True)

    def flush(self, graph: GraphView) -> list[gtsam.BetweenFactorPose3]:
        """The loop factors of every verification still running in a worker (end of the run:
        the pipeline adds them before the final optimisation); nothing when verifying
        in-process."""
        factors = self._collect(None)
        self.record.expire(None)
        return factors

    def close(self) -> None:
        """Stop the worker processes (if any); the plugin verifies in-process afterwards."""
        if self.pool is not None:
            self.pool.close()

    def _collect(self, kf_id: int | None) -> list[gtsam.BetweenFactorPose3]:
        """Results of the jobs due at keyframe ``kf_id`` (None: all), oldest first, waiting
        for the worker when one is not done yet."""
        factors = []
        while self._submitted and (kf_id is None or self._submitted[0].due <= kf_id):
            job = self._submitted.pop(0)
            factors += self.record.finish(job, self.pool.result(job))
        return factors

    # ------------------------------------------------------------------ outputs
    def stats(self) -> dict[str, float]:
        """Counts and timings (ms) for metrics.json (see :class:`slam.loop.timing.LoopTimes`).

        register_ms_mean: per candidate registered by GICP; skipped: candidates the odometry
        ruled out unregistered; wait_ms: time spent waiting for the workers.
        """
        r = self.record
        return {
            "keyframes": len(self.db),
            "verified": len(r.events),
            "registered": r.registrations,
            "skipped": r.skipped,
            "accepted": len(r.accepted),
            "unconfirmed": r.unconfirmed,
            **self.times.means(),
            "wait_ms": self.pool.wait_ms if self.pool is not None else 0.0,
            "register_ms_mean": r.register_ms / r.registrations if r.registrations else 0.0,
            **self.times.windows(),
        }

    def write_csv(self, path: str | Path) -> None:
        """loops.csv: one row per verified candidate (accepted or rejected with a reason)."""
        self.record.write_csv(path)
