"""LOAM edge/plane features and the covariance curvature correction."""

import numpy as np
import pytest

from slam.errors import InputError
from slam.features.curvature import covariance_curvature
from slam.features.loam import (
    FeatureConfig,
    _greedy_nms,
    extract_features,
    ring_from_elevation,
)

ROOM = (-12.0, 14.0, -9.0, 11.0)  # x0, x1, y0, y1 of the walls
BOX = (5.0, 7.0, 2.0, 4.0)  # x0, x1, y0, y1 of a box inside
CORNERS = np.array(
    [[ROOM[i], ROOM[j]] for i in (0, 1) for j in (2, 3)]
    + [[BOX[i], BOX[j]] for i in (0, 1) for j in (2, 3)]
)
FACES = [(0, ROOM[0]), (0, ROOM[1]), (1, ROOM[2]), (1, ROOM[3])] + [
    (0, BOX[0]),
    (0, BOX[1]),
    (1, BOX[2]),
    (1, BOX[3]),
]


def box_room_scan(seed=0, noise=0.005, elev_deg=None):
    """1800-column scan of a room with a box (both tall), ring and face id per point; beams at
    elev_deg (deg, default 16 beams over +-15 deg), stored beam by beam."""
    rng = np.random.default_rng(seed)
    elev_deg = np.linspace(-15.0, 15.0, 16) if elev_deg is None else np.asarray(elev_deg)
    el = np.radians(elev_deg)
    az = np.linspace(-np.pi, np.pi, 1800, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(len(el)), 1800).astype(np.int16)
    t = np.full(len(d), np.inf)
    face = np.full(len(d), -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for fid, (ax, c) in enumerate(FACES):
            tt = c / d[:, ax]
            ok = (tt > 0) & (tt < t)
            if fid >= 4:
                lo, hi = (BOX[2], BOX[3]) if ax == 0 else (BOX[0], BOX[1])
                other = tt * d[:, 1 - ax]
                ok &= (other >= lo) & (other <= hi)
            t = np.where(ok, tt, t)
            face[ok] = fid
    xyz = d * (t + rng.normal(0, noise, len(t)))[:, None]
    return xyz, ring, face


@pytest.fixture(scope="module")
def room():
    return box_room_scan()


def corner_distance(xy):
    return np.min(np.linalg.norm(xy[:, None, :2] - CORNERS[None], axis=2), axis=1)


def face_distance(xyz, face):
    ax = np.array([FACES[f][0] for f in face])
    c = np.array([FACES[f][1] for f in face])
    return np.abs(xyz[np.arange(len(xyz)), ax] - c)


def test_ring_from_elevation_recovers_beams(room):
    xyz, ring, _ = room
    assert np.array_equal(ring_from_elevation(xyz, 16, (-15.0, 15.0)), ring)
    assert np.array_equal(ring_from_elevation(xyz), ring)  # inferred from the scan
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(xyz))  # no layout: elevation histogram
    assert np.array_equal(ring_from_elevation(xyz[perm]), ring[perm])


HDL64 = np.r_[np.linspace(-24.33, -8.83, 32), np.linspace(-8.33, 2.0, 32)]


@pytest.mark.parametrize(
    "elev",
    [np.linspace(-30.67, 10.67, 32), HDL64, np.linspace(-22.5, 22.5, 128)],
    ids=["32", "64", "128"],
)
def test_features_for_32_to_128_beams_without_ring_field(elev):
    """Rings inferred from the data; every visible corner line found on nearly every beam
    that sees it, planes on the faces; no 16-beam assumption left."""
    xyz, ring, face = box_room_scan(elev_deg=elev)
    f = extract_features(xyz, None)
    # corners 5-20 m away at 0.2 deg azimuth steps: within three point spacings (mixed-up
    # rings would scatter edges over the walls)
    d = corner_distance(xyz[f.edge_idx])
    assert np.quantile(d, 0.98) < 0.06 and d.max() < 0.15
    assert face_distance(xyz[f.plane_idx], face[f.plane_idx]).max() < 0.03
    # the box corner (5, 2) at 5.4 m is seen by every beam (the box is tall, no ceiling)
    near = np.linalg.norm(xyz[f.edge_idx, :2] - [5.0, 2.0], axis=1) < 0.05
    assert len(np.unique(ring[f.edge_idx[near]])) >= 0.85 * len(elev)
    assert len(f.plane_idx) > 0.6 * len(xyz)


def test_top_picks_removed(room):
    xyz, ring, _ = room
    with pytest.raises(InputError):
        extract_features(xyz, ring, top_picks=True)


def test_edges_on_corner_lines_planes_on_faces(room):
    xyz, ring, face = room
    f = extract_features(xyz, ring)
    assert len(f.edge_idx) >= 80
    assert corner_distance(xyz[f.edge_idx]).max() < 0.05
    # every visible vertical corner line is found on (nearly) every ring; (14, 11) is hidden
    # behind the box and (7, 4) is the box's far corner
    counts = [np.sum(np.linalg.norm(xyz[f.edge_idx, :2] - c, axis=1) < 0.05) for c in CORNERS]
    visible = [i for i, c in enumerate(CORNERS.tolist()) if c not in ([14.0, 11.0], [7.0, 4.0])]
    assert min(counts[i] for i in visible) >= 14
    assert len(f.plane_idx) > 20000
    assert face_distance(xyz[f.plane_idx], face[f.plane_idx]).max() < 0.03
    assert not np.intersect1d(f.edge_idx, f.plane_idx).size
    assert f.curvature.shape == (len(xyz),) and np.isnan(f.curvature).sum() == 16 * 10


