"""Pipeline orchestration with a scripted front end: keyframes, trajectories, stops."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.config import SlamConfig
from slam.errors import InputError
from slam.frontend import KeyframeConfig, is_new_keyframe
from slam.io.trajectory import read_tum
from slam.outputs import write_outputs
from slam.pipeline import Pipeline, build_factor_plugins, resolved_config
from slam.state import StopReason
from slam.types import Odometry, Scan


def pose(x, y, z, yaw_deg, roll_deg=0.0, pitch_deg=0.0):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def circle_odometry(n=80, radius=8.0, wobble=True):
    """A drifting odometry along a circle with a little 6-DoF wobble."""
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n * 1.1
        out.append(
            pose(
                radius * np.sin(a),
                radius * (1 - np.cos(a)),
                0.02 * np.sin(3 * a) * wobble,
                np.degrees(a),
                0.5 * np.sin(a) * wobble,
                0.3 * np.cos(2 * a) * wobble,
            )
        )
    return np.stack(out)


class ScriptedFrontend:
    """Plays back a given odometry trajectory (no gtsam, like every front end)."""

    def __init__(self, poses, keyframe: KeyframeConfig | None = None):
        self.poses, self.kf_cfg, self.last_kf = poses, keyframe or KeyframeConfig(), None

    def process(self, scan: Scan) -> Odometry:
        T = self.poses[scan.index]
        rel = np.eye(4) if self.last_kf is None else np.linalg.solve(self.last_kf, T)
        is_kf = self.last_kf is None or is_new_keyframe(rel, self.kf_cfg)
        if is_kf:
            self.last_kf = T
        cloud = np.random.default_rng(scan.index).normal(size=(50, 3))
        return Odometry(scan.stamp, T, is_kf, rel, np.eye(6) * 1e4, cloud, {})


def scans(n, stop_with=None, at=None):
    for i in range(n):
        if stop_with is not None and i == at:
            raise stop_with
        yield Scan(stamp=100.0 + 0.1 * i, xyz=np.zeros((1, 3)), index=i)


def make_pipeline(poses, factors=None):
    config = SlamConfig(factors=factors or {"prior": {}, "odometry": {}})
    return Pipeline(config, frontend=ScriptedFrontend(poses))


def test_odometry_only_isam2_reproduces_frontend_exactly():
    poses = circle_odometry()
    pipe = make_pipeline(poses)
    st = pipe.run(scans(len(poses)))
    assert st.frames == len(poses)
    assert 20 < len(st.keyframes) < len(poses)
    traj = st.trajectory()
    assert np.abs(traj[:, :3, 3] - poses[:, :3, 3]).max() <= 1e-6
    assert np.abs(traj[:, :3, :3] - poses[:, :3, :3]).max() <= 1e-6


def test_every_frame_follows_its_keyframe():
    poses = circle_odometry(n=30)
    pipe = make_pipeline(poses)
    st = pipe.run(scans(len(poses)))
    shift = pose(1.0, 2.0, 0.0, 30.0)  # pretend the optimiser moved every keyframe
    st.estimates = {k: shift @ v for k, v in st.estimates.items()}
    expected = shift @ poses
    assert np.abs(st.trajectory() - expected).max() < 1e-9


def _interrupt_in_compiled_code() -> SystemError:
    """What Ctrl-C inside numba's dispatcher (loading or compiling a kernel) raises."""
    err = SystemError(
        "CPUDispatcher(<function ring_order>) returned a result with an exception set"
    )
    err.__cause__ = KeyboardInterrupt()
    return err


