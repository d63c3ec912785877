"""The ground as a plane in GICP (``slam.registration.ground_plane``): the fit, the
covariances it rewrites, and the pull of the rings it removes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError
from slam.registration.covariances import estimate_covariances
from slam.registration.feature_icp import FeatureIcpConfig, FeatureTarget, feature_icp_align
from slam.registration.gicp import GicpConfig, gicp_align
from slam.registration.ground_plane import (
    FixedNormals,
    GroundPlaneConfig,
    fit_ground,
    flatten_ground,
    on_ground,
)
from slam.registration.two_step import TwoStepConfig, plane_terms

HEIGHT = 1.8  # m: the sensor above the ground


def _rings(rng: np.random.Generator, tilt_deg: float = 0.0) -> np.ndarray:
    """Flat ground seen by a 32-beam sensor wherever it stands: the beams from -25 to -3 deg
    hit it on circles around the sensor, 0.2 deg apart along each (sensor frame, m); the
    ground tilted by ``tilt_deg`` about the y axis."""
    el = np.radians(np.linspace(-25.0, -3.0, 32))
    az = np.radians(np.arange(0.0, 360.0, 0.2))
    r = HEIGHT / np.tan(-el)
    r = r[r < 40.0]
    rr, aa = np.meshgrid(r, az)
    pts = np.column_stack([rr.ravel() * np.cos(aa.ravel()), rr.ravel() * np.sin(aa.ravel())])
    z = -HEIGHT + np.tan(np.radians(tilt_deg)) * pts[:, 0]
    return np.column_stack([pts, z + rng.normal(0.0, 0.01, len(pts))])


def _poles(origin: np.ndarray) -> np.ndarray:
    """Four thin poles 8-15 m from the road (world frame minus ``origin``: sensor frame)."""
    out = []
    for x, y in ((6.0, 9.0), (14.0, -11.0), (-7.0, 12.0), (-12.0, -8.0)):
        zs = np.linspace(-HEIGHT, 2.0, 40)
        a = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
        for ang in a:
            px, py = x + 0.15 * np.cos(ang), y + 0.15 * np.sin(ang)
            out.append(np.column_stack([np.full(40, px), np.full(40, py), zs]))
    return np.vstack(out) - np.array([origin[0], origin[1], 0.0])


def test_fit_finds_a_tilted_ground_under_walls_and_rejects_a_steep_one():
    rng = np.random.default_rng(0)
    ground = _rings(rng, tilt_deg=3.0)
    wall = np.column_stack(
        [rng.uniform(-20, 20, 5000), np.full(5000, 6.0), rng.uniform(-1.8, 4.0, 5000)]
    )
    plane = fit_ground(np.vstack([ground, wall]), GroundPlaneConfig())
    assert plane is not None
    n, d = plane
    truth = np.array([-np.sin(np.radians(3.0)), 0.0, np.cos(np.radians(3.0))])
    assert np.degrees(np.arccos(n @ truth)) < 0.1
    assert abs(d - HEIGHT * truth[2]) < 0.01
    steep = _rings(rng, tilt_deg=30.0)
    assert fit_ground(steep, GroundPlaneConfig()) is None
    assert fit_ground(wall, GroundPlaneConfig(min_share=0.5)) is None


def test_flatten_keeps_the_normal_spread_and_opens_the_plane():
    n = np.array([0.0, 0.0, 1.0])
    pts = np.array([[5.0, 0.0, -1.8], [5.0, 0.0, -1.5]])  # on the ground, 0.3 m above it
    covs = np.stack([np.diag([1e-4, 4e-4, 9e-4])] * 2)
    before = covs.copy()
    on = flatten_ground(pts, covs, (n, HEIGHT), GroundPlaneConfig(in_plane_sigma=3.0))
    assert on.tolist() == [True, False]
    np.testing.assert_allclose(covs[0], np.diag([9.0, 9.0, 9e-4]))
    np.testing.assert_array_equal(covs[1], before[1])


def test_config_is_checked():
    with pytest.raises(ConfigError):
        GroundPlaneConfig(min_range=5.0, max_range=2.0)
    with pytest.raises(ConfigError):
        GroundPlaneConfig(in_plane_sigma=0.0)
    with pytest.raises(ConfigError):
        GroundPlaneConfig(min_beams=-1)


def test_the_rings_pull_a_moving_scan_to_rest_and_the_plane_does_not():
    """Two scans 0.9 m apart on flat ground with four poles: the ground's rings (the same
    circles around the sensor in both) hold eq. (1) GICP near rest; with the ground as a
    plane the poles place it within 2 cm."""
    rng = np.random.default_rng(1)
    step = np.array([0.9, 0.0])
    target = np.vstack([_rings(rng), _poles(np.zeros(2))])
    source = np.vstack([_rings(rng), _poles(step)])
    cfg = GicpConfig(max_iterations=50)

    def register(flat: bool) -> float:
        covs = estimate_covariances(source, cfg.k_covariance, cfg.regularisation)
        if flat:
            plane = fit_ground(source, GroundPlaneConfig())
            assert plane is not None
            flatten_ground(source, covs, plane, GroundPlaneConfig())
        res = gicp_align(source, target, np.eye(4), cfg, covs)
        return float(res.T_target_source[0, 3])

    assert register(flat=False) < 0.05
    assert abs(register(flat=True) - 0.9) < 0.02


def _pole_edges(origin: np.ndarray) -> np.ndarray:
    """Edge features of eight poles 6-15 m from the road: each pole's column of returns, 5 cm
    apart (world frame minus ``origin``: sensor frame, m)."""
    xy = ((6.0, 9.0), (14.0, -11.0), (-7.0, 12.0), (-12.0, -8.0))
    xy += ((9.0, 7.0), (-10.0, -10.0), (11.0, -6.0), (-6.0, 8.0))
    zs = np.linspace(-HEIGHT, 2.0, 77)
    cols = [np.column_stack([np.full(len(zs), x), np.full(len(zs), y), zs]) for x, y in xy]
    return np.vstack(cols) - np.array([origin[0], origin[1], 0.0])


def test_loam_plane_terms_on_the_plane_do_not_hold_a_moving_scan():
    """floam's feature ICP, two scans 0.9 m apart: the poles as edges, the ground rings as
    planes. Five map neighbours on one ring fit a "plane" across the ring, which holds the
    scan near rest; with the fitted ground's normal the poles place it."""
    rng = np.random.default_rng(2)
    step = np.array([0.9, 0.0])
    edges_t, edges_s = _pole_edges(np.zeros(2)), _pole_edges(step)
    planes_t, planes_s = _rings(rng), _rings(rng)
    cfg = FeatureIcpConfig(max_iterations=50)
    e_map, p_map = FeatureTarget(edges_t), FeatureTarget(planes_t)

    def register(ground: bool) -> float:
        g = None
        if ground:
            plane = fit_ground(planes_s, GroundPlaneConfig())
            assert plane is not None
            g = FixedNormals(on_ground(planes_s, plane, 0.1), plane[0])
        res = feature_icp_align(edges_s, planes_s, e_map, p_map, np.eye(4), cfg, g)
        return float(res.T_target_source[0, 3])

    assert register(ground=False) < 0.5
    assert abs(register(ground=True) - 0.9) < 0.02


