"""A simulated 2D scan pair for the dpcr2d registration-step tests: the submap of office2d
scan 10, scan 14 and their true relative pose, and a pose's error against it."""

from __future__ import annotations

import numpy as np

from slam.eval.self_relations import scan_reference
from slam.mapping.grid2d import compose2d, inverse2d
from slam.registration.plicp import LineReference
from slam.sim.floorplan2d import simulate2d


def office_pair() -> tuple[LineReference, np.ndarray, np.ndarray]:
    """(reference of scan 10 at 5 cm, scan 14's points, the true pose of 14 in 10's frame)."""
    seq = simulate2d("office2d", frames=40, speed=1.0)
    a, b = seq.points(10), seq.points(14)
    truth = compose2d(inverse2d(seq.poses[10]), seq.poses[14])
    return scan_reference(a, 0.05), b, truth


def pose_error(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (m) and heading (deg) error of the 2D ``pose`` against ``truth``."""
    e = compose2d(inverse2d(truth), pose)
    return float(np.hypot(e[0], e[1])), abs(float(np.degrees(e[2])))