@pytest.mark.parametrize(
    "stop, reason",
    [
        (KeyboardInterrupt(), "interrupted"),
        (_interrupt_in_compiled_code(), "interrupted"),
        (InputError("bad message 17"), "bad input"),
    ],
)
def test_interrupted_run_keeps_everything_computed(tmp_path, stop, reason):
    """Bad input (a truncated bag) first processes the scans the reorder buffer holds and
    the scan read ahead; Ctrl-C does not: those were read, not computed, and an abort is at
    once."""
    poses = circle_odometry(n=40)
    pipe = make_pipeline(poses)
    st = pipe.run(scans(40, stop_with=stop, at=25))
    held = 0 if reason == "bad input" else pipe.config.source.reorder_window + 1
    n = 25 - held
    assert held in (0, 5) and st.frames == n and st.stopped_by.startswith(reason)
    assert st.stop.reason is {"interrupted": StopReason.INTERRUPTED,
                              "bad input": StopReason.BAD_INPUT}[reason]  # fmt: skip
    written = write_outputs(pipe, tmp_path, resolved_config=resolved_config(pipe.config))
    stamps, traj = read_tum(written["trajectory.tum"])
    assert len(stamps) == n
    assert np.abs(traj[:, :3, 3] - poses[:n, :3, 3]).max() < 1e-6
    for name in ("odometry.tum", "trajectory.kitti", "metrics.json", "config.yaml", "map.pcd"):
        assert (tmp_path / name).stat().st_size > 0
    # the map holds the keyframes seen before the stop (streamed from their clouds)
    assert json.loads((tmp_path / "metrics.json").read_text())["map_points"] > 50 * 5


class InterruptingFrontend(ScriptedFrontend):
    """Sends itself SIGINT ``times`` times while processing frame ``at``."""

    def __init__(self, poses, at, times):
        super().__init__(poses)
        self.at, self.times = at, times

    def process(self, scan: Scan) -> Odometry:
        if scan.index == self.at:
            for _ in range(self.times):
                os.kill(os.getpid(), signal.SIGINT)
        return super().process(scan)


@pytest.mark.parametrize("times, frames", [(1, 26), (2, 25)])
def test_ctrl_c_stops_after_the_frame_in_hand_twice_at_once(times, frames):
    """Ctrl-C never lands inside compiled code: the frame in hand finishes; a second one
    aborts at once. Python's handler is back afterwards."""
    poses = circle_odometry(n=40)
    pipe = Pipeline(SlamConfig(factors={"prior": {}, "odometry": {}}),
                    frontend=InterruptingFrontend(poses, at=25, times=times))  # fmt: skip
    st = pipe.run(scans(40))
    assert st.stopped_by.startswith("interrupted") and st.frames == frames
    assert np.abs(st.trajectory()[:, :3, 3] - poses[:frames, :3, 3]).max() < 1e-6
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_while_finishing_waits_for_the_final_estimate(monkeypatch):
    """Ctrl-C during the final optimisation (after the last frame) lets it finish: every
    frame keeps its final pose and the run says it was interrupted."""
    poses = circle_odometry(n=30)
    pipe = make_pipeline(poses)
    finish = pipe.finish
    seen = []

    def interrupted_finish():
        os.kill(os.getpid(), signal.SIGINT)
        seen.append(signal.getsignal(signal.SIGINT) is signal.default_int_handler)
        finish()

    monkeypatch.setattr(pipe, "finish", interrupted_finish)
    st = pipe.run(scans(30))
    assert seen == [False] and st.frames == 30 and st.stopped_by.startswith("interrupted")
    assert np.abs(st.trajectory()[:, :3, 3] - poses[:, :3, 3]).max() < 1e-6
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_system_error_not_caused_by_ctrl_c_is_not_swallowed():
    pipe = make_pipeline(circle_odometry(n=10))
    with pytest.raises(SystemError):
        pipe.run(scans(10, stop_with=SystemError("a real bug"), at=5))


def test_disabled_factor_plugin_is_not_built():
    sources = build_factor_plugins({"prior": {}, "odometry": {"enabled": False}})
    assert [s.name for s in sources] == ["prior"]


class RingRecorder(ScriptedFrontend):
    def process(self, scan: Scan) -> Odometry:
        self.rings = getattr(self, "rings", []) + [scan.ring]
        return super().process(scan)


def _ringless_scan(i: int, rng) -> tuple[Scan, np.ndarray]:
    """16 beams at -15..+15 deg on a 10-20 m cylinder, shuffled: no ring field, no layout."""
    elev = np.radians(np.linspace(-15.0, 15.0, 16))
    beam = rng.integers(0, 16, 20000)
    az = rng.uniform(-np.pi, np.pi, 20000)
    r = rng.uniform(10.0, 20.0, 20000)
    xyz = np.column_stack(
        [
            r * np.cos(elev[beam]) * np.cos(az),
            r * np.cos(elev[beam]) * np.sin(az),
            r * np.sin(elev[beam]),
        ]
    )
    return Scan(stamp=float(i), xyz=xyz, index=i), beam


