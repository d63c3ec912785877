"""Whether clouds stored beam by beam without a time field are motion-compensated.

KITTI (and every bag converted from it) publishes its scans compensated; an Ouster driver
that leaves out the time field does not, and at 12 m/s its scans are then smeared by up to
1.2 m. The layout gives made-up per-point times either way (``Scan.layout_time``); which
reading is right shows in the registration: at speed, the scan is registered as it is and
deskewed with the made-up times. The deskewed reading wins a frame when it fits the map
clearly better (RMSE at least ``min_gain`` lower) and loses it when it fits worse by
``max_loss``; in between the frame does not count (at low speed the smear is within the
noise: KITTI at 3-5 m/s differs by 1-3 %). ``margin`` more wins than losses (or losses than
wins) decide for the rest of the run; until then, and after ``trials`` compared frames
without a decision, the scans are read as compensated, unless the deskewed reading clearly
won that frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from slam.errors import ConfigError
from slam.types import Scan

log = logging.getLogger(__name__)


@dataclass
class LayoutTimeConfig:
    """trials: frames at speed compared at most (0 = never deskew with made-up times);
    min_step (m): the tracked motion per frame from which they are compared (0.3 m = 3 m/s
    at 10 Hz: up to 30 cm of smear); min_gain / max_loss: the RMSE ratio 1 - min_gain /
    1 + max_loss that makes a frame a win / a loss of the deskewed reading; margin: wins
    minus losses (either way) that decide (measured: OS-128 without ``t`` 0.91-0.98, real
    KITTI 04 at 14 m/s 1.06-1.12, KITTI 05 from standstill 0.97-1.02)."""

    trials: int = 20
    min_step: float = 0.3
    min_gain: float = 0.05
    max_loss: float = 0.02
    margin: int = 3

    def __post_init__(self) -> None:
        if self.trials < 0 or self.min_step <= 0 or self.margin < 1:
            raise ConfigError("layout_time needs trials >= 0, min_step > 0 m and margin >= 1")
        if not 0 <= self.min_gain < 1 or self.max_loss < 0:
            raise ConfigError("layout_time min_gain must be in [0, 1) and max_loss >= 0")


class LayoutTimeTrial:
    """The votes of the frames compared so far and, once made, the decision."""

    def __init__(self, cfg: LayoutTimeConfig):
        self.cfg = cfg
        self.votes: list[int] = []  # +1 / -1: the deskewed reading fitted clearly better / worse
        self.deskew: bool | None = None if cfg.trials else False

    def due(self, scan: Scan, step_m: float | None) -> bool:
        """Whether to compare both readings on ``scan``: it carries made-up times, no
        decision yet and the tracked motion per frame is at least ``min_step``."""
        return (
            scan.layout_time is not None
            and self.deskew is None
            and step_m is not None
            and step_m >= self.cfg.min_step
        )

    def timed(self, scan: Scan) -> Scan:
        """``scan`` with its made-up times as the time field."""
        return replace(scan, time=scan.layout_time, layout_time=None)

    def reading(self, scan: Scan) -> Scan:
        """``scan`` as the decision so far reads it: its made-up times as the time field
        once the clouds are known not to be compensated, else as it is."""
        if scan.layout_time is None or not self.deskew:
            return scan
        return self.timed(scan)

    def vote(self, plain_rmse: float, timed_rmse: float, index: int) -> bool:
        """Record one frame's comparison; returns whether this frame reads the scan
        deskewed (the deskewed reading clearly won it)."""
        cfg = self.cfg
        won = bool(np.isfinite(timed_rmse) and timed_rmse <= (1 - cfg.min_gain) * plain_rmse)
        lost = not won and not timed_rmse < (1 + cfg.max_loss) * plain_rmse
        self.votes.append(1 if won else -1 if lost else 0)
        net = sum(self.votes)
        if abs(net) >= cfg.margin or len(self.votes) >= cfg.trials:
            self.deskew = net >= cfg.margin
            log.info(
                "frame %d: beam-by-beam clouds without a time field are %s (deskewed with "
                "times from the azimuth: %d frames fitted clearly better, %d worse, of %d)",
                index,
                "not motion-compensated: deskewing them" if self.deskew else "motion-compensated",
                self.votes.count(1),
                self.votes.count(-1),
                len(self.votes),
            )
        return won
