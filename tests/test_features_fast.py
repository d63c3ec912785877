"""The compiled LOAM feature kernels (slam/features/loam_kernels.py) and the kappa kernel
(slam/features/curvature.py) against the numpy references they replace: identical edge/plane
indices, curvature and kappa on simulated 16- and 64-beam scans, real KITTI-raw HDL-64E scans
and edge cases."""

from __future__ import annotations

import tarfile
from dataclasses import replace

import numpy as np
import pytest
from shared_data import shared_path

from slam.errors import ConfigError
from slam.features import loam_kernels as kern
from slam.features.curvature import kappa_from_neighbours
from slam.features.loam import FeatureConfig, _greedy_nms, extract_features
from slam.io.folders import cloud_files, read_cloud
from slam.io.source import open_source
from slam.preprocess.knn import knn
from slam.sensor.beam_table import beams_from_rings, estimate_beams
from slam.types import Scan

KAPPA = FeatureConfig(use_covariance_curvature=True)


def assert_same(xyz, ring, cfg=None, azimuth_order=None, min_edges=0):
    """Both back ends on one input: identical features (and kappa); returns the fast one."""
    ref = extract_features(xyz, ring, cfg, azimuth_order=azimuth_order, backend="numpy")
    fast = extract_features(xyz, ring, cfg, azimuth_order=azimuth_order)
    assert np.array_equal(fast.edge_idx, ref.edge_idx)
    assert np.array_equal(fast.plane_idx, ref.plane_idx)
    assert np.array_equal(fast.curvature, ref.curvature, equal_nan=True)
    assert (fast.kappa is None) == (ref.kappa is None)
    if ref.kappa is not None:
        assert np.array_equal(fast.kappa, ref.kappa, equal_nan=True)
    assert fast.edge_idx.dtype == ref.edge_idx.dtype == np.int64
    assert len(fast.edge_idx) >= min_edges
    return fast


def first_scans(sim, n: int) -> list[Scan]:
    out = []
    for s in open_source(sim.bag):
        if isinstance(s, Scan):
            out.append(s)
            if len(out) == n:
                break
    return out


def test_simulated_16_beam_corridor(corridor_short):
    scans = first_scans(corridor_short, 2)
    for s in scans:
        assert s.ring is not None and len(s) > 20000
        f = assert_same(s.xyz, s.ring, min_edges=150)
        assert len(f.plane_idx) > 10000
        assert_same(s.xyz, s.ring, KAPPA, min_edges=150)
        # rings from the beam model (as the pipeline does without a ring field)
        model = beams_from_rings([s.xyz], [s.ring])
        assert_same(s.xyz, model.ring_of(s.xyz), min_edges=150)


def test_simulated_64_beam_urban(urban_hdl64_short):
    (s,) = first_scans(urban_hdl64_short, 1)
    assert s.ring is None and len(s) > 100000
    ring = estimate_beams([s.xyz]).ring_of(s.xyz)
    assert_same(s.xyz, ring, min_edges=2000)
    assert_same(s.xyz, ring, KAPPA, min_edges=1000)


@pytest.fixture(scope="module")
def kitti_scans(tmp_path_factory) -> list[Scan]:
    tmp = tmp_path_factory.mktemp("kitti_raw")
    with tarfile.open(shared_path("kitti_raw_drive", "data_1.tar.xz"), "r:xz") as tar:
        tar.extractall(tmp, filter="data")
    files = cloud_files(tmp / "data_1")
    return [read_cloud(f, index=i, stamp=0.1 * i) for i, f in enumerate(files[:2])]


def test_real_kitti_raw_hdl64(kitti_scans):
    model = estimate_beams([s.xyz for s in kitti_scans])
    assert model.n_beams == 64
    for s in kitti_scans:
        ring = model.ring_of(s.xyz)
        assert_same(s.xyz, ring, min_edges=2000)
    s = kitti_scans[0]
    ring = model.ring_of(s.xyz)
    assert_same(s.xyz, ring, KAPPA, min_edges=1000)
    # the firing time as the sort key, and the cloud in a shuffled order
    assert_same(s.xyz, ring, azimuth_order=model.time_of(s.xyz, 0.1), min_edges=2000)
    perm = np.random.default_rng(0).permutation(len(s))
    assert_same(s.xyz[perm], ring[perm], min_edges=2000)


