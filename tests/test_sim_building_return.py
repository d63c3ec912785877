"""The ``building_return`` and ``building_loop_return`` routes (slam/sim/building_return.py):
they come back over their own path in the opposite direction, stay clear of the floor's
walls, columns and moving things, and leave the other building routes' sequences (their
cache keys) alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.sim.building_return import (
    building_loop_return,
    building_return,
    loop_return_path,
    return_path,
)
from slam.sim.registry import SCENES, scene_sources

ROUTES = {
    "building_return": (building_return, return_path),
    "building_loop_return": (building_loop_return, loop_return_path),
}


@pytest.fixture(scope="module", params=sorted(ROUTES))
def route(request):
    make, path = ROUTES[request.param]
    return request.param, make(), path


def revisits(xy: np.ndarray, radius: float = 1.0, min_apart: float = 30.0) -> dict[str, float]:
    """Metres of the path within ``radius`` m of an earlier pass (at least ``min_apart`` m
    earlier along it) heading the opposite way (> 150 deg) or the same way (< 30 deg), and
    the number of points meeting an earlier pass at 60-120 deg (crossings)."""
    step = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    d = np.gradient(xy, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    tree = cKDTree(xy)
    opposite = np.zeros(len(xy), dtype=bool)
    same = np.zeros(len(xy), dtype=bool)
    crossing = 0
    for i, p in enumerate(xy):
        near = np.array(tree.query_ball_point(p, radius), dtype=int)
        earlier = near[s[near] < s[i] - min_apart]
        if len(earlier) == 0:
            continue
        dyaw = np.abs(np.angle(np.exp(1j * (yaw[earlier] - yaw[i]))))
        opposite[i] = bool(np.any(dyaw > np.deg2rad(150)))
        same[i] = bool(np.any(dyaw < np.deg2rad(30)))
        crossing += bool(np.any((dyaw > np.deg2rad(60)) & (dyaw < np.deg2rad(120))))
    return {
        "length": float(s[-1]),
        "opposite": float(np.sum(step[opposite[1:]])),
        "same": float(np.sum(step[same[1:]])),
        "crossing": crossing,
    }


def test_building_return_comes_back_over_its_way_out():
    r = revisits(return_path(ds=0.05))
    assert 495.0 < r["length"] < 505.0
    # Out: 122 m on the first corridor, 42 m of the middle spine, 64 m of the second
    # corridor up to the hall turnaround; back over all of it (less the corners' arcs).
    assert r["opposite"] > 220.0, r
    assert r["same"] == 0.0
    # The turnaround loop crosses the way out (at x = 213 m) at right angles.
    assert r["crossing"] > 0
    xy = return_path(ds=0.05)
    assert np.hypot(*(xy[0] - (24.0, 8.0))) < 1e-6
    assert np.hypot(*(xy[-1] - (16.0, 8.0))) < 1e-6  # 8 m past the start


def test_building_loop_return_drives_every_corridor_both_ways():
    r = revisits(loop_return_path(ds=0.05))
    assert 910.0 < r["length"] < 925.0
    # The whole way back (the rectangle, ~450 m) runs over the way out the other way; the
    # first corridor's x = 24-100 m is also driven twice eastbound on the way out.
    assert r["opposite"] > 440.0, r
    assert 160.0 < r["same"] < 180.0, r
    assert r["crossing"] > 0


def test_the_robot_keeps_to_the_corridors_and_clear_of_the_columns(route):
    import open3d as o3d

    _, scene, path = route
    xy = path(ds=0.05)[::20]  # every metre
    ang = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    origins = np.column_stack([xy, np.full(len(xy), 0.5)])  # the robot body's height
    rays = np.hstack([np.repeat(origins, len(ang), axis=0), np.tile(dirs, (len(xy), 1))])
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    dist = hit["t_hit"].numpy().reshape(len(xy), len(ang)).min(axis=1)
    # A 3.5 m corridor: 1.75 m to the walls, 1.45 m to a pilaster; in the halls' turnaround
    # loops at least 2 m to a wall or column.
    assert dist.min() > 1.4, dist.min()
    halls = ((xy[:, 0] > 200.0) & (xy[:, 0] < 232.0) & (xy[:, 1] > 40.0)) | (
        (xy[:, 0] > 74.0) & (xy[:, 0] < 108.5) & (xy[:, 1] < 26.0)
    )
    assert halls.sum() > 20
    assert dist[halls].min() > 1.9, dist[halls].min()


def test_workers_and_machinery_stay_clear_of_the_robot(route):
    _, scene, _ = route
    t = np.arange(0.0, scene.duration, 0.1)
    robot = scene.pose_at(t)[:, :2, 3]
    gap = np.inf
    for ped in scene.pedestrians:
        half = 0.5 * max(ped.size[0], ped.size[1])
        d = np.hypot(*(ped.position(t)[:, :2] - robot).T) - half
        gap = min(gap, float(d.min()))
    # Workers walk 1.1 m beside the corridor's centre line (0.25 m half width); the halls'
    # carts and workers pass farther from the turnaround loops.
    assert 0.6 < gap < 1.0, gap


@pytest.mark.parametrize(
    "name, duration, length",
    [("building_return", 181.8, 499.2), ("building_loop_return", 327.3, 918.3)],
)
def test_trajectory_limits(name, duration, length):
    scene = ROUTES[name][0](pedestrians=False)
    t = np.arange(0.0, scene.duration, 0.1)
    xy = scene.pose_at(t)[:, :2, 3]
    v = np.hypot(*np.diff(xy, axis=0).T) / 0.1
    assert scene.duration == pytest.approx(duration, abs=0.5)
    assert v.max() < 3.0 + 1e-3
    assert scene.trajectory.length == pytest.approx(length, abs=0.5)


def test_the_other_routes_keep_their_cache_keys():
    # The sequences of building / building_loop hash building.py (and the core files),
    # not this module: adding it regenerates none of them.
    for name in ("building", "building_loop"):
        assert "building_return.py" not in scene_sources(name)
    for name in ROUTES:
        assert {"building.py", "building_return.py"} <= set(scene_sources(name))
        assert SCENES[name].realistic
