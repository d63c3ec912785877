"""KITTI devkit drift against values computed by hand on synthetic trajectories."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import InputError
from slam.eval.kitti import (
    KITTI_LENGTHS,
    kitti_metric,
    kitti_metric_scaled,
    scaled_lengths,
    trajectory_distances,
)

H = 0.37  # pose spacing in m; L / H is never close to an integer for L = 100..800


def straight_line(length: float, h: float = H) -> np.ndarray:
    n = int(math.ceil(length / h)) + 1
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * h
    return poses


def hand_segments(n: int, lengths, h: float = H, step: int = 10):
    """(L, steps spanned) for every devkit segment of an evenly spaced straight line."""
    out = []
    for length in lengths:
        k = math.floor(length / h) + 1  # first index with dist > dist[first] + L
        out += [(length, k) for first in range(0, n, step) if first + k <= n - 1]
    return out


def test_scale_drift_of_one_percent_gives_one_percent():
    gt = straight_line(1000.0)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    res = kitti_metric(gt, est)
    segs = hand_segments(len(gt), KITTI_LENGTHS)
    expected = np.mean([0.01 * k * H / length for length, k in segs]) * 100
    # floor((2703 - k) / 10) + 1 firsts per L: 244 + 217 + 190 + 163 + 136 + 109 + 82 + 55
    assert res["segments"] == len(segs) == 1196
    assert res["t_rel_pct"] == pytest.approx(expected, rel=1e-9)
    assert round(res["t_rel_pct"], 2) == 1.00
    assert res["r_rel_deg_per_100m"] == pytest.approx(0.0, abs=1e-9)
    per = {row["length"]: row for row in res["per_length"]}
    assert per[800.0]["segments"] == len([s for s in segs if s[0] == 800])
    assert per[100.0]["t_rel_pct"] == pytest.approx(0.01 * (270 + 1) * H / 100 * 100, rel=1e-9)
    assert res["path_length"] == pytest.approx((len(gt) - 1) * H)


def test_constant_yaw_rate_error_gives_known_rotation_drift():
    gt = straight_line(1000.0)
    omega = math.radians(0.01)  # 0.01 deg per metre -> 1 deg / 100 m
    est = gt.copy()
    dist = trajectory_distances(gt)
    est[:, :3, :3] = Rotation.from_euler("z", (omega * dist)[:, None]).as_matrix()
    res = kitti_metric(gt, est)
    segs = hand_segments(len(gt), KITTI_LENGTHS)
    expected = np.mean([math.degrees(omega * k * H) / length for length, k in segs]) * 100
    assert res["r_rel_deg_per_100m"] == pytest.approx(expected, rel=1e-6)
    assert round(res["r_rel_deg_per_100m"], 2) == 1.00


def test_perfect_and_rigidly_moved_estimate_have_no_drift():
    gt = straight_line(900.0)
    gt[:, :3, :3] = Rotation.from_euler("z", np.linspace(0, 2, len(gt))[:, None]).as_matrix()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    T[:3, 3] = [10.0, -4.0, 2.0]
    res = kitti_metric(gt, T @ gt)
    assert res["segments"] > 0
    assert res["t_rel_pct"] == pytest.approx(0.0, abs=1e-9)
    assert res["r_rel_deg_per_100m"] == pytest.approx(0.0, abs=1e-5)


def test_short_run_reports_none_and_scaled_lengths_work():
    gt = straight_line(50.0)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    res = kitti_metric(gt, est)
    assert res["segments"] == 0
    assert res["t_rel_pct"] is None and res["r_rel_deg_per_100m"] is None
    scaled = kitti_metric_scaled(gt, est)
    assert scaled["lengths"] == [5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0]
    assert scaled["scaled"] is True
    segs = hand_segments(len(gt), scaled["lengths"])
    expected = np.mean([0.01 * k * H / length for length, k in segs]) * 100
    assert scaled["segments"] == len(segs)
    assert scaled["t_rel_pct"] == pytest.approx(expected, rel=1e-9)


def test_scaled_lengths_use_1_2_5_steps():
    assert scaled_lengths(105.0) == (10, 20, 30, 40, 50, 60, 70, 80)
    assert scaled_lengths(30.0) == (2, 4, 6, 8, 10, 12, 14, 16)
    assert scaled_lengths(1000.0) == KITTI_LENGTHS
    with pytest.raises(InputError):
        scaled_lengths(0.0)


def test_bad_input_raises_input_error():
    gt = straight_line(10.0)
    with pytest.raises(InputError, match="equal length"):
        kitti_metric(gt, gt[:-1])
    with pytest.raises(InputError):
        kitti_metric(gt, gt, step=0)
    with pytest.raises(InputError):
        kitti_metric(gt, gt, lengths=(-1.0,))
