"""The open-road mode of the feature front ends (floam, LeGO-LOAM): the scatter points'
point-to-point terms in both matchers, the gate's judgement of a scan, and the 16-beam
motorway from standstill."""

import numpy as np
import pytest

from slam.bench.peers import run_frontend
from slam.bench.robustness import step_errors
from slam.features.scatter import ALONG_ROAD
from slam.io.source import open_source
from slam.odometry.open_road import feature_observability
from slam.registration.feature_icp import FeatureIcpConfig, FeatureTarget, feature_icp_align
from slam.registration.ground_plane import FixedNormals, GroundPlaneConfig, fit_ground
from slam.registration.se3 import transform
from slam.registration.two_step import TwoStepConfig, two_step_align
from slam.sensor import estimate_beams
from slam.sim.cache import ensure_sequence
from slam.sim.highway import highway
from slam.sim.sensors import get_sensor
from slam.sim.simulate import STAMP0, effective_model, frame_stamps, published_scan
from tests.test_feature_icp import pole_scene

STEP = 0.6  # m along the road between the map and the scan


def _road(rng):
    """A straight road along x: the ground, two barriers (planes facing across it), two
    rails (lines along it) and the (edges, planes, ground) that see nothing along x; 40
    bushes (0.3 m clumps) beside it, a fresh sample of them at every call."""
    n = 1500
    x = rng.uniform(-30, 30, n)
    ground = np.c_[x, rng.uniform(-5, 5, n), np.zeros(n)]
    barriers = np.concatenate(
        [np.c_[x, np.full(n, s * 6.0), rng.uniform(0, 1, n)] for s in (-1, 1)]
    )
    rails = np.concatenate([np.c_[x, np.full(n, s * 6.2), np.full(n, 0.8)] for s in (-1, 1)])
    return rails, barriers, ground


def _bushes(rng, centres, per: int = 30):
    return np.concatenate([c + rng.normal(0, 0.3, (per, 3)) for c in centres])


def _pair(rng):
    centres = np.c_[
        rng.uniform(-25, 25, 40),
        rng.choice([-1, 1], 40) * rng.uniform(8, 15, 40),
        rng.uniform(0.5, 3.0, 40),
    ]
    world = [*_road(rng), _bushes(rng, centres)]
    T = np.eye(4)
    T[0, 3] = STEP
    scan = [transform(np.linalg.inv(T), p) for p in (*_road(rng), _bushes(rng, centres))]
    return world, scan


def test_scatter_points_carry_feature_icp_along_a_road_its_features_cannot_see():
    """Point-to-line on the rails and point-to-plane on the barriers and the ground hold
    the scan where the map was made (0.6 m behind); the bushes' point-to-point terms find
    the step. The reported RMSE stays the features' (the bushes' pairs are their spacing)."""
    rng = np.random.default_rng(3)
    (rails, barriers, ground, bushes), (e, b, g, s) = _pair(rng)
    targets = FeatureTarget(rails), FeatureTarget(np.concatenate([barriers, ground]))
    planes = np.concatenate([b, g])
    fixed = FixedNormals(np.r_[np.zeros(len(b), bool), np.ones(len(g), bool)], np.eye(3)[2])
    cfg = FeatureIcpConfig(max_iterations=40)
    held = feature_icp_align(e, planes, *targets, np.eye(4), cfg, fixed)
    assert abs(held.T_target_source[0, 3]) < 0.1
    res = feature_icp_align(e, planes, *targets, np.eye(4), cfg, fixed, s, FeatureTarget(bushes))
    assert abs(res.T_target_source[0, 3] - STEP) < 0.05, res.T_target_source[:3, 3]
    assert np.abs(res.T_target_source[1:3, 3]).max() < 0.02
    assert res.converged
    assert res.rmse < 0.02 and res.num_inliers > len(e) + len(planes)


def test_scatter_points_carry_the_two_step_matcher_along_the_road():
    """LeGO's matcher: the ground fixes [roll, pitch, z], the rails nothing along x; with
    the bushes in the second step and the refinement the step is found."""
    rng = np.random.default_rng(4)
    (rails, barriers, ground, bushes), (e, b, g, s) = _pair(rng)
    cfg = TwoStepConfig()
    args = (g, e, b, FeatureTarget(rails), FeatureTarget(np.concatenate([barriers, ground])))
    held = two_step_align(*args, np.eye(4), cfg)
    assert abs(held.T_target_source[0, 3]) < 0.1
    res = two_step_align(*args, np.eye(4), cfg, scatter_xyz=s, scatter_map=FeatureTarget(bushes))
    assert abs(res.T_target_source[0, 3] - STEP) < 0.05, res.T_target_source[:3, 3]
    assert np.abs(res.T_target_source[1:3, 3]).max() < 0.02