def test_scans_without_ring_get_rings_from_the_estimated_beam_table():
    rng = np.random.default_rng(3)
    made = [_ringless_scan(i, rng) for i in range(6)]
    fe = RingRecorder(np.stack([np.eye(4)] * 6))
    p = Pipeline(SlamConfig(), frontend=fe, factor_sources=[])
    p.run([s for s, _ in made])
    assert p.state.frames == 6 and len(fe.rings) == 6
    for ring, (_, truth) in zip(fe.rings, made, strict=True):
        np.testing.assert_array_equal(ring, truth)  # ring 0 = the lowest beam
    assert p.beams.n_beams == 16
    assert p.state.sensor.startswith("inferred 16 beams, +15.0..-15.0 deg")


def test_empty_first_scans_leave_no_beam_model_and_the_run_goes_on():
    fe = RingRecorder(np.stack([np.eye(4)] * 4))
    p = Pipeline(SlamConfig(), frontend=fe, factor_sources=[])
    p.run([Scan(stamp=float(i), xyz=np.zeros((0, 3)), index=i) for i in range(4)])
    assert p.state.frames == 4 and p.beams is False and p.state.sensor is None


class LateSlowPlugin:
    """A factor plugin that costs ``ms`` on every keyframe after frame ``after``."""

    def __init__(self, after: int, ms: float):
        self.after, self.ms = after, ms

    def on_keyframe(self, kf, graph):
        if kf.frame_index >= self.after:
            import time

            time.sleep(self.ms / 1e3)
        return []


def test_stage_timings_per_frame_show_which_stage_grows(tmp_path):
    from slam.pipeline import FactorSource

    n = 240
    poses = np.stack([pose(1.5 * i, 0.0, 0.0, 0.0) for i in range(n)])  # a keyframe per frame
    sources = build_factor_plugins({"prior": {}, "odometry": {}})
    sources.append(FactorSource("slow", LateSlowPlugin(after=n - 100, ms=8.0)))
    pipe = Pipeline(SlamConfig(), frontend=ScriptedFrontend(poses), factor_sources=sources)
    st = pipe.run(scans(n))
    assert all(len(s) == n for s in st.stage_frame_seconds.values())
    assert {"frontend", "factor:slow", "backend"} <= set(st.stage_frame_seconds)
    write_outputs(pipe, tmp_path, resolved_config={})
    m = json.loads((tmp_path / "metrics.json").read_text())
    first, last = m["stage_ms_first100"], m["stage_ms_last100"]
    # wall time: the sleep is a lower bound (no upper bounds: the machine may be loaded)
    assert last["factor:slow"] >= 8.0 and first["factor:slow"] < last["factor:slow"] - 4.0
    # the stages and the pipeline's own rest add up to the frame time of each window
    for window, frame in ((first, m["frame_ms_first100"]), (last, m["frame_ms_last100"])):
        assert sum(window.values()) == pytest.approx(frame, rel=1e-3, abs=0.01)
    # CPU time: sleeping costs none, so the slow stage does not grow there
    cpu_first, cpu_last = m["stage_cpu_ms_first100"], m["stage_cpu_ms_last100"]
    assert cpu_last["factor:slow"] < 0.5 * last["factor:slow"]
    for window, frame in ((cpu_first, m["frame_cpu_ms_first100"]),
                          (cpu_last, m["frame_cpu_ms_last100"])):  # fmt: skip
        assert sum(window.values()) == pytest.approx(frame, rel=1e-3, abs=0.01)


class HoldingLoopPlugin:
    """A loop plugin that holds one loop factor (last keyframe -> first) until flush."""

    is_loop = True

    def __init__(self, measured):
        self.measured, self.closed, self.last = measured, False, None

    def on_keyframe(self, kf, graph):
        self.last = kf.id
        return []

    def flush(self, graph):
        import gtsam

        from slam.factors import key

        noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)
        return [gtsam.BetweenFactorPose3(key(0), key(self.last), self.measured, noise)]

    def close(self):
        self.closed = True


