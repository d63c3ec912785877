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
