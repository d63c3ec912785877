"""The back-end contract: owns the factor graph; never sees point clouds."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import gtsam


@runtime_checkable
class Backend(Protocol):
    def update(
        self, factors: list[Any], initial: dict[int, gtsam.Pose3], loop_closed: bool = False
    ) -> None:
        """Add new factors and initial values of new keyframes (ids), then optimise.

        ``loop_closed`` asks for the configured extra iterations (after a loop factor).
        """
        ...

    def estimate(self) -> dict[int, gtsam.Pose3]:
        """Current estimate of every keyframe id."""
        ...

    def pose(self, kf_id: int) -> gtsam.Pose3:
        """Current estimate of one keyframe (cheap; raises KeyError if unknown)."""
        ...

    def finalize(self) -> dict[int, gtsam.Pose3]:
        """Final estimate (batch back ends optimise here)."""
        ...

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """All factors added so far (for the g2o export)."""
        ...
