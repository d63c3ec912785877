"""Tests of the named sensor models (slam/sim/sensors.py) and the car-speed urban scene
(slam/sim/urban.py, route trajectories of slam/sim/trajectory.py)."""

from __future__ import annotations

import numpy as np
import pytest

from slam.errors import InputError
from slam.io.bags import BagSource
from slam.io.info import describe
from slam.sim import SENSORS, LidarModel, ensure_sequence, get_sensor, make_scene, simulate
from slam.sim.cache import sequence_key
from slam.sim.registry import scene_sensor
from slam.sim.sensors import hdl64_elevations
from slam.sim.simulate import effective_model, full_frames
from slam.sim.trajectory import route_trajectory

# name: beams, elevation span (deg), layout, per-point fields the driver publishes, points
# per scan (urban start, realistic sensor): lower / upper bound.
EXPECTED = {
    "vlp16": (16, (-15.0, 15.0), "velodyne", {"ring", "time"}, (20_000, 28_800)),
    "hdl32": (32, (-30.67, 10.67), "velodyne", {"ring", "time"}, (50_000, 69_504)),
    "hdl64": (64, (-24.9, 2.0), "xyzi", set(), (100_000, 133_312)),
    "os128": (128, (-22.5, 22.5), "ouster", {"ring", "t", "range"}, (100_000, 131_072)),
}


def _elevation_clusters(xyz: np.ndarray, gap_deg: float = 0.1) -> np.ndarray:
    """Distinct beam elevations (deg, ascending) of the points: sorted elevations split
    where consecutive values differ by more than ``gap_deg``."""
    el = np.sort(np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))))
    cuts = np.flatnonzero(np.diff(el) > gap_deg)
    return np.array([c.mean() for c in np.split(el, cuts + 1)])


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sensor_models_beams_and_elevation_span(name):
    beams, (lo, hi), layout, _, _ = EXPECTED[name]
    spec = get_sensor(name)
    assert spec.layout == layout
    for realistic in (False, True):
        m = spec.model(realistic)
        el = np.degrees(m.elevations())
        assert m.beams == beams and el.shape == (beams,)
        assert np.all(np.diff(el) > 0.3)  # distinct, ascending (ring 0 at the bottom)
        assert el[0] == pytest.approx(lo, abs=1e-6) and el[-1] == pytest.approx(hi, abs=1e-6)
        assert m.rate_hz == 10.0 and m.has_calibration_error == realistic
    m = spec.model()
    step = 360.0 / m.columns
    assert 0.16 <= step <= 0.36  # realistic horizontal resolution at 10 Hz


def test_hdl64_has_two_blocks_of_beams():
    el = np.asarray(hdl64_elevations())
    lower, upper = np.diff(el[:32]), np.diff(el[32:])
    np.testing.assert_allclose(upper, 1.0 / 3.0, atol=2e-3)  # upper block: 1/3 deg
    np.testing.assert_allclose(lower, 0.517, atol=2e-3)  # lower block: ~1/2 deg
    assert el[32] - el[31] == pytest.approx(0.54, abs=0.01)
    assert get_sensor("hdl64").model().columns == 2083  # 0.17 deg at 10 Hz


def test_default_sensor_is_the_old_model_and_keys_are_separate():
    assert SENSORS["vlp16"].model() == LidarModel()
    assert SENSORS["vlp16"].model(realistic=True) == LidarModel.realistic()
    assert scene_sensor("park") == LidarModel.realistic() == effective_model("park")
    assert scene_sensor("corridor") == LidarModel() == effective_model(make_scene("plaza"))
    assert effective_model("urban") == LidarModel.realistic()
    assert effective_model("park", sensor="os128") == get_sensor("os128").model(True)
    assert effective_model(make_scene("plaza"), sensor="hdl64") == get_sensor("hdl64").model()
    keys = {
        s: sequence_key("corridor", frames=5, fmt="ros1", seed=0, pedestrians=True, sensor=s)
        for s in SENSORS
    }
    assert len(set(keys.values())) == len(SENSORS)
    assert keys["vlp16"].startswith("corridor-5-0-")  # older sequences keep their names
    assert keys["hdl64"].startswith("corridor-hdl64-5-0-")
    with pytest.raises(InputError, match="hdl64"):
        get_sensor("hdl65")
    with pytest.raises(InputError, match="ascending"):
        LidarModel(beams=3, elevations_deg=(0.0, -1.0, 1.0))