def test_scatter_points_do_not_pitch_the_two_step_matcher():
    """As in feature_icp: a beam meets a pole at another height from every pose, so the
    scatter points' heights are the rings', not the pose's; as 3D terms in the 6-DoF
    refinement they tilted a 16-beam scan 1.5 m on from its map (300 ground points against 80
    poles: 0.0065 deg, 0.001 deg horizontal only); the ground holds the height and tilt."""
    ground, scan_poles, map_poles, truth = pole_scene()
    g = ground[::10] - truth[:3, 3]
    res = two_step_align(
        g,
        np.zeros((0, 3)),
        g,
        None,
        FeatureTarget(ground),
        truth,
        TwoStepConfig(),
        ground_normal=FixedNormals(np.ones(len(g), dtype=bool), np.array([0.0, 0, 1])),
        scatter_xyz=scan_poles,
        scatter_map=FeatureTarget(map_poles),
    )
    D = np.linalg.inv(truth) @ res.T_target_source
    tilt = np.degrees(np.arccos(np.clip(D[2, 2], -1, 1)))
    assert res.converged and tilt < 0.003, tilt
    assert np.linalg.norm(D[:3, 3]) < 0.02, D[:3, 3]


def _motorway_scans(seed: int, first: int, count: int, sensor: str = "vlp16"):
    """Frames first.. of motorway ``seed`` as a bag without ring and time has them, with
    rings from the beam model of the first three, and their true poses."""
    scene = highway(seed)
    spec, model = get_sensor(sensor), effective_model(scene, None, sensor)
    rng = np.random.default_rng([first, 7])
    scans, poses = [], []
    for i, stamp in enumerate(frame_stamps(first + count, model)[first:]):
        scan, _ = published_scan(scene, float(stamp), model, spec, rng)
        scan.index, scan.ring, scan.time = i, None, None
        scans.append(scan)
        poses.append(scene.pose_at(np.array([float(stamp) - STAMP0]))[0])
    return scans, np.asarray(poses)


def _observability(scan, ring) -> float:
    from slam.features.loam import FeatureConfig, extract_features

    f = extract_features(scan.xyz, ring, FeatureConfig())
    candidates = np.zeros(len(scan.xyz), dtype=bool)
    candidates[f.edge_idx] = candidates[f.plane_idx] = True
    gc = GroundPlaneConfig(band=0.2)
    return feature_observability(scan.xyz, ring, candidates, fit_ground(scan.xyz, gc), gc.band)


def test_the_gate_tells_a_motorway_from_a_corridor():
    """The features of a 16-beam motorway scan run along the road (measured 0.03); a
    simulated corridor's, judged the same way, do not (0.30-0.60: door frames and the end
    wall at the features' own spacing; judged among all the scan's points, the near walls'
    density made it 0.03-0.06 and floam's corridor APE doubled in the mode)."""
    scans, _ = _motorway_scans(0, 40, 3)
    ring = estimate_beams([s.xyz for s in scans]).ring_of(scans[0].xyz)
    assert _observability(scans[0], ring) < ALONG_ROAD
    corridor = list(open_source(ensure_sequence("corridor", frames=100).bag))
    for k in (0, 50, 99):
        assert _observability(corridor[k], corridor[k].ring) > 2 * ALONG_ROAD


@pytest.mark.parametrize(("config", "bound"), [("floam", 0.15), ("lego_lpb", 0.3)])
def test_the_feature_front_ends_follow_a_16_beam_motorway_from_standstill(config, bound):
    """Motorway seed 2, VLP-16 without ring and time, from standstill to 8.5 m/s (60 frames):
    in the mode (on from the first scan) every step within ``bound`` m (measured floam
    0.12 m, lego_lpb 0.24 m over 80 frames); without it the ring samples hold the scan where
    the map was made (both at under 30 % of the distance)."""
    scans, gt = _motorway_scans(2, 0, 60)
    true_x = (np.linalg.inv(gt[0]) @ gt[-1])[0, 3]
    outs, _ = run_frontend(scans, config, [])
    assert all(o.diagnostics.flat()["open_road"] == 1 for o in outs)
    err = step_errors(np.array([o.pose for o in outs]), gt)
    assert err.max() < bound, err
    assert abs(outs[-1].pose[0, 3] - true_x) < 0.1 * true_x
    held, _ = run_frontend(scans, config, ["frontend.scatter.mode=never"])
    assert abs(held[-1].pose[0, 3]) < 0.3 * true_x


def test_a_scan_outside_the_mode_empties_floams_scatter_map():
    """floam's scatter map holds where the mode was last on; a trusted scan outside it
    empties the map, so that where the mode comes on again its first scan is not judged
    against a map that pairs nothing (``OpenRoad.insert``). The LeGO front ends keep theirs:
    their mode comes and goes within one corridor of the simulated building."""
    from frontends.floam import Floam
    from frontends.lego_loam import LegoLoam
    from slam.features.scatter import ScatterConfig
    from slam.odometry.open_road import OpenRoad, OpenRoadScan

    assert Floam().open_road.empty_outside and not LegoLoam().open_road.empty_outside
    rng = np.random.default_rng(0)
    edges, planes = rng.uniform(-5, 5, (50, 3)), rng.uniform(-5, 5, (50, 3))
    on = OpenRoadScan(True, rng.uniform(-20, 20, (500, 3)), 0.05, None)
    off = OpenRoadScan(False, np.zeros((0, 3)), 0.5, None)
    for empty_outside in (True, False):
        road = OpenRoad(ScatterConfig(confirm_distance=0.0), empty_outside=empty_outside)
        road.insert(on, edges, planes, np.eye(4), 0.2)
        held = len(road.map)
        assert held > 0 and road.target() is not None
        e, p = road.insert(off, edges, planes, np.eye(4), 0.2)
        assert len(road.map) == (0 if empty_outside else held)
        assert (road.target() is None) == empty_outside
        assert len(e) == len(edges) and len(p) == len(planes)
