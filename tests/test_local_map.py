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
    assert m.last_accepted.tolist() == [0, 1, 2, 5, 6]  # the input points now the last rows
    assert np.array_equal(m.points[-2:], pts[m.last_accepted[-2:]])
    assert m.add(pts[:1], covs[:1]) == 0  # the voxel is full
    assert len(m) == 5 and len(m.last_accepted) == 0


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


def _reference_add(ref: list, cfg: LocalMapConfig, pts: np.ndarray, origin=None) -> None:
    """The map's semantics in plain Python: prune by radius, then a voxel with c points
    accepts the first (cap - c) new points falling in it."""
    if origin is not None:
        ref[:] = [p for p in ref if np.sum((p - origin) ** 2) <= cfg.radius**2]
    counts: dict = {}
    for p in ref:
        key = tuple(np.floor(p / cfg.voxel_size).astype(int))
        counts[key] = counts.get(key, 0) + 1
    for p in pts:
        key = tuple(np.floor(p / cfg.voxel_size).astype(int))
        if counts.get(key, 0) < cfg.max_points_per_voxel:
            counts[key] = counts.get(key, 0) + 1
            ref.append(p)


def _check_structure(m: VoxelHashMap) -> None:
    """Every row is in its voxel's slot list, every voxel in its cell's list and the tables."""
    from slam.mapping import local_map_kernels as K

    n, nv, nc = (int(x) for x in m._state[:3])
    rows = m._vslots[np.repeat(np.arange(nv), m._vcount[:nv]), _ranks(m._vcount[:nv])]
    assert sorted(rows.tolist()) == list(range(n))
    assert np.all(m._vslots[m._pvox[:n], m._pslot[:n]] == np.arange(n))
    assert np.all(m._vkey[m._pvox[:n]] == m._pkeys[:n])
    assert np.all(m._vcount[:nv] >= 1) and np.all(m._vcount[:nv] <= m.cfg.max_points_per_voxel)
    for v in range(nv):
        assert m._tvals[K.slot(m._tkeys, m._vkey[v])] == v
    assert int(np.sum(m._tkeys != -1)) == nv and int(np.sum(m._ctkeys != -1)) == nc
    seen = []
    for c in range(nc):
        assert m._ctvals[K.slot(m._ctkeys, m._ckey[c])] == c
        v, chain = m._chead[c], []
        while v != -1:
            assert m._vcell[v] == c
            chain.append(v)
            v = m._vnext[v]
        assert len(chain) == m._cnvox[c] > 0
        seen += chain
    assert sorted(seen) == list(range(nv))


def _ranks(counts: np.ndarray) -> np.ndarray:
    """0..c-1 for each count c, concatenated."""
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    return np.arange(int(counts.sum())) - starts


def test_incremental_eviction_equals_the_reference_semantics():
    """Insertion with the cap and eviction by radius (holes filled from the last rows,
    voxels and cells removed from their tables) keep exactly the points of the plain
    reference, with their covariances, and a consistent hash after every step."""
    rng = np.random.default_rng(5)
    cfg = LocalMapConfig(voxel_size=0.5, max_points_per_voxel=3, radius=6.0, prune_distance=1.0)
    m = VoxelHashMap(cfg, with_covariances=True)
    ref: list = []
    pruned_at = None
    for step in range(40):
        origin = np.array([0.7 * step, 0.3 * np.sin(step), 0.0])
        pts = origin + rng.normal(0, 3.0, (300, 3)) * [1, 1, 0.3]
        pts[:50] = np.round(pts[:50] * 2) / 2  # points on voxel faces
        covs = pts[:, :, None] * pts[:, None, :] + np.eye(3)  # a function of the point
        prune = pruned_at is None or np.linalg.norm(origin - pruned_at) >= cfg.prune_distance
        _reference_add(ref, cfg, pts, origin if prune else None)
        pruned_at = origin if prune else pruned_at
        added = m.add(pts, covs, origin=origin)
        assert len(m) == len(ref)
        got, want = m.points, np.array(ref)
        np.testing.assert_array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])
        np.testing.assert_array_equal(m.covs, m.points[:, :, None] * m.points[:, None] + np.eye(3))
        assert added == 0 or np.all(np.isin(m.points[-added:], pts).all(axis=1))
        _check_structure(m)
    n_far = sum(np.sum((p - origin) ** 2) > cfg.radius**2 for p in ref)  # the last scan's
    assert n_far > 0 and m.remove_far(origin) == n_far and m.remove_far(origin) == 0
    _reference_add(ref, cfg, np.zeros((0, 3)), origin)
    assert len(m) == len(ref)
    assert m.remove_far(origin + [1000.0, 0, 0]) == len(ref) and len(m) == 0
    _check_structure(m)
    assert m.query(np.zeros((2, 3)), k=2)[1].tolist() == [[0, 0], [0, 0]]
    assert m.add(np.array(ref[:5]), np.tile(np.eye(3), (5, 1, 1))) == 5  # usable again


