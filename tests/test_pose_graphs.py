"""g2o reading/writing and the pose-by-pose iSAM2 vs batch LM optimisers."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from shared_data import SHARED_DATA, shared_path

from backends.isam2 import Isam2Config, isam2_params
from slam.errors import InputError, SlamError
from slam.factors import key, robust_noise
from slam.pose_graph import (
    batch_lm,
    detect_3d,
    incremental_isam2,
    read_g2o,
    total_error,
    values_from_poses,
    write_g2o,
)

DATA = SHARED_DATA / "pose_graphs"


def grid_graph_2d(n: int = 60, seed: int = 0):
    """A 2D odometry chain on a lawnmower path with loop edges every 10 poses to the pose
    two rows back; noisy measurements and an odometry-chained initial guess."""
    rng = np.random.default_rng(seed)
    truth = [gtsam.Pose2()]
    for i in range(1, n):
        turn = np.pi / 2 if i % 10 in (0, 1) else 0.0
        truth.append(truth[-1].compose(gtsam.Pose2(1.0, 0.0, turn)))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    initial.insert(0, truth[0])
    for i in range(1, n):
        rel = (
            truth[i - 1].between(truth[i]).compose(gtsam.Pose2(*rng.normal(0, [0.05, 0.05, 0.02])))
        )
        graph.add(gtsam.BetweenFactorPose2(i - 1, i, rel, noise))
        initial.insert(i, initial.atPose2(i - 1).compose(rel))
    for i in range(20, n, 5):
        j = i - 19
        graph.add(gtsam.BetweenFactorPose2(j, i, truth[j].between(truth[i]), noise))
    return graph, initial


def test_incremental_isam2_matches_batch_on_a_2d_graph():
    graph, initial = grid_graph_2d()
    batch, _ = batch_lm(graph, initial)
    isam, _ = incremental_isam2(graph, initial)
    e_init, e_batch, e_isam = (total_error(graph, v) for v in (initial, batch, isam))
    assert e_batch < e_init / 10
    assert abs(e_isam - e_batch) <= 0.01 * e_batch
    # the first pose is anchored where the initial guess put it
    assert batch.atPose2(0).equals(initial.atPose2(0), 1e-6)


def test_g2o_roundtrip_of_a_slam_graph_with_robust_and_unary_factors(tmp_path):
    poses = {i: gtsam.Pose3(gtsam.Rot3.Yaw(0.1 * i), np.array([i, 0.5 * i, 0.0])) for i in range(5)}
    values = values_from_poses(poses)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(key(0), poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    info = np.diag([1e4, 1e4, 1e4, 1e2, 1e2, 1e2])
    for i in range(1, 5):
        graph.add(
            gtsam.BetweenFactorPose3(
                key(i - 1),
                key(i),
                poses[i - 1].between(poses[i]),
                gtsam.noiseModel.Gaussian.Information(info),
            )
        )
    base = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    loop = poses[4].between(poses[0]).compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.3, 0, 0])))
    graph.add(gtsam.BetweenFactorPose3(key(4), key(0), loop, robust_noise(base, "cauchy", 1.0)))
    graph.add(
        gtsam.GPSFactor(key(2), gtsam.Point3(2.0, 1.0, 0.0), gtsam.noiseModel.Isotropic.Sigma(3, 1))
    )
    path = tmp_path / "graph.g2o"
    assert write_g2o(path, graph, values) == 5  # 4 odometry + 1 loop; prior and GPS left out
    assert detect_3d(path)
    g2, v2 = read_g2o(path)
    assert g2.size() == 5
    assert sorted(v2.keys()) == [0, 1, 2, 3, 4]
    for i in range(5):
        assert v2.atPose3(i).equals(poses[i], 1e-6)
    # the loop residual 0.3 m with sigma 0.1 comes back as a Gaussian edge: error 0.5 * 3^2
    assert total_error(g2, v2) == pytest.approx(4.5, rel=1e-4)


def test_read_g2o_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.g2o"):
        read_g2o(tmp_path / "missing.g2o")
    with pytest.raises(InputError, match="does not exist"):
        write_g2o(tmp_path / "no" / "out.g2o", gtsam.NonlinearFactorGraph(), gtsam.Values())
    bad = tmp_path / "bad.g2o"
    bad.write_text("hello world\n")
    with pytest.raises(InputError, match="bad.g2o"):
        read_g2o(bad)


def test_incremental_rejects_factors_on_unknown_poses():
    graph, initial = grid_graph_2d(n=10)
    graph.add(
        gtsam.BetweenFactorPose2(3, 99, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1.0))
    )
    with pytest.raises(InputError, match="without an initial value"):
        incremental_isam2(graph, initial)


@pytest.mark.parametrize("name", ["intel", "parking-garage"])
def test_real_pose_graph_isam2_reaches_the_batch_optimum(name):
    graph, initial = read_g2o(shared_path("pose_graphs", f"{name}.g2o"))
    batch, _ = batch_lm(graph, initial)
    isam, _ = incremental_isam2(
        graph,
        initial,
        params=isam2_params(Isam2Config(relinearize_threshold=0.1, relinearize_skip=10)),
    )
    e_init, e_batch, e_isam = (total_error(graph, v) for v in (initial, batch, isam))
    # measured: intel 277.0 -> 22.502 (iSAM2 22.522), garage 8363.6 -> 0.63419 (iSAM2 same)
    assert e_batch < e_init / 10
    assert abs(e_isam - e_batch) <= 0.01 * e_batch


def test_write_g2o_refuses_colliding_vertex_ids(tmp_path):
    values = gtsam.Values()
    values.insert(gtsam.symbol("x", 1), gtsam.Pose3())
    values.insert(gtsam.symbol("l", 1), gtsam.Pose3())
    with pytest.raises(SlamError, match="vertex id 1"):
        write_g2o(tmp_path / "c.g2o", gtsam.NonlinearFactorGraph(), values)
