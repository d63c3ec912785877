"""A stalled wheel odometry (``Dpcr2dConfig.stale_wheels``): readings that repeat the last
one exactly carry no motion, and the catch-up step after them is the stall's whole motion,
of which the scans already registered all but the last step."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2d
from frontends.dpcr2d_config import Dpcr2dConfig
from slam.mapping.grid2d import (
    StaleWheels,
    compose2d,
    inverse2d,
    matrix_to_pose2,
    stale_parts,
    wheel_step,
)
from slam.sim.floorplan2d import simulate2d
from slam.types import Scan


def _stalled(since: np.ndarray, a: np.ndarray, parts: str) -> StaleWheels:
    stale = StaleWheels()
    stale.update(a, False, False)
    stale.registered(since, "xy" in parts, "heading" in parts)
    return stale


def test_a_stall_s_catch_up_is_not_counted_twice():
    """MIT-CSAIL's scans 320 - 325 (4 stale readings): the wheels report 0.85 m / 49.7 deg
    at once, the scans registered 0.64 m / 44 deg meanwhile; the step is what is left."""
    a = np.array([1.0, 2.0, 0.3])
    stall = np.array([0.6, 0.1, np.radians(44.0)])  # registered while the wheels repeated a
    last = np.array([0.17, 0.0, np.radians(10.0)])  # the step to this scan
    motion = np.array([0.16, 0.0, np.radians(11.0)])  # the robot's last step
    odom = compose2d(a, compose2d(stall, last))
    step, xy, heading = wheel_step(a, odom, motion, _stalled(stall, a, "xy heading"), 0.1,
                                   np.radians(5.0))  # fmt: skip
    assert xy and heading and np.allclose(step, last, atol=1e-12)
    # the position alone stalled (the heading kept updating: MIT-CSAIL's scans 554 - 556)
    prev = np.array([1.0, 2.0, 0.3 + stall[2]])
    step, xy, heading = wheel_step(prev, odom, motion, _stalled(stall, a, "xy"), 0.1, 0.1)
    assert xy and not heading and np.allclose(step, last, atol=1e-12)
    # no stale reading: the plain step
    step, xy, heading = wheel_step(a, odom, motion, StaleWheels(), 0.1, 0.1)
    assert not (xy or heading) and np.allclose(step, compose2d(stall, last), atol=1e-12)


def test_a_turn_on_the_spot_is_not_a_stall():
    """The position repeats while the robot turns on the spot (FR079's scans 1440 - 1442),
    and the scans registered 3 cm of the laser's own swing meanwhile: the robot then
    moves off by 1 cm, as the plain step says, not 3 cm back."""
    a = np.array([1.0, 2.0, 0.3])
    turned = np.array([0.03, 0.0, np.radians(24.0)])
    odom = compose2d(a + [0.0, 0.0, turned[2]], np.array([0.01, 0.0, np.radians(8.0)]))
    prev = a + [0.0, 0.0, turned[2]]
    motion = np.array([0.0, 0.0, np.radians(8.0)])
    step, xy, heading = wheel_step(prev, odom, motion, _stalled(turned, a, "xy"), 0.1,
                                   np.radians(5.0))  # fmt: skip
    assert not xy and not heading
    assert np.allclose(step, compose2d(inverse2d(prev), odom), atol=1e-12)


def test_stale_parts():
    a = np.array([1.0, 2.0, 0.3])
    assert stale_parts(a, a.copy()) == (True, True)
    assert stale_parts(a, a + [0.0, 0.0, 1e-9]) == (True, False)
    assert stale_parts(a, a + [1e-9, 0.0, 0.0]) == (False, True)
    assert stale_parts(None, a) == (False, False)


@pytest.fixture(scope="module")
def office():
    return simulate2d("office2d", frames=110, speed=1.0)  # 10 Hz, a 70 deg turn at 80-89


def _end_error(seq, stale_wheels: bool, stall: int, parts=slice(0, 3)) -> tuple[float, float]:
    """(m, deg) off the true motion from the first to the last scan, with perfect wheels
    whose reading (``parts`` of it) repeats for ``stall`` scans from scan 82 (mid-turn),
    then catches up."""
    odom = seq.poses.copy()
    odom[82 : 82 + stall, parts] = odom[81, parts]
    fe, est = Dpcr2d(Dpcr2dConfig(stale_wheels=stale_wheels)), []
    for k in range(len(seq.stamps)):
        p = seq.points(k)
        xyz = np.column_stack([p, np.zeros(len(p))]).astype(np.float32)
        out = fe.process(Scan(stamp=float(seq.stamps[k]), xyz=xyz, odom=odom[k]))
        est.append(matrix_to_pose2(out.pose))
    truth = compose2d(inverse2d(seq.poses[0]), seq.poses[-1])
    e = compose2d(inverse2d(truth), compose2d(inverse2d(est[0]), est[-1]))
    return float(np.hypot(e[0], e[1])), abs(float(np.degrees(e[2])))


def test_a_stall_mid_turn_is_not_counted_twice(office):
    """Four stale readings mid-turn: taken as one step's motion, the catch-up counts the
    stall's turn twice (measured 1.22 m / 38.6 deg off over 11 m; the heading alone
    stalling 1.59 m / 38.5 deg); with ``stale_wheels`` the front end ends as it does with
    no stall at all (1.20 cm / 0.107 deg, heading alone 1.18 cm / 0.108 deg, position
    alone 1.24 cm / 0.119 deg vs 1.24 cm / 0.109 deg)."""
    m_none, deg_none = _end_error(office, False, 0)
    for parts in (slice(0, 3), slice(2, 3)):
        m_off, deg_off = _end_error(office, False, 4, parts)
        assert deg_off > 30.0 and m_off > 1.0
    for parts in (slice(0, 3), slice(2, 3), slice(0, 2)):
        m_on, deg_on = _end_error(office, True, 4, parts)
        assert m_on < 0.02 and deg_on < 0.2
        assert abs(m_on - m_none) < 0.005 and abs(deg_on - deg_none) < 0.05