def test_query_after_evictions_is_exact_for_isolated_and_far_queries():
    """After swap-removals the k-NN still equals cKDTree, also where the voxel shells do
    not settle a query (coarse cells), with a distance bound wider than MAX_BOUNDED_SHELLS
    voxels, and for queries far outside the map."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    m = VoxelHashMap(LocalMapConfig(voxel_size=0.5, max_points_per_voxel=6, radius=40.0))
    for step in range(12):
        origin = np.array([4.0 * step, 0.0, 0.0])
        ground = np.c_[rng.uniform(-30, 30, (4000, 2)), rng.normal(0, 0.03, 4000)] + origin
        sparse = origin + rng.uniform(-60, 60, (60, 3))  # reaches beyond the radius
        m.add(np.concatenate([ground, sparse]), origin=origin)
    tree = cKDTree(m.points)
    q = np.concatenate(
        [
            m.points[::50] + rng.normal(0, 0.2, (len(m.points[::50]), 3)),
            rng.uniform(-80, 120, (300, 3)),  # mostly isolated
            [[5000.0, 0, 0], [44.0, 0, 300.0]],  # far outside the map
        ]
    )
    for k, bound in [(1, np.inf), (10, np.inf), (3, 3.7), (20, 12.0), (1, 0.3)]:
        d, j = m.query(q, k=k, distance_upper_bound=bound)
        d_ref, _ = tree.query(q, k=k, distance_upper_bound=bound)
        np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-9)
        found = np.isfinite(d_ref)
        qq = np.broadcast_to(q[:, None], (len(q), k, 3)).reshape(d.shape + (3,))
        np.testing.assert_allclose(
            np.linalg.norm(m.points[j[found]] - qq[found], axis=-1), d_ref[found], atol=1e-9
        )
        assert np.all(j[~found] == len(m))


def test_map_buffers_stop_growing_on_a_long_drive():
    """Bounded by what is near, not by the distance driven: after the map has filled, the
    point, voxel, cell and table buffers keep their size over another 400 m."""
    rng = np.random.default_rng(2)
    m = VoxelHashMap(LocalMapConfig(voxel_size=0.5, max_points_per_voxel=4, radius=25.0))
    sizes = {}
    for step in range(300):
        origin = np.array([2.0 * step, 10 * np.sin(step / 30), 0.0])
        ring = rng.uniform(0, 2 * np.pi, 2000)
        r = rng.uniform(2, 40, 2000)
        scan = origin + np.c_[r * np.cos(ring), r * np.sin(ring), rng.normal(0, 0.5, 2000)]
        m.add(scan, origin=origin)
        if step == 100:
            sizes = {a: len(getattr(m, a)) for a in ("_pts", "_vkey", "_ckey", "_tkeys")}
    assert {a: len(getattr(m, a)) for a in sizes} == sizes
    assert m.num_cells < 2 * (2 * 40 / 4) ** 2 * 2  # cells of the disk within reach only


def test_hash_spreads_rows_of_voxels_over_the_table():
    """Every axis of a voxel key reaches the home slot: a 64 x 64 patch of voxels in any
    plane (x-y ground, x-z or y-z walls) lands on nearly as many distinct homes as a random
    hash would give, so linear probing stays short (the old hash ignored x: one home per
    y-z column)."""
    from slam.mapping.local_map import voxel_hash
    from slam.mapping.local_map_kernels import _home

    tkeys = np.full(1 << 14, -1, dtype=np.int64)  # 4096 voxels at load 1/4
    g = np.stack(np.meshgrid(np.arange(64), np.arange(64), indexing="ij"), -1).reshape(-1, 2)
    for axes in ((0, 1), (0, 2), (1, 2)):
        c = np.zeros((len(g), 3))
        c[:, axes] = g
        keys = voxel_hash((c + 0.5) * 0.5, 0.5)
        homes = {int(_home(tkeys, key)) for key in keys}
        # random placement: E[distinct] = m (1 - exp(-n / m)) ~ 0.88 n at n / m = 1/4
        assert len(homes) > 0.8 * len(keys), (axes, len(homes))


def test_shell_offsets_cover_each_shell_once_nearest_first():
    from slam.mapping.local_map_kernels import shell_offsets

    offsets, start = shell_offsets(3)
    assert start.tolist() == [0, 1, 27, 125, 343]
    for s in range(4):
        shell = offsets[start[s] : start[s + 1]]
        assert np.all(np.abs(shell).max(axis=1) == s)
        assert (
            len({tuple(o) for o in shell})
            == len(shell)
            == (2 * s + 1) ** 3 - max(2 * s - 1, 0) ** 3
        )
    # shell 1: the six faces come before the edges and corners that lie on their far sides
    one = offsets[start[1] : start[2]].tolist()
    assert one.index([1, 0, 0]) < one.index([-1, -1, 0]) and one[0] == [0, 0, 1]


def test_parallel_query_equals_the_serial_kernel_bit_for_bit():
    """Batches of at least PARALLEL_QUERIES run on numba's threads: the same distances and
    indices as the one-thread kernel (and so as the KD-tree), isolated queries included."""
    from scipy.spatial import cKDTree

    from slam.mapping import local_map

    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-30, 30, (60000, 2)), rng.normal(0, 0.05, 60000)]
    q = np.concatenate([pts[::10] + rng.normal(0, 0.2, (6000, 3)), rng.uniform(-90, 90, (50, 3))])
    assert len(q) >= local_map.PARALLEL_QUERIES
    out = []
    for threads in (1, 2):
        m = VoxelHashMap(LocalMapConfig(max_points_per_voxel=20, threads=threads))
        m.add(pts)
        out.append(m.query(q, k=10))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    d_ref, _ = cKDTree(m.points).query(q, k=10)
    np.testing.assert_allclose(out[1][0], d_ref, atol=1e-12)
