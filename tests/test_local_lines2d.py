"""Local line features of raw 2D points (``slam.registration.local_lines2d``): a wall's
points get its direction, a corner none, and PLICP on them registers a simulated room."""

from __future__ import annotations

import numpy as np
import pytest

from slam.mapping.grid2d import compose2d, inverse2d, transform2d
from slam.registration.local_lines2d import LocalLineConfig, local_line_reference, thin
from slam.registration.plicp import PlicpConfig, plicp
from slam.sim.floorplan2d import simulate2d


def test_a_wall_gets_its_direction_and_its_mean():
    rng = np.random.default_rng(0)
    x = np.arange(0.0, 3.0, 0.03)
    wall = np.column_stack([x, 0.5 * x + 1.0]) + rng.normal(0.0, 0.005, (len(x), 2))
    ref = local_line_reference(wall)
    direction = np.array([1.0, 0.5]) / np.hypot(1.0, 0.5)
    assert np.all(np.isfinite(ref.directions[:, 0]))
    assert np.all(np.abs(ref.directions @ direction) > 0.99)
    normal = np.array([-direction[1], direction[0]])
    raw = np.abs((wall - [0.0, 1.0]) @ normal)
    smooth = np.abs((ref.anchors - [0.0, 1.0]) @ normal)
    assert smooth.mean() < 0.6 * raw.mean()  # the neighbourhood's mean denoises


def test_a_corner_and_a_lone_point_carry_no_line():
    leg = np.arange(0.0, 1.0, 0.02)
    corner = np.vstack(
        [np.column_stack([leg, np.zeros_like(leg)]), np.column_stack([np.zeros_like(leg), leg])]
    )
    cloud = np.vstack([corner, [[5.0, 5.0]]])
    ref = local_line_reference(cloud, LocalLineConfig(radius=0.2, neighbours=16))
    assert np.isnan(ref.directions[0, 0])  # the corner point: both walls in its neighbourhood
    assert np.isnan(ref.directions[-1, 0])  # alone: point-to-point
    assert np.isfinite(ref.directions[25, 0]) and abs(ref.directions[25, 0]) > 0.99


def test_thin_keeps_one_point_per_cell():
    xy = np.array([[0.01, 0.01], [0.02, 0.04], [0.06, 0.0], [-0.01, -0.01]])
    assert len(thin(xy, 0.05)) == 3
    assert len(thin(xy, 0.0)) == 4


def test_plicp_on_local_lines_recovers_a_known_motion():
    """Measured: 0.6 mm / 0.004 deg (a scan of the simulated rooms on the previous 5)."""
    seq = simulate2d("rooms2d", frames=40, seed=3)
    k = 30
    scans = [thin(transform2d(seq.poses[i], seq.points(i)), 0.05) for i in range(25, k)]
    ref_pts = np.vstack(scans)
    ref = local_line_reference(ref_pts)
    truth = seq.poses[k]
    start = compose2d(truth, np.array([0.08, -0.05, np.radians(2.0)]))
    res = plicp(seq.points(k), ref, start, PlicpConfig(max_distance=0.3))
    err = compose2d(inverse2d(truth), res.pose)
    assert res.converged
    assert np.hypot(err[0], err[1]) < 0.005
    assert abs(np.degrees(err[2])) < 0.05


def test_bad_settings_are_refused():
    with pytest.raises(Exception, match="local lines"):
        LocalLineConfig(radius=0.0)
    with pytest.raises(Exception, match="local lines"):
        LocalLineConfig(min_neighbours=10, neighbours=8)
