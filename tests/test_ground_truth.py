"""Ground truth read before a run, in the run's frame: KITTI camera poses of a KITTI
sequence are evaluated in the LiDAR frame (RPE was metres off), stamped with the scans."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shared_data import shared_path

from slam.errors import InputError
from slam.eval.ground_truth import evaluate_truth, read_ground_truth
from slam.io.kitti import KittiSource
from slam.io.source import open_source
from slam.io.trajectory import write_kitti, write_tum


def provenance_tr() -> np.ndarray:
    """T_cam0_velo of KITTI odometry 04-12, the 3 rows of 4 numbers in PROVENANCE.txt."""
    rows = []
    for line in shared_path("kitti_odometry", "PROVENANCE.txt").read_text().splitlines():
        try:
            values = [float(p) for p in line.split()]
        except ValueError:
            continue
        if len(values) == 4:
            rows.append(values)
    tr = np.eye(4)
    tr[:3] = rows[:3]
    return tr


def kitti_copy(tmp_path, calib: bool):
    """The shared KITTI 04 sequence (scans linked), with a calib.txt holding Tr or not."""
    seq = shared_path("kitti_odometry", "04")
    root = tmp_path / ("04c" if calib else "04")
    root.mkdir()
    (root / "velodyne").symlink_to(seq / "velodyne")
    for name in ("times.txt", "poses.txt"):
        (root / name).write_text((seq / name).read_text())
    if calib:
        tr = " ".join(f"{v:.12e}" for v in provenance_tr()[:3].ravel())
        (root / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {tr}\n")
    return root


def test_kitti_poses_are_taken_to_the_lidar_frame_and_the_scan_stamps(tmp_path):
    root = kitti_copy(tmp_path, calib=True)
    src = open_source(root)
    truth = read_ground_truth(root / "poses.txt", src)
    cam = np.tile(np.eye(4), (10, 1, 1))
    cam[:, :3] = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    tr = provenance_tr()
    np.testing.assert_allclose(truth.poses, np.linalg.inv(tr) @ cam @ tr, atol=1e-12)
    # the car drives forward: LiDAR x (camera z), ~1.4 m per 0.1 s scan at 14 m/s
    step = np.linalg.inv(truth.poses[0]) @ truth.poses[1]
    assert step[0, 3] == pytest.approx(1.4, abs=0.2) and abs(step[2, 3]) < 0.1
    np.testing.assert_allclose(truth.stamps, np.loadtxt(root / "times.txt"))
    assert truth.warnings == []
    assert truth.notes == [
        f"ground truth {root / 'poses.txt'}: KITTI camera poses taken to the LiDAR frame "
        f"(Tr of {root / 'calib.txt'}), paired with the scans by their stamps"
    ]


def test_rpe_against_kitti_poses_is_in_the_lidar_frame(tmp_path):
    """A LiDAR trajectory 1 cm off the truth: RPE ~1 cm against the sequence's poses.txt
    with calib.txt (it was 1.9 m: camera motion against LiDAR motion); without calib.txt
    the same numbers come with a warning that says why."""
    rng = np.random.default_rng(0)
    good = kitti_copy(tmp_path, calib=True)
    truth = read_ground_truth(good / "poses.txt", open_source(good))
    est = truth.poses.copy()
    est[:, :3, 3] += rng.normal(0, 0.01, (len(est), 3))
    est[:, :3, :3] = (
        est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 1e-3, (len(est), 3))).as_matrix()
    )
    write_tum(tmp_path / "est.tum", truth.stamps, est)
    res = evaluate_truth(tmp_path / "est.tum", truth)
    assert res.n_matched == 10 and res.rpe_trans["mean"] < 0.03 and res.ape_trans["rmse"] < 0.02
    assert "LiDAR frame" in res.notes[0]
    bare = kitti_copy(tmp_path, calib=False)
    truth = read_ground_truth(bare / "poses.txt", open_source(bare))
    np.testing.assert_allclose(truth.poses, open_source(bare).ground_truth())  # as they are
    assert len(truth.warnings) == 1 and "calib.txt with the LiDAR transform Tr" in truth.warnings[0]
    res = evaluate_truth(tmp_path / "est.tum", truth)
    assert res.rpe_trans["mean"] > 1.0 and truth.warnings[0] in res.notes


def test_other_ground_truth_is_taken_as_it_is(tmp_path):
    """TUM ground truth (stamps of its own) and KITTI poses of a non-KITTI input are not
    touched; a KITTI file of another length is paired by index as before."""
    rng = np.random.default_rng(1)
    clouds = [rng.uniform(-9, 9, (20, 4)).astype(np.float32) for _ in range(4)]
    (tmp_path / "s" / "velodyne").mkdir(parents=True)
    for i, pts in enumerate(clouds):
        pts.tofile(tmp_path / "s" / "velodyne" / f"{i:06d}.bin")
    tr = np.eye(4)
    tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    (tmp_path / "s" / "calib.txt").write_text("Tr: " + " ".join(map(str, tr[:3].ravel())))
    src = KittiSource(tmp_path / "s")
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 2, 3] = np.arange(4.0)
    write_tum(tmp_path / "gt.tum", np.arange(4) * 0.1, poses)
    truth = read_ground_truth(tmp_path / "gt.tum", src)
    np.testing.assert_allclose(truth.poses, poses)
    assert truth.notes == truth.warnings == []
    write_kitti(tmp_path / "gt.txt", poses)
    assert read_ground_truth(tmp_path / "gt.txt").stamps is None  # no input: as it is
    lidar = read_ground_truth(tmp_path / "gt.txt", src)
    np.testing.assert_allclose(lidar.poses[:, 0, 3], np.arange(4.0), atol=1e-12)  # cam z = x
    np.testing.assert_allclose(lidar.stamps, [0.0, 0.1, 0.2, 0.3])
    write_kitti(tmp_path / "gt5.txt", np.tile(np.eye(4), (5, 1, 1)))
    assert read_ground_truth(tmp_path / "gt5.txt", src).stamps is None
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="columns"):
        read_ground_truth(tmp_path / "bad.txt", src)


def test_slam_run_on_kitti_with_its_own_poses_evaluates_in_the_lidar_frame(tmp_path, capsys):
    """``slam run SEQ --gt SEQ/poses.txt`` on a window of the sequence: RPE in centimetres
    (was 1.86 m), one line saying how the poses were taken."""
    from slam.cli import main

    root = kitti_copy(tmp_path, calib=True)
    out = tmp_path / "run"
    args = ["run", str(root), "--gt", str(root / "poses.txt"), "--out", str(out), "--quiet"]
    assert main([*args, "--start", "2", "--max-frames", "5"]) == 0
    err = capsys.readouterr().err
    assert f"note: ground truth {root / 'poses.txt'}: KITTI camera poses taken to the LiDAR" in err
    ape = json.loads((out / "ape.json").read_text())
    assert ape["n_matched"] == 5 and ape["rpe_trans"]["mean"] < 0.05
    assert ape["ape_trans"]["rmse"] < 0.05 and "LiDAR frame" in ape["notes"][0]
