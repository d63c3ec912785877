"""Tests of the building scenes (slam/sim/building.py): the paper 001 experiment floor, its
S-shaped route without revisits, the loop variant, corridors seen on both sides, workers
and machinery clear of the robot, mixed materials."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.io.trajectory import read_tum
from slam.sim import ensure_sequence, make_scene, simulate_scan_truth
from slam.sim.building import LANES, MAX_SPEED, SENSOR_HEIGHT, WIDTH
from slam.sim.simulate import effective_model, full_frames


@pytest.fixture(scope="module")
def building():
    return make_scene("building")


@pytest.fixture(scope="module")
def building_loop():
    return make_scene("building_loop")


def _samples(scene, dt: float = 0.5):
    """Times (s), ground-truth poses (M,4,4) and distance travelled (m) every dt s."""
    t = np.arange(0.0, scene.duration, dt)
    return t, scene.pose_at(t), scene.trajectory.distance_at(t)


def test_route_length_speed_and_frames(building):
    traj = building.trajectory
    assert 1230.0 < traj.length < 1330.0  # the paper's ~1.3 km
    t = np.arange(0.0, traj.duration, 0.1)  # the sensor's 10 Hz
    xyz = building.pose_at(t)[:, :3, 3]
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=1) / 0.1
    assert speed.max() <= MAX_SPEED + 1e-6
    assert speed.max() > 0.98 * MAX_SPEED
    assert 2.6 < np.mean(speed) < MAX_SPEED  # mostly at cruise speed
    np.testing.assert_allclose(xyz[:, 2], SENSOR_HEIGHT, atol=0.02)  # flat floor
    n = full_frames(building, effective_model(building))
    assert 4000 < n < 4700


def test_s_route_never_revisits(building):
    _, T, s = _samples(building)
    xy = T[:, :2, 3]
    tree = cKDTree(xy)
    pairs = np.array(sorted(tree.query_pairs(35.0)))
    far_along = np.abs(s[pairs[:, 0]] - s[pairs[:, 1]]) > 60.0
    # Points of the route more than 60 m apart along it are >= 35 m apart in space: the
    # corridors driven are 42 m apart (revisit radius 3 m).
    assert not np.any(far_along)
    assert building.revisit_radius < 35.0
    # S-shape: the four corridors are driven in turn, east, west, east, west.
    heading = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    for k, y in enumerate(LANES):
        on = (np.abs(xy[:, 1] - y) < 0.1) & (xy[:, 0] > 20.0) & (xy[:, 0] < 270.0)
        assert on.sum() * 0.5 * MAX_SPEED > 200.0  # >= 200 m in each corridor
        want = 0.0 if k % 2 == 0 else np.pi
        assert np.all(np.abs(np.angle(np.exp(1j * (heading[on] - want)))) < np.radians(3.0))


def test_loop_route_comes_back(building, building_loop):
    np.testing.assert_array_equal(building.vertices, building_loop.vertices)  # same floor
    assert 350.0 < building_loop.trajectory.length < 480.0
    t, T, s = _samples(building_loop, dt=0.05)
    xy = T[:, :2, 3]
    early, late = s < 60.0, s > building_loop.trajectory.length - 60.0
    d, _ = cKDTree(xy[early]).query(xy[late])
    again = s[late][d < 0.2]
    assert again.max() - again.min() > 30.0  # > 30 m of the start driven again
    assert t[late].min() - t[early].max() > 100.0  # after > 100 s (drift to close)


def test_route_clear_of_walls_and_walkers(building, building_loop):
    for scene in (building, building_loop):
        t, T, _ = _samples(scene, dt=1.0)
        az = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
        dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros_like(az)])
        for z in (0.2, SENSOR_HEIGHT):
            origins = np.repeat(T[:, :3, 3] * [1, 1, 0] + [0, 0, z], len(az), axis=0)
            hits = scene.cast(origins, np.tile(dirs, (len(t), 1)), pedestrians=False)
            assert hits.range.min() > 0.95  # corridors 3.5 m, pilasters 0.3 m, corners
        # Walkers and machinery never come within 0.5 m of the robot's footprint centre.
        t = np.arange(0.0, scene.duration, 0.1)
        robot = scene.pose_at(t)[:, :2, 3]
        for ped in scene.pedestrians:
            gap = np.linalg.norm(ped.position(t)[:, :2] - robot, axis=1)
            assert gap.min() - 0.5 * np.hypot(*ped.size[:2]) > 0.5


def _scan_at(scene, t: float):
    model = effective_model(scene)
    scan, truth = simulate_scan_truth(scene, scene.pose_at, t, model, np.random.default_rng(1))
    return scan, truth


@pytest.mark.parametrize("x_world", [40.0, 170.0])  # a plain stretch, a stretch with doors
def test_corridor_scans_see_both_walls(building, x_world):
    t_all, T, _ = _samples(building, dt=0.1)
    i = np.flatnonzero((np.abs(T[:, 1, 3] - LANES[0]) < 0.05) & (T[:, 0, 3] > x_world))[0]
    scan, truth = _scan_at(building, float(t_all[i]))
    p = scan.xyz
    near = (np.abs(p[:, 0]) < 10.0) & (p[:, 2] > -0.5) & (p[:, 2] < 2.5)
    for side in (1.0, -1.0):  # left and right wall faces at +-1.75 m (pilasters 0.3 m in)
        on_wall = near & (np.abs(side * p[:, 1] - WIDTH / 2) < 0.35)
        assert on_wall.sum() > 3000
    # Nothing closer than the wall faces sideways: a corridor, not an open space.
    assert np.all(np.abs(p[near & ~truth.dynamic & ~truth.spurious & ~truth.mixed, 1]) > 1.3)
    ground = np.abs(p[:, 2] + SENSOR_HEIGHT) < 0.1
    assert ground.sum() > 2000


def test_materials_and_moving_things(building):
    refl = np.unique(np.round(building.reflectivity, 3))
    assert len(refl) >= 6  # concrete, paint, wood, metal, glass, insulation, ...
    assert refl.min() < 0.1 and refl.max() > 0.8
    kinds = {tuple(p.size) for p in building.pedestrians}
    assert len(kinds) >= 3  # workers, scissor lifts, carts
    assert sum(p.speed < 1.0 and p.size[0] > 1.0 for p in building.pedestrians) >= 5
    # In the first hall the scan holds machinery and workers (flagged dynamic) and a wide
    # spread of intensities (glass to metal).
    t_all, T, _ = _samples(building, dt=0.1)
    i = np.flatnonzero((T[:, 0, 3] > 90.0) & (np.abs(T[:, 1, 3] - LANES[0]) < 0.05))[0]
    scan, truth = _scan_at(building, float(t_all[i]))
    assert truth.dynamic.sum() > 50
    assert np.percentile(scan.intensity, 95) - np.percentile(scan.intensity, 5) > 60.0


def test_ensure_sequence_building():
    seq = ensure_sequence("building", frames=20)
    assert seq.frames == 20 and seq.meta["scene"] == "building"
    assert seq.meta["full_frames"] > 4000
    assert seq.meta["sensor_height_m"] == SENSOR_HEIGHT
    stamps, poses = read_tum(seq.ground_truth)
    assert len(stamps) == 20
    np.testing.assert_allclose(np.diff(stamps), 0.1, atol=1e-6)
    assert seq.meta["model"]["mixed_pixel_prob"] > 0  # the realistic VLP-16
