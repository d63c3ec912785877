"""Scan Context descriptor and candidate search (slam/loop/scan_context.py, slam/loop/search.py)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from slam.loop.plugin import LoopClosurePlugin
from slam.loop.scan_context import (
    ScanContextParams,
    column_shift_distance,
    ring_key,
    scan_context,
    sector_key,
    sector_key_shift,
    shift_to_yaw,
    yaw_to_shift,
)
from slam.loop.search import ScanContextDatabase, SearchParams

SECTOR_DEG = 6.0  # 360 / 60


# --------------------------------------------------------------------------- synthetic town


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mesh = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    mesh.translate(lo)
    return o3d.t.geometry.TriangleMesh.from_legacy(mesh)


def _town(seed=0, blocks=4, block=30.0, street=12.0):
    """Grid of blocks with buildings 4-25 m tall and street trees; street centre lines at
    x or y = 6 + 42 k."""
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_box((-50, -50, -0.1), (blocks * (block + street) + 50,) * 2 + (0.0,)))
    pitch = block + street
    for i in range(blocks):
        for j in range(blocks):
            x0, y0 = street + i * pitch, street + j * pitch
            for _ in range(rng.integers(2, 5)):
                sx, sy = rng.uniform(6, 15, 2)
                x, y = x0 + rng.uniform(0, block - sx), y0 + rng.uniform(0, block - sy)
                scene.add_triangles(_box((x, y, 0), (x + sx, y + sy, rng.uniform(4, 25))))
            for _ in range(rng.integers(3, 8)):
                x, y = x0 + rng.uniform(0, block), y0 + rng.choice([0.5, block - 1.0])
                scene.add_triangles(_box((x, y, 0), (x + 0.6, y + 0.6, rng.uniform(4, 9))))
    return scene


def _rays(beams=16, columns=900):
    el = np.radians(np.linspace(-15.0, 15.0, beams))
    # half a column off 0: no ray lies exactly on a 6-degree sector boundary, where the bin
    # of a whole-sector rotation would depend on the last bit of atan2
    az = np.linspace(0, 2 * np.pi, columns, endpoint=False) + np.pi / columns
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


def _rz(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _scan(scene, x, y, yaw, rng, z=1.8, max_range=100.0):
    """Sensor-frame points of a 16-beam LiDAR at (x, y, z) with heading ``yaw``, 1 cm noise."""
    rays = _rays()
    d_world = rays @ _rz(yaw).T
    origin = np.broadcast_to([x, y, z], d_world.shape)
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origin, d_world]).astype(np.float32)))
    r = hit["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(r) & (r < max_range)
    return rays[ok] * (r[ok] + rng.normal(0.0, 0.01, ok.sum()))[:, None]


@pytest.fixture(scope="module")
def town():
    return _town(0)


@pytest.fixture(scope="module")
def street_scan(town):
    return _scan(town, 48.0, 6.0, 0.3, np.random.default_rng(0))


# --------------------------------------------------------------------------- descriptor


def test_bins_hold_max_height_above_ground_and_skip_far_points():
    p = ScanContextParams(rings=2, sectors=4, max_radius=10.0, lidar_height=2.0)
    pts = np.array(
        [
            [1.0, 0.1, 0.0],  # ring 0, sector 0: 2.0
            [2.0, 0.2, 0.5],  # same bin, higher: 2.5 wins
            [-0.1, 6.0, 1.0],  # ring 1, sector 1 (91 deg): 3.0
            [-3.0, 0.1, -3.0],  # ring 0, sector 1 (just under 180 deg): below ground -> 0
            [0.0, -20.0, 5.0],  # beyond max_radius: ignored
            [1.0, -1.0, 1.0],  # ring 0, sector 3 (315 deg): 3.0
        ]
    )
    expected = np.array([[2.5, 0.0, 0.0, 3.0], [0.0, 3.0, 0.0, 0.0]])
    np.testing.assert_allclose(scan_context(pts, p), expected)
    assert scan_context(np.zeros((0, 3)), p).sum() == 0.0
    np.testing.assert_allclose(ring_key(expected), [5.5 / 4, 3.0 / 4])
    np.testing.assert_allclose(sector_key(expected), [1.25, 1.5, 0.0, 1.5])


def test_column_distance_counts_only_columns_non_empty_in_both():
    q = np.array([[1.0, 0.0, 2.0, 1.0], [0.0, 0.0, 2.0, 1.0]])  # column 1 empty
    c = np.array([[1.0, 3.0, 0.0, 1.0], [2.0, 3.0, 0.0, 0.0]])  # column 2 empty
    # shift 0 pairs q col j with c col j: (q0, c0) cos 1/sqrt5, (q3, c3) cos 1/sqrt2
    d, s = column_shift_distance(q, c[None], shifts=np.array([[0]]))
    assert d[0] == pytest.approx(1.0 - (1.0 / np.sqrt(5.0) + 1.0 / np.sqrt(2.0)) / 2.0)
    assert s[0] == 0
    # shift 1: (q0, c1) 1/sqrt2, (q2, c3) 1/sqrt2, (q3, c0) 3/sqrt10
    d, _ = column_shift_distance(q, c[None], shifts=np.array([[1]]))
    assert d[0] == pytest.approx(1.0 - (2.0 / np.sqrt(2.0) + 3.0 / np.sqrt(10.0)) / 3.0)
    # all shifts: shift 3 pairs (q0, c3) and (q2, c1), both parallel; the other pairs have
    # an empty side -> d = 0, the unique minimum
    d, s = column_shift_distance(q, c[None])
    assert s[0] == 3
    assert d[0] == pytest.approx(0.0, abs=1e-12)
    d, _ = column_shift_distance(q, np.zeros((1, 2, 4)))
    assert d[0] == 1.0  # nothing to compare: maximal distance


@pytest.mark.parametrize("k", [1, 7, 30, 59])
def test_rotation_by_whole_sectors_is_a_column_shift(street_scan, k):
    ref = scan_context(street_scan)
    yaw = np.radians(k * SECTOR_DEG)
    query = street_scan @ _rz(-yaw).T  # query frame turned by +yaw: T_ref_query = Rz(yaw)
    d, s = column_shift_distance(scan_context(query), ref[None])
    assert d[0] < 2e-3
    assert s[0] == k
    rk, rk_ref = ring_key(scan_context(query)), ring_key(ref)
    assert np.linalg.norm(rk - rk_ref) < 0.03 * np.linalg.norm(rk_ref)  # rotation invariant
    assert shift_to_yaw(s[0], 60) == pytest.approx(np.pi - np.mod(np.pi - yaw, 2 * np.pi))


@pytest.mark.parametrize("yaw_deg", [-170.0, -95.5, -33.3, 12.7, 47.0, 133.9])
def test_yaw_recovered_within_one_sector_and_distance_invariant(street_scan, yaw_deg):
    ref = scan_context(street_scan)
    query = street_scan @ _rz(-np.radians(yaw_deg)).T
    dq = scan_context(query)
    d, s = column_shift_distance(dq, ref[None])
    err = (np.degrees(shift_to_yaw(s[0], 60)) - yaw_deg + 180.0) % 360.0 - 180.0
    assert abs(err) <= SECTOR_DEG
    assert d[0] < 0.15  # only bin-boundary effects remain
    # the sector key alone lands within one sector too, and the windowed search agrees
    s0 = sector_key_shift(sector_key(dq), sector_key(ref)[None])[0]
    assert abs((s0 - yaw_to_shift(np.radians(yaw_deg), 60) + 30) % 60 - 30) <= 1
    window = (s0 + np.arange(-3, 4))[None] % 60
    dw, sw = column_shift_distance(dq, ref[None], shifts=window)
    assert sw[0] == s[0] and dw[0] == pytest.approx(d[0])


def test_same_place_two_metres_aside_matches_and_other_places_do_not(town):
    """Street sites of the synthetic town: seen again from 2 m aside/along with any heading,
    the distance stays under the default threshold; other places (20-60 m away) exceed it."""
    rng = np.random.default_rng(1)
    threshold = LoopClosurePlugin.Config().search.threshold
    for x0, y0 in [(48.0, 6.0), (6.0, 70.0)]:
        ref = scan_context(_scan(town, x0, y0, 0.3, rng))
        near = [
            column_shift_distance(scan_context(_scan(town, x0 + dx, y0 + dy, yaw, rng)), ref[None])
            for dx, dy, yaw in [(0, 2, 1.0), (0, -2, -2.0), (2, 0, 0.5), (-2, 0, 3.0)]
        ]
        far = [
            column_shift_distance(scan_context(_scan(town, x0 + dx, y0 + dy, 0.3, rng)), ref[None])
            for dx, dy in [(42, 0), (-42, 0), (0, 42), (0, -42), (20, 0), (0, 20), (42, 42)]
        ]
        near_d = np.array([d[0] for d, _ in near])
        far_d = np.array([d[0] for d, _ in far])
        assert near_d.max() < threshold < far_d.min(), (x0, y0, near_d, far_d)
        # the yaw of T_ref_query is the heading difference: query heading - 0.3 rad
        for (_, s), yaw in zip(near, [1.0, -2.0, 0.5, 3.0], strict=True):
            err = np.degrees(shift_to_yaw(s[0], 60) - (yaw - 0.3) + np.pi) % 360.0 - 180.0
            assert abs(err) <= 2 * SECTOR_DEG


# --------------------------------------------------------------------------- search


def _random_descs(n, rng, rings=20, sectors=60):
    return rng.uniform(0.0, 10.0, (n, rings, sectors)) * (rng.random((n, rings, sectors)) < 0.5)


def test_search_excludes_recent_keyframes_by_count_and_time():
    rng = np.random.default_rng(0)
    descs = _random_descs(50, rng)
    db = ScanContextDatabase(20, 60, SearchParams(exclude_recent=30, exclude_seconds=25.0))
    for i, d in enumerate(descs):
        db.add(100 + i, float(i), d)
    # stamp 49 -> time window excludes stamps > 24, count window excludes rows >= 20
    assert db.eligible(49.0) == 20
    assert db.eligible(40.0) == 16  # time window: stamps <= 15
    hits = db.query(descs[10], 49.0)
    assert hits[0].kf_id == 110 and hits[0].distance == pytest.approx(0.0, abs=1e-6)
    assert all(h.row < 20 for h in hits)
    assert db.detect(descs[45], 49.0) is None or db.detect(descs[45], 49.0).row < 20
    assert db.query(descs[45], 10.0) == []  # nothing old enough yet


def test_lazy_tree_rebuild_gives_exact_top_k():
    rng = np.random.default_rng(1)
    n = 300
    descs = _random_descs(n, rng)
    params = SearchParams(exclude_recent=30, top_k=10, rebuild_every=25)
    db = ScanContextDatabase(20, 60, params)
    for i in range(n):
        db.add(i, float(i), descs[i])
        if i % 7 == 0:
            hits = db.query(descs[i], float(i))
            n_e = max(i + 1 - 30, 0)
            keys = ring_key(descs[:n_e])
            brute = np.argsort(np.linalg.norm(keys - ring_key(descs[i]), axis=1))[:10]
            assert sorted(h.row for h in hits) == sorted(brute.tolist())
    # rebuilt roughly every 25 eligible keyframes, not per keyframe
    assert 5 <= db.tree_builds <= (n - 30) // 25 + 2


def test_database_grows_past_its_initial_capacity():
    rng = np.random.default_rng(2)
    descs = _random_descs(200, rng)
    db = ScanContextDatabase(20, 60, SearchParams(exclude_recent=1))
    for i, d in enumerate(descs):
        db.add(i, float(i), d, position=[i, 0.0, 0.0])
    assert len(db) == 200
    np.testing.assert_allclose(db.descriptor(150), descs[150].astype(np.float32), rtol=1e-6)
    np.testing.assert_array_equal(db.near([100.0, 0.5, 0.0], 2.0, 300.0), [100, 99, 101])


def test_tree_rebuilds_grow_geometrically_and_stay_exact():
    """At 1000 keyframes the key tree is rebuilt a few dozen times, not every 10 keyframes,
    and the brute-force tail keeps the top-k exact."""
    rng = np.random.default_rng(3)
    n = 1000
    descs = _random_descs(n, rng)
    db = ScanContextDatabase(20, 60, SearchParams(exclude_recent=30, top_k=5, rebuild_every=10))
    for i in range(n):
        db.add(i, float(i), descs[i])
        hits = db.query(descs[i], float(i))
        if i % 97 == 0 and i > 30:
            keys = ring_key(descs[: i + 1 - 30])
            brute = np.argsort(np.linalg.norm(keys - ring_key(descs[i]), axis=1))[:5]
            assert sorted(h.row for h in hits) == sorted(brute.tolist())
    assert 20 <= db.tree_builds <= 45, db.tree_builds  # every 10 would be 97
