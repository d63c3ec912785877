"""The measures of benchmarks/robustness.py: stops found in the ground truth, the drift over
them, the ran-away rule, and the degraded bags it writes (no ring/time, jittered stamps,
dropped messages) read back as intended."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from slam.io.source import open_source
from slam.types import Scan

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "robustness.py"
_spec = importlib.util.spec_from_file_location("robustness", _PATH)
robustness = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(robustness)


def _drive(speeds: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) of a car driving along x at ``speeds`` (m per frame)."""
    T = np.tile(np.eye(4), (len(speeds), 1, 1))
    T[:, 0, 3] = np.cumsum(speeds)
    return T


def test_stops_and_the_drift_over_them():
    # 2 s at 1 m per frame, 3 s standing, 2 s driving again, 0.5 s standing (too short)
    speeds = np.r_[np.ones(20), np.zeros(30), np.ones(20), np.zeros(5), np.ones(5)]
    stamps = 0.1 * np.arange(len(speeds))
    gt = _drive(speeds)
    spans = robustness.stops(stamps, gt)
    assert spans == [(19, 49)]
    est = gt.copy()
    est[20:50, 1, 3] = np.linspace(0.0, 0.3, 30)  # creeps 0.3 m sideways while standing
    est[50:, 1, 3] = 0.3
    drift, n = robustness.stop_drift(stamps, est, gt)
    assert n == 1 and drift == pytest.approx(0.3, abs=1e-9)
    steps = robustness.step_errors(est, gt)
    assert steps.max() == pytest.approx(0.3 / 29, rel=1e-6)


def test_ran_away_rule():
    ok = robustness.verdict(
        {"frames": 100, "messages": 100, "path_m": 100.0, "ape_rmse": 0.5, "step_err_max": 0.1}
    )
    assert ok["ran_away"] == "" and ok["ape_pct"] == pytest.approx(0.5)
    assert "step error" in robustness.verdict({"frames": 9, "step_err_max": 0.6})["ran_away"]
    far = robustness.verdict({"frames": 9, "path_m": 100.0, "ape_rmse": 6.0})
    assert "APE 6.0 % of path" in far["ran_away"]
    # a short path (a standing robot) is not judged by its APE share
    assert robustness.verdict({"frames": 9, "path_m": 5.0, "ape_rmse": 1.0})["ran_away"] == ""
    assert "stop drift" in robustness.verdict({"frames": 9, "stop_drift_max": 0.7})["ran_away"]
    lost = robustness.verdict({"frames": 1, "messages": 400})
    assert lost["ran_away"] == "1 of 400 messages written"


def test_degraded_bags(tmp_path, corridor_short):
    clean = [s for s in open_source(corridor_short.bag) if isinstance(s, Scan)]
    true = np.array([s.stamp for s in clean])
    bag, stamp_map = robustness.rewrite_bag(corridor_short.bag, tmp_path / "strip.bag", "strip")
    strip = [s for s in open_source(bag) if isinstance(s, Scan)]
    assert len(strip) == len(clean) and all(s.ring is None and s.time is None for s in strip)
    assert np.abs(strip[5].xyz - clean[5].xyz).max() < 1e-5
    bag, stamp_map = robustness.rewrite_bag(corridor_short.bag, tmp_path / "jit.bag", "jitter")
    jit = np.array([s.stamp for s in open_source(bag) if isinstance(s, Scan)])
    pairs = np.load(stamp_map)
    assert np.allclose(pairs[:, 1], true) and np.allclose(pairs[:, 0], jit, atol=1e-6)
    assert 0.01 < np.abs(jit - true).max() <= 0.02 + 1e-6
    bag, stamp_map = robustness.rewrite_bag(corridor_short.bag, tmp_path / "drop.bag", "drop5")
    drop = np.array([s.stamp for s in open_source(bag) if isinstance(s, Scan)])
    assert len(drop) == len(clean) - len(clean) // 5
    assert np.allclose(drop, np.delete(true, np.arange(4, len(true), 5)), atol=1e-6)
