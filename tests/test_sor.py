"""Statistical outlier removal (classic and the paper's weighted variant) and voxel grid."""

import numpy as np
import open3d as o3d
import pytest

from slam.errors import ConfigError, InputError
from slam.preprocess.sor import SorConfig, apply_sor, classic_sor, range_bands, weighted_sor
from slam.preprocess.voxel import voxel_downsample

SURFACE, POLE, OUTLIER = 0, 1, 2


def lidar_scan(seed=0, noise=0.01, outlier_frac=0.005, pole=(15.0, 3.0, 0.1)):
    """16-beam, 1800-column spinning lidar in a walled yard (ground, 4 walls 5.5 m high) with a
    thin pole, 1 cm range noise and isolated outliers uniform in the volume. Returns xyz, label.
    """
    rng = np.random.default_rng(seed)
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    az = np.linspace(-np.pi, np.pi, 1800, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    x0, x1, y0, y1, zg, zt = -15.0, 25.0, -10.0, 12.0, -1.5, 4.0
    t = np.full(len(d), np.inf)
    label = np.zeros(len(d), dtype=int)
    with np.errstate(divide="ignore", invalid="ignore"):
        for c, ax in ((x0, 0), (x1, 0), (y0, 1), (y1, 1)):
            tt = c / d[:, ax]
            ok = (tt > 0) & (tt * d[:, 2] >= zg) & (tt * d[:, 2] <= zt) & (tt < t)
            t = np.where(ok, tt, t)
        tt = zg / d[:, 2]
        t = np.where((tt > 0) & (tt < t), tt, t)
        cx, cy, r = pole
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = -2 * (d[:, 0] * cx + d[:, 1] * cy)
        disc = b**2 - 4 * a * (cx**2 + cy**2 - r**2)
        tt = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        ok = (disc >= 0) & (tt > 0) & (tt * d[:, 2] >= zg) & (tt * d[:, 2] <= 3.0) & (tt < t)
    t = np.where(ok, tt, t)
    label[ok] = POLE
    hit = np.isfinite(t)
    pts = d[hit] * (t[hit] + rng.normal(0, noise, hit.sum()))[:, None]
    n_out = int(round(outlier_frac * len(pts)))
    out = rng.uniform([x0, y0, zg], [x1, y1, zt], (n_out, 3))
    return np.vstack([pts, out]), np.r_[label[hit], np.full(n_out, OUTLIER)]


@pytest.fixture(scope="module")
def scan():
    return lidar_scan(seed=0)


def test_classic_equals_open3d(scan):
    xyz, _ = scan
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    for alpha in (0.5, 1.0, 2.0):
        _, ind = pc.remove_statistical_outlier(nb_neighbors=11, std_ratio=alpha)
        ref = np.zeros(len(xyz), dtype=bool)
        ref[ind] = True
        assert np.array_equal(classic_sor(xyz, k=10, alpha=alpha), ref)


@pytest.mark.parametrize("seed", [0, 1])
def test_weighted_removes_outliers_keeps_surfaces(seed):
    xyz, label = lidar_scan(seed=seed)
    keep = weighted_sor(xyz, k=10, alpha=1.0)
    assert 1.0 - keep[label == OUTLIER].mean() >= 0.90  # measured 0.955 / 0.970
    assert keep[label == SURFACE].mean() >= 0.98  # measured 1.000
    assert keep[label == POLE].mean() >= 0.9


def test_weighted_keeps_thin_pole_that_classic_drops(scan):
    xyz, label = scan
    pole = label == POLE
    assert pole.sum() >= 30
    kept_w = weighted_sor(xyz, 10, 1.0)[pole].mean()
    kept_c = classic_sor(xyz, 10, 1.0)[pole].mean()
    assert kept_w >= 0.9 and kept_c <= 0.5  # measured 1.0 vs 0.0
    assert kept_w > kept_c


def test_density_term_only_relaxes_threshold(scan):
    xyz, _ = scan
    strict = weighted_sor(xyz, max_density_ratio=0.0)
    default = weighted_sor(xyz)
    lenient = weighted_sor(xyz, max_density_ratio=5.0)
    assert np.all(default[strict]) and np.all(lenient[default])
    assert strict.sum() < default.sum() < lenient.sum()


def test_weighted_isolated_point_removed_in_dense_cloud():
    rng = np.random.default_rng(3)
    plane = np.c_[rng.uniform(0, 2, (2000, 2)), rng.normal(0, 0.002, 2000)]
    xyz = np.vstack([plane, [[1.0, 1.0, 0.8]]])
    keep = weighted_sor(xyz)
    assert not keep[-1]
    assert keep[:-1].mean() > 0.95


def test_apply_sor_dispatch_and_errors(scan):
    xyz, _ = scan
    assert apply_sor(xyz, SorConfig(enabled=False)).all()
    classic = SorConfig(method="classic", mode="paper")
    assert np.array_equal(apply_sor(xyz, classic), classic_sor(xyz))
    assert np.array_equal(apply_sor(xyz, SorConfig(mode="paper")), weighted_sor(xyz))
    with pytest.raises(ConfigError, match="classic"):
        SorConfig(method="median")
    with pytest.raises(InputError):
        weighted_sor(np.array([[0.0, 0.0, np.nan]] * 5))
    with pytest.raises(InputError):
        classic_sor(np.zeros((5, 2)))


def test_voxel_downsample_one_point_per_voxel_nearest_to_centroid():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (5000, 3))
    idx = voxel_downsample(xyz, 0.25)
    cells = np.floor(xyz / 0.25).astype(int)
    n_cells = len(np.unique(cells, axis=0))
    assert len(idx) == n_cells == len(np.unique(cells[idx], axis=0))
    c0 = cells[idx[0]]
    members = np.flatnonzero((cells == c0).all(axis=1))
    centroid = xyz[members].mean(axis=0)
    best = members[np.argmin(np.linalg.norm(xyz[members] - centroid, axis=1))]
    assert idx[0] == best
    assert np.array_equal(voxel_downsample(xyz, 0.0), np.arange(5000))