def test_two_step_plane_terms_use_the_ground_normal_on_its_rows_only():
    """LeGO's point-to-plane terms: the rows on the scan's ground take its normal (rotated
    into the map at the current pose), the others keep their neighbours' fitted normal."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-12.0, 12.0, (20000, 2))  # the map: ground tilted 5 deg about y
    tilted = np.column_stack([xy, np.tan(np.radians(5.0)) * xy[:, 0] - HEIGHT])
    pts = tilted[np.abs(tilted[:, :2]).max(axis=1) < 6.0][:400] + [0.0, 0.0, 0.02]
    target = FeatureTarget(tilted)
    cfg = TwoStepConfig(plane_threshold=0.2)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T[:3, 3] = [0.1, 0.0, 0.0]
    rows = np.arange(len(pts)) % 2 == 0
    normal = np.array([0.0, 0.0, 1.0])
    free = plane_terms(T, pts, target, cfg)
    fixed = plane_terms(T, pts, target, cfg, fixed=FixedNormals(rows, normal))
    assert len(free.p) == len(fixed.p) > 300
    on = rows[np.flatnonzero(np.isin(pts[:, 0], fixed.p[:, 0]))]
    n_map = T[:3, :3] @ normal
    np.testing.assert_allclose(
        fixed.W[on], np.broadcast_to(np.outer(n_map, n_map), (on.sum(), 3, 3))
    )
    np.testing.assert_allclose(fixed.W[~on], free.W[~on])
    # the fitted normals are the map's tilted ground, 5 deg from the given one
    n_fit = np.sqrt(np.abs(np.diagonal(free.W[on], axis1=1, axis2=2)))
    assert np.degrees(np.arccos(np.median(n_fit[:, 2]))) == pytest.approx(5.0, abs=0.5)
