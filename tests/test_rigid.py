"""Poses stay rigid: the rotation block of chained poses is projected back onto SO(3).

Found on the 4412-scan building route: LeGO-LOAM's |R^T R - I| grew by rounding fed back
through the constant-velocity model (1e-12 -> 0.17 over 410 keyframes) until iSAM2 threw
an indeterminate-system error on an odometry chain.
"""

from __future__ import annotations

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from frontends.lego_loam import LegoLoam
from slam.factors import information_noise, key, pose3
from slam.rigid import kept_rigid, nearest_rotation, orthonormalized, rotation_error
from slam.types import Scan


def test_nearest_rotation_recovers_the_rotation_from_a_perturbed_matrix():
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=3).as_matrix()
    noisy = R + 1e-4 * rng.normal(size=(3, 3))
    out = nearest_rotation(noisy)
    assert rotation_error(out) < 1e-14
    assert np.linalg.det(out) > 0.999999
    assert np.abs(out - R).max() < 3e-4  # within the perturbation
    # a reflection is not returned as the nearest rotation
    assert np.linalg.det(nearest_rotation(np.diag([1.0, 1.0, -1.0]))) > 0


def test_kept_rigid_leaves_rigid_poses_bit_for_bit_and_fixes_scaled_ones():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [1.0, 2.0, 3.0]
    assert kept_rigid(T) is T
    bad = T.copy()
    bad[:3, :3] *= 1.0003
    fixed = kept_rigid(bad)
    assert rotation_error(fixed) < 1e-14
    assert np.allclose(fixed[:3, :3], T[:3, :3], atol=1e-12)
    assert np.array_equal(fixed[:3, 3], T[:3, 3])
    assert np.allclose(orthonormalized(bad), fixed)
    assert rotation_error(pose3(bad).rotation().matrix()) < 1e-14


def _chain(make_pose, n: int = 420) -> int:
    """An odometry chain whose relative rotations drift off SO(3) at the rate measured on the
    building route (x1.066 per keyframe); the keyframe at which iSAM2 fails (n: none)."""
    rng = np.random.default_rng(0)
    isam = gtsam.ISAM2()
    noise = information_noise(np.diag([1.3e5, 1.9e5, 1.9e5, 4e3, 4e3, 4e3]))
    P = np.eye(4)
    for i in range(n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)
            graph.add(gtsam.PriorFactorPose3(key(0), gtsam.Pose3(), prior))
        else:
            S = rng.normal(size=(3, 3))
            rel = np.eye(4)
            yaw = gtsam.Rot3.Rz(0.02 * np.sin(i / 30)).matrix()
            rel[:3, :3] = yaw @ (np.eye(3) + 1e-13 * 1.066**i * 0.5 * (S + S.T))
            rel[0, 3] = 1.2
            graph.add(gtsam.BetweenFactorPose3(key(i - 1), key(i), make_pose(rel), noise))
            P = P @ rel
        values.insert(key(i), make_pose(P))
        try:
            isam.update(graph, values)
        except RuntimeError:
            return i
    return n


def test_isam2_takes_an_odometry_chain_whose_rotations_drifted_off_so3():
    raw = _chain(lambda T: gtsam.Pose3(np.asarray(T, dtype=float)))
    assert raw < 420  # the defect: gtsam.Pose3 keeps the scaled "rotation", iSAM2 fails
    assert _chain(pose3) == 420


def test_front_end_pose_is_projected_back_onto_so3():
    """A prediction from a corrupted last pose (rotation scaled by 1.0003, as after ~1800
    building scans) comes out of ``process`` rigid."""
    fe = LegoLoam()
    fe.n_keyframes = 1  # tracking established: a skipped frame keeps the prediction
    fe.T_last = np.eye(4)
    fe.T_last[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix() * 1.0003
    fe.T_last[:3, 3] = [10.0, 2.0, 0.0]
    out = fe.process(Scan(stamp=1.0, xyz=np.ones((5, 3))))  # too few points: skipped
    assert rotation_error(out.pose) < 1e-12
    assert np.allclose(out.pose[:3, 3], [10.0, 2.0, 0.0])
    assert rotation_error(fe.T_last) < 1e-12
