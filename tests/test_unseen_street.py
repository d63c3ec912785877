"""The ``street`` scene (slam/sim/street.py): a straight drive at car speed with junction
stops and a wide avenue of few features, registered without touching other scenes' keys."""

from __future__ import annotations

import numpy as np

from slam.sim import cache, registry
from slam.sim.lidar import LidarModel, simulate_scan
from slam.sim.street import AVENUE, STOP_BEFORE, STOPS, WIDE, street


def _drive(scene, dt: float = 0.1):
    t = np.arange(0.0, scene.trajectory.duration, dt)
    T = scene.pose_at(t)
    v = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt
    return t, T, v


def test_street_drive_speed_stops_and_lanes():
    scene = street(0)
    t, T, v = _drive(scene)
    assert 850.0 < scene.trajectory.length < 900.0
    assert 14.5 < v.max() < 15.3  # car speed, within the limit
    # it reaches cruise speed inside the first 300 frames (the sweep's prefix) ...
    assert v[:300].max() > 14.5
    # ... and stands still at each junction stop for about its dwell time
    x = T[:, 0, 3]
    for xj, dwell in STOPS:
        still = (v < 0.05) & (np.abs(x[1:] - (xj - STOP_BEFORE)) < 1.0)
        assert abs(still.sum() * 0.1 - dwell) < 0.6, (xj, still.sum())
    # straight: the heading stays along +x (6.5 deg at most in the 60 m lane changes); the
    # avenue is driven on its middle lane
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    assert np.abs(yaw).max() < np.radians(7.0)
    mid = (x > AVENUE[0] + 20.0) & (x < AVENUE[1] - 20.0)
    assert np.allclose(T[mid, 1, 3], -WIDE["lane"], atol=0.05)


def test_street_scan_sees_the_wide_avenue():
    """A VLP-16 scan in the middle of the avenue: the facades 13.25 / 26.75 m to the sides
    and the ground; far fewer returns than in the city street at the start."""
    scene = street(0, pedestrians=False)
    model = LidarModel()
    t, T, _ = _drive(scene)
    k_avenue = int(np.argmin(np.abs(T[:, 0, 3] - 400.0)))
    k_street = int(np.argmin(np.abs(T[:, 0, 3] - 50.0)))
    counts = {}
    for name, k in (("avenue", k_avenue), ("street", k_street)):
        scan = simulate_scan(scene, scene.pose_at, float(t[k]), model)
        world = scan.xyz @ T[k, :3, :3].T + T[k, :3, 3]  # a 1.5 m sweep at most: enough
        counts[name] = len(world)
        if name == "avenue":
            y = world[:, 1]
            up = world[:, 2] > 2.0
            # facades at y = -20 and +20 (13.25 m right, 26.75 m left of the car)
            assert np.sum(up & (np.abs(y + 20.0) < 0.6)) > 500
            assert np.sum(up & (np.abs(y - 20.0) < 0.6)) > 200
            assert np.sum(np.abs(world[:, 2]) < 0.05) > 3000  # the road
    assert counts["avenue"] < counts["street"]


def test_street_registered_without_changing_other_keys():
    assert "street.py" in registry.scene_sources("street")
    for other in ("urban", "corridor", "plaza", "park", "building"):
        assert "street.py" not in registry.scene_sources(other)
    assert registry.SCENES["street"].realistic
    key = cache.sequence_key(
        "street", frames=300, fmt="ros1", seed=0, pedestrians=True, sensor="hdl64"
    )
    assert key.startswith("street-hdl64-300-0-")
