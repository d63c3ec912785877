"""Data passed between the stages of the pipeline.

Conventions: arrays are float64, points (N, 3) in the sensor frame unless the
name says otherwise; poses are 4x4 homogeneous matrices named ``T_target_source``
(``T_odom_sensor`` maps sensor-frame points into the odometry frame).
Information matrices are 6x6 in GTSAM's tangent ordering: rotation first
(rx, ry, rz), then translation (tx, ty, tz).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Scan:
    """One sensor sweep.

    stamp: header time in seconds. xyz: (N, 3) float64, finite. intensity: (N,)
    float32 or None. ring: (N,) int16 beam index or None. time: (N,) float64
    seconds from the start of the sweep (>= 0) or None when the driver gives none.
    odom: the robot's wheel odometry at the stamp, (x, y, theta) in m and rad in the
    odometry's own frame, when the input carries it (2D laser logs), else None.
    """

    stamp: float
    xyz: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None
    time: np.ndarray | None = None
    index: int = 0
    odom: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def select(self, mask: np.ndarray) -> Scan:
        """A new scan holding only the points where ``mask`` (bool or index array) selects."""
        return Scan(
            stamp=self.stamp,
            xyz=self.xyz[mask],
            intensity=None if self.intensity is None else self.intensity[mask],
            ring=None if self.ring is None else self.ring[mask],
            time=None if self.time is None else self.time[mask],
            index=self.index,
            odom=self.odom,
        )


@dataclass(frozen=True)
class SkippedMessage:
    """A message or file of the input that could not be made into a Scan; the run goes on.

    Readers yield it in place of the Scan. index: the message/file index. reason: a short
    category used to count skips (e.g. "corrupt message", "no finite points", "bad field
    datatype"). detail: the full explanation for the one warning line.
    """

    index: int
    reason: str
    detail: str


@dataclass
class Odometry:
    """What a front end returns for one scan.

    pose: T_odom_sensor at the scan stamp. relative: T_prevkf_current, the motion since
    the previous keyframe (identity for the first frame). info: 6x6 information of
    ``relative`` (rotation first), scaled to a plausible covariance. cloud: the scan's
    points in the sensor frame after deskew/filtering (voxel-thinned), kept by the pipeline
    for keyframes (float32 is stored as given; other dtypes are converted once); front
    ends may leave it empty on other frames.
    extras: diagnostics (feature counts, iterations, fitness, degenerate, ...).
    """

    stamp: float
    pose: np.ndarray
    is_keyframe: bool
    relative: np.ndarray
    info: np.ndarray
    cloud: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass
class Keyframe:
    """A keyframe as the factor plugins see it.

    id: 0, 1, 2, ... in order. frame_index: index of the input scan. pose_odom:
    T_odom_sensor from the front end. relative/info: motion from the previous keyframe and
    its information (None/identity for id 0). cloud: (N, 3) sensor-frame points, m; the
    pipeline stores it once, float32, voxel-thinned and read-only (the one copy of the run:
    plugins read it through ``GraphView.cloud`` instead of copying it). extras: the front
    end's scalar diagnostics of that frame (no arrays).
    """

    id: int
    stamp: float
    frame_index: int
    pose_odom: np.ndarray
    relative: np.ndarray
    info: np.ndarray
    cloud: np.ndarray
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass
class LoopConstraint:
    """An accepted or rejected loop candidate between two keyframes.

    T_target_source maps the source keyframe's sensor frame into the target's.
    """

    source: int
    target: int
    T_target_source: np.ndarray
    score: float
    fitness: float
    accepted: bool
    info: np.ndarray | None = None
    reason: str = ""
