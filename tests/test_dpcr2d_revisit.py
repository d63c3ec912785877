"""DPCR-SLAM front end on revisits (frontends/dpcr2d.py, ``revisit_search``): a robot that
comes back to a mapped region 12 deg / metres off (beyond the second registration's
basin) is moved back onto the region's map by the wide search, so that it does not draw
the region's walls a second time."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2d, Dpcr2dConfig
from slam.mapping.grid2d import compose2d, inverse2d, wrap
from slam.sim.floorplan2d import simulate2d
from slam.types import Scan


@pytest.fixture(scope="module")
def lap():
    """1.25 laps of the rooms at 2 m/s with exact wheel odometry."""
    return simulate2d("rooms2d", frames=250, speed=2.0, seed=7)


def _run(seq, cfg: Dpcr2dConfig, drift_at: int, drift: np.ndarray):
    """Front-end poses in the truth's frame; at ``drift_at`` the robot and its submap are
    moved by ``drift`` (a rotation about the robot and a shift): the state a real
    robot is in after a long stretch of heading drift."""
    fe = Dpcr2d(cfg)
    T0 = seq.poses[0]
    out = []
    for k in range(len(seq.stamps)):
        if k == drift_at:
            about = np.array([*fe.pose[:2], 0.0])
            fe._move(compose2d(compose2d(about, drift), inverse2d(about)))
        pts = seq.points(k)
        scan = Scan(float(seq.stamps[k]), np.column_stack([pts, np.zeros(len(pts))]),
                    odom=seq.poses[k].copy())  # fmt: skip
        fe.process(scan)
        out.append(compose2d(T0, fe.pose))
    return np.array(out), fe


def test_a_drifted_revisit_is_moved_back_onto_the_regional_map(lap):
    drift = np.array([0.3, 0.0, np.radians(12.0)])
    poses, fe = _run(lap, Dpcr2dConfig(), 80, drift)
    err = np.linalg.norm(poses[:, :2] - lap.poses[:, :2], axis=1)
    assert err[:80].max() < 0.05  # before the drift: tracking
    assert np.median(err[85:150]) > 0.5  # drifted: new regions drawn in the drifted frame
    assert fe.counts["reanchored"] >= 1
    back = np.flatnonzero(err[150:] < 0.05)
    assert len(back), err[150:].min()
    first = 150 + back[0]
    # once back on the map it stays there: within 5 cm and 0.3 deg of the truth
    assert err[first:].max() < 0.05, (first, err[first:].max())
    dth = np.degrees(np.abs(wrap(poses[first:, 2] - lap.poses[first:, 2])))
    assert dth.max() < 0.3
