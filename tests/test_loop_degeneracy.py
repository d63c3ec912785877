"""Loops that cannot be trusted: the degeneracy test of verification (a plain or periodic
corridor leaves its axis free) and the pairwise consistency of loops through the odometry
(slam.loop.verify.ambiguous_axis / free_information, slam.loop.consistency)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam.loop.consistency import (
    ConsistencyParams,
    LoopConsistency,
    PendingLoop,
    consistent,
    cycle_error,
)
from slam.loop.verify import VerifyParams, free_information, tilt_floor, verify, yaw_matrix

RANGE = 20.0  # m, sensor reach in the synthetic scenes


def _plane_points(rng, corner, u, v, density):
    """Points on the rectangle corner + a u + b v (a, b in [0, 1]), ``density`` per m^2."""
    area = np.linalg.norm(np.cross(u, v))
    n = int(density * area)
    a, b = rng.random(n), rng.random(n)
    return corner + a[:, None] * u + b[:, None] * v


def _corridor(rng, length=80.0, width=3.0, height=2.5, pillar_every=0.0):
    """A corridor along x (y in [-width/2, width/2], z in [0, height]): two walls, floor,
    optionally square pillars (0.4 m) against both walls every ``pillar_every`` m."""
    x0 = -length / 2
    parts = [
        _plane_points(rng, np.array([x0, -width / 2, 0]), [length, 0, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([x0, width / 2, 0]), [length, 0, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([x0, -width / 2, 0]), [length, 0, 0], [0, width, 0], 10),
    ]
    if pillar_every > 0:
        for x in np.arange(x0 + 2.0, -x0 - 2.0, pillar_every):
            for y in (-width / 2 + 0.2, width / 2 - 0.2):
                for dx, dy in ((-0.2, 0), (0.2, 0), (0, -0.2), (0, 0.2)):
                    face = np.array([x + dx, y + dy, 0.0])
                    u = np.array([0, 0.4, 0]) if dx else np.array([0.4, 0, 0])
                    parts.append(_plane_points(rng, face - u / 2, u, [0, 0, height], 400))
    return np.concatenate(parts)


def _room(rng, size=(12.0, 9.0), height=2.5):
    """A closed room with two pillars: every horizontal direction is fixed."""
    sx, sy = size
    parts = [
        _plane_points(rng, np.array([0, 0, 0]), [sx, 0, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([0, sy, 0]), [sx, 0, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([0, 0, 0]), [0, sy, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([sx, 0, 0]), [0, sy, 0], [0, 0, height], 40),
        _plane_points(rng, np.array([0, 0, 0]), [sx, 0, 0], [0, sy, 0], 10),
    ]
    for px, py in ((4.0, 3.0), (8.5, 6.0)):
        for dx, dy in ((-0.2, 0), (0.2, 0), (0, -0.2), (0, 0.2)):
            face = np.array([px + dx, py + dy, 0.0])
            u = np.array([0, 0.4, 0]) if dx else np.array([0.4, 0, 0])
            parts.append(_plane_points(rng, face - u / 2, u, [0, 0, height], 400))
    return np.concatenate(parts)


def _view(rng, world, T_world_sensor):
    """The world points within RANGE of the sensor, in its frame, 1 cm noise."""
    T_s_w = np.linalg.inv(T_world_sensor)
    pts = world @ T_s_w[:3, :3].T + T_s_w[:3, 3]
    pts = pts[np.linalg.norm(pts[:, :2], axis=1) < RANGE]
    return pts + rng.normal(0.0, 0.01, pts.shape)


def _sensor(x, y, yaw=0.0):
    return yaw_matrix(yaw, np.array([x, y, 1.0]))


def _sigmas_along(info, T, axis_target):
    """Sigma (m) of the loop's translation along a target-frame direction (info is in the
    source frame: the factor's tangent)."""
    cov = np.linalg.inv(info)[3:, 3:]
    a = T[:3, :3].T @ axis_target
    return float(np.sqrt(a @ cov @ a))


@pytest.fixture(scope="module")
def corridor_result():
    """Two views of a plain corridor 4 m apart along it, registered from the guess "same
    place": the registration cannot tell where along the corridor it is."""
    rng = np.random.default_rng(0)
    world = _corridor(rng)
    Ta, Tb = _sensor(0.0, 0.0), _sensor(4.0, 0.3, np.radians(2.0))
    res = verify(_view(rng, world, Ta), _view(rng, world, Tb), np.eye(4), VerifyParams())
    return res, np.linalg.solve(Ta, Tb)


