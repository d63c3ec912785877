"""Shared fixtures: simulated sequences (generated once, cached; see slam.sim.cache).

Short sequences (60 frames, ~6 s of driving) for fast tests; full ones (one lap and a
revisit of the start) for end-to-end runs; short urban pieces with the 64- and 128-beam
sensors (see slam.sim.sensors). The cache lives in $SLAM_CACHE/sim or
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


@pytest.fixture(scope="session")
def urban_short() -> SimResult:
    """60 frames of the car-speed urban drive (VLP-16 with realistic errors): 1 s at a
    standstill, then accelerating at 1.5 m/s^2 to ~7.5 m/s (~20 m)."""
    return ensure_sequence("urban", frames=SHORT_FRAMES)


@pytest.fixture(scope="session")
def urban_hdl64_short() -> SimResult:
    """30 frames of the urban drive with the KITTI-style HDL-64E (~130k points per scan,
    x y z intensity only: no ring, no per-point time)."""
    return ensure_sequence("urban", frames=30, sensor="hdl64")


@pytest.fixture(scope="session")
def urban_os128_short() -> SimResult:
    """30 frames of the urban drive with the Ouster OS1-128 (~120k points per scan, `t` in
    ns, 48-byte points, ring 0 = top beam, row-major)."""
    return ensure_sequence("urban", frames=30, sensor="os128")


@pytest.fixture(scope="module")
def evo_home(tmp_path_factory):
    """evo writes ~/.evo on its first import: a module using evo's plots gets its own HOME."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HOME", str(tmp_path_factory.mktemp("home")))
        yield
