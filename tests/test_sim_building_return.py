"""The ``building_return`` route (slam/sim/building_return.py): it comes back over its own
path in the opposite direction, stays clear of the floor's walls, columns and moving
things, and leaves the other building routes' sequences (their cache keys) alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.sim.building_return import building_return, return_path
from slam.sim.registry import SCENES, scene_sources


@pytest.fixture(scope="module")
def scene():
    return building_return()


def _headings(xy: np.ndarray) -> np.ndarray:
    d = np.gradient(xy, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def test_the_way_back_runs_over_the_way_out_in_the_opposite_direction():
    xy = return_path(ds=0.05)
    step = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    assert 495.0 < s[-1] < 505.0
    yaw = _headings(xy)
    tree = cKDTree(xy)
    back_opposite = np.zeros(len(xy), dtype=bool)
    crossings = 0
    for i, p in enumerate(xy):
        near = np.array(tree.query_ball_point(p, 1.0), dtype=int)
        earlier = near[s[near] < s[i] - 30.0]  # an earlier pass, not the same stretch
        if len(earlier) == 0:
            continue
        dyaw = np.abs(np.angle(np.exp(1j * (yaw[earlier] - yaw[i]))))
        back_opposite[i] = bool(np.any(dyaw > np.deg2rad(150)))
        crossings += bool(np.any((dyaw > np.deg2rad(60)) & (dyaw < np.deg2rad(120))))
    metres = float(np.sum(step[back_opposite[1:]]))
    # Out: 122 m on the first corridor, 42 m of the middle spine, 64 m of the second
    # corridor up to the hall turnaround; back over all of it (less the corners' arcs).
    assert metres > 215.0, metres
    # The turnaround loop crosses the way out (at x = 213 m): some points meet an earlier
    # pass at right angles.
    assert crossings > 0
    # The end is 8 m past the start, on the way out's line.
    assert np.hypot(*(xy[-1] - (16.0, 8.0))) < 1e-6
    assert np.hypot(*(xy[0] - (24.0, 8.0))) < 1e-6


def test_the_robot_keeps_to_the_corridors_and_clear_of_the_columns(scene):
    import open3d as o3d

    xy = return_path(ds=0.05)[::20]  # every metre
    ang = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    origins = np.column_stack([xy, np.full(len(xy), 0.5)])  # the robot body's height
    rays = np.hstack([np.repeat(origins, len(ang), axis=0), np.tile(dirs, (len(xy), 1))])
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    dist = hit["t_hit"].numpy().reshape(len(xy), len(ang)).min(axis=1)
    # A 3.5 m corridor: 1.75 m to the walls, 1.45 m to a pilaster; in the hall, 3.4 m to
    # the nearest column.
    assert dist.min() > 1.4, dist.min()
    in_hall = (xy[:, 0] > 200.0) & (xy[:, 0] < 232.0)  # clear of the openings
    assert dist[in_hall].min() > 3.0


def test_workers_and_machinery_stay_clear_of_the_robot(scene):
    t = np.arange(0.0, scene.duration, 0.1)
    robot = scene.pose_at(t)[:, :2, 3]
    gap = np.inf
    for ped in scene.pedestrians:
        half = 0.5 * max(ped.size[0], ped.size[1])
        d = np.hypot(*(ped.position(t)[:, :2] - robot).T) - half
        gap = min(gap, float(d.min()))
    # Workers walk 1.1 m beside the corridor's centre line (0.25 m half width); the
    # hall's cart passes 2.6 m north of the turnaround.
    assert 0.6 < gap < 1.0, gap


def test_trajectory_limits(scene):
    traj = scene.trajectory
    t = np.arange(0.0, scene.duration, 0.1)
    xy = scene.pose_at(t)[:, :2, 3]
    v = np.hypot(*np.diff(xy, axis=0).T) / 0.1
    assert 180.0 < scene.duration < 184.0
    assert v.max() < 3.0 + 1e-3
    assert traj.length == pytest.approx(499.2, abs=0.5)


def test_the_other_routes_keep_their_cache_keys():
    # The sequences of building / building_loop hash building.py (and the core files),
    # not this route's module: adding it regenerates none of them.
    assert "building_return.py" not in scene_sources("building")
    assert "building_return.py" not in scene_sources("building_loop")
    assert {"building.py", "building_return.py"} <= set(scene_sources("building_return"))
    assert SCENES["building_return"].realistic