def test_plain_corridor_leaves_its_axis_free(corridor_result):
    res, T_true = corridor_result
    assert res.accepted  # every wall point meets a wall: the judge alone cannot tell
    assert len(res.free_axes) == 1 and abs(res.free_axes[0] @ [1.0, 0.0, 0.0]) > 0.95
    assert res.ambiguity > 0.9
    # across the corridor the loop is right and keeps its claim; along it, it claims nothing
    assert abs(res.T_target_source[1, 3] - T_true[1, 3]) < 0.05
    assert _sigmas_along(res.info, res.T_target_source, np.array([0.0, 1.0, 0.0])) < 0.5
    assert _sigmas_along(res.info, res.T_target_source, np.array([1.0, 0.0, 0.0])) > 10.0
    # the error it does make along the axis is within what it claims (chi2 of 6 dof, 95 %)
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(T_true).between(gtsam.Pose3(res.T_target_source)))
    assert xi @ res.info @ xi < 12.6


def test_pillared_corridor_is_ambiguous_by_its_period():
    """Pillars every 5 m fix the position only up to the period: from a guess 5 m off the
    registration lands on the neighbouring bay, and the test flags the axis."""
    rng = np.random.default_rng(1)
    world = _corridor(rng, pillar_every=5.0)
    Ta, Tb = _sensor(0.0, 0.0), _sensor(5.0, 0.0)
    res = verify(_view(rng, world, Ta), _view(rng, world, Tb), np.eye(4), VerifyParams())
    assert len(res.free_axes) == 1 and abs(res.free_axes[0][0]) > 0.95
    assert res.ambiguity >= VerifyParams().ambiguity_ratio


def test_room_is_not_ambiguous():
    rng = np.random.default_rng(2)
    world = _room(rng)
    Ta, Tb = _sensor(5.0, 4.0), _sensor(6.0, 5.0, np.radians(20.0))
    T_true = np.linalg.solve(Ta, Tb)
    res = verify(_view(rng, world, Ta), _view(rng, world, Tb), yaw_matrix(np.radians(20.0)))
    assert res.accepted
    assert np.linalg.norm(res.T_target_source[:3, 3] - T_true[:3, 3]) < 0.05
    assert len(res.free_axes) == 0 and res.ambiguity < 0.6
    assert _sigmas_along(res.info, res.T_target_source, np.array([1.0, 0.0, 0.0])) < 0.5


def test_ambiguity_test_off_keeps_the_old_information(corridor_result):
    rng = np.random.default_rng(0)
    world = _corridor(rng)
    Ta, Tb = _sensor(0.0, 0.0), _sensor(4.0, 0.3, np.radians(2.0))
    off = verify(
        _view(rng, world, Ta), _view(rng, world, Tb), np.eye(4), VerifyParams(ambiguity_ratio=0)
    )
    assert len(off.free_axes) == 0
    assert _sigmas_along(off.info, off.T_target_source, np.array([1.0, 0.0, 0.0])) < 10.0


def test_free_information_frees_one_direction_and_keeps_the_others():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)
    axis = np.array([0.6, 0.8, 0.0])
    out = free_information(info, axis[None, :], 20.0)
    u = np.concatenate([np.zeros(3), axis])
    assert u @ out @ u == pytest.approx(1 / 400.0)
    assert np.allclose(out @ u, u / 400.0)  # no coupling left to the free direction
    P = np.eye(6) - np.outer(u, u)
    assert np.allclose(P @ out @ P, P @ info @ P)
    assert np.all(np.linalg.eigvalsh(out) > 0)


# --------------------------------------------------------------------------- consistency


def _loop(a, b, truth, odo, error=(0.0, 0.0, 0.0)):
    """Loop a -> b with a measurement off by ``error`` (m, target frame) from the truth;
    odometry poses and travel from the drifting ``odo``."""
    T = np.linalg.solve(truth[a], truth[b])
    T[:3, 3] += np.asarray(error)
    steps = np.linalg.norm(np.diff(odo[:, :3, 3], axis=0), axis=1)
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    return PendingLoop(a, b, T, odo[a], odo[b], float(travel[a]), float(travel[b]))


@pytest.fixture(scope="module")
def corridor_return():
    """Out along x 1 m per keyframe (0..49), back the other way (50..99): keyframe 99 - i
    stands where i did. The odometry drifts 0.2 deg and 1 % per metre."""
    truth = [_sensor(float(i), 0.0) for i in range(50)]
    truth += [_sensor(float(49 - i), 0.0, np.pi) for i in range(50)]
    odo = [truth[0]]
    for prev, cur in zip(truth[:-1], truth[1:], strict=True):
        rel = np.linalg.solve(prev, cur)
        rel[:3, 3] *= 1.01
        odo.append(odo[-1] @ rel @ yaw_matrix(np.radians(0.2)))
    return np.stack(truth), np.stack(odo)


