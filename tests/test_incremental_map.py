"""Incremental map vs a KD-tree rebuilt over the live points (slam/mapping/incremental_map.py)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.errors import ConfigError, InputError
from slam.mapping.incremental_map import IncrementalMap, IncrementalMapConfig


def _check_against_rebuilt(m: IncrementalMap, q: np.ndarray, k: int, r: float) -> None:
    ids = m.alive_ids()
    ref = cKDTree(m.points(ids))
    d_ref, j_ref = ref.query(q, k=k)
    d_ref, j_ref = d_ref.reshape(len(q), k), j_ref.reshape(len(q), k)
    id_ref = np.where(j_ref < len(ids), ids[np.minimum(j_ref, len(ids) - 1)], -1)
    d, i = m.knn(q, k)
    np.testing.assert_array_equal(i, id_ref)
    np.testing.assert_array_equal(d, d_ref)
    got = m.radius(q, r)
    for qi, want in enumerate(ref.query_ball_point(q, r)):
        assert sorted(got[qi].tolist()) == sorted(ids[want].tolist())
    # bounded: the same neighbours where they lie within the bound, inf / -1 beyond it
    db, ib = m.knn(q, k, distance_upper_bound=r)
    inside = d_ref <= r
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(ib, np.where(inside, id_ref, -1))
    np.testing.assert_array_equal(db, np.where(inside, d_ref, np.inf))


@pytest.mark.parametrize(
    ("merge_ratio", "index"), [(1.0, "buckets"), (4.0, "buckets"), (4.0, "merged")]
)
def test_knn_and_radius_equal_a_rebuilt_tree_through_inserts_deletes_restores(merge_ratio, index):
    rng = np.random.default_rng(0)
    m = IncrementalMap(IncrementalMapConfig(merge_ratio=merge_ratio, index=index))
    q = rng.uniform(-12, 12, size=(300, 3))
    deleted = []
    for step in range(25):
        m.insert(rng.uniform(-10, 10, size=(int(rng.integers(1, 800)), 3)))
        if step % 3 == 1:  # lazy delete by mask
            mask = rng.random(m.n_ids) < 0.15
            m.delete(mask)
            deleted.append(np.flatnonzero(mask))
        if step % 5 == 2:  # by box (a moving object's volume)
            c = rng.uniform(-8, 8, 3)
            m.delete(box=(c - 2.0, c + 2.0))
        if step % 7 == 3 and deleted:  # re-insertion of earlier deletions
            m.restore(deleted.pop(0))
        _check_against_rebuilt(m, q, k=int(rng.integers(1, 9)), r=1.0)
    if index == "merged":  # one tree, rebuilt once per change that a query followed
        assert m.n_buckets == 0 and m.rebuilt_points <= 25 * len(m) * 2
        return
    assert m.n_buckets <= 2 * int(np.log2(m.n_ids)) + 2
    # each point was put into a tree O(log N) times, not once per insert
    assert m.rebuilt_points < 3 * np.log2(m.n_ids) * m.n_ids


def test_sliding_window_and_exact_hits():
    rng = np.random.default_rng(1)
    m = IncrementalMap(IncrementalMapConfig(compact_fraction=0.3))
    pts = rng.uniform(-50, 50, size=(5000, 3))
    ids = m.insert(pts)
    d, i = m.knn(pts[:10], 1)  # a query on a map point finds it at distance 0
    np.testing.assert_array_equal(i[:, 0], ids[:10])
    assert np.all(d[:, 0] == 0.0)
    assert ids[0] in m.radius(pts[0], 0.0)[0]
    n = m.delete(box=(np.full(3, -20.0), np.full(3, 20.0)), outside=True)
    assert n == int((np.abs(pts) > 20).any(axis=1).sum()) and len(m) == 5000 - n
    assert np.all(np.abs(m.xyz) <= 20)
    _check_against_rebuilt(m, rng.uniform(-30, 30, size=(200, 3)), k=5, r=3.0)
    d, i = m.knn(np.zeros(3), k=len(m) + 3)  # more neighbours than points: padded
    assert np.all(i[0, -3:] == -1) and np.all(np.isinf(d[0, -3:]))


def test_empty_map_and_bad_input():
    m = IncrementalMap()
    d, i = m.knn(np.zeros((2, 3)), 3)
    assert np.all(i == -1) and np.all(np.isinf(d))
    assert [len(a) for a in m.radius(np.zeros((2, 3)), 1.0)] == [0, 0]
    m.insert(np.zeros((4, 3)))
    with pytest.raises(InputError):
        m.insert(np.zeros((3, 2)))
    with pytest.raises(InputError):
        m.delete()
    with pytest.raises(InputError):
        m.delete(np.ones(3, dtype=bool))
    with pytest.raises(InputError):
        m.knn(np.zeros((1, 3)), 0)
    with pytest.raises(ConfigError):
        IncrementalMapConfig(compact_fraction=1.0)
