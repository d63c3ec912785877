"""Shared fixtures: simulated sequences (generated once, cached; see slam.sim.cache).

Short sequences (60 frames, ~6 s of driving) for fast tests; full ones (one lap and a
revisit of the start) for end-to-end runs. The cache lives in $SLAM_CACHE/sim or
~/.cache/pyslam-graph/sim, so only the first test session pays for the simulation.
"""

from __future__ import annotations

import pytest

from slam.sim import SimResult, ensure_sequence

SHORT_FRAMES = 60


@pytest.fixture(scope="session")
def corridor_short() -> SimResult:
    """60 frames of the indoor corridor (ROS1 bag + ground truth), pedestrians on."""
    return ensure_sequence("corridor", frames=SHORT_FRAMES)


@pytest.fixture(scope="session")
def plaza_short() -> SimResult:
    """60 frames of the outdoor plaza (ROS1 bag + ground truth), pedestrians on."""
    return ensure_sequence("plaza", frames=SHORT_FRAMES)


@pytest.fixture(scope="session")
def corridor_full() -> SimResult:
    """The whole corridor drive (~1.1 laps, ~600 frames): loop closure is testable."""
    return ensure_sequence("corridor")


@pytest.fixture(scope="session")
def plaza_full() -> SimResult:
    """The whole plaza drive (~1.1 laps, ~750 frames)."""
    return ensure_sequence("plaza")
