"""The outcome of every verified loop candidate: events (loops.csv), counters, and the loop
factors of the candidates that pass verification and the pairwise consistency check."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import gtsam
import numpy as np

from slam.factors import information_noise, key, pose3, robust_noise
from slam.loop.background import KeyframeJob
from slam.loop.config import LoopConfig
from slam.loop.consistency import LoopConsistency, PendingLoop
from slam.loop.search import ScanContextDatabase
from slam.loop.verify import VerifyResult
from slam.types import LoopConstraint

log = logging.getLogger("slam.loop.plugin")

CSV_COLUMNS = (
    "source", "target", "stamp_source", "stamp_target", "score", "fitness", "yaw_deg",
    "accepted", "reason", "ambiguity", "free_axes",
)  # fmt: skip


class LoopRecord:
    """Events and counters of the verified candidates; admits loops through ``consistency``."""

    def __init__(self, cfg: LoopConfig, db: ScanContextDatabase):
        self.cfg, self.db = cfg, db
        self.consistency = LoopConsistency(cfg.consistency.pairwise)
        self.events: list[LoopConstraint] = []
        # per event: stamps, yaw (deg), ambiguity, number of free axes
        self._event_meta: list[tuple[float, float, float, float, int]] = []
        self.last_accepted = -(10**9)  # keyframe id of the last accepted loop
        self.registrations = 0  # candidates registered by GICP
        self.register_ms = 0.0  # their total time (ms)
        self.skipped = 0  # candidates ruled out by the odometry before registration
        self.unconfirmed = 0  # verified loops that no consistent partner confirmed

    @property
    def accepted(self) -> list[LoopConstraint]:
        return [e for e in self.events if e.accepted]

    def finish(
        self, job: KeyframeJob, results: list[tuple[VerifyResult, float]]
    ) -> list[gtsam.BetweenFactorPose3]:
        """Record a job's results; the loop factors its accepted candidate confirms."""
        for cj, (res, ms) in zip(job.candidates, results, strict=False):  # stops at accepted
            self._note(job, cj.cand, res, ms)
            if not res.accepted:
                log.debug("loop %d -> %d rejected: %s", job.kf_id, cj.cand.kf_id, res.reason)
                continue
            log.info(
                "loop %d -> %d verified: sc %.3f fitness %.3f m overlap %.2f yaw %.1f deg",
                job.kf_id, cj.cand.kf_id, cj.cand.distance, res.fitness, res.overlap,
                res.yaw_deg,
            )  # fmt: skip
            out = self._admit(job, cj, res)
            self.expire(job.kf_id)
            return out
        self.expire(job.kf_id)
        return []

    def _note(self, job: KeyframeJob, cand, res: VerifyResult, ms: float) -> None:
        if ms < 0:
            self.skipped += 1
        else:
            self.registrations += 1
            self.register_ms += ms
        self.events.append(
            LoopConstraint(
                source=job.kf_id, target=cand.kf_id, T_target_source=res.T_target_source,
                score=cand.distance, fitness=res.fitness, accepted=res.accepted, info=res.info,
                reason=res.reason,
            )
        )  # fmt: skip
        self._event_meta.append(
            (job.stamp, self.db.stamp(cand.row), res.yaw_deg, res.ambiguity, len(res.free_axes))
        )

    def _admit(self, job: KeyframeJob, cj, res: VerifyResult) -> list[gtsam.BetweenFactorPose3]:
        """Hold a verified loop for a consistent partner; the factors of the loops it confirms."""
        noise = robust_noise(information_noise(res.info), self.cfg.robust, self.cfg.robust_param)
        factor = gtsam.BetweenFactorPose3(
            key(cj.cand.kf_id), key(job.kf_id), pose3(res.T_target_source), noise
        )
        event = self.events[-1]
        event.accepted, event.reason = False, "awaiting a consistent loop"
        pending = PendingLoop(
            cj.cand.kf_id, job.kf_id, np.asarray(res.T_target_source, dtype=np.float64),
            cj.T_odom, job.T_odom, cj.travel, job.travel, payload=(event, factor),
        )  # fmt: skip
        out = []
        for m in self.consistency.add(pending):
            ev, f = m.payload
            ev.accepted, ev.reason = True, ""
            out.append(f)
            log.info("loop %d -> %d accepted", m.source, m.target)
        if out:
            self.last_accepted = job.kf_id
        return out

    def expire(self, latest: int | None) -> None:
        """Mark the verified loops no partner can confirm any more (None: all pending)."""
        window = self.cfg.consistency.pairwise.window
        for m in self.consistency.expire(latest):
            ev, _ = m.payload
            ev.reason = f"unconfirmed: no consistent loop within {window} keyframes"
            self.unconfirmed += 1

    def write_csv(self, path: str | Path) -> None:
        """loops.csv: one row per verified candidate (accepted or rejected with a reason)."""
        with Path(path).open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CSV_COLUMNS)
            for e, (st_s, st_t, yaw, amb, free) in zip(self.events, self._event_meta, strict=True):
                w.writerow(
                    [
                        e.source, e.target, f"{st_s:.9f}", f"{st_t:.9f}", f"{e.score:.6f}",
                        f"{e.fitness:.6f}", f"{yaw:.3f}", int(e.accepted), e.reason,
                        f"{amb:.3f}", free,
                    ]
                )  # fmt: skip
