"""`slam eval` of a LiDAR trajectory against KITTI camera poses: the calib.txt beside the
poses (or --calib) takes them to the LiDAR frame, as `slam run --gt` does."""

from __future__ import annotations

import json

import numpy as np
from scipy.spatial.transform import Rotation

from slam.cli import main
from slam.io.trajectory import write_kitti

# KITTI's Tr (velodyne -> left camera) of sequences 04-10, rounded
TR = np.array([[-0.0018, -0.9999, -0.0084, -0.0048],
               [-0.0065, 0.0084, -0.9999, -0.0731],
               [0.9999, -0.0019, -0.0065, -0.3334],
               [0.0, 0.0, 0.0, 1.0]])  # fmt: skip
_u, _, _vt = np.linalg.svd(TR[:3, :3])
TR[:3, :3] = _u @ _vt  # the nearest rotation: a calib.txt holds one to 1e-9


def _drive(n=60):
    """LiDAR poses of a car turning left at 8 m/s, 10 Hz."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.radians(0.8) * np.arange(n)
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    poses[:, 0, 3] = np.cumsum(0.8 * np.cos(yaw))
    poses[:, 1, 3] = np.cumsum(0.8 * np.sin(yaw))
    return poses


def _files(tmp_path, calib=True):
    lidar = _drive()
    camera = TR[None] @ lidar @ np.linalg.inv(TR)[None]  # what KITTI's poses.txt holds
    seq = tmp_path / "seq"
    seq.mkdir()
    write_kitti(seq / "poses.txt", camera)
    if calib:
        tr = " ".join(f"{v:.6e}" for v in TR[:3].ravel())
        (seq / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {tr}\n")
    write_kitti(tmp_path / "est.kitti", lidar)
    return seq, tmp_path / "est.kitti"


def _rpe(out):
    return json.loads((out / "ape.json").read_text())["rpe_trans"]["rmse"]


def test_camera_poses_beside_a_calib_are_compared_in_the_lidar_frame(tmp_path, capsys):
    seq, est = _files(tmp_path)
    assert main(["eval", str(est), str(seq / "poses.txt"), "--out", str(tmp_path / "o")]) == 0
    assert "KITTI camera poses taken to the LiDAR frame" in capsys.readouterr().err
    assert _rpe(tmp_path / "o") < 1e-6


def test_without_a_calib_the_frames_differ_and_it_says_so(tmp_path, capsys):
    seq, est = _files(tmp_path, calib=False)
    assert main(["eval", str(est), str(seq / "poses.txt"), "--out", str(tmp_path / "o")]) == 0
    assert "warning:" in capsys.readouterr().err
    assert _rpe(tmp_path / "o") > 0.05  # camera motion is not LiDAR motion in a turn
    other = tmp_path / "calib"
    other.mkdir()
    (other / "calib.txt").write_text("Tr: " + " ".join(f"{v:.6e}" for v in TR[:3].ravel()))
    code = main(["eval", str(est), str(seq / "poses.txt"), "--calib", str(other / "calib.txt"),
                 "--out", str(tmp_path / "o2")])  # fmt: skip
    assert code == 0 and _rpe(tmp_path / "o2") < 1e-6
    assert main(["eval", str(est), str(seq / "poses.txt"), "--calib", str(tmp_path / "x")]) == 2
