"""The stamps a CARMEN run's trajectory carries: the log's own (the ipc timestamp of each
laser line), which the Freiburg relations are given at, also where the log's clock jumps
and the reader repaired the stamps for the run."""

from __future__ import annotations

import bz2

import numpy as np
from shared_data import shared_path

from slam.config import load_config
from slam.eval.relations import match_stamps
from slam.io.carmen import CarmenSource
from slam.io.trajectory import read_tum
from slam.run import run_one

FRAMES = 200


def _log_stamps(path, n: int) -> np.ndarray:
    out = []
    with bz2.open(path, "rt") as fh:
        for line in fh:
            if line.startswith("FLASER "):
                out.append(float(line.split()[-3]))
                if len(out) == n:
                    break
    return np.array(out)


def test_output_stamps_give_back_the_logs_own():
    path = shared_path("laser2d", "intel.clf.bz2")
    src = CarmenSource(path)
    run = np.array([s.stamp for _, s in zip(range(FRAMES), src, strict=False)])
    log = _log_stamps(path, FRAMES)
    # 8 of the first 200 Intel stamps are out of order in the log (0.2 - 0.94 s off)
    repaired = np.flatnonzero(run != log)
    assert len(repaired) == 8 and np.all(np.diff(run) > 0)
    np.testing.assert_array_equal(src.output_stamps(run), log)
    assert src.output_stamps(np.array([1.5]))[0] == 1.5  # not a scan's: unchanged


def test_the_trajectory_is_found_at_the_logs_stamps(tmp_path):
    """dpcr2d on the first 200 Intel scans: every row of trajectory.tum / odometry.tum is
    found at its scan's log stamp (a relation given there scores that scan); with the
    run's repaired stamps each of the 8 repaired scans would score a neighbour instead."""
    path = shared_path("laser2d", "intel.clf.bz2")
    cfg = load_config("dpcr2d", [])
    cfg.source.max_frames = FRAMES
    run_one(path, cfg, tmp_path, quiet=True)
    log = _log_stamps(path, FRAMES)
    for name in ("trajectory.tum", "odometry.tum"):
        stamps, poses = read_tum(tmp_path / name)
        assert len(stamps) == FRAMES
        np.testing.assert_allclose(stamps, log, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(match_stamps(stamps, log, 1e-6), np.arange(FRAMES))
    src = CarmenSource(path)
    run = np.array([s.stamp for _, s in zip(range(FRAMES), src, strict=False)])
    bad = np.flatnonzero(run != log)
    found = match_stamps(run, log[bad], 0.1)  # the metric evaluator's 0.1 s window
    assert np.all((found >= 0) & (found != bad))  # each one matches a neighbour instead
