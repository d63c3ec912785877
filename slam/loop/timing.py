"""Wall and CPU time (ms) of the loop closure's two stages per keyframe, for metrics.json."""

from __future__ import annotations

import time

import numpy as np


class LoopTimes:
    """detect: descriptor + candidate search; verify: everything after it (0 without
    candidates). CPU time is this process's: a worker's verification is not in it."""

    def __init__(self) -> None:
        self.detect_ms: list[float] = []  # per keyframe: descriptor + search
        self.verify_ms: list[float] = []  # per keyframe with candidates: all of verification
        self.verify_ms_by_keyframe: list[float] = []  # per keyframe, 0 without candidates
        self.detect_cpu_ms: list[float] = []  # the same two in CPU ms of this process
        self.verify_cpu_ms: list[float] = []
        self._t, self._c = 0.0, 0.0

    def start(self) -> None:
        self._t, self._c = time.perf_counter(), time.process_time()

    def detected(self) -> None:
        """End of detection (and start of verification)."""
        self.detect_ms.append(1e3 * (time.perf_counter() - self._t))
        self.detect_cpu_ms.append(1e3 * (time.process_time() - self._c))
        self.start()

    def verified(self, had_candidates: bool) -> None:
        ms = 1e3 * (time.perf_counter() - self._t)
        if had_candidates:
            self.verify_ms.append(ms)
        self.verify_ms_by_keyframe.append(ms)
        self.verify_cpu_ms.append(1e3 * (time.process_time() - self._c))

    def means(self) -> dict[str, float]:
        """Mean and max detection, mean verification per keyframe with candidates, and
        verification spread over all keyframes (what it adds to the keyframe rate)."""
        n = len(self.detect_ms)
        total = float(np.sum(self.verify_ms)) if self.verify_ms else 0.0
        return {
            "detect_ms_mean": float(np.mean(self.detect_ms)) if n else 0.0,
            "detect_ms_max": float(np.max(self.detect_ms)) if n else 0.0,
            "verify_ms_mean": float(np.mean(self.verify_ms)) if self.verify_ms else 0.0,
            "verify_ms_per_keyframe": total / n if n else 0.0,
        }

    def windows(self) -> dict[str, float]:
        """*_first100 / *_last100: mean per keyframe over the first / last 100 keyframes
        (does detection or verification grow with the run?), wall and *_cpu_* CPU ms."""
        out = {}
        for name, series in (
            ("detect", self.detect_ms),
            ("verify", self.verify_ms_by_keyframe),
            ("detect_cpu", self.detect_cpu_ms),
            ("verify_cpu", self.verify_cpu_ms),
        ):
            if series:
                out[f"{name}_ms_first100"] = float(np.mean(series[:100]))
                out[f"{name}_ms_last100"] = float(np.mean(series[-100:]))
        return out
