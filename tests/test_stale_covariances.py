"""Map covariances recomputed on first use (``map_refresh: on_use``): a row that the next
registration reaches gets the value the eager refresh gives it."""

import numpy as np

from frontends.improved_floam import ImprovedFloam, ImprovedFloamConfig
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.mapping.stale_covariances import FreshCovarianceMap, mark_stale, stale_rows


def _map_with_covs(rng, n=3000):
    m = VoxelHashMap(LocalMapConfig(voxel_size=0.5), with_covariances=True)
    pts = rng.uniform(-5, 5, (n, 3)) * np.array([1, 1, 0.05])
    m.add(pts, np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros(3))
    return m


def test_query_recomputes_only_the_stale_rows_it_returns():
    rng = np.random.default_rng(0)
    m = _map_with_covs(rng)
    m.covs[:] = np.eye(3)
    calls = []

    def recompute(rows):
        calls.append(rows.copy())
        return np.broadcast_to(2 * np.eye(3), (len(rows), 3, 3))

    fresh = FreshCovarianceMap(m, recompute)
    mark_stale(m.covs, np.arange(0, 3000, 2))
    assert len(stale_rows(m.covs)) == 1500
    d, j = fresh.query(m.points[:10] + 1e-3, k=1)
    np.testing.assert_array_equal(j, np.arange(10))  # the nearest map point is itself
    assert set(calls[0]) == set(range(0, 10, 2))  # the stale rows among those returned
    np.testing.assert_array_equal(m.covs[0], 2 * np.eye(3))
    np.testing.assert_array_equal(m.covs[1], np.eye(3))  # not stale: untouched
    assert fresh.recomputed == 5
    fresh.refresh()  # everything left
    assert len(stale_rows(m.covs)) == 0 and fresh.recomputed == 1500


def test_on_use_tracks_like_the_eager_refresh(urban_short):
    """Eager refresh and refresh on first use over the urban start (standing, then moving):
    the same poses to 2 mm, stale rows while running, none in the map handed out."""
    import itertools

    from slam.io.source import open_source
    from slam.types import Scan

    scans = [s for s in itertools.islice(open_source(urban_short.bag), 24) if isinstance(s, Scan)]
    fes = {
        mode: ImprovedFloam(ImprovedFloamConfig(map_refresh=mode, map_refresh_thread=False))
        for mode in ("neighbours", "on_use")
    }
    poses = {mode: np.stack([fe.process(s).pose for s in scans]) for mode, fe in fes.items()}
    assert np.linalg.norm(poses["neighbours"][-1][:3, 3]) > 1.0  # it moved
    np.testing.assert_allclose(poses["on_use"][:, :3, 3], poses["neighbours"][:, :3, 3], atol=2e-3)
    lazy = fes["on_use"]
    assert len(stale_rows(lazy._map.covs)) > 0  # rows waiting for their first use
    assert len(stale_rows(lazy.map.covs)) == 0  # the map handed out is complete
    assert np.isfinite(lazy.map.covs).all()
