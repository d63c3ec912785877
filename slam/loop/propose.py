"""Loop candidates of a keyframe: the descriptor's KD-tree search (SC++: polar and
Cartesian), keyframes near the current estimate, or LeGO-LOAM's nearest one in a radius."""

from __future__ import annotations

import numpy as np

from slam.factors import GraphView
from slam.loop.angles import yaw_of
from slam.loop.config import SearchConfig
from slam.loop.describe import Describer
from slam.loop.estimates import current_estimate, estimate_of
from slam.loop.search import Candidate, ScanContextDatabase
from slam.types import Keyframe


class Proposer:
    """Candidates for verification, best first, from the database ``db`` the describer fills."""

    def __init__(self, search: SearchConfig, db: ScanContextDatabase, describer: Describer):
        self.cfg, self.db, self.describer = search, db, describer

    def candidates(
        self, kf: Keyframe, desc: np.ndarray, cc: np.ndarray | None, graph: GraphView
    ) -> list[Candidate]:
        """Descriptor candidates below the threshold (SC++: polar and Cartesian, best first),
        then proximity candidates (if on); with proposer radius only the nearest keyframe
        within ``radius`` m."""
        cfg = self.cfg
        out: list[Candidate] = []
        if cfg.proposer == "descriptor":
            out = [c for c in self.db.query(desc, kf.stamp) if c.distance < cfg.threshold]
            if cc is not None:
                out = self._merge_cartesian(out, cc, kf.stamp)
        radius = cfg.radius if cfg.proposer == "radius" else cfg.proximity_radius
        if radius > 0.0:
            self._refresh_positions(kf, graph)
            T_w_cur = current_estimate(graph, kf)
            seen = {c.row for c in out}
            rows = [r for r in self.db.near(T_w_cur[:3, 3], radius, kf.stamp)]
            if cfg.proposer == "radius":
                rows = rows[:1]  # LeGO-LOAM: the nearest one
            rows = [r for r in rows if r not in seen]
            for c in self.db.score(desc, np.asarray(rows, dtype=np.intp)):
                T_rel = np.linalg.inv(estimate_of(graph, c.kf_id)) @ T_w_cur
                c.yaw = yaw_of(T_rel)  # the estimate, not the descriptor, guides these
                c.shift = -1
                out.append(c)
        return out

    def _merge_cartesian(
        self, polar: list[Candidate], cc: np.ndarray, stamp: float
    ) -> list[Candidate]:
        """SC++: polar candidates and the Cartesian context's augmented matches below
        cc_threshold, one per keyframe (the lower distance wins), best first. A CC match
        carries its initial pose (half a turn or none, the lateral/longitudinal shift)."""
        by_row = {c.row: c for c in polar}
        for m in self.describer.cc_index.query(cc, self.db.eligible(stamp)):
            if m.distance >= self.cfg.cc_threshold:
                break
            if m.row in by_row and by_row[m.row].distance <= m.distance:
                continue
            by_row[m.row] = Candidate(
                row=m.row, kf_id=self.db.kf_id(m.row), distance=m.distance, shift=0,
                yaw=yaw_of(m.T_candidate_query), init=m.T_candidate_query,
            )  # fmt: skip
        return sorted(by_row.values(), key=lambda c: c.distance)

    def _refresh_positions(self, kf: Keyframe, graph: GraphView) -> None:
        """Keep proximity positions current: all rows every rebuild_every keyframes."""
        n = len(self.db)
        if (n - 1) % self.cfg.rebuild_every == 0:
            ids = [self.db.kf_id(r) for r in range(n)]
            pos = np.array([estimate_of(graph, i)[:3, 3] for i in ids])
            self.db.set_positions(np.arange(n), pos)
        else:
            self.db.set_positions(np.array([n - 1]), current_estimate(graph, kf)[None, :3, 3])
