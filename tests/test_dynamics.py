"""DBSCAN clusters and their motion between scans (slam/preprocess/dynamics.py)."""

import numpy as np
import pytest

from slam.errors import ConfigError, InputError
from slam.preprocess.dynamics import (
    STATE_COLUMNS,
    DynamicsConfig,
    cluster,
    cluster_stats,
    dbscan,
    remove_dynamic,
)
from slam.preprocess.ground import fit_ground, split_ground
from slam.sim.simulate import iter_scans, make_scene


def _world(t, rng):
    """World-frame non-ground points at time t (s): 3 poles, a 30 m wall, a walker at 1.3
    m/s; each surface sampled anew every scan (the rays hit other spots). Labels: 0 wall,
    1 pole, 2 walker."""
    parts, tags = [], []
    for x in (4.0, 9.0, 14.0):  # poles, r = 0.07 m, 4 m tall
        a = rng.uniform(0, 2 * np.pi, 40)
        parts.append(
            np.column_stack(
                [x + 0.07 * np.cos(a), 3.0 + 0.07 * np.sin(a), rng.uniform(0.2, 4.0, 40)]
            )
        )
        tags.append(np.full(40, 1))
    parts.append(
        np.column_stack(
            [rng.uniform(-5, 25, 1500), np.full(1500, -4.0), rng.uniform(0.2, 3.0, 1500)]
        )
    )
    tags.append(np.zeros(1500, dtype=int))
    centre = np.array([2.0 + 1.3 * t, 1.5])
    parts.append(
        np.column_stack(
            [
                centre[0] + rng.uniform(-0.25, 0.25, 60),
                centre[1] + rng.uniform(-0.25, 0.25, 60),
                rng.uniform(0.2, 1.7, 60),
            ]
        )
    )
    tags.append(np.full(60, 2))
    return np.vstack(parts), np.concatenate(tags)


def test_synthetic_walker_removed_poles_and_wall_kept():
    rng = np.random.default_rng(0)
    state, T_prev = None, None
    removed = {0: [], 1: [], 2: []}
    for k in range(20):
        t = 0.1 * k
        T_ws = np.eye(4)
        T_ws[:3, 3] = [1.0 * t, 0.0, 1.0]  # sensor drives along x at 1 m/s
        pw, tag = _world(t, rng)
        xyz = (pw - T_ws[:3, 3]) @ T_ws[:3, :3]
        T_prev_curr = np.eye(4) if T_prev is None else np.linalg.inv(T_prev) @ T_ws
        keep, state = remove_dynamic(xyz, state, T_prev_curr)
        assert state.shape[1] == len(STATE_COLUMNS)
        if k >= 5:
            for c in removed:
                removed[c].append((~keep[tag == c]).mean())
        T_prev = T_ws
    assert np.mean(removed[2]) > 0.95  # the walker, once tracked for 0.3 m
    assert max(removed[1]) == 0.0 and max(removed[0]) == 0.0


def _turning_run(cfg, yaw_error_deg):
    """The sensor turns at 15 deg/s, the motion given lacks ``yaw_error_deg`` per scan (a
    constant-velocity guess as the turn starts); fraction removed per tag from scan 5 on."""
    rng = np.random.default_rng(4)
    state, T_prev = None, None
    removed = {0: [], 1: [], 2: []}
    for k in range(20):
        t = 0.1 * k
        c, s_ = np.cos(np.radians(15 * t)), np.sin(np.radians(15 * t))
        T_ws = np.eye(4)
        T_ws[:3, :3] = [[c, -s_, 0], [s_, c, 0], [0, 0, 1]]
        T_ws[:3, 3] = [1.0 * t, 0.0, 1.0]
        pw, tag = _world(t, rng)
        xyz = (pw - T_ws[:3, 3]) @ T_ws[:3, :3]
        T_prev_curr = np.eye(4) if T_prev is None else np.linalg.inv(T_prev) @ T_ws
        e = np.radians(yaw_error_deg)
        err = np.eye(4)
        err[:2, :2] = [[np.cos(e), -np.sin(e)], [np.sin(e), np.cos(e)]]
        keep, state = remove_dynamic(xyz, state, T_prev_curr @ err, cfg)
        if k >= 5:
            for tg in removed:
                removed[tg].append((~keep[tag == tg]).mean())
        T_prev = T_ws
    return {tg: float(np.mean(v)) for tg, v in removed.items()}


def test_an_odometry_yaw_error_moves_no_static_cluster():
    bad = _turning_run(DynamicsConfig(refine_motion=False), 1.5)
    good = _turning_run(DynamicsConfig(), 1.5)
    print(f"1.5 deg yaw error per scan: removed without refinement {bad}, with {good}")
    assert bad[1] > 0.5  # the poles 8-14 m away seem to move 0.2-0.4 m per scan
    assert good[0] == 0.0 and good[1] == 0.0 and good[2] > 0.9


