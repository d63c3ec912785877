"""Self-consistency relations (``slam.eval.self_relations``) on a simulated 2D sequence:
the scan pairs kept are true relative poses (checked against the ground truth), and a
trajectory broken between two scans is caught by them."""

from __future__ import annotations

import numpy as np
import pytest

from slam.eval.relations import relation_errors
from slam.eval.self_relations import SelfRelationConfig, self_relations
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
