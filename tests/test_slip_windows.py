"""slam.bench.slip (benchmarks/slip_windows.py): the along-track slip per window against a
known slip."""

from __future__ import annotations

import numpy as np

from slam.bench.slip import along_track, plain_mask, windows
from slam.io.trajectory import write_tum
from slam.sim.building import LANES, PLAIN


def _path(heading_deg: float, step: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) driving along ``heading`` with per-frame steps ``step`` (m)."""
    h = np.deg2rad(heading_deg)
    R = np.array([[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0], [0, 0, 1]])
    poses = np.tile(np.eye(4), (len(step), 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = np.outer(np.cumsum(step) - step[0], R[:, 0])
    return poses


def test_along_track_measures_an_injected_slip_in_its_window_only():
    n = 400
    true_step = np.full(n, 0.3)
    est_step = true_step.copy()
    est_step[150:190] -= 0.05  # 40 frames 5 cm short: a 2 m slip in window 100-200
    gt, est = _path(37.0, true_step), _path(37.0, est_step)
    h = np.deg2rad(37.0)  # lateral drift (across the heading) must not count as along-track
    est[:, :2, 3] += np.outer(0.01 * np.arange(n), [-np.sin(h), np.cos(h)])
    starts, err = along_track(est, gt, 100)
    assert starts.tolist() == [0, 100, 200, 300]
    # 1 m lateral per 30 m window tilts it: the cosine loss is ~2 cm, the slip is 2 m
    assert abs(err[1] + 2.0) < 0.1
    assert np.all(np.abs(err[[0, 2, 3]]) < 0.1)


def test_plain_mask_marks_the_plain_stretches_of_the_floor():
    k, x0, x1 = PLAIN[2]
    xy = np.array([[0.5 * (x0 + x1), LANES[k]], [0.5 * (x0 + x1), LANES[k] + 3.0],
                   [x0 - 1.0, LANES[k]], [x1, LANES[k] - 1.5]])  # fmt: skip
    assert plain_mask(xy).tolist() == [True, False, False, True]


def test_windows_sums_plain_and_elsewhere(tmp_path):
    k, x0, _ = PLAIN[0]
    n = 300
    gt = _path(0.0, np.full(n, 0.1))
    gt[:, 0, 3] += x0  # frames 0-299 drive x0 .. x0 + 30 m on the plain stretch's lane
    gt[:, 1, 3] = LANES[k]
    gt[200:, 1, 3] += 5.0  # the last window is off the lane: not plain
    est = gt.copy()
    est[100:, 0, 3] -= 1.0  # a 1 m slip between frames 99 and 100 (window 0-100)
    est[250:, 0, 3] -= 0.5  # and 0.5 m off the lane
    stamps = np.arange(n) * 0.1
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    r = windows(tmp_path / "est.tum", tmp_path / "gt.tum", 100)
    assert r["plain"] == [True, True, False]
    assert abs(r["sum_abs_plain"] - 1.0) < 1e-6
    assert abs(r["sum_abs_elsewhere"] - 0.5) < 1e-6
