"""What a run has computed so far, and why it stopped (written out even when it stops early)."""

from __future__ import annotations

import resource
import sys
from array import array
from collections import defaultdict
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from slam.io.stream import StreamStats
from slam.spread import spread_corrections
from slam.timing import StageTimer
from slam.types import Keyframe, Odometry

MEMORY_REFERENCE_FRAME = 100  # frames after which the map, models and kernels are warm


def peak_memory_mb() -> float:
    """Peak resident memory of this process in MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


class StopReason(Enum):
    """Why a run ended before its input did."""

    INTERRUPTED = "interrupted"  # Ctrl-C / SIGINT
    BAD_INPUT = "bad input"  # unreadable input, stamps gone wrong, --strict
    BACKEND_FAILED = "back end failed"  # an update the back end could not take


@dataclass(frozen=True)
class Stop:
    """A run's early end: its reason and what went wrong, in words for the user."""

    reason: StopReason
    detail: str = ""

    def __str__(self) -> str:
        if self.reason is StopReason.INTERRUPTED:
            return "interrupted (Ctrl-C)"
        return f"{self.reason.value}: {self.detail}"


@dataclass
class RunState:
    """Per-frame results, keyframes, counts and clocks of one run."""

    stamps: list[float] = field(default_factory=list)
    odom_poses: list[np.ndarray] = field(default_factory=list)
    frame_kf: list[int] = field(default_factory=list)
    T_kf_frame: list[np.ndarray] = field(default_factory=list)
    frame_spread: array = field(default_factory=lambda: array("d"))  # NaN: not given
    keyframes: list[Keyframe] = field(default_factory=list)
    factor_counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    diagnostic_sums: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    diagnostic_counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    timer: StageTimer = field(default_factory=StageTimer)
    backend_seconds: array = field(default_factory=lambda: array("d"))  # per keyframe, s
    path_length: float = 0.0  # odometric distance travelled (m), summed frame to frame
    # (peak memory MiB, path length m) after MEMORY_REFERENCE_FRAME frames: the growth of the
    # peak from there per km travelled is metrics.json's memory_mb_per_km
    memory_reference: tuple[float, float] | None = None
    skipped_frames: int = 0  # frames the front end could not register (prediction kept)
    degenerate_frames: int = 0
    loops_closed: int = 0  # loop factors in the graph
    loop_pairs: list[tuple[int, int]] = field(default_factory=list)  # their keyframe ids
    estimates: dict[int, np.ndarray] = field(default_factory=dict)
    wall_seconds: float = 0.0
    input: StreamStats = field(default_factory=StreamStats)  # what the input stream dropped
    stop: Stop | None = None

    @property
    def frames(self) -> int:
        return len(self.stamps)

    def stopped(self, reason: StopReason, detail: str = "") -> None:
        """Record why the run stops, unless an earlier cause is already recorded."""
        if self.stop is None:
            self.stop = Stop(reason, detail)

    @property
    def stopped_by(self) -> str | None:
        """Why the run stopped early, in words (None: it ran to the end of its input)."""
        return None if self.stop is None else str(self.stop)

    # the input stream's counts and the stage clocks, under the names metrics.json uses
    @property
    def skipped_messages(self) -> dict[str, int]:
        return self.input.skipped

    @property
    def messages_skipped(self) -> int:
        """Input messages dropped before the front end (damaged, duplicated, out of order)."""
        return int(sum(self.input.skipped.values()))

    @property
    def clock_steps(self) -> list[tuple[int, float]]:
        return self.input.clock_steps

    @property
    def sensor(self) -> str | None:
        return self.input.sensor

    @property
    def stage_seconds(self) -> dict[str, float]:
        return self.timer.seconds

    @property
    def stage_max_seconds(self) -> dict[str, float]:
        return self.timer.max_seconds

    @property
    def frame_seconds(self) -> array:
        return self.timer.frame_seconds

    @property
    def frame_cpu_seconds(self) -> array:
        return self.timer.frame_cpu_seconds

    @property
    def stage_frame_seconds(self) -> dict[str, array]:
        return self.timer.stage_frame_seconds

    @property
    def stage_frame_cpu_seconds(self) -> dict[str, array]:
        return self.timer.stage_frame_cpu_seconds

    def add_diagnostics(self, odom: Odometry) -> None:
        """Count and accumulate a frame's typed front-end diagnostics: skipped and
        degenerate frames, and the numbers of ``odom.flat()`` (counts, *_ms timings; bools
        are not averaged)."""
        d = odom.diagnostics
        if d is not None:
            self.skipped_frames += bool(d.skipped)
            self.degenerate_frames += bool(d.degenerate)
        for k, v in odom.flat().items():
            if (
                isinstance(v, (int, float, np.integer, np.floating))
                and not isinstance(v, bool)
                and np.isfinite(v)
            ):
                self.diagnostic_sums[k] += float(v)
                self.diagnostic_counts[k] += 1

    def diagnostic_means(self) -> dict[str, float]:
        """Per-frame mean of each numeric diagnostic over the frames that reported it."""
        return {k: self.diagnostic_sums[k] / n for k, n in self.diagnostic_counts.items() if n}

    def trajectory(self) -> np.ndarray:
        """(N,4,4) optimised pose of every frame: keyframe estimate composed with T_kf_frame;
        between keyframes whose frames all report a spread, the change of correction
        spread over them (``slam.spread``)."""
        if not self.stamps:
            return np.zeros((0, 4, 4))
        n = len(self.stamps)
        spread = np.asarray(self.frame_spread[:n], dtype=np.float64)
        if not np.isfinite(spread).any():
            kf_poses = np.stack([self.estimates[k] for k in self.frame_kf[:n]])
            return kf_poses @ np.stack(self.T_kf_frame[:n])
        frame_kf = np.asarray(self.frame_kf[:n])
        ids, first = np.unique(frame_kf, return_index=True)  # a keyframe's own frame
        kf_frames = dict(zip(ids.tolist(), first.tolist(), strict=True))
        odom = np.stack(self.odom_poses[:n])
        return spread_corrections(odom, frame_kf, kf_frames, self.estimates, spread)