@pytest.fixture(scope="module")
def sensor_bags(tmp_path_factory):
    """Two scans of the urban scene's start per sensor: {name: SimResult}."""
    root = tmp_path_factory.mktemp("sensors")
    return {name: simulate("urban", root / name, frames=2, sensor=name) for name in EXPECTED}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sensor_bags_have_the_drivers_fields(sensor_bags, name):
    beams, (lo, hi), layout, extra, (n_lo, n_hi) = EXPECTED[name]
    res = sensor_bags[name]
    spec = get_sensor(name)
    info = describe(res.bag)
    topic = info["topics"][spec.topic]
    fields = {f["name"]: f for f in topic["fields"]}
    assert set(fields) == {"x", "y", "z", "intensity"} | extra | (
        {"reflectivity", "ambient"} if name == "os128" else set()
    )
    assert res.meta["topic"] == spec.topic and res.sensor == name
    assert topic["point_step"] == {"velodyne": 22, "xyzi": 16, "ouster": 48}[layout]
    scans = list(BagSource(res.bag))
    assert len(scans) == 2
    for scan in scans:
        assert n_lo <= len(scan) <= n_hi
        el = _elevation_clusters(scan.xyz)
        assert len(el) == beams
        assert el[0] == pytest.approx(lo, abs=0.01) and el[-1] == pytest.approx(hi, abs=0.01)
    scan = scans[1]
    if name == "hdl64":  # KITTI-converted: no ring, no per-point time
        assert scan.ring is None and scan.time is None
        # Scan lines one after the other, from the top beam down (KITTI .bin order).
        el = np.degrees(np.arctan2(scan.xyz[:, 2], np.hypot(scan.xyz[:, 0], scan.xyz[:, 1])))
        beam = np.searchsorted(np.asarray(hdl64_elevations()) - 0.05, el) - 1
        assert np.all(np.diff(beam) <= 0)
        return
    assert scan.ring.min() == 0 and scan.ring.max() == beams - 1
    assert scan.time.min() == pytest.approx(0.0, abs=1e-6)
    assert scan.time.max() == pytest.approx(0.1 - 0.1 / spec.model().columns, abs=1e-5)
    z_of_ring0 = scan.xyz[scan.ring == 0, 2] / np.linalg.norm(scan.xyz[scan.ring == 0], axis=1)
    if name == "os128":
        assert fields["t"]["datatype"] == "UINT32"
        assert (topic["time_field"], topic["time_unit"]) == ("t", "ns")
        assert np.all(z_of_ring0 > 0.38)  # Ouster's ring 0 is the top beam (+22.5 deg)
        # Row-major like the driver's organised cloud: ring by ring, time rising within.
        assert np.all(np.diff(scan.ring) >= 0)
        same = np.diff(scan.ring) == 0
        assert np.all(np.diff(scan.time)[same] >= 0)
    else:
        assert fields["time"]["datatype"] == "FLOAT32"
        assert np.all(z_of_ring0 < -0.25)  # Velodyne's ring 0 is the bottom beam
        assert np.all(np.diff(scan.time) >= 0)  # column-major firing order


def test_ensure_sequence_caches_sensors_separately(tmp_path):
    a = ensure_sequence("corridor", frames=2, sensor="hdl32", cache_dir=tmp_path)
    b = ensure_sequence("corridor", frames=2, cache_dir=tmp_path)
    assert a.bag.parent != b.bag.parent and "hdl32" in a.bag.parent.name
    assert a.sensor == "hdl32" and b.sensor == "vlp16" and "sensor" not in b.meta
    assert a.meta["model"]["beams"] == 32 and a.meta["layout"] == "velodyne"
    again = ensure_sequence("corridor", frames=2, sensor="hdl32", cache_dir=tmp_path)
    assert again.bag == a.bag
    np.testing.assert_array_equal(a.read_ground_truth()[1], b.read_ground_truth()[1])


# ---------------------------------------------------------------------------- urban


@pytest.fixture(scope="module")
def urban_drive():
    """(scene, stamps (N,) s at 10 Hz, poses (N,4,4)) of the whole urban drive."""
    scene = make_scene("urban")
    t = np.arange(full_frames(scene, LidarModel())) * 0.1
    return scene, t, scene.pose_at(t)


def test_urban_route_length_speed_and_stops(urban_drive):
    scene, t, T = urban_drive
    xy = T[:, :2, 3]
    step = np.hypot(*np.diff(xy, axis=0).T)
    speed = step / 0.1
    assert step.sum() >= 1000.0 and scene.trajectory.length >= 1000.0
    assert 12.0 <= speed.max() <= 15.0 + 1e-6
    # Braking <= 2.5 m/s^2 (+ the 0.1 s sampling of the speed at a standstill).
    assert np.all(np.abs(np.diff(speed)) / 0.1 <= 4.0)
    # Stops: runs of >= 3 s at speed 0 away from the start, at junctions.
    still = np.concatenate([[False], speed < 1e-3, [False]]).astype(int)
    starts, ends = np.flatnonzero(np.diff(still) == 1), np.flatnonzero(np.diff(still) == -1)
    long_stops = [(a, b) for a, b in zip(starts, ends, strict=True) if (b - a) * 0.1 >= 3.0]
    assert len(long_stops) >= 3
    assert T[-1, 2, 3] == pytest.approx(1.8, abs=0.05)  # roof-mounted sensor
    # Cornering: yaw rate and lateral acceleration of a car (< 3 m/s^2).
    yaw = np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    rate = np.diff(yaw) / 0.1
    assert np.abs(rate).max() < np.deg2rad(60.0)
    assert np.max(np.abs(rate) * speed) < 3.0
    assert len(scene.pedestrians) >= 10  # walkers and moving cars


