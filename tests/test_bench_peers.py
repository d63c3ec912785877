"""slam.bench.peers and the robustness sweeps' pair case: the reference systems on the real
HDL-32E scan pair against its reference transform (good to ~1 cm / 0.3 deg; the pair is
0.50 m / 0.71 deg apart, so staying at the identity fails every check)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from shared_data import shared_path

from slam.bench.peers import motion_error, small_gicp_odometry, small_gicp_pair, small_gicp_track
from slam.bench.robustness import pair_case
from slam.io.folders import read_cloud


def test_motion_error_of_a_known_motion():
    B = np.eye(4)
    B[:3, :3] = Rotation.from_euler("z", 10.0, degrees=True).as_matrix()
    B[:3, 3] = (3.0, 4.0, 0.0)
    t, r = motion_error(np.eye(4), B)
    assert abs(t - 5.0) < 1e-12 and abs(r - 10.0) < 1e-9


def test_small_gicp_on_the_real_pair_finds_the_reference_motion():
    pair = shared_path("scan_pair")
    T_ref = np.loadtxt(pair / "T_target_source.txt")
    scans = [read_cloud(pair / "target.ply", index=0, stamp=0.0),
             read_cloud(pair / "source.ply", index=1, stamp=0.1)]  # fmt: skip
    t, r = motion_error(small_gicp_pair(scans[0].xyz, scans[1].xyz), T_ref)
    assert t < 0.03 and r < 0.5  # the reference itself: ~1 cm / 0.3 deg
    track = list(small_gicp_track(scans))
    assert [s for s, _ in track] == [0.0, 0.1]
    poses = small_gicp_odometry(scans)  # the same poses (2 threads: not bit-identical)
    assert all(np.allclose(a, b, atol=1e-6) for (_, a), b in zip(track, poses, strict=True))
    t, r = motion_error(np.linalg.inv(poses[0]) @ poses[1], T_ref)
    assert t < 0.05 and r < 0.5


def test_pair_case_runs_the_front_end_on_the_real_pair():
    row = pair_case("floam", shared_path("scan_pair"))
    assert row["frames"] == row["messages"] == 2
    assert row["step_err_max"] < 0.05 and row["pair_rot_deg"] < 0.5
    assert row["ran_away"] == ""