def test_factors_a_plugin_holds_at_the_end_enter_the_final_estimate():
    import gtsam

    from slam.pipeline import FactorSource

    poses = circle_odometry(n=60)
    truth_last = gtsam.Pose3(poses[0]).between(gtsam.Pose3(poses[-1]))
    shifted = truth_last.compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.5, 0.0])))
    holder = HoldingLoopPlugin(shifted)
    sources = build_factor_plugins({"prior": {}, "odometry": {}})
    sources.append(FactorSource("loop", holder))
    pipe = Pipeline(SlamConfig(), frontend=ScriptedFrontend(poses), factor_sources=sources)
    st = pipe.run(scans(len(poses)))
    assert holder.closed and st.loops_closed == 1 and st.factor_counts["loop"] == 1
    assert st.loop_pairs == [(0, holder.last)]
    last = st.estimates[len(st.keyframes) - 1]
    # the held loop (0.5 m aside, 10x tighter than odometry) pulls the last keyframe over
    moved = np.linalg.solve(poses[0], last)[:3, 3] - truth_last.translation()
    assert 0.2 < moved[1] < 0.55


class FailingIsam2:
    """iSAM2 that throws what GTSAM throws on an ill-posed system at its ``at``-th update."""

    def __new__(cls, at: int):
        from backends.isam2 import Isam2Backend

        class _Failing(Isam2Backend):
            def update(self, factors, initial, loop_closed=False):
                if self.n_updates == at:
                    raise RuntimeError("Indeterminate linear system detected near x12")
                super().update(factors, initial, loop_closed=loop_closed)

        return _Failing()


def test_a_back_end_failure_stops_the_run_and_keeps_every_frame(tmp_path):
    """The run stops at the keyframe the back end cannot take; the factors it had taken are
    optimised again in batch, so every frame up to the failure is written."""
    poses = circle_odometry(n=60)
    config = SlamConfig(factors={"prior": {}, "odometry": {}})
    pipe = Pipeline(config, frontend=ScriptedFrontend(poses), backend=FailingIsam2(at=12))
    st = pipe.run(scans(60))
    assert st.stopped_by.startswith("back end failed: Indeterminate")
    assert st.stop.reason is StopReason.BACKEND_FAILED and st.stop.detail.startswith("Indet")
    assert len(st.keyframes) == 13 and st.frames < 60
    written = write_outputs(pipe, tmp_path, resolved_config=resolved_config(pipe.config))
    stamps, traj = read_tum(written["trajectory.tum"])
    assert len(stamps) == st.frames
    # keyframes 0-11 from the batch re-optimisation, keyframe 12 from its odometry pose
    assert np.abs(traj[:, :3, 3] - poses[: st.frames, :3, 3]).max() < 1e-6
    assert json.loads((tmp_path / "metrics.json").read_text())["stopped_by"].startswith("back")


def _stamped(stamps) -> list[Scan]:
    return [Scan(stamp=float(t), xyz=np.zeros((1, 3)), index=i) for i, t in enumerate(stamps)]


def test_scans_recorded_out_of_order_are_put_back_in_order():
    """Every 10th pair of messages swapped: the reorder buffer keeps all of them, each with
    the pose of its stamp; one 6 places late (beyond the 4 held) is dropped and counted."""
    poses = circle_odometry(n=40)
    order = np.arange(40)
    for k in range(0, 39, 10):
        order[[k, k + 1]] = order[[k + 1, k]]
    items = [_stamped(100.0 + 0.1 * np.arange(40))[i] for i in order]
    st = make_pipeline(poses).run(items)
    assert st.frames == 40 and st.messages_skipped == 0
    np.testing.assert_array_equal(st.stamps, 100.0 + 0.1 * np.arange(40))
    assert np.abs(st.trajectory()[:, :3, 3] - poses[:, :3, 3]).max() < 1e-6
    late = list(range(40))
    late.insert(26, late.pop(20))  # message 20 recorded after 25
    st = make_pipeline(poses).run([_stamped(100.0 + 0.1 * np.arange(40))[i] for i in late])
    assert st.frames == 39 and dict(st.skipped_messages) == {"stamp out of order": 1}
    assert 100.0 + 0.1 * 20 not in st.stamps
    off = make_pipeline(poses)
    off.config.source.reorder_window = 0  # without the buffer every swapped pair costs one
    assert off.run(items).frames == 36


