"""Which trusted scans enter the local map: only once the sensor moved.

A standing sensor's scans sample the same spots on the same rays; in the map the k
neighbours of a point become repeated samples of one ray (a covariance along the ray),
registration snaps departing scans back onto them and the gate's normal learns a fitness
no moving scan has.
"""

from __future__ import annotations

import numpy as np

from slam.odometry.config import CommonConfig
from slam.registration.plausibility import motion_magnitude


class MapInsertPolicy:
    """The pose of the last scan put in the map and the motion needed for the next one
    (``map_min_translation`` m / ``map_min_rotation_deg`` deg)."""

    def __init__(self, cfg: CommonConfig):
        self._c = cfg
        self.T_inserted: np.ndarray | None = None

    def wants(self, pose: np.ndarray) -> bool:
        """Whether a trusted scan at ``pose`` is far enough from the last one inserted."""
        if self.T_inserted is None:
            return True
        t, r = motion_magnitude(np.linalg.inv(self.T_inserted) @ pose)
        return t >= self._c.map_min_translation or r >= self._c.map_min_rotation_deg

    def inserted(self, pose: np.ndarray) -> None:
        """The scan at ``pose`` entered the map."""
        self.T_inserted = pose.copy()
