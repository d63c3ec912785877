"""Tests of the simulator: sensor geometry, noise, motion distortion, scenes, bags, cache."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from slam.errors import InputError
from slam.io.source import open_source
from slam.sim import (
    LidarModel,
    Pedestrian,
    Scene,
    ensure_sequence,
    iter_scans,
    make_scene,
    simulate,
    simulate_scan,
    simulate_scan_truth,
)
from slam.sim import geometry as g
from slam.sim.simulate import STAMP0, full_frames

ROOM = (10.0, 8.0, 4.0)  # box room (m), sensor 2 m above its floor


def _room_scene(**kwargs) -> Scene:
    sx, sy, sz = ROOM
    walls = [
        g.box_minmax((-sx / 2 - 0.2, -sy / 2 - 0.2, -0.2), (sx / 2 + 0.2, sy / 2 + 0.2, 0.0)),
        g.box_minmax((-sx / 2 - 0.2, -sy / 2 - 0.2, sz), (sx / 2 + 0.2, sy / 2 + 0.2, sz + 0.2)),
        g.box_minmax((-sx / 2 - 0.2, -sy / 2 - 0.2, 0), (-sx / 2, sy / 2 + 0.2, sz)),
        g.box_minmax((sx / 2, -sy / 2 - 0.2, 0), (sx / 2 + 0.2, sy / 2 + 0.2, sz)),
        g.box_minmax((-sx / 2, -sy / 2 - 0.2, 0), (sx / 2, -sy / 2, sz)),
        g.box_minmax((-sx / 2, sy / 2, 0), (sx / 2, sy / 2 + 0.2, sz)),
    ]
    return Scene.from_parts("room", walls, **kwargs)


def _room_distance(points_world: np.ndarray) -> np.ndarray:
    """Distance (m) of world points to the nearest face of the room."""
    sx, sy, sz = ROOM
    p = points_world
    return np.min(
        np.column_stack(
            [sx / 2 - np.abs(p[:, 0]), sy / 2 - np.abs(p[:, 1]), p[:, 2], sz - p[:, 2]]
        ),
        axis=1,
    )


def _moving(v: float = 2.0, yaw_rate: float = 0.0):
    """pose_at of a sensor at (0, -1, 2) m moving along +x at v m/s, turning at yaw_rate."""

    def pose_at(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        T = np.tile(np.eye(4), (t.size, 1, 1))
        T[:, :3, :3] = Rotation.from_euler("z", (yaw_rate * t)[:, None]).as_matrix()
        T[:, 0, 3] = -2.0 + v * t
        T[:, 1, 3] = -1.0
        T[:, 2, 3] = 2.0
        return T

    return pose_at


def _to_world(xyz: np.ndarray, poses: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", poses[:, :3, :3], xyz) + poses[:, :3, 3]


# ---------------------------------------------------------------------------- sensor model


def test_model_rays_rings_and_times():
    m = LidarModel()
    d = m.directions()
    assert d.shape == (1800, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    elev = np.rad2deg(np.arcsin(d[0, :, 2]))
    np.testing.assert_allclose(elev, np.linspace(-15, 15, 16), atol=1e-9)
    t = m.column_times()
    assert t[0] == 0.0 and abs(t[-1] - (0.1 - 0.1 / 1800)) < 1e-12
    # Clockwise seen from above: the azimuth decreases with time (from behind via the left).
    az = np.unwrap(np.arctan2(d[:, 0, 1], d[:, 0, 0]))
    assert np.all(np.diff(az) < 0)
    np.testing.assert_allclose(az[0] - az[-1], 2 * np.pi * (1 - 1 / 1800), atol=1e-9)
    with pytest.raises(InputError):
        LidarModel(spurious_fraction=1.5)


def test_static_scan_noise_spurious_and_fields():
    scene = _room_scene()
    model = LidarModel(spurious_fraction=0.02, range_sigma=0.012)
    scan, truth = simulate_scan_truth(scene, _moving(v=0.0), 5.0, model, np.random.default_rng(3))
    assert scan.stamp == 5.0
    assert len(scan) == 1800 * 16  # closed room: every ray returns
    assert scan.ring.dtype == np.int16 and scan.ring.min() == 0 and scan.ring.max() == 15
    elev = np.rad2deg(np.arctan2(scan.xyz[:, 2], np.hypot(scan.xyz[:, 0], scan.xyz[:, 1])))
    np.testing.assert_allclose(elev, -15.0 + 2.0 * scan.ring, atol=1e-6)
    assert scan.time.min() == 0.0 and 0.0995 < scan.time.max() < 0.1
    assert np.all(np.diff(scan.time) >= 0)  # firing order
    assert scan.intensity.dtype == np.float32 and 0 <= scan.intensity.min()
    assert scan.intensity.max() <= 255

    dist = _room_distance(_to_world(scan.xyz, _moving(0.0)(scan.stamp + scan.time)))
    off = dist > 0.1  # measured from the geometry alone
    assert 0.016 < off.mean() < 0.024  # ~ the 2 % asked for
    assert np.mean(off == truth.spurious) > 0.999
    sigma = np.std(dist[~off])
    assert 0.009 < sigma < 0.015  # range noise 0.012 m (projected on the walls: <= sigma)
    # Spurious returns float in the air, well in front of the surface.
    assert np.all(dist[truth.spurious] > 0.1) and np.mean(dist[truth.spurious] > 0.3) > 0.9
    assert np.median(scan.intensity[truth.spurious]) < np.median(scan.intensity[~off]) / 3


def test_motion_distortion_is_undone_by_per_point_time():
    """A sensor driving at 2 m/s while turning 0.5 rad/s: points are exact only when each is
    placed with the pose at its own time."""
    scene = _room_scene()
    pose_at = _moving(v=2.0, yaw_rate=0.5)
    model = LidarModel(spurious_fraction=0.0, range_sigma=0.0)
    scan = simulate_scan(scene, pose_at, 1.0, model, np.random.default_rng(0))
    exact = _room_distance(_to_world(scan.xyz, pose_at(scan.stamp + scan.time)))
    naive = _room_distance(_to_world(scan.xyz, pose_at(np.full(len(scan), scan.stamp))))
    assert np.percentile(np.abs(exact), 99) < 1e-3
    assert np.percentile(np.abs(naive), 90) > 0.05  # up to 0.2 m + 0.05 rad over the sweep


def test_pedestrian_is_seen_moving_and_flagged():
    ped = Pedestrian((2.0, -3.0), (2.0, 3.0), speed=1.2)
    np.testing.assert_allclose(ped.position(np.array([0.0, 1.0]))[:, :2], [[2, -3], [2, -1.8]])
    np.testing.assert_allclose(
        ped.position(np.array([6.0]))[0, :2], [2.0, 1.8]
    )  # turned back at 3 m
    model = LidarModel(spurious_fraction=0.0, range_sigma=0.0)
    with_ped = _room_scene(pedestrians=[ped])
    scans = [
        simulate_scan_truth(with_ped, _moving(v=0.0), t, model, np.random.default_rng(0))
        for t in (0.5, 1.5)
    ]
    centre_y = []
    for scan, truth in scans:
        world = _to_world(scan.xyz, _moving(0.0)(scan.stamp + scan.time))
        assert truth.dynamic.sum() > 100
        assert np.all(world[truth.dynamic, 2] <= 1.7 + 1e-6)
        assert np.all(np.abs(world[truth.dynamic, 0] - 2.0) <= 0.25 + 1e-6)
        centre_y.append(np.median(world[truth.dynamic, 1]))
    assert 0.9 < centre_y[1] - centre_y[0] < 1.5  # walked ~1.2 m in 1 s
    empty, truth = simulate_scan_truth(
        _room_scene(), _moving(v=0.0), 0.5, model, np.random.default_rng(0)
    )
    assert truth.dynamic.sum() == 0


# ---------------------------------------------------------------------------- scenes


@pytest.mark.parametrize("name", ["corridor", "plaza"])
def test_trajectory_smooth_and_revisits_start(name):
    scene = make_scene(name)
    model = LidarModel()
    t = np.arange(0.0, scene.duration, 0.01)
    T = scene.pose_at(t)
    xyz = T[:, :3, 3]
    v = np.diff(xyz, axis=0) / 0.01
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() < 1.6 and speed[200:].min() > 0.4
    assert np.max(np.linalg.norm(np.diff(v, axis=0), axis=1)) < 0.02  # no velocity jumps
    np.testing.assert_allclose(xyz[:, 2], 0.5)
    ypr = Rotation.from_matrix(T[:, :3, :3]).as_euler("ZYX", degrees=True)
    assert np.abs(ypr[:, 1:]).max() < 1.01 and np.abs(ypr[:, 1:]).max() > 0.5
    heading = np.rad2deg(np.arctan2(v[:, 1], v[:, 0]))
    yaw_err = (ypr[1:, 0] - heading + 180) % 360 - 180
    assert np.abs(yaw_err).max() < 1.0  # yaw follows the path tangent
    # Revisit: after a lap the robot passes within 0.1 m of where it started.
    lap = scene.trajectory.loop_length
    travelled = scene.trajectory.distance_at(t)
    later = travelled > 0.9 * lap
    assert np.linalg.norm(xyz[later] - xyz[0], axis=1).min() < 0.1
    assert travelled[-1] > 1.05 * lap
    assert 400 < full_frames(scene, model) < 800


def test_corridor_has_a_repeated_section():
    """The south and north legs share a door pattern: a noise-free sweep in the middle of
    the south leg equals one from the point-reflected pose on the north leg nearby."""
    scene = make_scene("corridor", pedestrians=False)
    model = LidarModel(spurious_fraction=0.0, range_sigma=0.0)
    south = np.eye(4)
    south[:3, 3] = [0.0, -5.75, 0.5]
    north = np.eye(4)
    north[:3, :3] = Rotation.from_euler("z", np.pi).as_matrix()
    north[:3, 3] = [0.0, 5.75, 0.5]
    ranges = []
    for T in (south, north):
        scan, truth = simulate_scan_truth(
            scene, lambda t, T=T: np.repeat(T[None], len(t), 0), 0.0, model
        )
        grid = np.full(1800 * 16, np.inf)
        grid[truth.column * 16 + scan.ring] = truth.true_range
        ranges.append(grid)
    near = ranges[0] < 5.0
    same = np.abs(ranges[0] - ranges[1]) < 0.01
    assert near.sum() > 10000 and same[near].mean() > 0.95
    # ...whereas another place of the same leg looks different.
    other = np.eye(4)
    other[:3, 3] = [-6.0, -5.75, 0.5]
    scan, truth = simulate_scan_truth(
        scene, lambda t: np.repeat(other[None], len(t), 0), 0.0, model
    )
    grid = np.full(1800 * 16, np.inf)
    grid[truth.column * 16 + scan.ring] = truth.true_range
    assert (np.abs(grid - ranges[0]) < 0.01)[near].mean() < 0.8


def test_simulate_is_deterministic_and_seeded():
    scene = make_scene("plaza")
    a = next(iter_scans(scene, 1, seed=1))
    b = next(iter_scans(scene, 1, seed=1))
    c = next(iter_scans(scene, 1, seed=2))
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert len(a) != len(c) or not np.array_equal(a.xyz, c.xyz)
    with pytest.raises(InputError, match="corridor"):
        make_scene("moon")


# ---------------------------------------------------------------------------- bags & cache


def test_bag_reads_back_as_written(corridor_short):
    scene = make_scene("corridor", seed=corridor_short.seed)
    expected = list(iter_scans(scene, 4, seed=corridor_short.seed))
    source = open_source(corridor_short.bag)
    assert len(source) == corridor_short.frames == 60
    stamps, poses = corridor_short.read_ground_truth()
    read = []
    for scan in source:
        read.append(scan)
        if len(read) == len(expected):
            break
    for want, got in zip(expected, read, strict=True):
        assert got.stamp == pytest.approx(want.stamp, abs=1e-6)
        np.testing.assert_allclose(got.xyz, want.xyz, atol=1e-5)
        np.testing.assert_array_equal(got.ring, want.ring)
        np.testing.assert_allclose(got.time, want.time, atol=1e-6)
        np.testing.assert_allclose(got.intensity, want.intensity, atol=1e-3)
    # Ground truth: one pose per scan at its header stamp = sweep start.
    assert len(stamps) == 60
    np.testing.assert_allclose(stamps[:4], [s.stamp for s in read], atol=1e-6)
    np.testing.assert_allclose(np.diff(stamps), 0.1, atol=1e-6)
    np.testing.assert_allclose(poses, scene.pose_at(stamps - STAMP0), atol=1e-6)


def _gt_pose_at(stamps, poses, times):
    """Per-point poses interpolated from ground truth (linear + slerp)."""
    slerp = Slerp(stamps, Rotation.from_matrix(poses[:, :3, :3]))
    T = np.tile(np.eye(4), (len(times), 1, 1))
    T[:, :3, :3] = slerp(times).as_matrix()
    for k in range(3):
        T[:, k, 3] = np.interp(times, stamps, poses[:, k, 3])
    return T


def test_ground_truth_reprojects_a_known_wall(corridor_short):
    """The end wall of the south leg (x = 12 m) seen 4 m apart: after undoing the per-column
    motion with the ground truth, points lie on the wall within a few cm; without, not."""
    stamps, poses = corridor_short.read_ground_truth()
    scans = {}
    for scan in open_source(corridor_short.bag):
        if scan.index in (24, 58):
            scans[scan.index] = scan
    assert poses[58, 0, 3] - poses[24, 0, 3] > 4.0
    fits = []
    for scan in scans.values():
        T = _gt_pose_at(stamps, poses, scan.stamp + scan.time)
        world = _to_world(scan.xyz, T)
        sel = (world[:, 0] > 11.5) & (world[:, 1] > -6.8) & (world[:, 1] < -4.7)
        sel &= (world[:, 2] > 0.3) & (world[:, 2] < 2.7)
        assert sel.sum() > 30
        res = np.abs(world[sel, 0] - 12.0)
        assert np.percentile(res, 95) < 0.05
        fits.append(np.median(world[sel, 0]))
        naive = _to_world(scan.xyz[sel], np.repeat(poses[scan.index][None], sel.sum(), 0))
        assert np.median(np.abs(naive[:, 0] - 12.0)) > 0.045  # ~1.25 m/s * 0.05 s uncorrected
    assert abs(fits[0] - fits[1]) < 0.01


def test_plaza_short_sequence(plaza_short):
    source = open_source(plaza_short.bag)
    assert len(source) == 60
    sizes = []
    for scan in source:
        sizes.append(len(scan))
        assert scan.time.max() - scan.time.min() > 0.099
    assert 15000 < np.mean(sizes) < 28800  # the sky returns nothing
    stamps, poses = plaza_short.read_ground_truth()
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert 0.12 < step[-10:].mean() < 0.15  # ~1.4 m/s at 10 Hz
    assert plaza_short.meta["loop_max_radius"] == 40.0


def test_cache_reuses_and_formats(tmp_path):
    a = ensure_sequence("corridor", frames=2, cache_dir=tmp_path, pedestrians=False)
    mtime = a.bag.stat().st_mtime_ns
    b = ensure_sequence("corridor", frames=2, cache_dir=tmp_path, pedestrians=False)
    assert b.bag == a.bag and b.bag.stat().st_mtime_ns == mtime
    c = ensure_sequence("corridor", frames=2, cache_dir=tmp_path, pedestrians=False, seed=1)
    assert c.bag.parent != a.bag.parent
    assert sorted(p.name.split("-")[0] for p in tmp_path.iterdir()) == ["corridor"] * 2
    assert (a.bag.parent / "ground_truth.tum").is_file()
    (c.bag.parent / "cache.json").write_text('{"digest": "old-version"}')  # made by old code
    d = ensure_sequence("corridor", frames=2, cache_dir=tmp_path, fmt="mcap")
    assert not c.bag.parent.exists() and a.bag.exists()  # stale sequences are pruned
    assert d.bag.is_dir()
    scans = list(open_source(d.bag))
    assert len(scans) == 2 and scans[1].stamp == pytest.approx(STAMP0 + 0.1)


def test_cache_key_covers_only_the_scene_own_sources(tmp_path, monkeypatch):
    from slam.sim import cache, registry

    assert "urban.py" not in registry.scene_sources("corridor")
    assert "registry.py" not in registry.scene_sources("urban")
    a = ensure_sequence("corridor", frames=2, cache_dir=tmp_path, pedestrians=False)
    key = a.bag.parent.name
    # a new scene in its own module leaves the corridor's key and its sequence alone
    extra = registry.SceneEntry("slam.sim.urban:urban", ("urban.py",))
    monkeypatch.setitem(registry.SCENES, "extra", extra)
    assert cache.sequence_key("corridor", frames=2, fmt="ros1", seed=0, pedestrians=False) == key
    gone = tmp_path / "extra-2-0-0000000000"
    gone.mkdir()
    (gone / "cache.json").write_text('{"digest": "old", "scene": "extra"}')
    unknown = tmp_path / "newer-2-0-0000000000"  # a scene of newer code running beside
    unknown.mkdir()
    (unknown / "cache.json").write_text('{"digest": "x", "scene": "not_registered_here"}')
    assert cache.prune_stale(tmp_path) == [gone]
    assert a.bag.exists() and unknown.exists()
    # a change to a source the scene uses changes its key
    monkeypatch.setattr(registry, "CORE_SOURCES", registry.CORE_SOURCES + ("urban.py",))
    assert cache.sequence_key("corridor", frames=2, fmt="ros1", seed=0, pedestrians=False) != key


def test_simulate_rejects_bad_arguments(tmp_path):
    with pytest.raises(InputError):
        simulate("corridor", tmp_path, frames=100000)
    with pytest.raises(InputError):
        simulate("corridor", tmp_path, frames=2, fmt="zip")
    with pytest.raises(InputError, match="os128"):
        simulate("corridor", tmp_path, frames=2, sensor="vlp32")
    with pytest.raises(InputError, match="urban"):
        simulate("city", tmp_path, frames=2)
