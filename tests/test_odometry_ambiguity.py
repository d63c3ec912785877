"""Degeneracy-aware odometry information (slam.registration.ambiguity): the slide test of a
keyframe against the previous keyframes' clouds, and the loosened information."""

from __future__ import annotations

import numpy as np
import pytest
from test_loop_degeneracy import _corridor, _room, _sensor, _view

from slam.errors import ConfigError
from slam.odometry import CommonConfig
from slam.registration.ambiguity import (
    OdometryAmbiguityConfig,
    loosened_information,
    odometry_ambiguity,
    weakest_horizontal,
)

CFG = OdometryAmbiguityConfig(enabled=True)
# a registration Hessian (rotation first) that constrains x (the corridor's axis) least
H_WEAK_X = np.diag([50.0, 50.0, 50.0, 1.0, 400.0, 400.0])


def _pair(world, rng, x_prev=0.0, x_now=1.0, y=0.0):
    """(source, target): the scan at x_now and the one at x_prev put in the source's frame
    by the true motion (the odometry of a front end that did not slip)."""
    src = _view(rng, world, _sensor(x_now, y))
    prev = _view(rng, world, _sensor(x_prev, y))
    return src, prev + np.array([x_prev - x_now, 0.0, 0.0])


def test_weakest_horizontal_is_the_weak_translation_axis():
    v = weakest_horizontal(H_WEAK_X)
    assert abs(abs(v[0]) - 1.0) < 1e-12 and v[2] == 0.0


@pytest.mark.parametrize("pillars", [0.0, 4.0])
def test_plain_and_periodic_corridors_are_ambiguous_along_their_axis(pillars):
    rng = np.random.default_rng(1)
    world = _corridor(rng, pillar_every=pillars)
    src, tgt = _pair(world, rng)
    amb = odometry_ambiguity(src, tgt, H_WEAK_X, CFG)
    assert amb.ambiguous
    assert abs(abs(amb.axis[0]) - 1.0) < 1e-9
    # plain: no surface faces the axis at all; pillars every 4 m: the next bay fits again
    assert amb.ratio > 0.85


def test_a_room_with_end_walls_is_not_ambiguous():
    rng = np.random.default_rng(2)
    world = _room(rng)
    src, tgt = _pair(world, rng, x_prev=5.0, x_now=6.0, y=4.5)
    amb = odometry_ambiguity(src, tgt, H_WEAK_X, CFG)
    assert not amb.ambiguous
    assert amb.ratio < 0.5


def test_too_few_points_is_ambiguous():
    amb = odometry_ambiguity(np.zeros((10, 3)), np.zeros((10, 3)), H_WEAK_X, CFG)
    assert amb.ambiguous and amb.ratio == 1.0


def test_loosened_information_has_the_sigma_along_the_axis_and_is_unchanged_across():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)
    yaw = 0.6
    axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    out = loosened_information(info, axis, 0.3)
    u = np.r_[0, 0, 0, axis]
    cov = np.linalg.inv(out)
    assert np.sqrt(u @ cov @ u) == pytest.approx(0.3, rel=1e-9)
    # across the axis (every direction orthogonal to u) the information is the same
    Q = np.linalg.svd(np.eye(6) - np.outer(u, u))[0][:, :5]
    assert np.allclose(Q.T @ out @ Q, Q.T @ info @ Q, rtol=1e-12, atol=1e-9)
    assert np.allclose(out @ u, u / 0.09)  # no coupling left
    assert np.all(np.linalg.eigvalsh(out) > 0)


def test_config_errors_are_clear():
    with pytest.raises(ConfigError, match="slide range"):
        OdometryAmbiguityConfig(min_shift=2.0, max_shift=1.0)
    with pytest.raises(ConfigError, match="sigma"):
        OdometryAmbiguityConfig(sigma=0.0)


def test_off_by_default_in_every_front_end():
    assert CommonConfig().odometry_ambiguity.enabled is False
