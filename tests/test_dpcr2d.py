"""DPCR-SLAM end to end (paper 003): the 2D front end, the region-graph back end and the
region edges on simulated floor plans with ground truth, and on the real Intel log."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest
from shared_data import shared_path

from backends.region_graph import RegionGraphBackend, planar_factor, pose2_of
from frontends.dpcr2d import Dpcr2d, matrix_to_pose2
from slam.cli import main
from slam.factors import key
from slam.io.carmen import CarmenSource
from slam.io.grid_map import read_pgm
from slam.sim.floorplan2d import simulate2d, wheel_odometry, write_sequence


@pytest.fixture(scope="module")
def rooms_log(tmp_path_factory):
    """1.3 laps of the three rooms at 1.5 m/s (720-beam 360 deg scanner, 12 m), with a
    poor wheel odometry (3 % slip, heading random walk 0.5 deg / sqrt(m))."""
    out = tmp_path_factory.mktemp("rooms2d")
    seq = simulate2d("rooms2d", frames=340, speed=1.5, seed=3)
    odo = wheel_odometry(seq.poses, slip=0.03, yaw_slip=0.05, heading_deg_per_sqrt_m=0.5)
    log, gt = write_sequence(seq, out, odo)
    return log, gt, out


def _ape(out) -> dict:
    return json.loads((out / "ape.json").read_text())["ape_trans"]


def test_region_graph_projects_pose3_factors_on_the_plane():
    prior = gtsam.PriorFactorPose3(key(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3))
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), gtsam.Point3(1.0, 0.5, 0.0))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 0.01, 0.05, 0.05, 1e-3]))
    between = gtsam.BetweenFactorPose3(key(0), key(1), step, noise)
    f2 = planar_factor(between)
    assert isinstance(f2, gtsam.BetweenFactorPose2)
    assert np.allclose(np.diag(f2.noiseModel().covariance()), [0.05**2, 0.05**2, 0.01**2])
    backend = RegionGraphBackend()
    backend.update([prior], {0: gtsam.Pose3()})
    backend.update([between], {1: gtsam.Pose3(gtsam.Rot3.Yaw(0.2), gtsam.Point3(0.8, 0.3, 0))})
    est = pose2_of(backend.estimate()[1])
    assert [est.x(), est.y(), est.theta()] == pytest.approx([1.0, 0.5, 0.3], abs=1e-6)
    assert backend.stats()["optimizations"] == 2


def test_region_graph_survives_an_underconstrained_graph():
    """A vertex with no factor: the optimisation must not stop the run (Gauss-Newton
    raises on an indeterminant system; the back end then tries LM, else keeps its last
    estimate)."""
    backend = RegionGraphBackend()
    prior = gtsam.PriorFactorPose3(key(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3))
    backend.update([prior], {0: gtsam.Pose3(), 1: gtsam.Pose3()})
    est = backend.finalize()
    assert set(est) == {0, 1} and np.allclose(est[0].matrix(), np.eye(4), atol=1e-6)


def test_dpcr_front_end_tracks_the_rooms_loop(rooms_log):
    log, gt, _ = rooms_log
    fe = Dpcr2d()
    truth = np.loadtxt(gt)
    poses = np.array([matrix_to_pose2(fe.process(s).pose) for s in CarmenSource(log)])
    th0 = 2 * np.arctan2(truth[0, 6], truth[0, 7])
    c, s = np.cos(th0), np.sin(th0)
    xy = truth[0, 1:3] + poses[:, :2] @ np.array([[c, s], [-s, c]])
    err = np.linalg.norm(xy - truth[: len(xy), 1:3], axis=1)
    assert err.max() < 0.15 and np.sqrt(np.mean(err**2)) < 0.06
    assert len(fe.regions) >= 8
    storage = fe.storage_bytes()
    assert storage["regional_maps"] > 0 and storage["submap"] > 0


def test_region_edges_cut_the_drift_of_wheel_odometry(rooms_log, tmp_path):
    """Registration switched off (the maps follow the poor wheel odometry): the
    region graph, linking regional maps of revisited regions, cuts the APE (measured:
    RMSE 0.155 -> 0.108 m, median 0.112 -> 0.055 m). The graph's feedback into the
    front end is off here: with no registration nothing measures the robot against the
    moved maps (with it on: RMSE 0.144 m, median 0.057 m)."""
    log, gt, _ = rooms_log
    off = [
        "--set",
        "frontend.first_registration=false",
        "--set",
        "frontend.second_registration=false",
        "--set",
        "frontend.graph_feedback=false",
    ]
    base = ["run", str(log), "--config", "dpcr2d_regions", "--gt", str(gt), "--quiet", *off]
    assert (
        main([*base, "--out", str(tmp_path / "odo"), "--set", "factors.region_edges.enabled=false"])
        == 0
    )
    assert main([*base, "--out", str(tmp_path / "graph")]) == 0
    odo, graph = _ape(tmp_path / "odo"), _ape(tmp_path / "graph")
    assert graph["rmse"] < 0.8 * odo["rmse"], (odo, graph)
    assert graph["median"] < 0.6 * odo["median"], (odo, graph)
    metrics = json.loads((tmp_path / "graph" / "metrics.json").read_text())
    assert metrics["factors"]["region_edges"] > 10
    assert metrics["backend_stats"]["optimizations"] >= metrics["keyframes"] - 1
    # the global map in the map_server format, fused from the regional maps
    img = read_pgm(tmp_path / "graph" / "map.pgm")
    meta = (tmp_path / "graph" / "map.yaml").read_text()
    assert "resolution: 0.050000" in meta and "image: map.pgm" in meta
    occupied, free = (img == 0).sum(), (img == 254).sum()
    # the rooms' walls (~ 95 m of wall, cells 5 cm, about 2 cells thick) and their floor
    assert 2000 < occupied < 8000 and free > 10 * occupied


def test_dpcr_runs_on_the_real_intel_log(tmp_path):
    out = tmp_path / "intel"
    log = shared_path("laser2d", "intel.clf.bz2")
    assert main(["run", str(log), "--config", "dpcr2d", "--out", str(out), "--quiet",
                 "--max-frames", "150"]) == 0  # fmt: skip
    traj = np.loadtxt(out / "trajectory.tum")
    assert len(traj) == 150 and np.all(np.isfinite(traj))
    steps = np.linalg.norm(np.diff(traj[:, 1:3], axis=0), axis=1)
    assert steps.max() < 0.5  # no jump: the Intel robot moves < 0.5 m between scans
    metrics = json.loads((out / "metrics.json").read_text())
    # the robot moves 0.3 m in these scans, along a region border: 1 or more keyframes
    assert metrics["frames"] == 150 and metrics["keyframes"] >= 1
    assert 0.2 < np.linalg.norm(traj[-1, 1:3] - traj[0, 1:3]) < 0.5


def test_simulate_a_2d_floor_plan_and_run_it(tmp_path):
    assert main(["simulate", "office2d", str(tmp_path / "sim"), "--frames", "60"]) == 0
    log = tmp_path / "sim" / "office2d.clf"
    gt = tmp_path / "sim" / "ground_truth.tum"
    assert len(np.loadtxt(gt)) == 60
    out = tmp_path / "run"
    assert main(["run", str(log), "--config", "dpcr2d", "--gt", str(gt), "--out", str(out),
                 "--quiet"]) == 0  # fmt: skip
    assert _ape(out)["rmse"] < 0.03
    assert (out / "map.pgm").is_file() and (out / "map.yaml").is_file()


def test_dpcr_on_a_laserscan_bag(tmp_path):
    """sensor_msgs/LaserScan in a bag (no wheel odometry: constant-velocity prediction)."""
    from slam.io.bag_writer import write_laserscan_bag
    from slam.io.trajectory import write_tum

    seq = simulate2d("office2d", frames=80, seed=4)
    bag = write_laserscan_bag(
        tmp_path / "scan.mcap",
        seq.stamps,
        np.where(np.isfinite(seq.ranges), seq.ranges, np.inf),
        angle_min=float(seq.angles[0]),
        angle_increment=float(seq.angles[1] - seq.angles[0]),
        range_max=seq.scanner.max_range,
        range_min=seq.scanner.min_range,
        fmt="mcap",
    )
    T = np.repeat(np.eye(4)[None], len(seq.poses), axis=0)
    c, s = np.cos(seq.poses[:, 2]), np.sin(seq.poses[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, :2, 3] = seq.poses[:, :2]
    write_tum(tmp_path / "gt.tum", seq.stamps, T)
    out = tmp_path / "run"
    assert main(["run", str(bag), "--config", "dpcr2d", "--gt", str(tmp_path / "gt.tum"),
                 "--out", str(out), "--quiet"]) == 0  # fmt: skip
    assert len(np.loadtxt(out / "trajectory.tum")) == 80
    assert _ape(out)["rmse"] < 0.03


def test_odometry_prior_widens_to_the_wheels_it_sees():
    """The wheel-odometry prior of the first registration starts wide (2 deg, 5 cm per
    frame) until the accepted registrations have shown the robot's wheels, then follows
    their running disagreement: 100 frames of good wheels bring it down to the model
    (0.5 deg, 2 cm per still frame); 100 frames of wheels 3 deg off per frame (FR079's
    worst) widen its heading sigma to ~3 deg; translation follows the same way."""
    fe = Dpcr2d()
    still = np.zeros(3)

    def sigmas():
        info = fe._prior_info(still)
        return 1 / np.sqrt(info[0, 0]), np.degrees(1 / np.sqrt(info[2, 2]))

    assert sigmas() == pytest.approx((0.05, 2.0), rel=1e-6)
    for _ in range(100):
        fe._learn_odometry_noise(still, np.array([0.001, -0.001, np.radians(0.05)]))
    assert sigmas() == pytest.approx((0.02, 0.5), rel=1e-6)
    rng = np.random.default_rng(0)
    for _ in range(100):
        off = np.array([rng.normal(0, 0.05), rng.normal(0, 0.05), rng.choice([-1, 1]) * 0.0524])
        fe._learn_odometry_noise(still, off)
    sigma_t, sigma_deg = sigmas()
    assert sigma_deg == pytest.approx(3.0, rel=0.1)
    assert sigma_t == pytest.approx(0.05, rel=0.25)
