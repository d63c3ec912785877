"""Per-beam elevation / azimuth / range offsets learned from registration residuals."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError
from slam.sensor.beam_calibration import (
    BeamCalibration,
    BeamCalibrationConfig,
    beam_jacobian,
    normal_equations,
    rotate_beams,
)
from slam.sensor.beam_calibration_kernels import apply_offsets, normal_equations_kernel


def test_rotate_beams_moves_elevation_azimuth_and_range_only():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3)) * 10
    d = np.column_stack([np.full(50, 0.01), np.full(50, -0.02), np.full(50, 0.05)])
    q = rotate_beams(p, d)
    r, rq = np.linalg.norm(p, axis=1), np.linalg.norm(q, axis=1)
    np.testing.assert_allclose(rq, r + 0.05, atol=1e-12)
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    elq = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
    np.testing.assert_allclose(elq - el, 0.01, atol=1e-12)
    az = np.angle(np.exp(1j * (np.arctan2(q[:, 1], q[:, 0]) - np.arctan2(p[:, 1], p[:, 0]))))
    np.testing.assert_allclose(az, -0.02, atol=1e-12)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20, 3)) * 10
    J = beam_jacobian(p)
    for k in range(3):
        d = np.zeros((20, 3))
        d[:, k] = 1e-7
        fd = (rotate_beams(p, d) - p) / 1e-7
        np.testing.assert_allclose(fd, J[:, :, k], atol=1e-4)


def _street(n_beams: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Rays of a 16-beam sensor 1.8 m above a ground plane between two facades 8 m to
    either side: (points, ring) of the true surface hits."""
    el = np.radians(np.linspace(-15.0, 1.0, n_beams))
    az = np.radians(np.arange(0.0, 360.0, 0.4))
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    t = np.full(E.shape, np.inf)
    down = d[..., 2] < -1e-6
    t[down] = -1.8 / d[..., 2][down]
    side = np.abs(d[..., 1]) > 1e-6
    t_side = np.full(E.shape, np.inf)
    t_side[side] = 8.0 / np.abs(d[..., 1][side])
    t = np.minimum(t, t_side)
    ok = np.isfinite(t) & (t < 40.0)
    pts = d[ok] * t[ok][:, None]
    ring = np.broadcast_to(np.arange(n_beams)[:, None], E.shape)[ok]
    return pts, ring


def _surface_normals(p: np.ndarray) -> np.ndarray:
    """The true surface normal at each hit of ``_street``: ground or facade."""
    n = np.zeros_like(p)
    ground = np.abs(p[:, 2] + 1.8) < 1e-6 * (1 + np.abs(p[:, 2]))
    n[ground, 2] = 1.0
    n[~ground, 1] = np.sign(p[~ground, 1])
    return n


def test_offsets_of_a_miscalibrated_sensor_are_recovered():
    """Scans of a miscalibrated sensor registered (at the true pose) on a map of the true
    surfaces: the learned offsets converge to the sensor's errors."""
    truth_pts, ring = _street()
    rng = np.random.default_rng(2)
    errors = np.column_stack(
        [
            rng.normal(0, np.radians(0.1), 16),
            rng.normal(0, np.radians(0.1), 16),
            rng.normal(0, 0.02, 16),
        ]
    )
    # what the driver reports: the true hit seen along the nominal direction and range
    measured = rotate_beams(truth_pts, -errors[ring])
    # the map: the true surfaces sampled on a 5 cm grid, independent of the rays
    g = np.arange(-40.0, 40.0, 0.05)
    gx, gy = np.meshgrid(g, np.arange(-8.0, 8.0, 0.05), indexing="ij")
    gz = np.arange(-1.8, 6.0, 0.05)
    fx, fz = np.meshgrid(g, gz, indexing="ij")
    dense = np.concatenate(
        [
            np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.8)]),
            np.column_stack([fx.ravel(), np.full(fx.size, 8.0), fz.ravel()]),
            np.column_stack([fx.ravel(), np.full(fx.size, -8.0), fz.ravel()]),
        ]
    )
    tree = cKDTree(dense)
    cal = BeamCalibration(BeamCalibrationConfig(enabled=True, memory=20.0, max_gain=0.5))
    for _ in range(60):
        p = cal.correct(measured, ring)
        _, j = tree.query(p)
        n = _surface_normals(dense[j])
        W = 1e4 * np.einsum("ni,nj->nij", n, n) + 1e-2 * np.eye(3)
        # the map point: the true surface under the corrected point, along its normal
        q = p - np.einsum("ni,ni->n", p - dense[j], n)[:, None] * n
        cal.update(p, ring, np.eye(4), q, W)
    # the corrected points lie on the true surfaces (ground-only beams cannot tell an
    # elevation from a range offset, so the offsets themselves are not all observable)
    n_true = _surface_normals(truth_pts)
    before = np.abs(np.einsum("ni,ni->n", measured - truth_pts, n_true))
    after = np.abs(np.einsum("ni,ni->n", cal.correct(measured, ring) - truth_pts, n_true))
    assert np.percentile(before, 99) > 0.02
    assert np.percentile(after, 99) < 0.002
    # beams that see both facades and the ground: every offset is recovered
    both = [
        b for b in range(16) if len(np.unique(_surface_normals(truth_pts[ring == b]), axis=0)) == 3
    ]
    err = np.abs(cal.offsets[both] - errors[both])
    assert len(both) >= 4
    assert np.degrees(err[:, :2]).max() < 0.02 and err[:, 2].max() < 0.005


def test_correct_is_identity_without_rings_or_offsets():
    cal = BeamCalibration(BeamCalibrationConfig(enabled=True))
    p = np.random.default_rng(3).normal(size=(10, 3))
    assert cal.correct(p, None) is p
    assert cal.correct(p, np.zeros(10, dtype=int)) is p


def test_kernels_equal_their_numpy_references():
    rng = np.random.default_rng(4)
    p = rng.normal(size=(300, 3)) * 15
    rings = rng.integers(-1, 12, 300)
    table = np.column_stack(
        [rng.normal(0, 2e-3, 10), rng.normal(0, 2e-3, 10), rng.normal(0, 0.03, 10)]
    )
    ok = (rings >= 0) & (rings < 10)
    delta = np.zeros((300, 3))
    delta[ok] = table[rings[ok]]
    np.testing.assert_allclose(apply_offsets(p, rings, table), rotate_beams(p, delta), atol=1e-12)

    rings = rng.integers(0, 10, 300)
    a = rng.normal(size=3) * 0.1
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(a).as_matrix()
    T[:3, 3] = [1.0, -2.0, 0.5]
    q = p @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.05, (300, 3))
    L = rng.normal(size=(300, 3, 3))
    W = np.einsum("nij,nkj->nik", L, L) + np.eye(3)
    w = rng.uniform(0, 1, 300)
    ref = normal_equations(p, rings, T, q, W, w, 10)
    got = normal_equations_kernel(p, rings, T[:3, :3].copy(), T[:3, 3].copy(), q, W, w, 10)
    for r, g in zip(ref, got, strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-10, atol=1e-9)


def test_config_is_checked():
    with pytest.raises(ConfigError):
        BeamCalibrationConfig(max_gain=0)
    with pytest.raises(ConfigError):
        BeamCalibrationConfig(prior_range=0)
