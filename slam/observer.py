"""Watching a run as it goes (a live viewer, a recorder): the :class:`RunObserver` hooks.

``SlamSystem(..., observers=[...])`` calls every observer's hooks in the order given; with
none nothing is called and nothing is computed for them. An observer that raises is
dropped with one warning: a viewer must never lose the run.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from slam.types import Odometry, Scan

log = logging.getLogger(__name__)


@runtime_checkable
class RunObserver(Protocol):
    """Hooks called by the SLAM system while it runs (all poses 4x4 T_world_sensor, m)."""

    def on_frame(self, index: int, scan: Scan, odom: Odometry) -> None:
        """Every processed frame (``index`` 0, 1, ... in the run); ``odom.pose`` is the
        front end's world pose."""

    def on_keyframe(
        self, kf_id: int, frame_index: int, pose: np.ndarray, cloud: np.ndarray
    ) -> None:
        """A new keyframe at the front end's pose; ``cloud``: its stored (N, 3) float32
        sensor-frame points (read-only, shared: copy to keep)."""

    def on_loop(self, kf_a: int, kf_b: int) -> None:
        """An accepted loop factor between keyframes ``kf_a`` and ``kf_b``."""

    def on_optimised(self, poses: dict[int, np.ndarray]) -> None:
        """Keyframe id -> optimised pose, after each back-end update and once at the end."""

    def close(self) -> None:
        """The run is over (called once, also when it stopped early)."""


class Observers:
    """The observers of one run, called in turn; false when there are none."""

    def __init__(self, observers: Sequence[RunObserver] = ()) -> None:
        self._all = list(observers)

    def __bool__(self) -> bool:
        return bool(self._all)

    def _call(self, hook: str, *args: object) -> None:
        for observer in list(self._all):
            try:
                getattr(observer, hook)(*args)
            except Exception as exc:  # noqa: BLE001 - a viewer must not lose the run
                log.warning("run observer %s failed in %s (%s): dropped", observer, hook, exc)
                self._all.remove(observer)

    def on_frame(self, index: int, scan: Scan, odom: Odometry) -> None:
        self._call("on_frame", index, scan, odom)

    def on_keyframe(
        self, kf_id: int, frame_index: int, pose: np.ndarray, cloud: np.ndarray
    ) -> None:
        self._call("on_keyframe", kf_id, frame_index, pose, cloud)

    def on_loop(self, kf_a: int, kf_b: int) -> None:
        self._call("on_loop", kf_a, kf_b)

    def on_optimised(self, poses: dict[int, np.ndarray]) -> None:
        self._call("on_optimised", poses)

    def close(self) -> None:
        self._call("close")