def test_one_stamp_far_ahead_costs_that_scan_only():
    """One glitched stamp 100 s ahead: before the buffer every later scan was dropped; now
    the scans recorded after it overtake it and it alone is skipped."""
    poses = circle_odometry(n=40)
    stamps = 100.0 + 0.1 * np.arange(40)
    stamps[12] += 100.0
    st = make_pipeline(poses).run(_stamped(stamps))
    assert st.frames == 39 and dict(st.skipped_messages) == {"stamp out of order": 1}
    np.testing.assert_array_equal(st.stamps, np.delete(stamps, 12))
    assert np.abs(st.trajectory()[:, :3, 3] - np.delete(poses, 12, axis=0)[:, :3, 3]).max() < 1e-6


def test_a_clock_stepping_back_is_followed_or_stops_the_run():
    """The clock steps back 5 s at message 20 and goes on at the sweep period (a PTP
    correction, a driver restarting its clock): before, every later scan was dropped. Now
    the scans from there on are stamped on the run's clock (one period after the last
    before the step) and all 40 kept; with source.stamps=header the run stops as bad input
    saying what to do. Stamps not at the sweep period (all equal, unset) stop it too."""
    poses = circle_odometry(n=40)
    stamps = 100.0 + 0.1 * np.arange(40)
    stamps[20:] -= 5.0
    notes: list[str] = []

    class Source(list):
        pass

    src = Source(_stamped(stamps))
    src.notes = notes
    st = make_pipeline(poses).run(src)
    assert st.frames == 40 and st.messages_skipped == 0 and st.stopped_by is None
    np.testing.assert_allclose(st.stamps, 100.0 + 0.1 * np.arange(40), atol=1e-9)
    assert st.clock_steps == [(20, pytest.approx(5.0))]
    assert len(notes) == 1 and "stepped back by 4.900 s at message 20" in notes[0]
    assert np.abs(st.trajectory()[:, :3, 3] - poses[:, :3, 3]).max() < 1e-6
    pipe = make_pipeline(poses)
    pipe.config.source.stamps = "header"
    st = pipe.run(_stamped(stamps))
    assert st.frames == 20 and st.skipped_messages["stamp out of order"] == 10
    assert st.stopped_by.startswith("bad input: the stamps of the last 10 messages (20 to 29)")
    assert "(101.500000000 s; the first one by 4.500 s): the clock stepped back" in st.stopped_by
    assert "--set source.stamps=auto goes on across the step" in st.stopped_by
    np.testing.assert_array_equal(st.stamps, stamps[:20])
    st = make_pipeline(poses).run(_stamped(np.zeros(40)))  # a driver that never sets them
    assert st.frames == 1 and st.skipped_messages["duplicated stamp"] == 10
    assert "all equal the last kept scan's (0.000000000 s)" in st.stopped_by
    # fewer than 10 in a row (a short burst of late messages) are skipped and the run goes on
    stamps = 100.0 + 0.1 * np.arange(40)
    stamps[20:29] -= 5.0
    st = make_pipeline(poses).run(_stamped(stamps))
    assert st.frames == 31 and st.stopped_by is None and st.messages_skipped == 9


def test_the_record_clock_needs_a_bag():
    pipe = make_pipeline(circle_odometry(n=5))
    pipe.config.source.stamps = "record"
    with pytest.raises(InputError, match="only bags have a record time"):
        pipe.run(scans(5))


def test_the_figures_draw_the_loop_edges_in_the_graph_not_every_verified_one():
    """A verified loop that a consistency check holds back is no edge of the graph: the
    figures' count is metrics.json's loops_closed (a 2D run drew 92 where 90 entered)."""
    from types import SimpleNamespace

    from slam.pipeline import FactorSource
    from slam.viz.birdseye import loop_pairs

    poses = circle_odometry(n=60)
    holder = HoldingLoopPlugin(gtsam_pose(poses[0], poses[-1]))
    holder.events = [SimpleNamespace(accepted=True, source=3, target=1)]  # verified, held
    sources = build_factor_plugins({"prior": {}, "odometry": {}})
    sources.append(FactorSource("loop", holder))
    pipe = Pipeline(SlamConfig(), frontend=ScriptedFrontend(poses), factor_sources=sources)
    st = pipe.run(scans(len(poses)))
    assert loop_pairs(pipe) == [(0, holder.last)] and st.loops_closed == 1


def gtsam_pose(a, b):
    import gtsam

    return gtsam.Pose3(a).between(gtsam.Pose3(b))
