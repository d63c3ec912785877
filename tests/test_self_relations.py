"""Self-consistency relations (``slam.eval.self_relations``) on a simulated 2D sequence:
the scan pairs kept are true relative poses (checked against the ground truth), and a
trajectory broken between two scans is caught by them."""

from __future__ import annotations

import numpy as np
import pytest

from slam.eval.relations import relation_errors
from slam.eval.self_relations import (
    RevisitRelationConfig,
    SelfRelationConfig,
    revisit_relations,
    self_relations,
)
from slam.mapping.grid2d import pose2_to_matrix
from slam.sim.floorplan2d import simulate2d, wheel_odometry


@pytest.fixture(scope="module")
def office():
    seq = simulate2d("office2d", frames=200, speed=1.0)
    odom = wheel_odometry(seq.poses, slip=0.03, yaw_slip=0.05, heading_deg_per_sqrt_m=0.5)
    scans = [seq.points(k) for k in range(len(seq.stamps))]
    truth = np.array([pose2_to_matrix(p) for p in seq.poses])
    rel, stats = self_relations(seq.stamps, scans, odom, SelfRelationConfig(every=5))
    return seq, truth, rel, stats


def test_kept_relations_are_true_relative_poses(office):
    seq, truth, rel, stats = office
    assert stats.pairs == len(rel) + sum(stats.rejected.values())
    assert len(rel) >= 0.5 * stats.pairs and len(rel) >= 50
    err = relation_errors(seq.stamps, truth, rel, max_dt=1e-6)
    assert err.unmatched == 0
    assert err.trans.max() < 0.02 and err.rot_deg.max() < 0.3
    assert np.median(err.trans) < 0.005


def test_a_trajectory_broken_between_two_scans_is_caught(office):
    seq, truth, rel, _ = office
    bad = truth.copy()
    kick = pose2_to_matrix(np.array([0.1, 0.05, np.radians(1.0)]))
    bad[100:] = truth[99] @ kick @ np.linalg.inv(truth[99]) @ truth[100:]
    err = relation_errors(seq.stamps, bad, rel, max_dt=1e-6)
    t1 = rel.t1[err.index]
    t2 = rel.t2[err.index]
    across = (t1 <= seq.stamps[99]) & (t2 >= seq.stamps[100])
    assert across.sum() >= 3
    assert err.trans[across].min() > 0.08 and err.trans[~across].max() < 0.02


@pytest.fixture(scope="module")
def rooms_loop():
    """1.2 laps of the simulated rooms (the start seen again), poor wheel odometry, and
    the revisit relations proposed by the wheels and the truth."""
    seq = simulate2d("rooms2d", speed=1.0, laps=1.2, seed=2)
    odom = wheel_odometry(seq.poses, slip=0.03, yaw_slip=0.05, heading_deg_per_sqrt_m=0.5)
    scans = [seq.points(k) for k in range(len(seq.stamps))]
    truth = np.array([pose2_to_matrix(p) for p in seq.poses])
    cfg = RevisitRelationConfig(every=10)
    rel, stats = revisit_relations(seq.stamps, scans, odom, [odom, np.asarray(seq.poses)], cfg)
    return seq, truth, rel, stats


def test_revisit_relations_are_true_and_long(rooms_loop):
    """Kept revisits are true relative poses of scans far apart in path and time."""
    seq, truth, rel, stats = rooms_loop
    assert stats.pairs == len(rel) + sum(stats.rejected.values())
    assert len(rel) >= 10
    err = relation_errors(seq.stamps, truth, rel, max_dt=1e-6)
    assert err.unmatched == 0
    assert err.trans.max() < 0.03 and err.rot_deg.max() < 0.3
    assert np.min(rel.t2 - rel.t1) >= 9.0  # >= 10 m of wheel path at ~1 m/s


def test_revisit_relations_see_a_bent_loop_short_ones_do_not(rooms_loop):
    """A trajectory bent by 0.05 deg per scan after scan 150 (a wrong loop edge's doing,
    or drift) keeps every short relation within 1.5 cm but not the revisits."""
    seq, truth, rel, _ = rooms_loop
    bent = truth.copy()
    for k in range(150, len(truth)):
        kick = pose2_to_matrix(np.array([0.0, 0.0, np.radians(0.05)]))
        rel_k = np.linalg.inv(truth[k - 1]) @ truth[k]
        bent[k] = bent[k - 1] @ kick @ rel_k
    short, _ = self_relations(seq.stamps, [seq.points(k) for k in range(len(seq.stamps))],
                              np.asarray(seq.poses), SelfRelationConfig(every=20))  # fmt: skip
    e_short = relation_errors(seq.stamps, bent, short, max_dt=1e-6)
    e_long = relation_errors(seq.stamps, bent, rel, max_dt=1e-6)
    assert np.median(e_short.trans) < 0.015
    assert np.median(e_long.trans) > 0.3