def test_true_loops_agree_and_an_aliased_one_does_not(corridor_return):
    truth, odo = corridor_return
    p = ConsistencyParams()
    good1, good2 = _loop(10, 89, truth, odo), _loop(12, 87, truth, odo)
    e, rot, travelled = cycle_error(good1, good2)
    assert np.linalg.norm(e) < 0.1 and rot < 1.0 and travelled == pytest.approx(4.04, abs=0.01)
    assert consistent(good1, good2, p)
    aliased = _loop(11, 88, truth, odo, error=np.array([3.0, 0.0, 0.0]))  # 3 m along the axis
    assert not consistent(good1, aliased, p)
    across = _loop(11, 88, truth, odo, error=np.array([0.0, 0.8, 0.0]))
    assert not consistent(good1, across, p)
    assert consistent(good1, _loop(11, 88, truth, odo, error=np.array([0.0, 0.3, 0.0])), p)


def test_a_loop_enters_once_a_partner_confirms_it_and_outliers_expire(corridor_return):
    truth, odo = corridor_return
    lc = LoopConsistency(ConsistencyParams(window=5))
    assert lc.add(_loop(10, 89, truth, odo)) == []  # alone: waits
    false1 = _loop(8, 90, truth, odo, error=np.array([5.0, 0.0, 0.0]))
    assert lc.add(false1) == []  # contradicts the first: waits too
    got = lc.add(_loop(12, 91 - 4, truth, odo))  # agrees with the first: both enter
    assert [(m.target, m.source) for m in got] == [(10, 89), (12, 87)]
    false2 = _loop(13, 86, truth, odo, error=np.array([-4.0, 0.0, 0.0]))
    assert lc.add(false2) == []  # two confirmed loops contradict it
    got = lc.add(_loop(15, 84, truth, odo))
    assert [(m.target, m.source) for m in got] == [(15, 84)]
    assert lc.expire(84) == []  # 86 and 90 are within the window of 84
    assert lc.expire(96) == [false1, false2]
    assert not false1.confirmed and false1.expired


def test_window_zero_confirms_every_loop_at_once(corridor_return):
    truth, odo = corridor_return
    lc = LoopConsistency(ConsistencyParams(window=0))
    loop = _loop(8, 90, truth, odo, error=np.array([5.0, 0.0, 0.0]))
    assert lc.add(loop) == [loop] and loop.confirmed


def test_tilt_floor_lifts_roll_and_pitch_only():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 6))
    C = A @ A.T * 1e-5 + np.diag([1e-6, 4e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    info = np.linalg.inv(C)
    floor = np.radians(1.0)
    out = np.linalg.inv(tilt_floor(info, floor))
    sig, sig0 = np.sqrt(np.diag(out)), np.sqrt(np.diag(C))
    assert sig[0] == pytest.approx(floor) and sig[1] == pytest.approx(floor)
    assert np.allclose(sig[2:], sig0[2:])  # yaw and translation as they were
    corr = out / np.outer(sig, sig)
    assert np.allclose(corr, C / np.outer(sig0, sig0))  # correlations kept
    assert np.allclose(tilt_floor(info, np.radians(0.01)), info)  # already weaker: unchanged


def test_free_sigma_zero_rejects_a_loop_with_a_free_axis(corridor_result):
    """free_sigma <= 0: a loop whose position along its axis is only the start's is not
    kept (the plain corridor's 4 m offset registers as ~0 from the guess "same place")."""
    res, T_true = corridor_result
    assert abs(res.T_target_source[0, 3] - T_true[0, 3]) > 3.0  # what an accepted one claims
    rng = np.random.default_rng(0)
    world = _corridor(rng)
    Ta, Tb = _sensor(0.0, 0.0), _sensor(4.0, 0.3, np.radians(2.0))
    rej = verify(
        _view(rng, world, Ta), _view(rng, world, Tb), np.eye(4), VerifyParams(free_sigma=0.0)
    )
    assert not rej.accepted and "not unique along" in rej.reason
    assert len(rej.free_axes) == 1 and np.all(np.isfinite(rej.info))
    # a room keeps its loop
    rng = np.random.default_rng(2)
    world = _room(rng)
    Ta, Tb = _sensor(5.0, 4.0), _sensor(6.0, 5.0, np.radians(20.0))
    ok = verify(
        _view(rng, world, Ta), _view(rng, world, Tb), yaw_matrix(np.radians(20.0)),
        VerifyParams(free_sigma=0.0),
    )  # fmt: skip
    assert ok.accepted
