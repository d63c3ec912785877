"""Loop closure end to end on the simulated corridor and plaza loops, against ground truth.

The scans and keyframe clouds are the simulator's; the odometry is the ground truth with
a systematic heading drift injected (0.4 deg per metre driven), as a drifting front end
would give. Loop closure must find the true revisit, accept no false loop among the
corridor's look-alike sections, and cut the APE at least in half.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.config import from_dict
from slam.deskew import deskew
from slam.eval.metrics import evaluate_arrays
from slam.frontend import KeyframeConfig, is_new_keyframe
from slam.io.source import open_source
from slam.io.trajectory import read_tum
from slam.pipeline import Pipeline
from slam.preprocess.voxel import voxel_downsample
from slam.types import Odometry

DRIFT_DEG_PER_M = 0.4


def drifting_odometry(gt: np.ndarray) -> np.ndarray:
    """Compose ground-truth increments with an extra yaw of DRIFT_DEG_PER_M per metre."""
    odom = [gt[0]]
    for a, b in zip(gt[:-1], gt[1:], strict=True):
        rel = np.linalg.solve(a, b)
        bias = np.eye(4)
        bias[:3, :3] = Rotation.from_euler(
            "z", DRIFT_DEG_PER_M * np.linalg.norm(rel[:3, 3]), degrees=True
        ).as_matrix()
        odom.append(odom[-1] @ bias @ rel)
    return np.stack(odom)


class ReplayFrontend:
    """Plays back (pose, cloud) pairs like a front end would emit them."""

    def __init__(self, poses, clouds):
        self.poses, self.clouds, self.last_kf = poses, clouds, None
        self.kf_cfg = KeyframeConfig()

    def process(self, scan):
        T = self.poses[scan.index]
        rel = np.eye(4) if self.last_kf is None else np.linalg.solve(self.last_kf, T)
        is_kf = self.last_kf is None or is_new_keyframe(rel, self.kf_cfg)
        if is_kf:
            self.last_kf = T
        info = np.diag([1 / 0.01**2] * 3 + [1 / 0.05**2] * 3)  # 0.6 deg, 5 cm
        return Odometry(scan.stamp, T, is_kf, rel, info, self.clouds[scan.index], {})


@pytest.fixture(scope="module", params=["corridor", "plaza"])
def replay(request):
    seq = request.getfixturevalue(f"{request.param}_full")
    stamps, gt = read_tum(seq.ground_truth)
    scans, clouds = [], []
    for scan in open_source(seq.bag):
        i = scan.index
        motion = np.linalg.solve(gt[i], gt[min(i + 1, len(gt) - 1)])
        xyz = deskew(scan.xyz, scan.time, motion, 0.1)
        clouds.append(xyz[voxel_downsample(xyz, 0.15)])
        scans.append(scan.select(np.zeros(len(scan), dtype=bool)))  # the poses need no points
    return stamps, gt, scans, clouds, request.param


def run(replay, factors):
    stamps, gt, scans, clouds, _ = replay
    pipe = Pipeline(
        # the replayed scans carry no points (the poses need none): no beam model to estimate
        from_dict({"factors": factors, "source": {"beam_scans": 0}}),
        frontend=ReplayFrontend(drifting_odometry(gt), clouds),
    )
    st = pipe.run(iter(scans))
    return pipe, st.trajectory()


def test_loop_closure_halves_ape_with_no_false_loop(replay):
    stamps, gt, _, _, scene = replay
    _, odom = run(replay, {"prior": {}, "odometry": {}})
    pipe, loop = run(replay, {"prior": {}, "odometry": {}, "loop_closure": {}})
    ape_odom = evaluate_arrays(stamps, odom, stamps, gt).ape_trans["rmse"]
    ape_loop = evaluate_arrays(stamps, loop, stamps, gt).ape_trans["rmse"]
    plugin = pipe.factor_sources[-1].plugin
    accepted = [e for e in plugin.events if e.accepted]
    assert accepted, "the true revisit was not closed"
    kfs = pipe.state.keyframes
    for ev in accepted:  # every accepted loop is a true revisit with an accurate transform
        T_true = np.linalg.solve(gt[kfs[ev.target].frame_index], gt[kfs[ev.source].frame_index])
        err = np.linalg.solve(T_true, ev.T_target_source)
        assert np.linalg.norm(err[:3, 3]) < 0.10
        assert np.degrees(Rotation.from_matrix(err[:3, :3]).magnitude()) < 1.0
    if scene == "corridor":  # its look-alike legs are proposed, and must be turned down
        assert any(not e.accepted for e in plugin.events)
    assert ape_odom > 0.3  # the injected drift is real
    assert ape_loop < 0.5 * ape_odom
