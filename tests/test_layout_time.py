"""Beam-by-beam clouds without a time field (``slam.odometry.layout_time``): deskewed with
times made up from the azimuth only once registrations at speed show they are not
motion-compensated (an Ouster driver without its ``t`` field), never for clouds that are
(KITTI and the bags converted from it: ``tests/test_real_scans.py``)."""

from pathlib import Path

import numpy as np
import pytest

from slam.bench.degrade import rewrite_bag
from slam.config import load_config
from slam.errors import ConfigError
from slam.eval.metrics import EvalOptions, evaluate_arrays
from slam.io.source import open_source
from slam.odometry.layout_time import LayoutTimeConfig, LayoutTimeTrial
from slam.pipeline import Pipeline
from slam.types import Scan


def _scan(with_layout=True) -> Scan:
    xyz = np.zeros((4, 3))
    t = np.array([0.0, 0.03, 0.06, 0.09]) if with_layout else None
    return Scan(0.0, xyz, layout_time=t)


def test_a_decision_takes_clear_wins_or_losses_at_speed():
    trial = LayoutTimeTrial(LayoutTimeConfig(trials=6, margin=2))
    assert not trial.due(_scan(), 0.2)  # too slow for a smear to show
    assert not trial.due(_scan(), None)  # no tracked velocity
    assert not trial.due(_scan(with_layout=False), 1.0)  # a time field or column order
    assert trial.due(_scan(), 1.2)
    assert trial.reading(_scan()).time is None  # undecided: read as compensated
    # within the noise (KITTI from standstill: 0.97-1.02) a frame does not count
    assert not trial.vote(0.200, 0.194, 2) and not trial.vote(0.200, 0.203, 3)
    assert trial.votes == [0, 0] and trial.deskew is None
    assert trial.vote(0.110, 0.100, 4)  # clearly better (OS-128 without t: 0.91)
    assert not trial.vote(0.20, 0.22, 5)  # clearly worse (KITTI 04 at 14 m/s: 1.06-1.12)
    assert not trial.vote(0.20, np.inf, 6)  # a failed deskewed registration loses
    assert trial.deskew is None and not trial.vote(0.20, 0.23, 7)
    assert trial.deskew is False and not trial.due(_scan(), 1.2)  # 1 win, 3 losses
    won = LayoutTimeTrial(LayoutTimeConfig(trials=6, margin=2))
    for i in range(2):
        won.vote(0.02, 0.018, i)
    assert won.deskew is True
    timed = won.reading(_scan())
    assert np.allclose(timed.time, [0.0, 0.03, 0.06, 0.09]) and timed.layout_time is None
    never = LayoutTimeTrial(LayoutTimeConfig(trials=3))
    for i in range(3):  # no decision within the trials: compensated
        never.vote(0.2, 0.2, i)
    assert never.deskew is False
    assert LayoutTimeTrial(LayoutTimeConfig(trials=0)).deskew is False  # never
    with pytest.raises(ConfigError):
        LayoutTimeConfig(min_step=0.0)


def test_an_ouster_driver_without_its_time_field_is_deskewed(tmp_path):
    """The simulated OS-128 (row by row, like the Ouster driver) rewritten without ring and
    t, 60 frames up to 7.5 m/s: the comparison finds the sweeps smeared and deskews them."""
    from slam.sim.cache import ensure_sequence

    seq = ensure_sequence("urban", frames=60, sensor="os128")
    bag, _ = rewrite_bag(Path(seq.bag), tmp_path / "strip.bag", "strip")
    st = Pipeline(load_config("improved_floam", [])).run(open_source(bag))
    assert st.diagnostic_sums["layout_time_deskewed"] >= 10
    _, gt = seq.read_ground_truth()
    poses = np.stack(st.odom_poses)
    res = evaluate_arrays(None, poses, None, gt[: len(poses)], EvalOptions())
    # measured 0.106 m (decided at 5 m/s); read as compensated 0.187 m; with t 0.023 m
    assert res.ape_trans["rmse"] < 0.13