def test_knn_distances_equal_scipy(scan):
    from scipy.spatial import cKDTree

    from slam.preprocess.sor import knn_distances

    xyz, _ = scan
    ref, _ = cKDTree(xyz).query(xyz, k=11)
    assert np.allclose(knn_distances(xyz, 10), ref[:, 1:], atol=1e-12)
    assert knn_distances(xyz[:4], 10).shape == (4, 3)


def test_voxel_downsample_ties_go_to_lowest_index():
    xyz = np.array([[0.75, 0.75, 0.75], [0.25, 0.25, 0.25], [0.75, 0.75, 0.75], [0.25] * 3])
    assert np.array_equal(voxel_downsample(xyz, 1.0), [0])  # all 0.433 m from the centroid
    assert np.array_equal(voxel_downsample(np.zeros((0, 3)), 1.0), np.arange(0))


def test_weighted_sor_eq7_hand_computed():
    """Eqs. (4)-(9) on five points of a line, x = 0, 1, 2, 3, 10 m, k = 2, computed by hand.

    Neighbour distances (ascending): p0 (1, 2), p1 (1, 1), p2 (1, 1), p3 (1, 2), p4 (7, 8).
    (5) d_avg = (3 + 2 + 2 + 3 + 15) / 10 = 2.5 m.
    (4)+(6) p0, p3: w = e^-0.4, e^-0.8 -> d = (e^-0.4 + 2 e^-0.8) / (e^-0.4 + e^-0.8) = 1.40131;
    p1, p2: d = 1; p4: d = (7 e^-2.8 + 8 e^-3.2) / (e^-2.8 + e^-3.2) = 7.40131.
    (8) mu = (2 * 1.40131 + 2 + 7.40131) / 5 = 2.44079.
    (9) sigma = sqrt(sum (d - mu)^2 / 4) + delta = sqrt(30.9195 / 4) = 2.78027 (delta = 0).
    rho = k / (4/3 pi r_k^3): r_k = 2, 1, 1, 2, 8 -> 0.059683, 0.477465, 0.477465, 0.059683,
    0.000933; rho_avg = 0.215046; rho_avg / rho = 3.6031, 0.4504, 0.4504, 3.6031, 230.6, clamped
    to 1 -> (7) Theta = mu + alpha sigma (1 + ratio) = 8.00132, 6.47326, 6.47326, 8.00132, 8.00132
    (alpha = 1). The outlier p4 (7.40 m) stays: with five points it inflates sigma itself.
    alpha = 0.5 -> Theta_4 = 2.44079 + 0.5 * 2.78027 * 2 = 5.22106 < 7.40: removed, p0-p3 kept.
    """
    xyz = np.c_[[0.0, 1.0, 2.0, 3.0, 10.0], np.zeros(5), np.zeros(5)]
    dist = np.array([[1.0, 2.0], [1.0, 1.0], [1.0, 1.0], [1.0, 2.0], [7.0, 8.0]])
    from slam.preprocess.sor import knn_distances, weighted_sor_terms

    assert np.array_equal(knn_distances(xyz, 2), dist)
    t = weighted_sor_terms(dist, alpha=1.0, delta=0.0)
    np.testing.assert_allclose(t.d, [1.40131, 1.0, 1.0, 1.40131, 7.40131], atol=1e-5)
    assert t.mu == pytest.approx(2.44079, abs=1e-5)
    assert t.sigma == pytest.approx(2.78027, abs=1e-5)
    np.testing.assert_allclose(t.rho, [0.059683, 0.477465, 0.477465, 0.059683, 0.000933], atol=1e-6)
    np.testing.assert_allclose(t.theta, [8.00132, 6.47326, 6.47326, 8.00132, 8.00132], atol=1e-5)
    assert weighted_sor(xyz, k=2, alpha=1.0, delta=0.0).all()
    keep = weighted_sor(xyz, k=2, alpha=0.5, delta=0.0)
    assert keep.tolist() == [True, True, True, True, False]
    # the density term: unclamped (ratio 3.6 at p0) the sparse ends earn a wider threshold
    wide = weighted_sor_terms(dist, alpha=1.0, delta=0.0, max_density_ratio=10.0)
    assert wide.theta[0] == pytest.approx(2.44079 + 2.78027 * (1 + 3.60312), abs=1e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_weighted_terms_kernel_equals_numpy_reference(seed):
    """The fused numba pass (used by weighted_sor) against the numpy eqs. (4)-(9)."""
    from slam.preprocess.sor import knn_distances, weighted_sor_terms, weighted_sor_terms_fast

    xyz, _ = lidar_scan(seed=seed)
    dist = knn_distances(xyz, 10)
    for alpha, mdr in ((1.0, 1.0), (0.5, 0.0), (2.0, 5.0)):
        ref = weighted_sor_terms(dist, alpha, 1e-5, mdr)
        fast = weighted_sor_terms_fast(dist, alpha, 1e-5, mdr)
        for f in ("d", "rho", "theta"):
            np.testing.assert_allclose(getattr(fast, f), getattr(ref, f), rtol=1e-12, atol=0)
        assert fast.mu == pytest.approx(ref.mu, rel=1e-12)
        assert fast.sigma == pytest.approx(ref.sigma, rel=1e-12)
        assert np.array_equal(fast.d <= fast.theta, ref.d <= ref.theta)


def test_vectorised_exp_within_one_ulp_of_numpy():
    """exp_neg (the SIMD exp of eq. (4)) against np.exp over the whole range of weights."""
    from slam.preprocess.sor_kernels import exp_neg

    x = np.r_[np.linspace(0.0, 50.0, 200_001), np.geomspace(50.0, 800.0, 1001), 1e-300, 0.0]
    w = np.empty(len(x))
    exp_neg(x, 1.0, w, np.empty(len(x), dtype=np.int64))
    ref = np.exp(-x)
    normal = ref >= np.finfo(float).tiny
    assert np.max(np.abs(w[normal] - ref[normal]) / np.spacing(ref[normal])) <= 1.0
    assert np.all(w[~normal] <= np.finfo(float).tiny) and w[-1] == 1.0
    w3 = np.empty(3)
    exp_neg(np.array([1.0, 2.0, 4.0]), 0.5, w3, np.empty(3, dtype=np.int64))
    np.testing.assert_allclose(w3, np.exp([-0.5, -1.0, -2.0]), rtol=2e-16)


def test_simd_and_libm_kernels_same_keep_mask(scan):
    """The vectorised-exp kernel (used) and the libm-exp kernel (the earlier one) agree.
    Their sums differ in order (chunked partial sums vs one running sum over N k values):
    3e-14 relative in d measured."""
    from slam.preprocess.sor import knn_distances
    from slam.preprocess.sor_kernels import weighted_sor_kernel, weighted_sor_kernel_simd

    xyz, _ = scan
    dist = np.ascontiguousarray(knn_distances(xyz, 10))
    a = weighted_sor_kernel(dist, 1.0, 1e-5, 1.0)
    b = weighted_sor_kernel_simd(dist, 1.0, 1e-5, 1.0)
    np.testing.assert_allclose(b[0], a[0], rtol=1e-13, atol=0)
    assert abs(b[1] - a[1]) <= 1e-13 * a[1] and abs(b[2] - a[2]) <= 1e-13 * a[2]
    assert np.array_equal(a[0] <= a[4], b[0] <= b[4])


@pytest.fixture(scope="module")
def street64():
    """Frame 20 of the simulated straight street seen by a 64-beam HDL-64E (cached
    simulation, ~130k points): xyz, ring and range (m)."""
    import itertools

    from slam.io.source import open_source
    from slam.sim import ensure_sequence
    from slam.types import Scan

    sim = ensure_sequence("street", frames=21, sensor="hdl64")
    scans = (s for s in open_source(sim.bag) if isinstance(s, Scan))
    sc = next(itertools.islice(scans, 20, None))
    return sc.xyz, sc.ring, np.linalg.norm(sc.xyz, axis=1)


def test_paper_mode_is_the_scan_wide_filter_of_eqs_4_to_9(scan):
    """mode "paper" is the filter as printed: one statistic for the scan, the same mask
    as the numpy reference of eqs. (4)-(9) (the default is "banded")."""
    from slam.preprocess.sor import knn_distances, weighted_sor_terms

    xyz, _ = scan
    assert SorConfig().mode == "banded"
    ref = weighted_sor_terms(knn_distances(xyz, 10))
    keep = apply_sor(xyz, SorConfig(mode="paper"))
    np.testing.assert_array_equal(keep, ref.d <= ref.theta)
    np.testing.assert_array_equal(keep, weighted_sor(xyz))


def test_banded_equals_numpy_reference_per_band(street64):
    """mode "banded": eqs. (4)-(9) within each range band, equal to the numpy reference run
    on each band's rows."""
    from slam.preprocess.sor import banded_sor, knn_distances, range_bands, weighted_sor_terms

    xyz = street64[0]
    cfg = SorConfig(mode="banded")
    dist = knn_distances(xyz, cfg.k)
    label, n_bands = range_bands(xyz, cfg.band_edges, cfg.band_min_points)
    assert n_bands == 3  # 0-15, 15-30, 30 and beyond (the ~900 returns past 50 m join it)
    ref = np.ones(len(xyz), dtype=bool)
    for b in range(n_bands):
        t = weighted_sor_terms(dist[label == b])
        ref[label == b] = t.d <= t.theta
    np.testing.assert_array_equal(banded_sor(xyz, dist, cfg), ref)
    np.testing.assert_array_equal(apply_sor(xyz, cfg), ref)


def test_range_bands_merge_small_bands_inwards():
    xyz = np.zeros((1000, 3))
    xyz[:, 0] = np.r_[np.full(600, 5.0), np.full(390, 20.0), np.full(10, 60.0)]
    label, n = range_bands(xyz, (15.0, 30.0, 50.0), 100)
    assert n == 2  # 30-50 empty, the 10 far points join 15-30
    assert np.array_equal(label, np.r_[np.zeros(600), np.ones(400)].astype(int))
    label, n = range_bands(xyz[:50], (15.0,), 100)
    assert n == 1 and not label.any()


def test_banded_keeps_the_far_field_of_a_dense_scan(street64):
    """The scan-wide statistic of a dense sensor is set by its near field and strips the
    sparse far field (the poles and facades that hold a street's along axis); per range
    band the far field is judged against far points."""
    xyz, ring, r = street64
    paper = apply_sor(xyz, SorConfig(mode="paper"), ring=ring)
    banded = apply_sor(xyz, SorConfig(), ring=ring)
    far = (r >= 30) & (r < 50)
    assert 1 - paper[far].mean() > 0.25  # measured 0.354
    assert 1 - paper[r >= 50].mean() > 0.6  # measured 0.828
    assert 1 - banded[far].mean() < 0.05  # measured 0.006
    assert 1 - banded[r >= 50].mean() < 0.3  # measured 0.192 (its ~900 returns join 30-50 m)
    assert banded[r < 15].mean() > 0.98  # measured 0.992


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_banded_removes_injected_outliers_as_the_paper_filter(seed):
    """Per range band, the injected outliers of the 16-beam yard are removed as by the
    scan-wide filter (mean over seeds 0-3: 0.959 both)."""
    xyz, label = lidar_scan(seed=seed)
    paper = apply_sor(xyz, SorConfig(mode="paper"))
    banded = apply_sor(xyz, SorConfig())
    out = label == OUTLIER
    assert 1.0 - banded[out].mean() >= 1.0 - paper[out].mean() - 0.02
    assert 1.0 - banded[out].mean() >= 0.93
    assert banded[label == SURFACE].mean() >= 0.98 and banded[label == POLE].mean() >= 0.9


def test_sor_mode_and_bands_are_checked():
    for bad in (
        dict(mode="exact"),
        dict(band_edges=(30.0, 15.0)),
        dict(band_edges=(0.0, 15.0)),
        dict(band_min_points=2),
    ):
        with pytest.raises(ConfigError):
            SorConfig(**bad)
    assert SorConfig(band_edges=[15, 30]).band_edges == (15.0, 30.0)  # a YAML list


def _grid_and_a_stray(spacing=0.005, stray=(5.0, 0.0, -12.0)):
    """A 60 x 60 grid of ``spacing`` (m) on the plane x = 5 m and one stray point 12 m from
    it in the same range band: exp(-12 / ~0.008) underflows, every weight of its row is 0."""
    g = np.arange(60) * spacing
    Y, Z = np.meshgrid(g, g)
    grid = np.c_[np.full(Y.size, 5.0), Y.ravel(), Z.ravel()]
    return np.vstack([grid, stray])


def test_a_row_whose_weights_all_underflow_is_an_outlier_not_a_division_by_zero():
    """The stray point's weighted mean distance (6) is its nearest distance (the weights
    relative to the nearest neighbour's), the same in the numba kernels and the numpy
    reference; the grid is kept, the stray removed (was ZeroDivisionError in numba)."""
    from slam.preprocess.sor import knn_distances, weighted_sor_terms, weighted_sor_terms_fast
    from slam.preprocess.sor_kernels import weighted_sor_kernel

    xyz = _grid_and_a_stray()
    dist = knn_distances(xyz, 10)
    assert np.exp(-dist[-1] / dist.mean()).sum() == 0.0  # the case: every weight underflows
    ref = weighted_sor_terms(dist)
    fast = weighted_sor_terms_fast(dist)
    plain = weighted_sor_kernel(np.ascontiguousarray(dist), 1.0, 1e-5, 1.0)
    nearest = dist[-1, 0]
    assert nearest == pytest.approx(12.0)
    for d in (ref.d, fast.d, plain[0]):
        assert np.isfinite(d).all() and nearest <= d[-1] < dist[-1, -1]
        np.testing.assert_allclose(d, ref.d, rtol=1e-12)
    for cfg in (SorConfig(), SorConfig(mode="paper")):
        keep = apply_sor(xyz, cfg)
        assert not keep[-1] and keep[:-1].all()


@pytest.mark.parametrize(
    "dist",
    [
        np.zeros((0, 10)),  # no points
        np.zeros((5, 0)),  # no neighbours
        np.array([[1.0, 2.0, 3.0]]),  # one point
        np.zeros((50, 10)),  # identical points
        np.array([[1.0, 2.0], [1.0, 1e120], [1.0, 3.0]]),  # radius^3 overflows: density 0
    ],
    ids=["no-points", "k0", "one-point", "identical", "density0"],
)
def test_sor_terms_of_degenerate_neighbourhoods_keep_the_points(dist):
    """Degenerate distance tables give finite terms that keep every point, the same from
    the numba kernels and the numpy reference (all but the identical points raised: a
    ZeroDivisionError in numba, an IndexError without neighbours)."""
    from slam.preprocess.sor import weighted_sor_terms, weighted_sor_terms_fast
    from slam.preprocess.sor_kernels import weighted_sor_kernel

    ref = weighted_sor_terms(dist)
    n = len(dist)
    for d, mu, sigma, rho, theta in (
        (ref.d, ref.mu, ref.sigma, ref.rho, ref.theta),
        tuple(weighted_sor_kernel(np.ascontiguousarray(dist), 1.0, 1e-5, 1.0)),
        tuple(vars(weighted_sor_terms_fast(dist)).values()),
    ):
        assert d.shape == rho.shape == theta.shape == (n,)
        assert np.isfinite([mu, sigma]).all() and sigma >= 1e-5
        assert np.isfinite(d).all() and np.isfinite(theta).all()
        assert (d <= theta).all()
        np.testing.assert_allclose(d, ref.d, rtol=1e-12)
        np.testing.assert_allclose(theta, ref.theta, rtol=1e-12)


@pytest.mark.parametrize("method", ["weighted", "classic"])
@pytest.mark.parametrize(
    "xyz",
    [
        np.zeros((0, 3)),
        np.array([[1.0, 2.0, 3.0]]),
        np.tile([[4.0, 1.0, 0.5]], (40, 1)),  # one point 40 times
        np.vstack([_grid_and_a_stray(), [[1e150, 0.0, 0.0]]]),  # distances that overflow
    ],
    ids=["empty", "one", "identical", "huge"],
)
def test_apply_sor_on_degenerate_clouds_returns_a_mask(xyz, method):
    """Any finite cloud gives a keep-mask: empty, a single point and one point repeated
    are kept whole; a point 1e150 m away is removed and the grid kept."""
    for mode in ("banded", "paper"):
        keep = apply_sor(xyz, SorConfig(method=method, mode=mode))
        assert keep.shape == (len(xyz),) and keep.dtype == bool
        if len(xyz) < 100:
            assert keep.all()
        else:
            assert not keep[-1] and keep[:3600].all()
