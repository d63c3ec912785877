"""Two-step LM matching (LeGO-LOAM, paper 001 section 3.3): a known 6-DoF transform between
two simulated scans is recovered, with and without the ground residual; each restricted
step moves only its own degrees of freedom."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.lego_loam import LegoFeatureConfig, lego_features
from slam.errors import ConfigError
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.preprocess.ground import fit_ground
from slam.registration.feature_icp import FeatureTarget
from slam.registration.gicp import RegistrationError
from slam.registration.two_step import (
    EDGE_DOF,
    GROUND_DOF,
    TwoStepConfig,
    plane_terms,
    plane_to_odom,
    solve_restricted,
    two_step_align,
)
from slam.sim.lidar import simulate_scan
from slam.sim.registry import SCENES, scene_sensor

# the known motion between the scans: 0.27 m, 2.1 deg
D = np.eye(4)
D[:3, :3] = Rotation.from_euler("xyz", [0.5, -0.4, 2.0], degrees=True).as_matrix()
D[:3, 3] = [0.25, -0.1, 0.03]


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(T_true) @ T_est
    return float(np.linalg.norm(E[:3, 3])), float(
        np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))
    )


@pytest.fixture(scope="module")
def plaza_pair():
    """Two static HDL-64E scans of the plaza, the second one D away from the first: the
    features of each (LeGO-LOAM segmentation + features) and the first one's maps."""
    scene = SCENES["plaza"].load()(0, pedestrians=False)
    model = scene_sensor("plaza", "hdl64")
    T_a = scene.pose_at(np.array([20.0]))[0]
    out = []
    for T, seed in ((T_a, 1), (T_a @ D, 2)):
        scan = simulate_scan(
            scene,
            lambda t, T=T: np.repeat(T[None], len(t), 0),
            0.0,
            model,
            np.random.default_rng(seed),
        )
        out.append((scan, lego_features(scan.xyz, scan.ring, LegoFeatureConfig())))
    (_, fa), (scan_b, fb) = out
    edge_map = VoxelHashMap(LocalMapConfig(voxel_size=0.2, max_points_per_voxel=2))
    plane_map = VoxelHashMap(LocalMapConfig(voxel_size=0.4, max_points_per_voxel=2))
    edge_map.add(fa.edges)
    plane_map.add(np.concatenate([fa.ground, fa.planes]))
    return fa, fb, scan_b, FeatureTarget(edge_map.points), FeatureTarget(plane_map.points)


def test_two_step_recovers_a_known_transform(plaza_pair):
    fa, fb, _, edges, planes = plaza_pair
    assert len(fb.ground) > 1000 and len(fb.edges) > 300 and len(fb.planes) > 500
    res = two_step_align(fb.ground, fb.edges, fb.planes, edges, planes, np.eye(4))
    dt, dr = _errors(res.T_target_source, D)
    assert dt < 0.02 and dr < 0.1, (dt, dr)  # measured 0.4 cm / 0.01 deg
    assert res.converged and res.H.shape == (6, 6)


def test_ground_residual_joins_the_refinement(plaza_pair):
    """E_ground: the ground points of the second scan against the plane fitted on the first
    scan (its frame is the odometry frame here); the transform is still recovered."""
    fa, fb, scan_b, edges, planes = plaza_pair
    gp = fit_ground(np.concatenate([fa.ground, fa.planes]))
    plane = plane_to_odom(gp.normal, gp.d, np.eye(4))
    cfg = TwoStepConfig(ground_weight=1.0)
    res = two_step_align(fb.ground, fb.edges, fb.planes, edges, planes, np.eye(4), cfg, plane)
    dt, dr = _errors(res.T_target_source, D)
    assert dt < 0.02 and dr < 0.1, (dt, dr)
    # the ground residual alone pins height, roll and pitch: from a pose 10 cm too high and
    # 1 deg tilted, step 1 with E_ground only brings z and tilt back
    T0 = D.copy()
    T0[:3, :3] = Rotation.from_euler("x", 1.0, degrees=True).as_matrix() @ T0[:3, :3]
    T0[2, 3] += 0.1
    from slam.registration.two_step import ground_terms

    T1, n = solve_restricted(T0, lambda T: ground_terms(T, fb.ground, plane, cfg), GROUND_DOF, 10)
    assert n > 1000
    E = np.linalg.inv(D) @ T1
    tilt = np.degrees(np.arccos(np.clip(E[2, 2], -1, 1)))
    assert abs(E[2, 3]) < 0.02 and tilt < 0.1, (E[2, 3], tilt)


