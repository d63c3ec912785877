"""Map points a second scan confirms: what moves between two scans stays out of the map.

A vehicle's points inserted into a scan-to-map odometry's map pair, one scan later, with the
same vehicle moved on: the registration is pulled towards moving with it. On an open road,
where the traffic is a large share of what the sensor sees, two oncoming 12 m trucks pulled
a simulated HDL-32E motorway drive 0.2 m short per frame for five frames (docs/robustness.md,
"Traffic on an open road"). A static surface sampled again from the next pose lies within
the sample spacing of its first samples; a vehicle at 10 m/s is 1 m on at 10 Hz. So a point
enters the map only when the previous inserted scan had a point within ``distance`` m
horizontally and ``height`` m vertically (a beam meets a vertical surface at another height
once the range changed). The ground is exempt: its rings move with the sensor, and as a
plane it constrains height, roll and pitch only.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def seen_before(
    points: np.ndarray, previous: np.ndarray, distance: float, height: float
) -> np.ndarray:
    """(N,) whether each of ``points`` (N, 3, m) has one of ``previous`` (M, 3) within
    ``distance`` m horizontally and ``height`` m along z (a scaled-z ball, a little
    stricter than that cylinder at its rim)."""
    if not len(points) or not len(previous):
        return np.zeros(len(points), dtype=bool)
    scale = np.array([1.0, 1.0, distance / height])
    # scipy's unbalanced build is the cheapest for one query per point (slam.preprocess.knn)
    tree = cKDTree(previous * scale, leafsize=16, balanced_tree=False, compact_nodes=False)
    d, _ = tree.query(points * scale, k=1, distance_upper_bound=distance)
    return np.isfinite(d)


class SecondSighting:
    """The previous inserted scan's points (odometry frame), and which of a new scan's
    points it confirms. ``reset`` forgets it (e.g. when the map is no longer the one those
    points went into); the first scan after a reset is kept whole."""

    def __init__(self, distance: float, height: float):
        self.distance = distance
        self.height = height
        self._previous: np.ndarray | None = None

    def reset(self) -> None:
        self._previous = None

    def keep(self, points: np.ndarray, exempt: np.ndarray) -> np.ndarray:
        """(N,) which of ``points`` (N, 3, odometry frame) go into the map: those the
        previous scan confirms and the ``exempt`` ones (N,) bool; all of them after a reset.
        The non-exempt points are remembered for the next scan."""
        previous, self._previous = self._previous, points[~exempt]
        if previous is None:
            return np.ones(len(points), dtype=bool)
        return exempt | seen_before(points, previous, self.distance, self.height)
