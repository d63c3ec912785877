"""The voxel-hash local map: per-voxel cap, radius bound, incremental insertion."""

import numpy as np

from slam.mapping.local_map import LocalMapConfig, VoxelHashMap


def test_cap_per_voxel_and_covariances_follow_points():
    m = VoxelHashMap(LocalMapConfig(voxel_size=1.0, max_points_per_voxel=3), with_covariances=True)
    pts = np.array([[0.1, 0.1, 0.1]] * 5 + [[1.5, 0.2, 0.2]] * 2)
    covs = np.arange(7)[:, None, None] * np.eye(3)
    assert m.add(pts, covs) == 5  # 3 in the first voxel, 2 in the second
    assert m.num_voxels == 2
    assert sorted(m.covs[:, 0, 0].tolist()) == [0, 1, 2, 5, 6]
    assert m.add(pts[:1], covs[:1]) == 0  # the voxel is full
    assert len(m) == 5


def test_map_stays_bounded_while_driving():
    rng = np.random.default_rng(0)
    m = VoxelHashMap(LocalMapConfig(voxel_size=0.5, max_points_per_voxel=5, radius=20.0))
    sizes = []
    for k in range(60):
        origin = np.array([k * 2.0, 0.0, 0.0])
        scan = origin + rng.uniform(-15, 15, (3000, 3)) * [1, 1, 0.1]  # reaches 21.3 m
        added = m.add(scan, origin=origin)
        # pruned every prune_distance (3 m) of travel: no earlier point beyond radius + 3 m
        # (+ a voxel of slack), the newest scan within its own reach
        d = np.linalg.norm(m.points - origin, axis=1)
        assert d.max() <= 20.0 + 3.0 + 0.5, d.max()
        if k % 2 == 0:  # just pruned (moved 4 m since): only the new scan beyond the radius
            assert np.all(np.flatnonzero(d > 20.0) >= len(m) - added), k
        sizes.append(len(m))
    # bounded: the map after 120 m of driving is no larger than after 40 m (steady state)
    assert max(sizes[40:]) < 1.3 * sizes[20]
    version = m.version
    tree = m.tree()
    assert m.tree() is tree and m.version == version  # cached until the map changes


def test_query_through_the_hash_equals_a_kd_tree():
    """The map's k-NN (voxel shells, brute force for isolated points) is exact: the same
    neighbours and distances as scipy's cKDTree, with and without a distance bound."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    m = VoxelHashMap(LocalMapConfig(voxel_size=0.5, max_points_per_voxel=4))
    floor = np.c_[rng.uniform(-20, 20, (20000, 2)), rng.normal(0, 0.02, 20000)]
    wall = np.c_[rng.uniform(-20, 20, 5000), np.full(5000, 7.0), rng.uniform(0, 3, 5000)]
    far = rng.uniform(-200, 200, (30, 3))  # isolated points: the brute-force fallback
    m.add(np.concatenate([floor, wall, far]))
    assert m.add(floor[:100]) < 100  # full voxels refuse points
    tree = cKDTree(m.points)
    q = np.concatenate([floor[::50] + rng.normal(0, 0.3, (400, 3)), far + 0.5, [[500, 0, 0]]])
    for k, bound in [(1, 1.0), (1, np.inf), (10, np.inf), (5, 0.7)]:
        d, j = m.query(q, k=k, distance_upper_bound=bound)
        d_ref, j_ref = tree.query(q, k=k, distance_upper_bound=bound)
        np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-12)
        found = np.isfinite(d_ref)  # the indices point at those neighbours (ties: any)
        qq = np.broadcast_to(q[:, None], (len(q), k, 3)).reshape(d.shape + (3,))
        dj = np.linalg.norm(m.points[j[found]] - qq[found], axis=-1)
        np.testing.assert_allclose(dj, d_ref[found], atol=1e-12)
        assert np.all(j[~found] == len(m))
    n_before = len(m)
    n_far = int(np.sum(np.linalg.norm(far, axis=1) > 60.0))
    assert n_far > 20 and m.remove_far(np.zeros(3)) == n_far  # the hash follows
    assert len(m) == n_before - n_far
    d, j = m.query(q, k=3)
    d_ref, j_ref = cKDTree(m.points).query(q, k=3)
    np.testing.assert_allclose(d, d_ref, atol=1e-12)