def ring_scan(n_rings=4, n_cols=1800, seed=0):
    """A noisy box room seen by a few beams, column-major, with a pillar for occlusions."""
    rng = np.random.default_rng(seed)
    az = np.linspace(-np.pi, np.pi, n_cols, endpoint=False)
    el = np.radians(np.linspace(-10, 10, n_rings))
    A, E = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.minimum(np.abs(6.0 / d[:, 0]), np.abs(4.0 / d[:, 1]))
    pillar = (np.abs(A.ravel() - 0.3) < 0.05) & (t > 2.0)
    t[pillar] = 2.0
    xyz = d * (t + rng.normal(0, 0.01, len(t)))[:, None]
    ring = np.tile(np.arange(n_rings), n_cols).astype(np.int16)
    return xyz, ring


@pytest.mark.parametrize(
    "cfg",
    [
        FeatureConfig(),
        FeatureConfig(window=1, n_sectors=1, max_less_sharp=1),
        FeatureConfig(window=3, max_less_sharp=2, edge_threshold=0.0, plane_threshold=1.0),
        FeatureConfig(reject_occluded=False, reject_parallel=False, neighbor_gap=1e9),
        FeatureConfig(edge_threshold=1e9, plane_threshold=-1.0, n_sectors=50),
        FeatureConfig(min_range=4.5, max_range=6.5),
        replace(KAPPA, kappa_plane_max=1.3, kappa_edge_max=1.2),
    ],
    ids=["default", "w1", "w3-few", "no-rejection", "nothing", "range-crop", "kappa"],
)
def test_configurations(cfg):
    xyz, ring = ring_scan()
    f = assert_same(xyz, ring, cfg)
    if cfg == FeatureConfig():  # 4 room corners and 2 pillar sides on each of the 4 rings
        assert len(f.edge_idx) >= 24


def test_edge_cases():
    xyz, ring = ring_scan(n_rings=6)
    # empty input, nothing usable, no ring at all
    assert_same(np.empty((0, 3)), np.empty(0, dtype=np.int16))
    assert_same(xyz, np.full(len(xyz), -1))
    assert_same(xyz, np.full(len(xyz), -5, dtype=np.int8))
    assert_same(xyz, None)
    # empty rings (ids 0, 3, 7 only), negative rings skipped, wide ring dtypes
    sparse = np.array([0, 3, -1, 7, 3, 0])[ring]
    assert_same(xyz, sparse.astype(np.int64), min_edges=1)
    assert_same(xyz, sparse.astype(np.int32) + 40000)
    # rings shorter than the window (1, 3, 10, 11 points) beside a long one
    short = np.full(len(xyz), 5)
    for r, m in enumerate((1, 3, 10, 11)):
        short[np.flatnonzero(ring == 0)[r * 20 : r * 20 + m]] = r
    assert_same(xyz, short)
    # all-equal ranges and azimuth ties: a circle per ring, every point duplicated
    az = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = np.c_[5 * np.cos(az), 5 * np.sin(az), np.zeros(200)]
    dup = np.repeat(circle, 2, axis=0)
    assert_same(dup, np.zeros(len(dup), dtype=np.int16))
    same = np.tile([[3.0, 1.0, 0.5]], (300, 1))
    f = assert_same(same, np.repeat(np.arange(3), 100))
    assert len(f.plane_idx) == 3 * (100 - 10)  # c = 0 everywhere inside the rings
    # a key with NaN (reference decides), and a constant key (order = index)
    key = np.arctan2(xyz[:, 1], xyz[:, 0])
    key[7] = np.nan
    assert_same(xyz, ring, azimuth_order=key)
    assert_same(xyz, ring, azimuth_order=np.zeros(len(xyz)))
    # non-integer rings go to the reference
    assert_same(xyz, ring.astype(np.float64))
    with pytest.raises(ConfigError):
        extract_features(xyz, ring, backend="cuda")


@pytest.mark.parametrize("seed", range(3))
def test_stable_argsort_equals_numpy(seed):
    rng = np.random.default_rng(seed)
    x = np.r_[
        rng.random(300),
        np.linspace(1, 0, 200),  # strictly decreasing run
        np.repeat(rng.random(20), 5),  # ties
        np.linspace(0, 1, 100),
        np.full(50, 0.5),
        -(np.linspace(0, 1, 30) ** 2),
    ]
    for key in (x, x[::-1], rng.permutation(x), x[:1], x[:0], np.round(x * 10)):
        key = np.ascontiguousarray(key)
        assert np.array_equal(kern.stable_argsort(key), np.argsort(key, kind="stable"))


@pytest.mark.parametrize("seed", range(4))
def test_greedy_nms_kernel_equals_parallel_reference(seed):
    rng = np.random.default_rng(seed)
    n = 2000
    key = rng.random(n)
    key[100:300] = np.linspace(1, 0, 200)  # a long cluster
    key[500:520] = 0.5  # equal keys: ties by position
    cand = rng.random(n) < (0.9 if seed % 2 else 0.3)
    run = np.cumsum(rng.random(n) < 0.02)
    for w in (1, 5):
        fast = kern.greedy_nms(key, cand, run.astype(np.int32), w)  # int32 as from loam_scores
        assert np.array_equal(fast, _greedy_nms(key, cand, run, w))


