"""A first registration with a poor fit searched again (``frontends.dpcr2d_steps.search_poor_fit``):
above ``poor_fit_rmse`` a correlative search around the prediction, then PLICP, and the
searched pose taken only when it fits the submap better."""

from __future__ import annotations

import numpy as np
from office2d_pair import office_pair, pose_error

from frontends.dpcr2d_config import Dpcr2dConfig
from frontends.dpcr2d_steps import search_poor_fit
from slam.mapping.grid2d import compose2d
from slam.registration.plicp import PlicpResult, plicp


def test_a_registration_settled_off_in_a_turn_is_searched_back():
    ref, b, truth = office_pair()
    cfg = Dpcr2dConfig(poor_fit_rmse=0.04)
    # PLICP settled 0.15 m / 10 deg off (a wall's basin in a fast turn), RMSE 6 cm
    off = compose2d(truth, np.array([0.0, 0.15, np.radians(10.0)]))
    wrong = PlicpResult(off, 0.06, 200, 10, True, np.eye(3))
    predicted = compose2d(truth, np.array([0.1, 0.0, np.radians(-8.0)]))  # wheels off too
    extras: dict = {}
    kept = search_poor_fit(b, ref, predicted, wrong, {}, cfg, extras)
    assert extras["poor_fit_kept"] == 1
    assert extras["poor_fit_search_fit"] > extras["poor_fit_fit"] + 0.3
    m, deg = pose_error(kept.pose, truth)
    assert m < 0.01 and deg < 0.1


def test_a_good_registration_with_a_high_rmse_is_kept():
    ref, b, truth = office_pair()
    cfg = Dpcr2dConfig(poor_fit_rmse=0.005)  # below this scan's own residual (1.3 cm)
    good = plicp(b, ref, truth, cfg.plicp)
    assert good.rmse > cfg.poor_fit_rmse
    extras: dict = {}
    kept = search_poor_fit(b, ref, truth, good, {}, cfg, extras)
    assert extras["poor_fit"] == 1 and "poor_fit_kept" not in extras
    assert kept is good


def test_below_the_rmse_or_switched_off_nothing_is_searched():
    ref, b, truth = office_pair()
    off = compose2d(truth, np.array([0.0, 0.15, np.radians(10.0)]))
    wrong = PlicpResult(off, 0.06, 200, 10, True, np.eye(3))
    for cfg in (Dpcr2dConfig(poor_fit_rmse=0.0), Dpcr2dConfig(poor_fit_rmse=0.07)):
        extras: dict = {}
        assert search_poor_fit(b, ref, truth, wrong, {}, cfg, extras) is wrong
        assert not extras
