"""GICP (paper 000, section 2.2): synthetic 6-DoF recovery and the real HDL-32E scan pair."""

from pathlib import Path

import numpy as np
import pytest

from slam.preprocess.voxel import voxel_downsample
from slam.registration.gicp import (
    GicpConfig,
    GicpTarget,
    RegistrationError,
    estimate_covariances,
    gicp_align,
    se3_exp,
    transform,
)
from slam.registration.information import information_from_hessian

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "scan_pair"


def pose_error(T_est, T_true):
    D = np.linalg.inv(T_true) @ T_est
    angle = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(D[:3, 3])), float(angle)


def room_scan(rng, n=6000):
    """Points on a 3-D structured scene: floor, walls of a 12 x 8 x 3 m room, two boxes."""
    u = rng.uniform(size=(n, 2))
    faces = rng.integers(0, 7, n)
    p = np.zeros((n, 3))
    p[faces == 0] = np.c_[u[:, 0] * 12 - 6, u[:, 1] * 8 - 4, np.zeros(n)][faces == 0]
    p[faces == 1] = np.c_[np.full(n, -6), u[:, 0] * 8 - 4, u[:, 1] * 3][faces == 1]
    p[faces == 2] = np.c_[np.full(n, 6), u[:, 0] * 8 - 4, u[:, 1] * 3][faces == 2]
    p[faces == 3] = np.c_[u[:, 0] * 12 - 6, np.full(n, -4), u[:, 1] * 3][faces == 3]
    p[faces == 4] = np.c_[u[:, 0] * 12 - 6, np.full(n, 4), u[:, 1] * 3][faces == 4]
    p[faces == 5] = np.c_[np.full(n, 2.0), u[:, 0] * 1 - 1, u[:, 1] * 1.2][faces == 5]
    p[faces == 6] = np.c_[u[:, 0] * 1.5 - 3, np.full(n, 1.5), u[:, 1] * 0.8][faces == 6]
    return p + rng.normal(0, 0.003, p.shape)


def test_covariances_of_a_plane_are_flat_and_regularised():
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(0, 1, (500, 2)), np.zeros(500)]
    cov = estimate_covariances(xyz, k=10, lambda_reg=1e-6)
    assert cov.shape == (500, 3, 3)
    assert np.allclose(cov[:, 2, 2], 1e-6)  # the lambda*I of eq. (1) on the normal
    assert np.all(cov[:, 0, 0] > 1e-4)
    plane = estimate_covariances(xyz, k=10, lambda_reg=0.0, mode="plane")
    assert np.allclose(np.linalg.eigvalsh(plane), [1e-3, 1.0, 1.0], atol=1e-9)


def test_shape_covariances_trust_only_what_the_support_samples():
    """A ring on open ground (one scan line) is no plane: isotropic; several rings: a plane
    with the ground normal; a pole sampled by several rings: a line."""
    rng = np.random.default_rng(0)
    az = np.linspace(-0.3, 0.3, 60)
    rings = [np.c_[r * np.cos(az), r * np.sin(az), rng.normal(0, 1e-3, 60)] for r in (4, 4.4)]
    pole = np.c_[np.full(12, 3.0), np.full(12, -1.0), np.linspace(0, 1.1, 12)]
    xyz = np.concatenate(rings + [pole])
    ring = np.r_[np.zeros(60), np.ones(60), np.arange(12)].astype(int)
    one = np.flatnonzero(ring[:120] == 0)[30:31]
    kw = {"k": 10, "lambda_reg": 0.0, "mode": "shape"}
    iso = estimate_covariances(xyz, query=xyz[one], labels=ring, **kw)
    assert np.allclose(iso[0], np.eye(3))
    assert not np.allclose(estimate_covariances(xyz, query=xyz[one], **kw)[0], np.eye(3))
    raw = estimate_covariances(xyz, query=xyz[one], labels=ring, k=10, lambda_reg=0.0)
    extent = np.linalg.eigvalsh(estimate_covariances(xyz, query=xyz[one], k=10, lambda_reg=0.0))[
        0, 2
    ]
    assert np.allclose(raw[0], np.eye(3) * raw[0, 0, 0]) and np.isclose(raw[0, 0, 0], extent)
    both = estimate_covariances(xyz[:120], query=xyz[one], labels=ring[:120], k=30, mode="shape")
    w, v = np.linalg.eigh(both[0])
    assert np.allclose(w, [1e-3, 1, 1], atol=1e-5) and abs(v[2, 0]) > 0.99  # ground normal z
    line = estimate_covariances(pole, query=pole[5:6], labels=ring[120:], k=8, mode="shape")
    w, v = np.linalg.eigh(line[0])
    assert np.allclose(w, [1e-3, 1e-3, 1], atol=1e-5) and abs(v[2, 2]) > 0.99  # along z


@pytest.mark.parametrize("mode", ["raw", "plane", "shape"])
def test_gicp_recovers_known_transform(mode):
    rng = np.random.default_rng(1)
    target = room_scan(rng)
    T_true = se3_exp(np.array([0.02, -0.03, 0.08, 0.4, -0.25, 0.1]))
    source = transform(np.linalg.inv(T_true), room_scan(rng))  # independent samples
    res = gicp_align(source, target, np.eye(4), GicpConfig(covariance_mode=mode))
    t_err, r_err = pose_error(res.T_target_source, T_true)
    assert res.converged
    assert t_err < 0.005 and r_err < 0.05, (t_err, r_err)
    assert res.H.shape == (6, 6) and np.all(np.linalg.eigvalsh(res.H) > 0)
    assert res.rmse < 0.2  # nearest-neighbour spacing of independent samples


def test_gicp_needs_overlap():
    rng = np.random.default_rng(2)
    target = room_scan(rng, 500)
    with pytest.raises(RegistrationError):
        gicp_align(target + 100.0, target, np.eye(4))


def test_hessian_ordering_is_rotation_first():
    rng = np.random.default_rng(3)
    target = room_scan(rng, 3000)
    res = gicp_align(target, GicpTarget.from_points(target), np.eye(4))
    # a pure x-translation perturbation must show in the translation block (index 3)
    xi = np.zeros(6)
    xi[3] = 1.0
    assert xi @ res.H @ xi > 0
    info = information_from_hessian(res.H, res.cost / res.dof)
    sig = np.sqrt(np.diag(np.linalg.inv(info.info)))
    assert np.all(sig[3:] >= 0.0099) and np.all(sig[:3] >= np.radians(0.0499))
    assert not info.degenerate


@pytest.mark.skipif(not (DATA / "source.ply").is_file(), reason="shared scan pair absent")
def test_gicp_real_hdl32_pair():
    import open3d as o3d

    src = np.asarray(o3d.io.read_point_cloud(str(DATA / "source.ply")).points, dtype=np.float64)
    tgt = np.asarray(o3d.io.read_point_cloud(str(DATA / "target.ply")).points, dtype=np.float64)
    T_ref = np.loadtxt(DATA / "T_target_source.txt")
    src = src[voxel_downsample(src, 0.1)]
    tgt = tgt[voxel_downsample(tgt, 0.1)]
    res = gicp_align(src, tgt, np.eye(4), GicpConfig(covariance_mode="plane"))
    t_err, r_err = pose_error(res.T_target_source, T_ref)
    assert t_err < 0.02 and r_err < 0.1, (t_err, r_err)
