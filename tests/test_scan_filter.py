"""improved_floam's point filter (column stride + SOR before deskew): filtered ahead on a
worker thread or inline, each scan gets the same answer, and the stride's phase follows
the stream order."""

import itertools

import numpy as np

from frontends.improved_floam import ImprovedFloamConfig
from frontends.improved_floam_filter import ScanFilter, filter_scan
from slam.io.source import open_source
from slam.odometry.scan_to_map import crop
from slam.types import Scan


def _scans(sim, n):
    return [s for s in itertools.islice(open_source(sim.bag), n) if isinstance(s, Scan)]


def _same(a, b):
    np.testing.assert_array_equal(a.keep, b.keep)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.nbh.idx, b.nbh.idx)
    assert a.stride == b.stride


def test_ahead_and_inline_give_the_same_filter(urban_short):
    cfg = ImprovedFloamConfig(max_scan_points=20000, min_ring_columns=100)  # strided scans
    scans = _scans(urban_short, 5)
    ahead, inline = ScanFilter(cfg, threaded=True), ScanFilter(cfg, threaded=False)
    for i, scan in enumerate(scans):
        work = crop(scan, cfg.min_range, cfg.max_range)
        ahead.ahead(scan)
        a, _ = ahead.get(scan, work)
        b, _ = inline.get(scan, work)
        _same(a, b)
        ref = filter_scan(work, cfg, phase=i)  # the phase advances once per dense scan
        _same(a, ref)
        assert a.stride == 2 and a.kept is not None and len(a.raw) < len(work)
        assert 0.9 < a.keep.mean() < 1.0  # SOR removed a few points
    ahead.close()


def test_moved_to_keeps_the_decisions_on_deskewed_points(urban_short):
    cfg = ImprovedFloamConfig()
    scan = _scans(urban_short, 1)[0]
    work = crop(scan, cfg.min_range, cfg.max_range)
    flt = filter_scan(work, cfg, phase=0)
    shifted = work.xyz + np.array([0.01, 0.0, 0.0])
    moved = flt.moved_to(shifted)
    np.testing.assert_array_equal(moved.xyz, shifted[flt.keep])
    np.testing.assert_array_equal(moved.raw, shifted)


def test_filter_does_not_depend_on_numba_threads(urban_short):
    """The window search runs its rings in parallel (prange) and the box search its rows:
    one or two numba threads give the same keep-mask, neighbours and distances, so the
    filter thread may use either."""
    from slam.deferred import numba_threads

    cfg = ImprovedFloamConfig()
    for i, scan in enumerate(_scans(urban_short, 3)):
        work = crop(scan, cfg.min_range, cfg.max_range)
        with numba_threads(1):
            one = filter_scan(work, cfg, phase=i)
            one_dist = one.nbh.dist.copy()
        with numba_threads(2):
            two = filter_scan(work, cfg, phase=i)
        _same(one, two)
        np.testing.assert_array_equal(one_dist, two.nbh.dist)
        assert not one.keep.all()