def test_restricted_steps_move_only_their_coordinates(plaza_pair):
    _, fb, _, edges, planes = plaza_pair
    cfg = TwoStepConfig()
    T0 = np.eye(4)
    T1, n = solve_restricted(T0, lambda T: plane_terms(T, fb.ground, planes, cfg), GROUND_DOF, 8)
    assert n > 100
    # yaw, x, y untouched by step 1
    assert np.allclose(T1[:2, 3], 0.0, atol=1e-12)
    assert abs(np.arctan2(T1[1, 0], T1[0, 0])) < 1e-3
    from slam.registration.two_step import edge_terms

    T2, _ = solve_restricted(T1, lambda T: edge_terms(T, fb.edges, edges, cfg), EDGE_DOF, 8)
    assert T2[2, 3] == pytest.approx(T1[2, 3], abs=1e-12)  # z untouched by step 2
    assert np.allclose(T2[2, :3], T1[2, :3], atol=1e-9)  # nor the tilt (world z row of R)
    assert np.linalg.norm(T2[:2, 3] - D[:2, 3]) < 0.05


def test_what_moved_weighs_nothing_beyond_three_sigmas(plaza_pair):
    """A fifth of the second scan's edge and plane features 1 m from where the map saw them
    (a vehicle that moved): Huber alone is pulled 3.3 cm / 0.1 deg (measured), with the
    residuals beyond 3 robust sigmas weighing 0 the pose is within 2 mm (measured 1.7)."""
    _, fb, _, edges, planes = plaza_pair
    centre = fb.edges[0]

    def moved(p: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(p - centre, axis=1)
        q = p.copy()
        q[d <= np.quantile(d, 0.2), 0] += 1.0
        return q

    e2, p2 = moved(fb.edges), moved(fb.planes)
    errs = [
        _errors(
            two_step_align(
                fb.ground, e2, p2, edges, planes, np.eye(4), TwoStepConfig(outlier_sigmas=k)
            ).T_target_source,
            D,
        )
        for k in (0.0, 3.0)
    ]
    (dt_huber, dr_huber), (dt_cut, dr_cut) = errs
    assert dt_huber > 0.02 and dr_huber > 0.05, errs[0]
    assert dt_cut < 0.005 and dr_cut < 0.02, errs[1]
    # settled by Huber first (a start that is not a tracked prediction), then cut: the same
    settled = two_step_align(
        fb.ground, e2, p2, edges, planes, np.eye(4), TwoStepConfig(), settle=True
    )
    dt, dr = _errors(settled.T_target_source, D)
    assert dt < 0.005 and dr < 0.02, (dt, dr)
    with pytest.raises(ConfigError):
        TwoStepConfig(outlier_sigmas=-1.0)


def test_two_step_inputs():
    with pytest.raises(RegistrationError, match="at least 6"):
        two_step_align(np.zeros((2, 3)), np.zeros((0, 3)), np.zeros((1, 3)), None, None)
    with pytest.raises(ConfigError):
        TwoStepConfig(ground_weight=-1.0)


def test_neighbour_cache_gives_the_uncached_terms(plaza_pair):
    """Terms through a NeighbourCache (analyses kept while the neighbours stay) equal the
    terms analysed afresh, to the bit, along the poses of a restricted solve."""
    from slam.registration.two_step import NeighbourCache, edge_terms

    _, fb, _, edges, planes = plaza_pair
    cfg = TwoStepConfig()
    cache = NeighbourCache()
    for s in np.linspace(0.0, 1.0, 5):
        T = np.eye(4)
        T[:3, 3] = s * D[:3, 3]
        for fn, pts, target in ((plane_terms, fb.ground, planes), (edge_terms, fb.edges, edges)):
            a, b = fn(T, pts, target, cfg, cache), fn(T, pts, target, cfg)
            for f in ("p", "c", "W", "w", "sqd"):
                np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