def test_occlusion_rejection_prevents_background_edges(room):
    xyz, ring, _ = room
    with_rej = extract_features(xyz, ring)
    without = extract_features(xyz, ring, FeatureConfig(reject_occluded=False))
    # without LOAM's rejection, wall points just behind the box silhouettes become "edges"
    assert corner_distance(xyz[without.edge_idx]).max() > 1.0
    assert corner_distance(xyz[with_rej.edge_idx]).max() < 0.05


def test_rings_guessed_and_order_key_give_same_features(room):
    xyz, ring, _ = room
    ref = extract_features(xyz, ring)
    guessed = extract_features(xyz)
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    keyed = extract_features(xyz, ring, azimuth_order=az)
    for f in (guessed, keyed):
        assert np.array_equal(f.edge_idx, ref.edge_idx)
        assert np.array_equal(f.plane_idx, ref.plane_idx)


def greedy_reference(key, cand, run, w):
    """A-LOAM's sequential loop, for checking the vectorised version."""
    picked = np.zeros(len(key), dtype=bool)
    blocked = np.zeros(len(key), dtype=bool)
    for i in sorted(np.flatnonzero(cand), key=lambda i: (-key[i], i)):
        if blocked[i]:
            continue
        picked[i] = True
        for j in range(max(i - w, 0), min(i + w + 1, len(key))):
            if run[j] == run[i]:
                blocked[j] = True
    return np.flatnonzero(picked)


@pytest.mark.parametrize("seed", range(5))
def test_parallel_nms_equals_sequential_greedy(seed):
    rng = np.random.default_rng(seed)
    n = 600
    key = rng.random(n)
    key[100:200] = np.linspace(1, 0, 100)  # a monotone chain needs many rounds
    cand = rng.random(n) < 0.7
    run = np.cumsum(rng.random(n) < 0.03)
    assert np.array_equal(_greedy_nms(key, cand, run, 5), greedy_reference(key, cand, run, 5))


def test_covariance_curvature_reference_values():
    rng = np.random.default_rng(0)
    g = np.linspace(-1, 1, 30)
    X, Y = np.meshgrid(g, g)
    plane = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    line = np.c_[np.linspace(0, 5, 500), np.zeros(500), np.zeros(500)]
    blob = rng.normal(size=(3000, 3))
    kp = np.median(covariance_curvature(plane, 20))
    kl = np.median(covariance_curvature(line, 10))
    kb = np.median(covariance_curvature(blob, 50))
    assert abs(kp - np.sqrt(2)) < 0.03
    assert abs(kl - 1.0) < 1e-9
    assert abs(kb - np.sqrt(3)) < 0.15


def test_covariance_curvature_rejects_pseudo_edges():
    # a densely, isotropically sampled floor patch read in a scrambled ring order: LOAM's
    # curvature sees zig-zags (pseudo-edges) although every neighbourhood is a plane
    rng = np.random.default_rng(1)
    g = np.arange(-0.6, 0.6, 0.02)
    X, Y = np.meshgrid(g + 4.0, g)
    xyz = np.c_[X.ravel(), Y.ravel(), np.full(X.size, -1.0)][:3600]
    xyz[:, :2] += rng.normal(0, 0.002, (3600, 2))
    ring = np.repeat(np.arange(8), 450).astype(np.int16)
    order_key = rng.random(3600)
    cfg = FeatureConfig(reject_occluded=False, reject_parallel=False, edge_threshold=0.02, cov_k=20)
    plain = extract_features(xyz, ring, cfg, azimuth_order=order_key)
    assert len(plain.edge_idx) >= 100
    cfg.use_covariance_curvature = True
    corrected = extract_features(xyz, ring, cfg, azimuth_order=order_key)
    # away from the patch border (where a kNN neighbourhood is one-sided) none survive
    inner = (np.abs(xyz[:, 0] - 4.0) < 0.5) & (np.abs(xyz[:, 1]) < 0.5)
    assert inner[plain.edge_idx].sum() >= 100
    assert inner[corrected.edge_idx].sum() <= 0.02 * inner[plain.edge_idx].sum()
    assert np.nanmedian(corrected.kappa[inner]) > 1.4


def test_covariance_curvature_keeps_true_corners(room):
    xyz, ring, _ = room
    plain = extract_features(xyz, ring)
    corrected = extract_features(xyz, ring, FeatureConfig(use_covariance_curvature=True))
    assert len(corrected.edge_idx) >= 0.95 * len(plain.edge_idx)
    assert corner_distance(xyz[corrected.edge_idx]).max() < 0.05


def test_covariance_curvature_on_a_subset_equals_full(room):
    xyz, _, _ = room
    full = covariance_curvature(xyz, 10)
    q = np.random.default_rng(0).choice(len(xyz), 700, replace=False)
    assert np.array_equal(covariance_curvature(xyz, 10, query_idx=q), full[q])


def test_kappa_only_where_needed_gives_the_full_decisions(room):
    xyz, ring, _ = room
    cfg = FeatureConfig(use_covariance_curvature=True, kappa_edge_max=1.2, kappa_plane_max=1.3)
    f = extract_features(xyz, ring, cfg)
    full = covariance_curvature(xyz, cfg.cov_k)
    done = ~np.isnan(f.kappa)
    assert np.array_equal(f.kappa[done], full[done])
    assert done[f.edge_idx].all() and done[f.plane_idx].all()
    assert (full[f.edge_idx] <= 1.2).all() and (full[f.plane_idx] <= 1.3).all()
    # with kappa_plane_max >= sqrt(3) planes never need kappa: only picked edges are queried
    lazy = extract_features(
        xyz, ring, FeatureConfig(use_covariance_curvature=True, kappa_plane_max=2.0)
    )
    assert (~np.isnan(lazy.kappa)).sum() < 0.05 * len(xyz)
