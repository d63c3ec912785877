"""Loop edges really switched off (``slam.graph2d_gate``): a chain of odometry with one
right and several wrong loop edges; the Cauchy kernel alone lets the wrong ones pull, the
gate leaves them out, and the disagreement with the front end is measured."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam.graph2d_gate import chain_values, disagreement, frontend_check, is_loop, optimize_gated


def _chain(n=20, sigma_m=0.1, sigma_rad=0.05):
    factors = [gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-4))]
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m, sigma_m, sigma_rad]))
    factors += [gtsam.BetweenFactorPose2(i, i + 1, gtsam.Pose2(1, 0, 0), odo) for i in range(n)]
    start = gtsam.Values()
    for i in range(n + 1):
        start.insert(i, gtsam.Pose2(i, 0, 0))
    return factors, start


def _loop(a, b, z):
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(1.0),
        gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, np.radians(1.0)])),
    )
    return gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(*z), noise)


def _lm(graph, values):
    return gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()


def test_wrong_loop_edges_are_switched_off_and_right_ones_kept():
    factors, start = _chain()
    factors.append(_loop(0, 20, (20.0, 0.0, 0.0)))  # right
    wrong = [_loop(5, 15, (9.0, 0.8, 0.05)), _loop(6, 16, (9.0, 0.8, 0.05)),
             _loop(7, 17, (9.0, 0.8, 0.05))]  # fmt: skip
    factors += wrong
    assert [is_loop(f) for f in factors].count(True) == 4
    robust_only = optimize_gated(factors, start, _lm, gate_sigma=0.0)
    gated = optimize_gated(factors, start, _lm, gate_sigma=4.0)
    err = [np.hypot(r.values.atPose2(15).x() - 15, r.values.atPose2(15).y())
           for r in (robust_only, gated)]  # fmt: skip
    assert err[0] > 0.05  # the Cauchy kernel lets three agreeing wrong edges pull
    assert err[1] < 1e-6
    assert list(np.flatnonzero(gated.off)) == [22, 23, 24]
    d0 = disagreement(factors, robust_only.sigmas, robust_only.off)
    d1 = disagreement(factors, gated.sigmas, gated.off)
    assert d0["frontend_residual_max_sigma"] > 0.3 and d0["loop_edges_off"] == 0
    assert d1["frontend_residual_max_sigma"] < 1e-6 and d1["loop_edges_off"] == 3
    assert d1["loop_edges"] == 4 and d1["loop_residual_max_sigma"] < 1e-6


def test_a_switched_off_edge_comes_back_when_it_agrees():
    """An edge off at a poor start estimate is checked again at the next one."""
    factors, start = _chain(sigma_m=0.02, sigma_rad=0.01)
    factors.append(_loop(0, 20, (20.0, 0.0, 0.0)))
    bad_start = gtsam.Values(start)
    bad_start.update(20, gtsam.Pose2(21.0, 0.0, 0.0))
    res = optimize_gated(factors, bad_start, _lm, gate_sigma=4.0)
    assert not res.off.any()
    assert abs(res.values.atPose2(20).x() - 20.0) < 1e-6


def test_chain_values_compose_the_front_end():
    factors, start = _chain(n=5)
    factors[3] = gtsam.BetweenFactorPose2(3, 2, gtsam.Pose2(-1, 0, 0), factors[3].noiseModel())
    moved = gtsam.Values()
    for i in range(6):
        moved.insert(i, gtsam.Pose2(i + 0.3, 0.2 * i, 0.01 * i))  # an optimised estimate
    moved.update(0, gtsam.Pose2())
    fe = chain_values(factors, moved)
    assert all(abs(fe.atPose2(i).x() - i) < 1e-12 and abs(fe.atPose2(i).y()) < 1e-12
               for i in range(6))  # fmt: skip
    assert chain_values(factors[:3] + factors[4:], moved) is None  # the chain is broken


def test_front_end_kept_when_every_loop_edge_agrees_within_its_noise():
    """Loop edges within their noise of the front end (2 cm off, sigma 5 cm) only add that
    noise: the front end is kept; one edge 0.5 m off the front end and agreeing with the
    others (a real drift) makes the graph's result the answer."""
    factors, start = _chain(sigma_m=0.002, sigma_rad=0.0005)
    rng = np.random.default_rng(3)
    factors += [_loop(i, i + 10, (10.0 + rng.normal(0, 0.02), rng.normal(0, 0.02), 0.0))
                for i in range(0, 10, 2)]  # fmt: skip
    gate = optimize_gated(factors, start, _lm, gate_sigma=4.0)
    check = frontend_check(factors, gate, sigma=3.0)
    assert check.keep_frontend and check.max_sigma < 1.5
    assert abs(check.values.atPose2(20).x() - 20.0) < 1e-9
    assert not frontend_check(factors, gate, sigma=0.0).keep_frontend

    drift, start = _chain(sigma_m=0.1, sigma_rad=0.01)
    drift += [_loop(0, 20, (19.75, 0.0, 0.0))]  # the front end 0.25 m long over the loop
    gate = optimize_gated(drift, start, _lm, gate_sigma=4.0)
    check = frontend_check(drift, gate, sigma=3.0)
    assert not check.keep_frontend and check.max_sigma > 4.5
    assert abs(gate.values.atPose2(20).x() - 19.75) < 0.02


def test_an_edge_without_a_robust_kernel_is_never_switched_off():
    """A front end's re-anchor (Gaussian, ``region_edges`` on a visit keyframe): 0.5 m
    against a chain of 2 cm steps is far beyond the gate, yet it stays and the chain bends
    to it; the same edge under the Cauchy kernel is switched off."""
    factors, start = _chain(sigma_m=0.02, sigma_rad=0.01)
    z = (20.5, 0.0, 0.0)
    gaussian = gtsam.BetweenFactorPose2(
        0, 20, gtsam.Pose2(*z), gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
    )
    kept = optimize_gated([*factors, gaussian], start, _lm, gate_sigma=4.0)
    off = optimize_gated([*factors, _loop(0, 20, z)], start, _lm, gate_sigma=4.0)
    assert not kept.off.any() and list(np.flatnonzero(off.off)) == [len(factors)]
    # the chain takes its share by the information: 0.5 m x 20 (2 cm)^2 / (20 (2 cm)^2 + (5 cm)^2)
    assert kept.values.atPose2(20).x() == pytest.approx(20.0 + 0.5 * 0.008 / 0.0105, abs=1e-3)
    assert abs(off.values.atPose2(20).x() - 20.0) < 1e-6
