"""Loops whose constraints are the truth: what loop closure could do at best.

:class:`OracleLoops` is a factor plugin (``factors.oracle.plugin=slam.bench.oracle:OracleLoops``)
that adds BetweenFactorPose3 loops with the true relative pose of two keyframes (from the
ground truth, nearest stamp) and a tight noise (5 cm / 0.5 deg): either the loops of a run
(``pairs``: its graph.g2o loop edges) or every pair of keyframes truly within ``radius`` m
and at least ``min_gap`` keyframes apart. :func:`loosen_plain` and :func:`reloosen` rewrite
a loop_replay recording's odometry information (an oracle of degeneracy-aware odometry, and
the front end's own ambiguity test redone with other parameters).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from slam.bench.loop_audit import keyframe_stamps, loop_edges, loop_pairs
from slam.factors import FactorConfig, GraphView, key, pose3
from slam.io.trajectory import read_tum
from slam.types import Keyframe


def run_pairs(run_dir: Path) -> set[tuple[float, float]]:
    """(stamp_target, stamp_source) of the loops in a run's pose graph (its graph.g2o loop
    edges, stamps from its loops.csv): the loops it kept, unconfirmed ones excluded."""
    stamps = keyframe_stamps(run_dir / "loops.csv")
    edges = loop_edges(run_dir / "graph.g2o", loop_pairs(run_dir / "loops.csv"))
    return {(round(stamps[a], 6), round(stamps[b], 6)) for a, b, _, _ in edges}


class OracleLoops:
    """True loops (see the module doc)."""

    is_loop = True

    @dataclass
    class Config(FactorConfig):
        gt: str = ""
        pairs: str = ""  # a run's folder: the loops of its graph.g2o only
        radius: float = 3.0
        min_gap: int = 30
        all_pairs: bool = False
        sigma_trans: float = 0.05
        sigma_rot_deg: float = 0.5

    def __init__(self, config: Config):
        self.config = config
        self._stamps, self._poses = read_tum(Path(config.gt))
        self._pairs = run_pairs(Path(config.pairs)) if config.pairs else None
        self._kf_true: list[np.ndarray] = []
        self._kf_stamp: list[float] = []
        s = np.radians(config.sigma_rot_deg)
        t = config.sigma_trans
        self._noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s, s, s, t, t, t]))
        self.added: list[tuple[int, int]] = []

    def _true(self, stamp: float) -> np.ndarray:
        i = int(np.clip(np.searchsorted(self._stamps, stamp), 1, len(self._stamps) - 1))
        j = i if abs(self._stamps[i] - stamp) < abs(self._stamps[i - 1] - stamp) else i - 1
        return self._poses[j]

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        T = self._true(kf.stamp)
        self._kf_true.append(T)
        self._kf_stamp.append(float(kf.stamp))
        c = self.config
        targets: list[int] = []
        if self._pairs is not None:
            me = round(float(kf.stamp), 6)
            targets = [
                j for j, st in enumerate(self._kf_stamp[:-1]) if (round(st, 6), me) in self._pairs
            ]
        elif kf.id >= c.min_gap:
            old = np.array([P[:3, 3] for P in self._kf_true[: kf.id - c.min_gap + 1]])
            d = np.linalg.norm(old - T[:3, 3], axis=1)
            near = np.flatnonzero(d < c.radius)
            if len(near):
                targets = list(near) if c.all_pairs else [int(near[np.argmin(d[near])])]
        out = []
        for j in targets:
            rel = np.linalg.inv(self._kf_true[j]) @ T
            out.append(gtsam.BetweenFactorPose3(key(j), key(kf.id), pose3(rel), self._noise))
            self.added.append((int(j), int(kf.id)))
        return out


def loosen_plain(rec: dict, gt: Path, sigma: float) -> int:
    """In place: the odometry information of the recording's keyframes that truly lie in a
    plain corridor stretch of the building floor (slam.sim.building.PLAIN, within 2 m of
    the corridor's centre line) loses its along-track part, replaced by 1 / sigma^2 (m):
    what a degeneracy-aware front end would report there, located by the truth (an
    oracle). Returns the number of keyframes changed."""
    from slam.sim.building import LANES, PLAIN

    tg, G = read_tum(gt)
    info = rec["info"].copy()
    n = 0
    for i in np.flatnonzero(rec["is_kf"]):
        j = min(int(np.searchsorted(tg, rec["stamps"][i] - 1e-6)), len(tg) - 1)
        x, y = G[j][0, 3], G[j][1, 3]
        if not any(abs(y - LANES[k]) < 2.0 and x0 <= x <= x1 for k, x0, x1 in PLAIN):
            continue
        t = rec["relative"][i][:3, 3]
        if np.linalg.norm(t) < 1e-3:
            continue
        u = t / np.linalg.norm(t)
        lam = np.trace(info[i][3:, 3:]) / 3.0
        info[i][3:, 3:] = lam * (np.eye(3) - np.outer(u, u)) + np.outer(u, u) / sigma**2
        n += 1
    rec["info"] = info
    return n


def reloosen(rec: dict, ratio: float, sigma: float) -> int:
    """In place: the recording's keyframe odometry information as the front end's
    ``odometry_ambiguity`` would have given it with another ``ratio`` / ``sigma`` (the slide
    test's ratio and axis of every keyframe are in the recording's extras, the information
    before loosening in ``info_raw``): exact, not an oracle. Returns the keyframes loosened."""
    from slam.registration.ambiguity import loosened_information

    extras = json.loads(str(rec["extras"]))
    info = rec["info_raw"].copy()
    n = 0
    for i, e in enumerate(extras):
        if "ambiguity" in e and e["ambiguity"] >= ratio:
            axis = np.array([e["ambiguity_axis_x"], e["ambiguity_axis_y"], 0.0])
            info[i] = loosened_information(info[i], axis, sigma)
            n += 1
    rec["info"] = info
    return n
