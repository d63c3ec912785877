"""The raw points of the last few 2D scans, kept where the robot moved: the reference of
a fine scan-to-scans registration (``slam.registration.local_lines2d``).

A scan joins only when the robot is at least ``min_move`` m or ``min_turn_deg`` from
where the newest one was taken: scans from one place add no geometry, only the
registration's own noise fed back (a robot standing still would drift on its own
scans, and a person walking past would be followed).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slam.errors import ConfigError
from slam.mapping.grid2d import compose2d, inverse2d, transform2d
from slam.registration.local_lines2d import LocalLineConfig, local_line_reference, thin
from slam.registration.plicp import LineReference


@dataclass
class ScanWindowConfig:
    """scans: how many scans the window holds (0: no window); min_move (m) /
    min_turn_deg: a scan joins when the robot moved or turned this much since the newest;
    lines: the local lines fitted to the window's points (each scan thinned to
    ``lines.voxel`` first)."""

    scans: int = 0
    min_move: float = 0.05
    min_turn_deg: float = 2.0
    lines: LocalLineConfig = field(default_factory=LocalLineConfig)

    def __post_init__(self) -> None:
        if self.scans < 0 or self.min_move < 0 or self.min_turn_deg < 0:
            raise ConfigError("scan window: scans, min_move and min_turn_deg must be >= 0")


class ScanWindow:
    """The window: thinned scan points (own frame) with their poses (x, y, theta, map
    frame); the local-line reference of all of them in the map frame, fitted again when
    the window changes or moves (lines through the points of several scans)."""

    def __init__(self, cfg: ScanWindowConfig):
        self.cfg = cfg
        self.scans: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(cfg.scans, 1))
        self._ref: LineReference | None = None

    def __len__(self) -> int:
        return len(self.scans)

    def add(self, points: np.ndarray, pose: np.ndarray) -> bool:
        """Add scan ``points`` (N, 2, own frame) taken at ``pose`` when the robot moved
        enough since the newest scan; True when it joined."""
        pose = np.asarray(pose, dtype=np.float64)
        if self.scans:
            step = compose2d(inverse2d(self.scans[-1][1]), pose)
            if (
                np.hypot(step[0], step[1]) < self.cfg.min_move
                and abs(np.degrees(step[2])) < self.cfg.min_turn_deg
            ):
                return False
        self.scans.append((thin(np.asarray(points, dtype=np.float64), self.cfg.lines.voxel), pose))
        self._ref = None
        return True

    def move(self, delta: np.ndarray) -> None:
        """Move every scan by the map-frame correction ``delta`` (x, y, theta)."""
        self.scans = deque(((p, compose2d(delta, q)) for p, q in self.scans),
                           maxlen=self.scans.maxlen)  # fmt: skip
        self._ref = None

    def reference(self) -> LineReference | None:
        """The window's points (map frame) with their local lines; None when empty."""
        if self._ref is None and self.scans:
            pts = np.vstack([transform2d(q, p) for p, q in self.scans])
            self._ref = local_line_reference(pts, self.cfg.lines)
        return self._ref
