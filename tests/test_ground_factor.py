"""Ground factor plugin (slam/ground_factor.py): z / roll / pitch from the ground plane."""

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError, InputError
from slam.factor_plugins import OdometryConfig, OdometryFactorPlugin, PriorFactorPlugin
from slam.factors import GraphView, key
from slam.ground_factor import (
    GroundFactorConfig,
    GroundFactorPlugin,
    ground_corrected,
    plane_of,
    transform_plane,
)
from slam.types import Keyframe

HEIGHT = 0.9  # m, sensor above the floor (z = 0)


def _pose(x, y, z, roll, pitch, yaw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def _truth(n=100, seed=0):
    """Keyframes 1 m apart on a curving path over a flat floor, wobbling +-0.3 deg."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(np.full(n, 1.5))  # deg
    xy = np.cumsum(np.column_stack([np.cos(np.radians(yaw)), np.sin(np.radians(yaw))]), axis=0)
    wob = rng.uniform(-0.3, 0.3, size=(n, 2))
    return [_pose(xy[i, 0], xy[i, 1], HEIGHT, wob[i, 0], wob[i, 1], yaw[i]) for i in range(n)]


def _cloud(T_ws, rng, n=2500):
    """Sensor-frame scan: floor points (1 cm noise) within 2-20 m and 30 % wall clutter."""
    n_g = int(0.7 * n)
    r, a = rng.uniform(2, 20, n_g), rng.uniform(-np.pi, np.pi, n_g)
    g = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(0, 0.01, n_g)])
    g[:, :2] += T_ws[:2, 3]
    w = np.column_stack(
        [
            T_ws[0, 3] + rng.uniform(-15, 15, n - n_g),
            T_ws[1, 3] + np.where(rng.random(n - n_g) < 0.5, -3.0, 3.0),
            rng.uniform(0, 3, n - n_g),
        ]
    )
    world = np.vstack([g, w])
    return (world - T_ws[:3, 3]) @ T_ws[:3, :3]


def _keyframes(truth, pitch_bias_deg=0.02, seed=1, with_clouds=True, planes=False):
    """Odometry with a pitch bias per keyframe (a front end that climbs) and small noise."""
    rng = np.random.default_rng(seed)
    kfs, T_odom = [], truth[0].copy()
    for i, T in enumerate(truth):
        if i == 0:
            rel = np.eye(4)
        else:
            rel = np.linalg.inv(truth[i - 1]) @ T
            err = _pose(
                *rng.normal(0, 0.005, 3), *(rng.normal(0, 0.01, 3) + [0, pitch_bias_deg, 0])
            )
            rel = rel @ err
            T_odom = T_odom @ rel
        plane = None
        if planes:  # the plane a front end would report: n = R^T z, d = height
            plane = np.r_[T[:3, :3].T @ np.array([0, 0, 1.0]), T[2, 3]]
        cloud = _cloud(T, rng) if with_clouds else np.zeros((0, 3), np.float32)
        kfs.append(
            Keyframe(i, 0.1 * i, i, T_odom.copy(), rel, np.eye(6), cloud, ground_plane=plane)
        )
    return kfs


def _optimise(kfs, plugins):
    """As the pipeline runs: iSAM2, one update per keyframe, the new keyframe's guess is
    the previous estimate composed with the odometry's relative motion."""
    isam = gtsam.ISAM2()
    seen, est = [], {}

    def estimate(i):
        return est[i]

    view = GraphView(seen, estimate)
    for kf in kfs:
        seen.append(kf)
        est[kf.id] = kf.pose_odom if kf.id == 0 else est[kf.id - 1] @ kf.relative
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for p in plugins:
            for f in p.on_keyframe(kf, view):
                graph.add(f)
        values.insert(key(kf.id), gtsam.Pose3(est[kf.id]))
        isam.update(graph, values)
        result = isam.calculateEstimate()
        est = {i: result.atPose3(key(i)).matrix() for i in est}
    return np.stack([est[kf.id] for kf in kfs])


def _base_plugins():
    odo = OdometryFactorPlugin(
        OdometryConfig(use_frontend_information=False, rotation_sigma=0.002, translation_sigma=0.02)
    )
    return [PriorFactorPlugin(), odo]


def _errors(est, truth):
    tz = np.array([T[2, 3] for T in truth])
    txy = np.array([T[:2, 3] for T in truth])
    return np.abs(est[:, 2, 3] - tz).max(), np.linalg.norm(est[:, :2, 3] - txy, axis=1).max()


def test_chain_mode_cuts_z_drift_of_a_pitch_biased_chain():
    truth = _truth()
    kfs = _keyframes(truth)
    z_odo, xy_odo = _errors(_optimise(kfs, _base_plugins()), truth)
    ground = GroundFactorPlugin()  # defaults: chain mode, planes fitted from the clouds
    z_gnd, xy_gnd = _errors(_optimise(kfs, _base_plugins() + [ground]), truth)
    print(
        f"chain: max z error {z_odo:.3f} -> {z_gnd:.3f} m ({z_odo / z_gnd:.0f}x), "
        f"xy {xy_odo:.3f} -> {xy_gnd:.3f} m, {ground.added} factors, skipped {ground.skipped}"
    )
    assert z_odo > 1.0  # the biased chain climbs
    # defaults are cautious (0.5 deg, 10 m segments: planes of real 16-beam scans scatter
    # by 0.3-1 deg and hills bend within 10 m): a 1 % climb is cut to a third
    assert z_gnd < 0.5 and z_odo / z_gnd > 2.5
    tight = GroundFactorPlugin(GroundFactorConfig(sigma_tilt_deg=0.2, segment_length=20.0))
    z_tight, _ = _errors(_optimise(kfs, _base_plugins() + [tight]), truth)
    print(f"chain, 0.2 deg / 20 m segments (a flat floor): {z_tight:.3f} m")
    assert z_tight < 0.3 and z_tight < z_gnd
    assert xy_gnd < xy_odo + 0.05  # x, y are left to the odometry
    assert ground.added + sum(ground.skipped.values()) == len(kfs) - 1 and ground.added > 90


def test_global_mode_from_front_end_planes():
    truth = _truth(seed=2)
    kfs = _keyframes(truth, pitch_bias_deg=-0.03, with_clouds=False, planes=True)
    z_odo, _ = _errors(_optimise(kfs, _base_plugins()), truth)
    ground = GroundFactorPlugin(GroundFactorConfig(mode="global"))
    z_gnd, _ = _errors(_optimise(kfs, _base_plugins() + [ground]), truth)
    print(f"global: max z error {z_odo:.3f} -> {z_gnd:.3f} m")
    assert z_odo > 1.0 and z_gnd < 0.02
    assert ground.added == len(kfs) - 1 and not ground.skipped


def test_gate_rejects_a_slope_change_and_missing_ground_is_skipped():
    truth = _truth(n=4)
    kfs = _keyframes(truth, with_clouds=False, planes=True)
    kfs[2].ground_plane[0], kfs[2].ground_plane[2] = np.sin(0.2), np.cos(0.2)  # a ramp
    kfs[3].ground_plane = None
    kfs[3].cloud = np.zeros((0, 3), np.float32)
    plugin = GroundFactorPlugin()
    view = GraphView(kfs, lambda i: kfs[i].pose_odom)
    counts = [len(plugin.on_keyframe(kf, view)) for kf in kfs]
    assert counts == [0, 1, 0, 0] and plugin.skipped == {"gate": 1, "no cloud": 1}


def test_plane_geometry_and_config():
    T = _pose(1.0, 2.0, 0.5, 3.0, -2.0, 40.0)
    n_b = np.array([0.05, -0.02, 1.0])
    n_b /= np.linalg.norm(n_b)
    n_a, d_a = transform_plane(T, n_b, 1.2)
    p_b = np.array([3.0, 1.0, 0.0])
    p_b -= (n_b @ p_b + 1.2) * n_b  # a point of the plane in b
    assert abs(n_a @ (T[:3, :3] @ p_b + T[:3, 3]) + d_a) < 1e-12
    T_bad = T @ _pose(0.0, 0.0, 0.1, 1.0, 0.5, 0.0)
    fixed, tilt, step = ground_corrected(T_bad, n_a, d_a, n_b, 1.2)
    n2, d2 = transform_plane(fixed, n_b, 1.2)
    assert np.allclose(n2, n_a) and abs(d2 - d_a) < 1e-12 and tilt > 0 and abs(step) > 0.05
    n, d = plane_of({"normal": [0, 0, 2.0], "d": 2.0})
    assert np.allclose(n, [0, 0, 1.0]) and d == 1.0
    with pytest.raises(InputError):
        plane_of([0.0, 0.0, 0.0, 1.0])
    with pytest.raises(ConfigError):
        GroundFactorConfig(mode="flat")
    with pytest.raises(ConfigError):
        GroundFactorConfig(sigma_height=0.0)
