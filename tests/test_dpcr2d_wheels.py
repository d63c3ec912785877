"""The first registration checked against the wheels (``frontends.dpcr2d_steps.check_wheels``):
a registration far from the wheel odometry is kept only when it fits the submap better
than PLICP started at the wheels."""

from __future__ import annotations

import numpy as np
from office2d_pair import office_pair, pose_error

from frontends.dpcr2d_config import Dpcr2dConfig
from frontends.dpcr2d_steps import check_wheels
from slam.mapping.grid2d import compose2d
from slam.registration.plicp import PlicpResult, plicp


def test_a_jump_away_from_good_wheels_is_replaced():
    ref, b, truth = office_pair()
    cfg = Dpcr2dConfig()
    # a registration that landed 0.3 m / 15 deg off (a wrong wall, as on MIT-CSAIL)
    off = compose2d(truth, np.array([0.0, 0.3, np.radians(15.0)]))
    wrong = PlicpResult(off, 0.05, 200, 10, True, np.eye(3))
    extras: dict = {}
    kept = check_wheels(b, ref, truth, wrong, {}, cfg, extras)
    assert extras["wheel_kept"] == 1 and extras["wheel_check_near_fit"] > extras["wheel_check_fit"]
    m, deg = pose_error(kept.pose, truth)
    assert m < 0.01 and deg < 0.1


def test_a_good_registration_beats_wrong_wheels():
    ref, b, truth = office_pair()
    cfg = Dpcr2dConfig()
    good = plicp(b, ref, truth, cfg.plicp)
    wheels = compose2d(truth, np.array([0.25, 0.0, np.radians(6.0)]))  # the wheels slipped
    extras: dict = {}
    kept = check_wheels(b, ref, wheels, good, {}, cfg, extras)
    assert extras["wheel_check"] == 1 and "wheel_kept" not in extras
    assert kept is good


def test_near_the_wheels_nothing_is_checked():
    ref, b, truth = office_pair()
    cfg = Dpcr2dConfig()
    good = plicp(b, ref, truth, cfg.plicp)
    extras: dict = {}
    assert check_wheels(b, ref, truth, good, {}, cfg, extras) is good and not extras