def test_kappa_kernel_equals_numpy_reference(kitti_scans):
    xyz = kitti_scans[0].xyz
    q = np.random.default_rng(0).choice(len(xyz), 3000, replace=False)
    idx, _ = knn(xyz, xyz[q], 10)
    fast = kappa_from_neighbours(xyz, q, idx)
    ref = kappa_from_neighbours(xyz, q, idx, backend="numpy")
    assert np.abs(fast - ref).max() < 1e-12
    assert 1.0 <= fast.min() and fast.max() <= np.sqrt(3) + 1e-12
    assert np.median(fast) > 1.1  # real neighbourhoods are not all lines
    # degenerate neighbourhoods (all points equal: 1 by definition) and k = 1
    same = np.zeros((5, 3))
    nb = np.zeros((5, 4), dtype=np.int64)
    assert np.array_equal(kappa_from_neighbours(same, np.arange(5), nb), np.ones(5))
    one = idx[:, :1]
    assert np.array_equal(
        kappa_from_neighbours(xyz, q, one), kappa_from_neighbours(xyz, q, one, backend="numpy")
    )
    with pytest.raises(ConfigError):
        kappa_from_neighbours(xyz, q, idx, backend="cuda")


def test_random_clouds_and_configurations():
    """Random small clouds (duplicated points, coarse azimuths: many ties), random rings and
    settings: the kernels decide exactly as the reference, every time."""
    rng = np.random.default_rng(7)
    n_edges = 0
    for _ in range(60):
        n = int(rng.integers(0, 600))
        xyz = np.round(rng.normal(0, 6, (n, 3)), int(rng.integers(0, 3)))
        if n and rng.random() < 0.3:
            xyz[rng.integers(0, n, n // 3)] = xyz[0]
        ring = rng.integers(-1, int(rng.integers(1, 12)), n)
        cfg = FeatureConfig(
            window=int(rng.integers(1, 7)),
            n_sectors=int(rng.integers(1, 8)),
            edge_threshold=float(rng.choice([0.0, 0.1, 5.0])),
            plane_threshold=float(rng.choice([0.1, 1.0, 50.0])),
            max_less_sharp=int(rng.integers(1, 30)),
            min_range=float(rng.choice([0.0, 0.5, 3.0])),
            neighbor_gap=float(rng.choice([0.05, 1.0, 1e9])),
            reject_occluded=bool(rng.random() < 0.7),
            reject_parallel=bool(rng.random() < 0.7),
            occlusion_gap=float(rng.choice([0.1, 1.0])),
            occlusion_ratio=float(rng.choice([0.1, 0.5])),
            parallel_ratio=float(rng.choice([0.0002, 0.05])),
        )
        key = None if rng.random() < 0.5 else np.round(rng.random(n), 2)
        n_edges += len(assert_same(xyz, ring, cfg, azimuth_order=key).edge_idx)
    assert n_edges > 200  # the comparisons are not between empty selections


def test_ring_order_equals_lexsort():
    """Used points by (ring, key, index) for the ring shapes the shortcuts take (sorted,
    strictly decreasing, a turn starting mid-ring, overlapping itself with ties, three runs,
    random), rings interleaved as in a column-major cloud."""
    rng = np.random.default_rng(3)
    t = np.linspace(-np.pi, np.pi, 500, endpoint=False)
    over = np.r_[t[200:], t[:260]]  # 560 points: the turn overlaps its start (60 ties)
    shapes = [t, t[::-1], np.r_[t[300:], t[:300]], over, np.r_[t[:100], t[:200], t[50:]]]
    shapes += [rng.random(500), np.round(rng.random(500), 1), np.r_[t[:250], t[250:][::-1]]]
    n = max(len(s) for s in shapes)
    key = np.full((n, len(shapes)), np.nan)
    for r, s in enumerate(shapes):
        key[: len(s), r] = s
    ring = np.tile(np.arange(len(shapes)), n)
    key = key.ravel()
    xyz = rng.normal(0, 10, (len(key), 3))
    keep = ~np.isnan(key)
    xyz, ring, key = xyz[keep], ring[keep], key[keep]
    order, start = kern.ring_order(xyz, ring, key, 0.0, np.inf, len(shapes))
    assert np.array_equal(order, np.lexsort((key, ring)))
    assert np.array_equal(np.diff(start), [len(s) for s in shapes])
