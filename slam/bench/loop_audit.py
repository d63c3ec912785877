"""False loops of a run against the ground truth: every loop edge of ``graph.g2o`` checked.

A loop closure is false when its constraint (the loop edge ``T_target_source`` in
graph.g2o) differs from the true relative pose of its two keyframes by more than
``max_trans`` m or ``max_rot_deg`` deg (defaults 1 m / 3 deg). The keyframes' stamps come
from the run's loops.csv (accepted rows), their true poses from the ground truth TUM file
(nearest stamp). Also per loop: the error whitened by the edge's own information
(``chi2``: a degenerate loop that leaves the corridor axis free may be off along it and
still claim nothing wrong) and the edge's weakest translation sigma.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from slam.io.trajectory import read_tum


@dataclass
class LoopCheck:
    """One loop edge against the truth: keyframe ids (target = the older one), true
    distance between them (m), constraint error (m, deg), chi2 of the error under the
    edge's information, weakest translation sigma (m), false by the thresholds."""

    target: int
    source: int
    true_distance: float
    err_trans: float
    err_rot_deg: float
    chi2: float
    sigma_max: float
    false: bool


def pose_error(T_true: np.ndarray, T_meas: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(translation m, rotation deg, tangent 6-vector rotation first) of T_true^-1 T_meas."""
    E = np.linalg.solve(T_true, T_meas)
    xi = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(E)), dtype=float)
    rot = float(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))
    return float(np.linalg.norm(E[:3, 3])), rot, xi


def nearest(stamps: np.ndarray, t: float) -> int:
    i = int(np.searchsorted(stamps, t))
    cand = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    return min(cand, key=lambda j: abs(stamps[j] - t))


def keyframe_stamps(loops_csv: Path) -> dict[int, float]:
    """Keyframe id -> stamp from every row of loops.csv (source and target)."""
    out: dict[int, float] = {}
    with loops_csv.open() as fh:
        for row in csv.DictReader(fh):
            out[int(row["source"])] = float(row["stamp_source"])
            out[int(row["target"])] = float(row["stamp_target"])
    return out


def loop_pairs(loops_csv: Path) -> set[tuple[int, int]]:
    """(target, source) of the accepted rows of loops.csv."""
    with loops_csv.open() as fh:
        return {
            (int(r["target"]), int(r["source"]))
            for r in csv.DictReader(fh)
            if str(r.get("accepted", "")).strip().lower() in ("1", "true", "yes")
        }


def loop_edges(
    g2o: Path, pairs: set[tuple[int, int]] | None = None
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(target, source, T_target_source, info 6x6 rotation first) of every between factor
    that does not join consecutive keyframes (the odometry chain); with ``pairs`` only those
    (other factor plugins, e.g. the ground factor's relative mode, add between factors
    too)."""
    graph, _ = gtsam.readG2o(str(g2o), True)
    out = []
    for i in range(graph.size()):
        f = graph.at(i)
        if not isinstance(f, gtsam.BetweenFactorPose3):
            continue
        a, b = (gtsam.Symbol(k).index() for k in f.keys())
        if abs(b - a) == 1 or (pairs is not None and (a, b) not in pairs):
            continue
        R = np.asarray(f.noiseModel().R(), dtype=float)
        out.append((a, b, f.measured().matrix(), R.T @ R))
    return out


def audit(
    run_dir: Path, gt: Path, max_trans: float = 1.0, max_rot_deg: float = 3.0
) -> list[LoopCheck]:
    """Every loop edge of ``run_dir``/graph.g2o checked against ``gt``."""
    stamps = keyframe_stamps(run_dir / "loops.csv")
    gt_stamps, gt_poses = read_tum(gt)
    checks = []
    for a, b, T_meas, info in loop_edges(run_dir / "graph.g2o", loop_pairs(run_dir / "loops.csv")):
        if a not in stamps or b not in stamps:
            raise KeyError(f"loop edge {a} -> {b}: keyframe stamp not in loops.csv")
        Ta = gt_poses[nearest(gt_stamps, stamps[a])]
        Tb = gt_poses[nearest(gt_stamps, stamps[b])]
        T_true = np.linalg.solve(Ta, Tb)
        et, er, xi = pose_error(T_true, T_meas)
        cov = np.linalg.pinv(info)
        checks.append(
            LoopCheck(
                a, b, float(np.linalg.norm(T_true[:3, 3])), et, er, float(xi @ info @ xi),
                float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:]).max())),
                bool(et > max_trans or er > max_rot_deg),
            )
        )  # fmt: skip
    return checks


def summary(checks: list[LoopCheck]) -> dict:
    """loops, false, median / max constraint error (m)."""
    err = [c.err_trans for c in checks]
    return {
        "loops": len(checks),
        "false": sum(c.false for c in checks),
        "err_median_m": float(np.median(err)) if err else None,
        "err_max_m": float(np.max(err)) if err else None,
    }