def test_urban_revisits_streets_in_both_directions(urban_drive):
    scene, t, T = urban_drive
    xy, heading = T[:, :2, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])
    moving = np.flatnonzero(np.hypot(*np.diff(xy, axis=0).T) > 0.5)  # > 5 m/s
    i, j = np.meshgrid(moving, moving, indexing="ij")
    later = (t[j] - t[i]) > 30.0
    near = np.hypot(*(xy[i] - xy[j]).T) < scene.revisit_radius
    turn = np.abs(np.angle(np.exp(1j * (heading[i] - heading[j]))))
    opposite = later & near & (turn > np.deg2rad(160.0))
    # Along a whole street (> 100 m of the first pass), the other lane ~4.4 m away.
    rows = np.unique(i[opposite])
    travelled = np.hypot(*np.diff(xy[rows], axis=0).T)
    assert travelled[travelled < 2.0].sum() > 200.0
    dist = np.where(opposite, np.hypot(*(xy[i] - xy[j]).T), np.inf)
    gap = dist.min(axis=1)[np.isfinite(dist.min(axis=1))]  # nearest pose of the other pass
    assert np.median(gap) == pytest.approx(4.4, abs=0.3)


@pytest.mark.parametrize("name", ["hdl64", "os128"])
def test_urban_runs_with_dense_sensors(sensor_bags, name):
    res = sensor_bags[name]
    stamps, poses = res.read_ground_truth()
    assert len(stamps) == 2 and res.meta["scene"] == "urban"
    assert res.meta["model"]["beams"] == EXPECTED[name][0]
    assert res.meta["model"]["calib_elevation_deg"] > 0  # the scene's realistic errors


def test_route_trajectory_stops_and_limits():
    xy = np.column_stack([np.arange(0.0, 200.01, 0.05), np.zeros(4001)])
    traj = route_trajectory(
        xy,
        speed_limit=np.full(len(xy), 10.0),
        stops=[(100.0, 4.0)],
        height=1.8,
        rng=np.random.default_rng(0),
        accel=1.0,
        decel=2.0,
        wobble_deg=0.0,
        vibration_deg=0.0,
    )
    # Accelerate 50 m (v^2 = 2 a s), brake 25 m, stop 4 s, again: analytic duration.
    t_run = 10.0 / 1.0 + 10.0 / 2.0  # ramps (s)
    cruise = (100.0 - 50.0 - 25.0) / 10.0
    assert traj.duration == pytest.approx(2 * (t_run + cruise) + 4.0, rel=2e-3)
    t_stop = t_run + cruise
    x = traj.pose_at(np.array([t_stop + 0.1, t_stop + 2.0, t_stop + 3.9]))[:, 0, 3]
    np.testing.assert_allclose(x, 100.0, atol=1e-3)
    T = traj.pose_at(np.array([t_stop + 2.0, 5.0, t_stop - 2.0]))
    pitch = -np.arcsin(T[:, 2, 0])
    assert abs(pitch[0]) < 1e-9  # at rest: no sway
    assert pitch[1] < -np.deg2rad(0.1) and pitch[2] > np.deg2rad(0.3)  # squat / dive


def test_kitti_style_hdl64_scans_are_motion_compensated():
    """The HDL-64E is published as KITTI publishes it: every point in the sensor frame at the
    sweep start (the header stamp). Moved into the world with the pose at the stamp, each
    point lies at its measured range from where the sensor was when its column fired; the
    VLP-16's raw points, moved the same way, are off by the car's motion over the sweep."""
    from itertools import islice

    from slam.sim.simulate import iter_scans

    scene = make_scene("urban")
    for name in ("hdl64", "vlp16"):
        ideal = get_sensor(name).model()  # range noise only, no calibration errors
        scans = iter_scans(scene, 80, model=ideal, with_truth=True, sensor=name)
        scan, truth = next(islice(scans, 79, None))  # the car at speed
        T = truth.T_world_sensor_columns
        speed = np.linalg.norm(T[-1][:3, 3] - T[0][:3, 3]) / ideal.period
        assert speed > 5.0, speed
        world = scan.xyz @ T[0][:3, :3].T + T[0][:3, 3]
        fired_from = T[truth.column][:, :3, 3]
        off = np.abs(np.linalg.norm(world - fired_from, axis=1) - truth.true_range)
        real = ~truth.spurious
        late = real & (truth.column > 0.8 * ideal.columns)
        if name == "hdl64":
            assert scan.time is None  # nothing left to deskew
            # measured at 10.4 m/s: 2.6 cm (the range noise's 99th percentile) compensated,
            # 101 cm with the raw points
            assert np.percentile(off[real], 99) < 4 * ideal.range_sigma, off[real].max()
        else:
            assert np.median(off[late]) > 0.2 * speed * ideal.period, np.median(off[late])  # 76 cm
