"""The same bag twice gives the same poses, bit for bit: the threads (the map refresh's
worker, the local map's parallel queries, the range-image k-NN, small_gicp's threads) must
not make results depend on timing."""

import itertools

import numpy as np

from slam.config import load_config
from slam.io.source import open_source
from slam.pipeline import Pipeline
from slam.types import Scan


def _poses(bag, config: str, n: int, overrides: list[str]) -> np.ndarray:
    scans = itertools.islice((s for s in open_source(bag) if isinstance(s, Scan)), n)
    state = Pipeline(load_config(config, overrides)).run(list(scans))
    return np.stack(state.odom_poses)


def test_improved_floam_twice_identical_poses(urban_short):
    """Car-speed urban drive: the next scan filtered on a worker thread while the map
    refresh runs on another and the scan in hand registers, the registration's map queries
    on 2 threads (5k queries per iteration, above PARALLEL_QUERIES), banded SOR included;
    against all of it inline and serial."""
    from slam.mapping.local_map import PARALLEL_QUERIES

    assert PARALLEL_QUERIES <= 5000
    sets = ["frontend.map.threads=2", "frontend.sor.mode=banded"]
    a = _poses(urban_short.bag, "improved_floam", 40, sets)
    b = _poses(urban_short.bag, "improved_floam", 40, sets)
    assert len(a) == 40
    assert np.linalg.norm(a[-1][:3, 3] - a[0][:3, 3]) > 3.0  # it moved
    np.testing.assert_array_equal(a, b)
    inline = [
        "frontend.map.threads=1",
        "frontend.map_refresh_thread=false",
        "frontend.filter_ahead=false",
    ]
    serial = _poses(urban_short.bag, "improved_floam", 40, sets[1:] + inline)
    np.testing.assert_array_equal(a, serial)  # threads change the timing, not the answers
