"""Constant-velocity deskew."""

import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from slam.deskew import deskew, interpolate_pose, se3_log, time_from_firing_order
from slam.errors import ConfigError, InputError

PERIOD = 0.1


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# 1.5 m/s forward with 0.3 m/s sideways, yawing 60 deg/s and a little roll: over one 0.1 s sweep
T_START_END = pose([0.01, 0.0, np.radians(6.0)], [0.15, 0.03, 0.005])


def distorted_wall(seed=0):
    """Points of the wall x = 8 (start frame) as seen by a sensor moving with a constant twist."""
    rng = np.random.default_rng(seed)
    y, z = rng.uniform(-6, 6, 800), rng.uniform(-1, 2, 800)
    wall = np.c_[np.full(800, 8.0), y, z]
    stamps = np.linspace(0, PERIOD, 40)  # firing blocks
    block = np.sort(rng.integers(0, 40, 800))
    time = stamps[block]
    twist = np.real(logm(T_START_END))  # independent of the code under test
    T = np.stack([expm(s * twist) for s in stamps / PERIOD])[block]
    R, t = T[:, :3, :3], T[:, :3, 3]
    measured = np.einsum("nji,nj->ni", R, wall - t)  # p = R(s)^T (q - t(s))
    return wall, measured, time


def test_deskew_recovers_straight_wall():
    wall, measured, time = distorted_wall()
    assert np.abs(measured[:, 0] - 8.0).max() > 0.1  # the distortion is real
    fixed = deskew(measured, time, T_START_END, PERIOD)
    assert np.abs(fixed[:, 0] - 8.0).max() < 0.005
    assert np.abs(fixed - wall).max() < 1e-6


def test_interpolation_is_the_se3_geodesic():
    R, t = interpolate_pose(T_START_END, np.array([0.0, 0.5, 1.0]))
    assert np.allclose(R[0], np.eye(3)) and np.allclose(t[0], 0.0)
    assert np.allclose(R[2], T_START_END[:3, :3]) and np.allclose(t[2], T_START_END[:3, 3])
    half = np.eye(4)
    half[:3, :3], half[:3, 3] = R[1], t[1]
    assert np.allclose(half @ half, T_START_END, atol=1e-12)
    rho, phi = se3_log(pose([0, 0, 0], [1.0, 2.0, 3.0]))
    assert np.allclose(rho, [1, 2, 3]) and np.allclose(phi, 0)


def test_deskew_passthrough_and_errors():
    xyz = np.ones((5, 3))
    assert deskew(xyz, None, T_START_END, PERIOD) is xyz
    assert np.allclose(deskew(xyz, np.zeros(5), T_START_END, PERIOD), xyz)
    with pytest.raises(InputError):
        deskew(xyz, np.zeros(4), T_START_END, PERIOD)
    with pytest.raises(InputError):
        deskew(xyz, np.zeros(5), np.eye(3), PERIOD)
    with pytest.raises(InputError):
        deskew(xyz, np.zeros(5), T_START_END, 0.0)


@pytest.mark.parametrize(
    "T",
    [
        T_START_END,
        pose([0.3, -0.2, 1.0], [0.5, 2.0, 0.1]),
        pose([0.0, 0.0, 1e-7], [0.1, 0.0, 0.0]),
        pose([0.0, 0.0, 0.0], [0.1, -0.2, 0.3]),
    ],
)
def test_closed_form_deskew_equals_per_point_geodesic(T):
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-30, 30, (500, 3))
    time = np.r_[0.0, PERIOD, rng.uniform(0, PERIOD, 498)]
    R, t = interpolate_pose(T, time / PERIOD)
    expected = np.einsum("nij,nj->ni", R, xyz) + t
    assert np.abs(deskew(xyz, time, T, PERIOD) - expected).max() < 1e-9


@pytest.mark.parametrize(
    "T",
    [
        T_START_END,
        pose([0.3, -0.2, 1.0], [0.5, 2.0, 0.1]),
        pose([0.0, 0.0, 1e-3], [1.5, 0.0, 0.0]),  # x = s theta crosses the series bound
        pose([0.0, 0.0, 1e-7], [0.1, 0.0, 0.0]),
        pose([0.0, 0.0, 0.0], [0.1, -0.2, 0.3]),
    ],
)
def test_compiled_deskew_equals_numpy_reference(T):
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-80, 80, (3000, 3))
    # firing columns: runs of equal stamps (one cos/sin per run), then distinct stamps
    time = np.r_[np.repeat(np.linspace(0, PERIOD, 100), 16), rng.uniform(0, PERIOD, 1400)]
    fast = deskew(xyz, time, T, PERIOD)
    ref = deskew(xyz, time, T, PERIOD, backend="numpy")
    assert np.abs(fast - ref).max() < 1e-9
    assert np.abs(fast - xyz).max() > 1e-3  # the motion moved the points


def test_compiled_deskew_on_simulated_scan(corridor_short):
    from slam.io.source import open_source
    from slam.types import Scan

    scan = next(s for s in open_source(corridor_short.bag) if isinstance(s, Scan))
    assert scan.time is not None and len(scan) > 20000
    T = pose([0.0, 0.0, np.radians(3.0)], [0.15, 0.0, 0.0])
    fast = deskew(scan.xyz, scan.time, T, PERIOD)
    ref = deskew(scan.xyz, scan.time, T, PERIOD, backend="numpy")
    assert np.abs(fast - ref).max() < 1e-9
    with pytest.raises(ConfigError):
        deskew(scan.xyz, scan.time, T, PERIOD, backend="cuda")


def test_time_from_firing_order_is_the_drivers_time(urban_short, urban_hdl64_short):
    """A VLP-16 cloud stored column by column (the Velodyne driver's order): the time read
    from the azimuth along the order is the driver's time field; a cloud stored beam by beam
    (KITTI-style HDL-64E: several turns), shuffled or cut to a few points gives None."""
    from slam.io.source import open_source
    from slam.types import Scan

    scans = [s for s in open_source(urban_short.bag) if isinstance(s, Scan)][:3]
    for scan in scans:
        t = time_from_firing_order(scan.xyz, PERIOD)
        assert t is not None and t.min() == 0.0 and t.max() <= PERIOD
        assert np.abs(t - scan.time).max() < 1e-6
        # twice the period: twice the times (the fraction of the turn is what it knows)
        assert np.allclose(time_from_firing_order(scan.xyz, 2 * PERIOD), 2 * t)
    scan = scans[0]
    with_gaps = scan.xyz.copy()
    with_gaps[::97] = 0.0  # drivers write (0, 0, 0) for a missing return
    t = time_from_firing_order(with_gaps, PERIOD)
    assert np.abs(t - scan.time).max() < 1e-3
    rng = np.random.default_rng(0)
    assert time_from_firing_order(scan.xyz[rng.permutation(len(scan))], PERIOD) is None
    assert time_from_firing_order(scan.xyz[:50], PERIOD) is None
    kitti = next(s for s in open_source(urban_hdl64_short.bag) if isinstance(s, Scan))
    assert kitti.time is None
    assert time_from_firing_order(kitti.xyz, PERIOD) is None
    with pytest.raises(InputError):
        time_from_firing_order(scan.xyz, 0.0)
