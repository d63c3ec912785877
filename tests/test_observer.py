"""The run observer hooks (slam/observer.py): what a live viewer sees of a run."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam.config import SlamConfig, load_config
from slam.factor_sources import FactorSource, build_factor_plugins
from slam.factors import key
from slam.io.trajectory import read_tum
from slam.observer import Observers, RunObserver
from slam.pipeline import Pipeline
from slam.run import run_one
from slam.types import Odometry, Scan


class Recorder:
    """Keeps every call it gets."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, float, np.ndarray]] = []
        self.keyframes: list[tuple[int, int, np.ndarray, int]] = []
        self.loops: list[tuple[int, int]] = []
        self.optimised: list[dict[int, np.ndarray]] = []
        self.closed = 0

    def on_frame(self, index: int, scan: Scan, odom: Odometry) -> None:
        self.frames.append((index, scan.stamp, np.array(odom.pose)))

    def on_keyframe(self, kf_id, frame_index, pose, cloud) -> None:
        self.keyframes.append((kf_id, frame_index, np.array(pose), len(cloud)))

    def on_loop(self, kf_a: int, kf_b: int) -> None:
        self.loops.append((kf_a, kf_b))

    def on_optimised(self, poses) -> None:
        self.optimised.append({k: np.array(v) for k, v in poses.items()})

    def close(self) -> None:
        self.closed += 1


def test_a_recording_observer_sees_every_frame_keyframe_and_optimisation(tmp_path, corridor_short):
    """30 frames of the simulated corridor: one on_frame per frame with the odometry written
    to odometry.tum, one on_keyframe per keyframe, one on_optimised per back-end update
    plus the final one (which is the written trajectory's keyframes), one close."""
    rec = Recorder()
    assert isinstance(rec, RunObserver)
    config = load_config("improved_floam", ["source.max_frames=30"])
    summary = run_one(corridor_short.bag, config, tmp_path, quiet=True, observers=[rec])
    st = summary["system"].state
    assert st.frames == 30 and summary["stop"] is None
    assert [f[0] for f in rec.frames] == list(range(30))
    stamps, odom = read_tum(tmp_path / "odometry.tum")
    np.testing.assert_allclose([f[1] for f in rec.frames], stamps, atol=1e-6)
    np.testing.assert_allclose(np.stack([f[2][:3, 3] for f in rec.frames]), odom[:, :3, 3],
                               atol=1e-6)  # fmt: skip
    assert [k[:2] for k in rec.keyframes] == [(kf.id, kf.frame_index) for kf in st.keyframes]
    assert all(n == len(kf.cloud) > 100 for (*_, n), kf in zip(rec.keyframes, st.keyframes,
                                                               strict=True))  # fmt: skip
    assert len(rec.optimised) == len(st.keyframes) + 1  # each update, then the final one
    assert sorted(rec.optimised[-1]) == sorted(st.estimates)
    for k, T in st.estimates.items():
        np.testing.assert_array_equal(rec.optimised[-1][k], T)
    assert rec.loops == [] and rec.closed == 1
    assert "observers" in st.stage_seconds  # their time is booked apart, not as SLAM's


class ScriptedFrontend:
    """A straight line, 1.5 m per frame: a keyframe every frame."""

    def process(self, scan: Scan) -> Odometry:
        T = np.eye(4)
        T[0, 3] = 1.5 * scan.index
        rel = np.eye(4)
        rel[0, 3] = 1.5 if scan.index else 0.0
        cloud = np.random.default_rng(scan.index).normal(size=(20, 3))
        return Odometry(scan.stamp, T, True, rel, np.eye(6) * 1e4, cloud, {})


class LoopAt:
    """A loop plugin that closes keyframe ``at`` onto keyframe 0 (at the odometry)."""

    is_loop = True

    def __init__(self, at: int) -> None:
        self.at = at

    def on_keyframe(self, kf, graph):
        if kf.id != self.at:
            return []
        noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-2)
        rel = gtsam.Pose3(gtsam.Rot3(), np.array([1.5 * self.at, 0.0, 0.0]))
        return [gtsam.BetweenFactorPose3(key(0), key(kf.id), rel, noise)]


class Broken(Recorder):
    def on_frame(self, index, scan, odom) -> None:
        raise RuntimeError("window closed")


def test_an_accepted_loop_reaches_on_loop_and_a_failing_observer_is_dropped():
    sources = build_factor_plugins({"prior": {}, "odometry": {}})
    sources.append(FactorSource("loop", LoopAt(at=7)))
    rec, broken = Recorder(), Broken()
    pipe = Pipeline(SlamConfig(), frontend=ScriptedFrontend(), factor_sources=sources,
                    observers=[broken, rec])  # fmt: skip
    st = pipe.run(Scan(stamp=float(i), xyz=np.zeros((1, 3)), index=i) for i in range(12))
    assert st.frames == 12 and st.loops_closed == 1
    assert rec.loops == [(0, 7)] and len(rec.frames) == 12
    assert broken.frames == [] and broken.closed == 0  # dropped at its first failure


def test_without_observers_nothing_is_called_or_timed():
    observers = Observers()
    assert not observers
    pipe = Pipeline(SlamConfig(), frontend=ScriptedFrontend(), factor_sources=[])
    st = pipe.run(Scan(stamp=float(i), xyz=np.zeros((1, 3)), index=i) for i in range(5))
    assert st.frames == 5 and "observers" not in st.stage_seconds


def test_observers_are_closed_when_the_run_cannot_start(tmp_path, corridor_short):
    from slam.errors import InputError

    rec = Recorder()
    config = load_config("floam", ["source.start=100000"])
    with pytest.raises(InputError, match="has only"):
        run_one(corridor_short.bag, config, tmp_path, quiet=True, observers=[rec])
    assert rec.closed == 1 and rec.frames == []
