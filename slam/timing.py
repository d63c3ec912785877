"""Stage clocks of a run: ``with timer("frontend"): ...`` books wall and CPU seconds.

Inside a frame (``with timer.frame():``) a stage is booked three ways: its run total, its
slowest single call and its share of this frame (a per-frame series aligned with the frame
times, 0 on frames where it did not run), so that metrics.json can say which stage grows
from the start of a run to its end. Outside a frame (final flush, map) only the total is
booked. A stage whose block raises is not booked.
"""

from __future__ import annotations

import time
from array import array
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager


class Lap:
    """One timed block: ``wall`` and ``cpu`` seconds (this process, all its threads) once
    it has ended; booked under ``stage`` (None: measured only, see :meth:`StageTimer.measure`).
    ``plus``: an earlier lap counted as part of this one."""

    __slots__ = ("_c0", "_t0", "_timer", "cpu", "stage", "wall")

    def __init__(self, timer: StageTimer, stage: str | None, plus: Lap | None = None) -> None:
        self._timer, self.stage = timer, stage
        self.wall, self.cpu = (plus.wall, plus.cpu) if plus is not None else (0.0, 0.0)
        self._t0 = self._c0 = 0.0

    def __enter__(self) -> Lap:
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.wall += time.perf_counter() - self._t0
        self.cpu += time.process_time() - self._c0
        if exc_type is None and self.stage is not None:
            self._timer.add(self.stage, self.wall, self.cpu)
        return False


class StageTimer:
    """Seconds per stage of a run (wall and CPU), in total, at most and per frame."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)  # wall s per stage, whole run
        self.max_seconds: dict[str, float] = defaultdict(float)  # slowest call in a frame
        # wall / CPU s of every frame (8 bytes an entry: runs of 100k frames stay small)
        self.frame_seconds = array("d")
        self.frame_cpu_seconds = array("d")
        # per stage, its wall / CPU s in each frame, aligned with frame_seconds
        self.stage_frame_seconds: dict[str, array] = {}
        self.stage_frame_cpu_seconds: dict[str, array] = {}
        self._in_frame = False
        self._frame: dict[str, float] = {}  # wall / CPU s per stage in the open frame
        self._frame_cpu: dict[str, float] = {}

    def __call__(self, stage: str, *, plus: Lap | None = None) -> Lap:
        """A context manager that books its block under ``stage`` (with ``plus`` added)."""
        return Lap(self, stage, plus)

    def measure(self) -> Lap:
        """A context manager that measures its block without booking it (to add later)."""
        return Lap(self, None)

    def add(self, stage: str, wall: float, cpu: float = 0.0) -> None:
        """Book ``wall`` / ``cpu`` seconds under ``stage`` (see the module doc)."""
        self.seconds[stage] += wall
        if not self._in_frame:
            return
        self.max_seconds[stage] = max(self.max_seconds[stage], wall)
        self._frame[stage] = self._frame.get(stage, 0.0) + wall
        self._frame_cpu[stage] = self._frame_cpu.get(stage, 0.0) + cpu

    @contextmanager
    def frame(self) -> Iterator[None]:
        """Time one frame; on a normal exit its time and its stages' are appended (a frame
        that raised leaves no entry)."""
        t0, c0 = time.perf_counter(), time.process_time()
        self._in_frame = True
        try:
            yield
            self.frame_seconds.append(time.perf_counter() - t0)
            self.frame_cpu_seconds.append(time.process_time() - c0)
            self._close_frame()
        finally:
            self._in_frame = False
            self._frame, self._frame_cpu = {}, {}

    def _close_frame(self) -> None:
        """Append this frame's seconds to every stage's series (0 for a stage that did not
        run; a stage seen for the first time gets 0 on the earlier frames)."""
        n = len(self.frame_seconds)
        for per_frame, out in ((self._frame, self.stage_frame_seconds),
                               (self._frame_cpu, self.stage_frame_cpu_seconds)):  # fmt: skip
            for stage in per_frame:
                if stage not in out:
                    out[stage] = array("d", bytes(8 * (n - 1)))
            for stage, series in out.items():
                series.append(per_frame.get(stage, 0.0))
