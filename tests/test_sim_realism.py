"""Tests of the simulator's realism options (calibration errors, range-dependent noise,
mixed pixels, porous vegetation, vehicle motion on uneven ground) and of the park scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import InputError
from slam.io.source import open_source
from slam.sim import LidarModel, Scene, ensure_sequence, iter_scans, make_scene
from slam.sim import geometry as g
from slam.sim.cache import sequence_key
from slam.sim.lidar import simulate_scan_truth
from slam.sim.simulate import effective_model, full_frames, model_dict
from slam.sim.trajectory import closed_curve_trajectory, rounded_rectangle

IDEAL = dict(range_sigma=0.0, spurious_fraction=0.0)


def _static(x=0.0, y=0.0, z=1.0):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return lambda t: np.repeat(T[None], len(np.atleast_1d(t)), 0)


def _world(scan, truth) -> np.ndarray:
    T = truth.T_world_sensor_columns[truth.column]
    return np.einsum("nij,nj->ni", T[:, :3, :3], scan.xyz) + T[:, :3, 3]


def _wall_scene(distance: float = 10.0, extra=()) -> Scene:
    """A floor and a large wall facing the sensor at x = distance (m)."""
    parts = [
        g.box_minmax((-30, -30, -0.2), (30, 30, 0.0)),
        g.box_minmax((distance, -30, 0.0), (distance + 0.3, 30, 12.0)),
        *extra,
    ]
    return Scene.from_parts("wall", parts)


# ---------------------------------------------------------------------------- defaults


def test_realism_is_off_by_default_and_draws_are_unchanged():
    m = LidarModel()
    assert m.range_sigma_per_m == 0 and m.mixed_pixel_prob == 0
    assert m.calib_elevation_deg == m.calib_azimuth_deg == m.calib_range_m == 0
    assert not m.has_calibration_error
    np.testing.assert_array_equal(m.true_directions(), m.directions())
    scene = make_scene("corridor")
    pose_at = scene.pose_at
    rng = np.random.default_rng(5)
    scan, truth = simulate_scan_truth(scene, pose_at, 3.0, m, rng)
    # Same scan with the realism options spelled out as zero (and another calibration seed).
    explicit = LidarModel(
        range_sigma_per_m=0.0,
        calib_elevation_deg=0.0,
        calib_azimuth_deg=0.0,
        calib_range_m=0.0,
        calibration_seed=9,
        mixed_pixel_prob=0.0,
    )
    again, _ = simulate_scan_truth(scene, pose_at, 3.0, explicit, np.random.default_rng(5))
    for key in ("xyz", "intensity", "ring", "time"):
        np.testing.assert_array_equal(getattr(scan, key), getattr(again, key))
    assert not truth.mixed.any() and not truth.porous.any()
    # The random draws are exactly those of the original model: range noise, intensity
    # noise, spurious selection (+ ranges and intensities of the k spurious returns).
    ref = np.random.default_rng(5)
    n, k = len(scan), int(truth.spurious.sum())
    ref.normal(0.0, m.range_sigma, n)
    ref.normal(0.0, 1.5, n)
    ref.random(n)
    ref.random(k)
    ref.random(k)
    assert ref.bit_generator.state == rng.bit_generator.state
    assert effective_model("corridor") == effective_model("plaza") == LidarModel()
    assert make_scene("plaza").sensor is None


def test_model_validation_and_preset():
    with pytest.raises(InputError):
        LidarModel(mixed_pixel_prob=1.5)
    with pytest.raises(InputError):
        LidarModel(calib_range_m=-0.01)
    with pytest.raises(InputError):
        LidarModel(mixed_pixel_min_gap=3.0, mixed_pixel_max_gap=2.0)
    r = LidarModel.realistic()
    assert r.has_calibration_error and r.mixed_pixel_prob > 0 and r.range_sigma_per_m > 0
    assert LidarModel.realistic(mixed_pixel_prob=0.0).mixed_pixel_prob == 0.0
    # Calibration: fixed per sensor (seed), about the configured spread.
    a, b = r.calibration(), r.calibration()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    other = LidarModel.realistic(calibration_seed=1).calibration()
    assert not np.array_equal(a[0], other[0])
    big = LidarModel(beams=2000, fov_deg=(-15, 15), calib_elevation_deg=0.1, calib_range_m=0.02)
    d_el, d_az, d_r = big.calibration()
    assert np.rad2deg(d_el.std()) == pytest.approx(0.1, rel=0.1)
    assert d_r.std() == pytest.approx(0.02, rel=0.1) and not d_az.any()


# ---------------------------------------------------------------------------- calibration


def test_elevation_offset_moves_points_by_range_times_angle():
    """The ray travels 0.2 deg higher than the driver assumes: at 10 m the published point
    is 3.5 cm away from where the ray really hit the wall (below it)."""
    m = LidarModel(calib_elevation_deg=0.2, **IDEAL)
    off = np.deg2rad(0.2)
    m.calibration = lambda: (np.full(m.beams, off), np.zeros(m.beams), np.zeros(m.beams))
    scene = _wall_scene(10.0)
    scan, truth = simulate_scan_truth(scene, _static(z=2.0), 0.0, m)
    true_hit = truth.ray_dir * truth.true_range[:, None]
    moved = np.linalg.norm(scan.xyz - true_hit, axis=1)
    np.testing.assert_allclose(moved, 2 * truth.true_range * np.sin(off / 2), rtol=1e-6)
    # The beams near the horizon, straight ahead: the wall point is 3.5 cm too low.
    world = _world(scan, truth)
    az = np.arctan2(scan.xyz[:, 1], scan.xyz[:, 0])
    ahead = (np.abs(az) < np.deg2rad(1.0)) & (np.abs(world[:, 0] - 10.0) < 0.05)
    el = np.deg2rad(-15.0 + 2.0 * scan.ring[ahead])
    dz = world[ahead, 2] - (2.0 + 10.0 * np.tan(el + off))  # published - true hit height
    # r (sin el - sin(el + off)) with r = 10 / cos(el + off): about -10 m x 0.2 deg.
    np.testing.assert_allclose(
        dz, 10 * (np.sin(el) - np.sin(el + off)) / np.cos(el + off), atol=5e-4
    )
    assert np.all(np.abs(dz + 0.0349) < 0.002)
    # Without the error the same points lie where the rays hit.
    ideal, it = simulate_scan_truth(scene, _static(z=2.0), 0.0, LidarModel(**IDEAL))
    np.testing.assert_allclose(ideal.xyz, it.ray_dir * it.true_range[:, None], atol=1e-9)


def test_azimuth_and_range_offsets_per_beam():
    m = LidarModel(calib_azimuth_deg=0.15, calib_range_m=0.03, calibration_seed=4, **IDEAL)
    d_el, d_az, d_r = m.calibration()
    assert not d_el.any() and np.abs(d_r).max() > 0.02
    scan, truth = simulate_scan_truth(_wall_scene(10.0), _static(z=2.0), 0.0, m)
    # Published range = true range + the beam's offset; direction = the nominal one.
    r = np.linalg.norm(scan.xyz, axis=1)
    np.testing.assert_allclose(r - truth.true_range, d_r[scan.ring], atol=1e-9)
    nominal = m.directions().reshape(-1, 3)[truth.column * m.beams + scan.ring]
    np.testing.assert_allclose(scan.xyz / r[:, None], nominal, atol=1e-12)
    # The true ray is turned by the azimuth offset (scaled by cos elevation on the sphere).
    cosang = np.clip(np.sum(truth.ray_dir * nominal, axis=1), -1, 1)
    el = np.deg2rad(-15.0 + 2.0 * scan.ring)
    expected = np.arccos(
        np.clip(np.sin(el) ** 2 + np.cos(el) ** 2 * np.cos(d_az[scan.ring]), -1, 1)
    )
    np.testing.assert_allclose(np.arccos(cosang), expected, atol=2e-6)


def test_range_noise_grows_with_range():
    m = LidarModel(range_sigma=0.005, range_sigma_per_m=0.001, spurious_fraction=0.0)
    scene = Scene.from_parts(
        "two walls",
        [
            g.box_minmax((4.0, -3, -5), (4.3, 3, 5)),  # near wall ahead, 4 m
            g.box_minmax((-40.3, -30, -25), (-40.0, 30, 25)),  # far wall behind, 40 m
        ],
    )
    scan, truth = simulate_scan_truth(scene, _static(z=0.0), 0.0, m, np.random.default_rng(1))
    err = np.linalg.norm(scan.xyz, axis=1) - truth.true_range
    near, far = truth.true_range < 6, truth.true_range > 39
    assert near.sum() > 500 and far.sum() > 500
    assert np.std(err[near]) == pytest.approx(
        0.005 + 0.001 * np.mean(truth.true_range[near]), rel=0.12
    )
    assert np.std(err[far]) == pytest.approx(
        0.005 + 0.001 * np.mean(truth.true_range[far]), rel=0.12
    )


# ---------------------------------------------------------------------------- mixed pixels


def test_mixed_pixels_float_between_foreground_and_background():
    """Twenty posts 6 m ahead of a wall at 12 m: returns next to the posts' vertical edges
    become mixed pixels at the configured rate, strictly between the two ranges."""
    boxes = [g.box_minmax((6.0, y, 0.0), (6.5, y + 0.4, 3.0)) for y in np.arange(-8.0, 8.0, 0.8)]
    scene = _wall_scene(12.0, boxes)
    m = LidarModel(mixed_pixel_prob=0.3, mixed_pixel_max_gap=8.0, **IDEAL)
    scan, truth = simulate_scan_truth(scene, _static(z=1.0), 0.0, m, np.random.default_rng(2))
    ideal, it = simulate_scan_truth(scene, _static(z=1.0), 0.0, LidarModel(**IDEAL))
    assert len(ideal) == len(scan)
    np.testing.assert_array_equal(it.true_range, truth.true_range)
    # Edge returns from the ideal range image: a same-beam neighbour 0.3-8 m nearer/farther.
    grid = np.full((m.columns, m.beams), np.nan)
    grid[it.column, ideal.ring] = it.true_range
    gaps = [
        np.abs(np.diff(grid, axis=0, prepend=np.nan)),
        np.abs(np.diff(grid, axis=0, append=np.nan)),
    ]
    with np.errstate(invalid="ignore"):
        ok = [np.where((x >= 0.3) & (x <= 8.0), x, 0.0) for x in gaps]
    edge = np.fmax(*ok)[it.column, ideal.ring]
    big = edge > 3.0  # post / wall edges (the rest: the posts' sides)
    edge = edge > 0
    assert big.sum() > 400
    assert not truth.mixed[~edge].any()
    assert 0.24 < truth.mixed[edge].mean() < 0.36  # +-3.5 sigma
    assert 0.23 < truth.mixed[big].mean() < 0.37
    r = np.linalg.norm(scan.xyz, axis=1)
    x = _world(scan, truth)[:, 0]
    mixed = truth.mixed
    # Veil points float in the air between the boxes' front (x = 6) and the wall (x = 12).
    assert np.all((x[mixed & big] > 6.2) & (x[mixed & big] < 11.8))
    np.testing.assert_allclose(r[~mixed], truth.true_range[~mixed], atol=1e-9)  # untouched
    assert np.median(scan.intensity[mixed]) < np.median(scan.intensity[edge & ~mixed])


# ---------------------------------------------------------------------------- porous


def test_porous_crown_returns_spread_inside_the_volume():
    """A porous sphere (radius 2 m, extinction 1/m) 8 m ahead of a wall at 14 m: returns lie
    inside the crown at exponentially distributed depths; some rays pass through."""
    centre, radius, k = np.array([8.0, 0.0, 3.2]), 2.0, 1.0
    crown = g.porous(g.sphere(centre, radius, g.FOLIAGE, 24), k)
    scene = _wall_scene(14.0, [crown])
    assert scene.porous_triangles is not None and len(scene.porous_triangles) > 100
    m = LidarModel(**IDEAL)
    scan, truth = simulate_scan_truth(scene, _static(z=1.0), 0.0, m, np.random.default_rng(3))
    world = _world(scan, truth)
    leafy = truth.porous
    assert leafy.sum() > 500
    inner = np.linalg.norm(world[leafy] - centre, axis=1)
    assert np.all(inner < radius + 0.01)
    assert np.mean(inner < radius - 0.3) > 0.4  # not only on the surface
    # Depth of each return behind the (analytic) entry point, and each ray's chord.
    d = truth.ray_dir
    oc = np.array([0.0, 0.0, 1.0]) - centre
    bq = np.sum(d * oc, axis=1)
    disc = bq**2 - (oc @ oc - radius**2)
    entry = -bq - np.sqrt(np.maximum(disc, 0))
    through = (disc > 0.05) & (entry > 0)  # rays crossing the sphere (not grazing)
    chord = 2 * np.sqrt(np.maximum(disc, 0))
    depth = truth.true_range[leafy & through] - entry[leafy & through]
    assert np.all(depth > -0.02)
    # Exponential depth truncated at the chord: E[depth] = 1/k - L e^{-kL} / (1 - e^{-kL}).
    L = chord[leafy & through]
    expected = 1 / k - L * np.exp(-k * L) / (1 - np.exp(-k * L))
    assert np.mean(depth) == pytest.approx(np.mean(expected), rel=0.08)
    # Pass-through rate matches Beer-Lambert over each ray's chord.
    crossing = through & (truth.true_range > entry - 0.01)
    assert crossing.sum() > 500
    passed = crossing & ~leafy
    assert passed.sum() > 20
    assert passed.sum() / crossing.sum() == pytest.approx(
        np.mean(np.exp(-k * chord[crossing])), rel=0.25
    )
    assert np.all(np.abs(world[passed, 0] - 14.0) < 0.05)  # ...and hit the wall behind


# ---------------------------------------------------------------------------- motion


def test_trajectory_on_terrain_with_vibration_and_speed_changes():
    path = rounded_rectangle(40.0, 20.0, corner_length=4.0)
    kw = dict(loops=1.0, speed=2.0, height=0.8)
    flat = closed_curve_trajectory(path, rng=np.random.default_rng(0), **kw)
    same = closed_curve_trajectory(
        path, rng=np.random.default_rng(0), speed_variation=0.0, vibration_deg=0.0, **kw
    )
    t = np.linspace(0, flat.duration, 3000)
    np.testing.assert_array_equal(flat.pose_at(t), same.pose_at(t))
    traj = closed_curve_trajectory(
        path,
        rng=np.random.default_rng(0),
        speed_variation=0.2,
        vibration_deg=0.3,
        terrain=lambda x, y: 0.05 * x,
        **kw,
    )
    t = np.arange(0, traj.duration, 0.01)
    T = traj.pose_at(t)
    np.testing.assert_allclose(T[:, 2, 3], 0.05 * T[:, 0, 3] + 0.8, atol=1e-3)
    v = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / 0.01
    assert v[500:].max() > 2.1 and v[500:].min() < 1.8  # accelerates and brakes
    ypr = Rotation.from_matrix(T[:, :3, :3]).as_euler("ZYX")
    # On the south side (heading +x, uphill 5 %) the nose points up by ~2.9 deg.
    south = (np.abs(T[:, 1, 3] + 10.0) < 0.01) & (np.abs(T[:, 0, 3]) < 10)
    assert np.rad2deg(np.median(ypr[south, 1])) == pytest.approx(
        -np.rad2deg(np.arctan(0.05)), abs=0.3
    )
    # High-frequency vibration: a few tenths of a degree above 1.5 Hz.
    spec = np.abs(np.fft.rfft(ypr[:, 2] - ypr[:, 2].mean())) / len(t) * 2
    f = np.fft.rfftfreq(len(t), 0.01)
    assert 0.05 < np.rad2deg(spec[f > 1.5].max()) < 0.3


# ---------------------------------------------------------------------------- park


def test_park_scene_route_and_revisits():
    scene = make_scene("park")
    assert scene.sensor == LidarModel.realistic() == effective_model("park")
    assert scene.porous_triangles is not None and len(scene.porous_triangles) > 5000
    assert 50.0 <= scene.loop_max_radius <= 80.0 and scene.revisit_radius == 5.0
    span = scene.vertices.max(0) - scene.vertices.min(0)
    assert span[0] >= 150 and span[1] >= 120
    traj = scene.trajectory
    assert 300 < traj.length < 400
    t = np.arange(0.0, scene.duration, 0.1)
    T = scene.pose_at(t)
    xyz = T[:, :3, 3]
    v = np.linalg.norm(np.diff(xyz, axis=0), axis=1) / 0.1
    assert 1.8 < np.mean(v) < 2.1 and v.max() < 2.5
    assert 1.0 < np.ptp(xyz[:, 2]) < 2.0  # uneven ground
    # The avenue (|x| < 12) is driven east on y = -1.5 (from the start, and again at the
    # end of the lap) and in between back west on y = +1.5.
    yaw = np.arctan2(np.diff(xyz[:, 1]), np.diff(xyz[:, 0]))
    s = traj.distance_at(t[:-1])
    ave = np.abs(xyz[:-1, 0]) < 12
    east = ave & (np.cos(yaw) > 0.9)
    west = ave & (np.cos(yaw) < -0.9)
    assert east.sum() > 100 and west.sum() > 100
    np.testing.assert_allclose(xyz[:-1][east, 1], -1.5, atol=0.01)
    np.testing.assert_allclose(xyz[:-1][west, 1], 1.5, atol=0.01)
    gap = np.min(
        np.linalg.norm(xyz[:-1][west][:, None, :2] - xyz[:-1][east][None, :, :2], axis=2), 1
    )
    assert np.all(gap < scene.revisit_radius) and np.all(gap > 2.5)
    # It ends past the start: the route closes on itself.
    later = s > 0.9 * traj.loop_length
    assert np.linalg.norm(xyz[:-1][later] - xyz[0], axis=1).min() < 0.1
    assert 1500 < full_frames(scene, scene.sensor) < 2000


def test_park_short_sequence(tmp_path):
    res = ensure_sequence("park", frames=5, cache_dir=tmp_path)
    assert res.meta["model"] == json.loads(json.dumps(model_dict(LidarModel.realistic())))
    assert "elevations_deg" not in res.meta["model"]  # sim.json as before the sensor table
    assert res.meta["loop_max_radius"] == make_scene("park").loop_max_radius
    scans = list(open_source(res.bag))
    assert len(scans) == 5
    for scan in scans:
        assert 15000 < len(scan) < 28800 and np.isfinite(scan.xyz).all()
    # The cache key follows the effective model.
    key = sequence_key("park", frames=5, fmt="ros1", seed=0, pedestrians=True)
    assert key == res.bag.parent.name
    assert key == sequence_key(
        "park", frames=5, fmt="ros1", seed=0, pedestrians=True, model=LidarModel.realistic()
    )
    assert key != sequence_key(
        "park", frames=5, fmt="ros1", seed=0, pedestrians=True, model=LidarModel()
    )
    scene = make_scene("park")
    (scan, truth), *_ = iter_scans(scene, 1, with_truth=True)
    assert truth.porous.mean() > 0.05 and truth.mixed.any()
