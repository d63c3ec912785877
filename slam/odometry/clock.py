"""The sensor's sweep clock: how long the sensor moved between two header stamps."""

from __future__ import annotations

from collections import deque

import numpy as np


def off_duration(ratio: float) -> bool:
    """Whether a frame gap ``ratio`` times the motion model's duration is a different
    duration (a dropped message, a burst) rather than stamp jitter: outside [2/3, 3/2]."""
    return not 2.0 / 3.0 <= ratio <= 1.5


class SweepClock:
    """The recent stamp gaps of a spinning LiDAR and the last stamp seen.

    A spinning LiDAR's scans are whole turns: a gap of 1.4 periods is one period and a late
    stamp (driver stamps jitter by tens of ms), not 1.4 periods of motion.
    """

    def __init__(self, history: int = 100):
        self.gaps: deque[float] = deque(maxlen=history)  # recent stamp gaps (s)
        self.last_stamp: float | None = None

    def observe(self, stamp: float) -> None:
        """Record the stamp (s) of a processed frame."""
        if self.last_stamp is not None and stamp > self.last_stamp:
            self.gaps.append(float(stamp) - self.last_stamp)
        self.last_stamp = float(stamp)

    def period(self) -> float | None:
        """The sweep period (s): the span of the recent gaps over the sweeps they hold (each
        gap rounded to whole multiples of their median), robust to dropped messages and to
        jitter (the median alone is ~3 % off under +-20 ms). None before any gap."""
        if not self.gaps:
            return None
        gaps = np.asarray(self.gaps)
        sweeps = np.maximum(1.0, np.round(gaps / np.median(gaps)))
        return float(gaps.sum() / sweeps.sum())

    def duration(self, t0: float | None, t1: float) -> float | None:
        """Time (s) the sensor moved between the scans stamped ``t0`` and ``t1`` (None when
        ``t1`` is not after ``t0``): the gap rounded to a whole number (>= 1) of sweep
        periods. Until three gaps give the period, and for a gap within 1e-4 periods of a
        whole number of them (exact stamps), the gap as it is."""
        if t0 is None or not t1 > t0:
            return None
        gap = float(t1) - float(t0)
        if len(self.gaps) < 3:
            return gap
        period = self.period()
        whole = max(1.0, float(np.round(gap / period))) * period
        return gap if abs(gap - whole) <= 1e-4 * period else whole

    def since_last(self, stamp: float) -> float | None:
        """``duration`` from the last processed frame to ``stamp``."""
        return self.duration(self.last_stamp, stamp)
