"""slam.bench.oracle (benchmarks/loop_oracle.py): the true loops it adds (the bound of a
loop closure) and the recorded odometry information loosened anew."""

from __future__ import annotations

import json

import numpy as np

from slam.bench.oracle import OracleLoops, reloosen
from slam.io.trajectory import write_tum
from slam.types import Keyframe


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = (x, y)
    return T


def test_radius_mode_ties_each_revisit_to_its_nearest_old_keyframe(tmp_path):
    # Out along x (1 m steps) and back 0.4 m beside the way out, facing the other way.
    out = [_pose(float(i), 0.0, 0.0) for i in range(40)]
    back = [_pose(39.5 - i, 0.4, np.pi) for i in range(40)]
    poses = np.stack(out + back)
    stamps = 100.0 + 0.5 * np.arange(len(poses))
    write_tum(tmp_path / "gt.tum", stamps, poses)
    cfg = OracleLoops.Config(gt=str(tmp_path / "gt.tum"), radius=1.0, min_gap=10)
    oracle = OracleLoops(cfg)
    factors = []
    for i, t in enumerate(stamps):
        kf = Keyframe(i, float(t), i, np.eye(4), np.eye(4), np.eye(6), np.zeros((0, 3)))
        factors += oracle.on_keyframe(kf, graph=None)
    # Revisits: every keyframe of the way back within 1 m of one on the way out that is
    # at least 10 keyframes older (the first five of the way back are too recent).
    assert len(factors) == len(oracle.added) == 35
    for (j, i), f in zip(oracle.added, factors, strict=True):
        assert j < 40 <= i and i - j >= 10
        rel = np.linalg.inv(poses[j]) @ poses[i]
        got = f.measured().matrix()
        np.testing.assert_allclose(got, rel, atol=1e-9)
        d = np.linalg.norm(poses[:40, :2, 3] - poses[i, :2, 3], axis=1)
        assert j == int(np.argmin(np.where(np.arange(40) <= i - 10, d, np.inf)))


def test_reloosen_redoes_the_front_ends_loosening_with_another_ratio_and_sigma():
    raw = np.stack([np.eye(6) * 1e4] * 4)
    axis = np.array([0.6, 0.8, 0.0])
    extras = [
        {},  # not a keyframe
        {"ambiguity": 0.5, "ambiguity_axis_x": 0.6, "ambiguity_axis_y": 0.8},
        {"ambiguity": 0.95, "ambiguity_axis_x": 0.6, "ambiguity_axis_y": 0.8},
        {"ambiguity": 0.7, "ambiguity_axis_x": 0.6, "ambiguity_axis_y": 0.8},
    ]
    rec = {"info": raw.copy(), "info_raw": raw, "extras": json.dumps(extras)}
    assert reloosen(rec, 0.7, 0.5) == 2
    u = np.r_[0, 0, 0, axis]
    sig = [float(np.sqrt(u @ np.linalg.inv(rec["info"][i]) @ u)) for i in range(4)]
    assert np.allclose(sig, [0.01, 0.01, 0.5, 0.5])
    assert reloosen(rec, 2.0, 0.5) == 0 and np.array_equal(rec["info"], raw)