def test_first_scan_and_bare_centroids_and_errors():
    rng = np.random.default_rng(1)
    xyz, _ = _world(0.0, rng)
    keep, state = remove_dynamic(xyz, None, np.eye(4))
    assert keep.all() and len(state) >= 5
    keep, _ = remove_dynamic(xyz, state[:, :3], np.eye(4))  # (M, 3) centroids: no count test
    assert keep.all()
    labels = cluster(xyz)
    c, n, ext = cluster_stats(xyz, labels, np.eye(3)[:2])
    assert n.sum() == (labels >= 0).sum() and np.all(ext < 31)
    with pytest.raises(InputError):
        remove_dynamic(xyz, state, np.eye(3))
    with pytest.raises(InputError):
        remove_dynamic(xyz, state[:, :2], np.eye(4))
    with pytest.raises(ConfigError):
        DynamicsConfig(motion_threshold=2.0, match_radius=1.0)
    with pytest.raises(ConfigError):
        DynamicsConfig(z_scale=0.0)


def test_simulated_plaza_pedestrians_removed_lamp_poles_kept():
    """30 scans of the plaza (VLP-16, 4 walkers at 16-30 m, 8-30 points each; lamp poles of
    7 cm radius): motion from the ground truth, as the odometry would give it."""
    scene = make_scene("plaza")
    cfg = DynamicsConfig()
    state, T_prev = None, None
    dyn_n = dyn_rm = st_n = st_rm = pole_n = pole_rm = 0
    for k, (scan, truth) in enumerate(iter_scans(scene, 30, with_truth=True)):
        T = truth.T_world_sensor_columns[len(truth.T_world_sensor_columns) // 2]
        _, nonground = split_ground(scan.xyz, fit_ground(scan.xyz))
        xyz, dyn = scan.xyz[nonground], truth.dynamic[nonground]
        labels = cluster(xyz, cfg)
        if k % 10 == 0:  # the scipy DBSCAN equals scikit-learn's, voxelled and point-wise
            assert np.array_equal(labels, cluster(xyz, cfg, reference=True))
            fine = DynamicsConfig(voxel=0.0)
            assert np.array_equal(cluster(xyz, fine), cluster(xyz, fine, reference=True))
        T_prev_curr = np.eye(4) if T_prev is None else np.linalg.inv(T_prev) @ T
        keep, state = remove_dynamic(xyz, state, T_prev_curr, cfg, labels=labels)
        T_prev = T
        if k < 5:  # tracks need 0.3 m of motion first
            continue
        dyn_n, dyn_rm = dyn_n + dyn.sum(), dyn_rm + (~keep[dyn]).sum()
        st_n, st_rm = st_n + (~dyn).sum(), st_rm + (~keep[~dyn]).sum()
        for lab in np.unique(labels[(labels >= 0) & ~dyn]):  # pole-like static clusters
            m = labels == lab
            p = xyz[m]
            if np.ptp(p[:, 0]) < 0.4 and np.ptp(p[:, 1]) < 0.4 and np.ptp(p[:, 2]) > 1.5:
                pole_n, pole_rm = pole_n + m.sum(), pole_rm + (~keep[m]).sum()
    print(
        f"plaza: pedestrians removed {dyn_rm / dyn_n:.3f}, static removed "
        f"{st_rm / st_n:.4f}, pole points {pole_n} removed {pole_rm}"
    )
    assert dyn_rm / dyn_n > 0.75
    assert st_rm / st_n < 0.01
    assert pole_n > 100 and pole_rm / pole_n < 0.01


def test_dbscan_core_border_noise_and_numbering():
    """Two scan lines 0.74 m apart (cores: 17 points within eps), a point half-way between
    them within eps of cores of both but itself not core (it takes the lower-numbered
    cluster, as scikit-learn does) and isolated noise."""
    from sklearn.cluster import DBSCAN

    y = np.arange(-22, 23) * 0.045
    line_b = np.column_stack([np.full(len(y), 0.74), y, np.zeros(len(y))])
    line_a = np.column_stack([np.zeros(len(y)), y, np.zeros(len(y))])
    pts = np.vstack([line_b, line_a, [[0.37, 0, 0]], [[5, 5, 5]], [[-5, 5, 5]]])
    labels = dbscan(pts, 0.4, 17)
    assert np.array_equal(labels, DBSCAN(eps=0.4, min_samples=17).fit_predict(pts))
    n = len(y)
    assert labels[0] == 0 and labels[n] == 1  # numbered by their first core point
    assert labels[2 * n] == 0 and labels[2 * n + 1] == labels[2 * n + 2] == -1
    assert np.array_equal(dbscan(np.zeros((0, 3)), 0.4, 5), np.zeros(0))


@pytest.mark.parametrize(("eps", "min_samples"), [(0.3, 2), (0.5, 5), (0.8, 12)])
def test_dbscan_kernel_equals_the_numpy_reference_and_scikit_learn(eps, min_samples):
    """The compiled union-find labelling gives the reference's labels (clumps, a sparse
    background, border points between clumps)."""
    from sklearn.cluster import DBSCAN

    rng = np.random.default_rng(3)
    clumps = [c + rng.normal(0, 0.3, (300, 3)) for c in rng.uniform(-6, 6, (8, 3))]
    pts = np.vstack([*clumps, rng.uniform(-8, 8, (1500, 3))])
    labels = dbscan(pts, eps, min_samples)
    assert np.array_equal(labels, dbscan(pts, eps, min_samples, reference=True))
    assert np.array_equal(labels, DBSCAN(eps=eps, min_samples=min_samples).fit_predict(pts))
    assert labels.max() >= 1 and (labels == -1).any()
