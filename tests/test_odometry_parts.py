"""The parts of the scan-to-map frame loop (``slam.odometry``), each on its own: sweep
clock, motion model, tracking gate, map-insert policy, keyframe policy, legacy extras."""

import numpy as np
import pytest

from slam.odometry.clock import SweepClock
from slam.odometry.config import CommonConfig
from slam.odometry.extras import legacy_extras
from slam.odometry.gate import TrackingGate
from slam.odometry.keyframes import KeyframePolicy
from slam.odometry.map_policy import MapInsertPolicy
from slam.odometry.motion import MotionModel
from slam.registration.gicp import RegistrationResult, se3_exp
from slam.registration.information import Information
from slam.types import OdometryDiagnostics, RegistrationDiagnostics


def pose(x=0.0, y=0.0, yaw_deg=0.0) -> np.ndarray:
    return se3_exp(np.array([0.0, 0.0, np.radians(yaw_deg), x, y, 0.0]))


def result(rmse=0.05, inliers=1800, source=2000, converged=True) -> RegistrationResult:
    return RegistrationResult(
        T_target_source=np.eye(4),
        H=np.eye(6),
        b=np.zeros(6),
        cost=1.0,
        fitness=rmse**2,
        rmse=rmse,
        num_inliers=inliers,
        num_source=source,
        iterations=5,
        converged=converged,
        stop_reason="step" if converged else "max_iterations",
    )


def clock_with(stamps) -> SweepClock:
    c = SweepClock()
    for s in stamps:
        c.observe(s)
    return c


def test_clock_rounds_jittered_gaps_to_whole_sweeps():
    c = clock_with([0.0, 0.1, 0.2, 0.3])
    assert c.period() == pytest.approx(0.1)
    assert c.duration(0.3, 0.414) == pytest.approx(0.1)  # a late stamp: one sweep
    assert c.duration(0.3, 0.61) == pytest.approx(0.3)  # two dropped scans
    assert c.duration(0.3, 0.3) is None and c.duration(None, 1.0) is None
    assert clock_with([0.0, 0.1]).duration(0.1, 0.2137) == pytest.approx(0.1137)  # raw early


def test_motion_model_constant_velocity_and_gap_scaling():
    clock = clock_with([0.0, 0.1, 0.2, 0.3])
    m = MotionModel(CommonConfig(), clock)
    m.T_last, m.T_motion, m.motion_dt = pose(3.0), pose(1.0), 0.1
    assert np.allclose(m.predict(0.4)[:3, 3], [4.0, 0, 0])  # one sweep: as it is
    assert np.allclose(m.predict(0.6)[:3, 3], [6.0, 0, 0])  # three sweeps: scaled
    # beyond max_extrapolation_seconds the motion stops there
    assert np.allclose(m.predict(10.3)[:3, 3], [3.0 + 30.0, 0, 0])
    m2 = MotionModel(CommonConfig(constant_velocity=False), clock)
    m2.T_last, m2.T_motion = pose(3.0), pose(1.0)
    assert np.allclose(m2.predict(0.4), pose(3.0))


def test_gap_hypotheses_span_braking_and_speeding_up():
    clock = clock_with([0.0, 0.1, 0.2, 0.3])
    m = MotionModel(CommonConfig(), clock)
    m.T_motion, m.motion_dt = pose(1.2), 0.1  # 12 m/s
    assert m.gap_hypotheses(0.4) == []  # no gap
    starts = m.gap_hypotheses(0.3 + 2.0)  # a 2 s stall: 24 m +- 0.5 * 3 * 4 = 6 m
    xs = [T[0, 3] for T in starts]
    assert min(xs) == pytest.approx(18.0) and max(xs) == pytest.approx(30.0)
    assert np.allclose(np.diff(xs), xs[1] - xs[0]) and xs[1] - xs[0] <= 2.0 + 1e-9


def test_motion_model_learns_and_restarts():
    clock = clock_with([0.0, 0.1])
    m = MotionModel(CommonConfig(deskew_smoothing=0.5), clock)
    m.learn(pose(0.5), 0.2)
    assert m.motion_dt == pytest.approx(0.1) and np.allclose(m.T_motion, pose(0.5))
    assert np.allclose(m.twist[3:], [0.5, 0, 0])  # no smoothing before two frames
    m.advance(pose(0.5))
    m.restart(pose(3.0), lost_for=0.6, n=6)  # 6 frames over the lost stretch
    assert m.motion_dt == pytest.approx(0.1) and np.allclose(m.T_motion[:3, 3], [0.5, 0, 0])


def test_gate_rejects_a_jump_and_recovers_after_losing():
    clock = clock_with([0.0, 0.1, 0.2, 0.3])
    gate = TrackingGate(CommonConfig(), clock)
    for i in range(3):
        gate.trust(pose(0.1 * i), 0.1 * i, result(), 30.0, learn=True)
    assert gate.n_trusted == 3 and len(gate.normal) == 3
    # 10 m in one sweep from the last trusted pose: faster than max_speed
    why = gate.judge(result(), 30.0, pose(10.2), pose(0.3), 0.3)
    assert why is not None and "speed" in why
    assert gate.judge(result(), 30.0, pose(0.3), pose(0.3), 0.3) is None
    assert gate.miss() and gate.miss() and gate.lost_frames == 2 and gate.lost
    out = gate.trust(pose(0.5), 0.5, result(), 30.0, learn=True)
    assert out.recovered and out.n == 3 and np.allclose(out.T_rel[:3, 3], [0.3, 0, 0])
    assert not gate.lost


def test_gate_relaxes_after_lost_seconds_and_restarts_its_normal():
    clock = clock_with([0.0, 0.1, 0.2, 0.3])
    gate = TrackingGate(CommonConfig(max_lost_seconds=1.0, fitness_relax_seconds=0.0), clock)
    gate.trust(pose(), 0.0, result(), 30.0, learn=True)
    assert gate.relaxation(5.0) == 1.0  # not lost: never relaxed
    gate.miss()
    assert gate.relaxation(0.5) == 1.0 and gate.relaxation(2.5) == 4.0
    out = gate.trust(pose(), 2.5, result(), 30.0, learn=True)
    assert out.reinitialised and len(gate.normal) == 1
    assert not TrackingGate(CommonConfig(), SweepClock()).miss()  # before the map: not lost


def test_map_policy_needs_motion():
    p = MapInsertPolicy(CommonConfig(map_min_translation=0.05, map_min_rotation_deg=0.5))
    assert p.wants(np.eye(4))
    p.inserted(np.eye(4))
    assert not p.wants(pose(0.04)) and p.wants(pose(0.06))
    assert not p.wants(pose(yaw_deg=0.4)) and p.wants(pose(yaw_deg=0.6))


def test_keyframe_policy_selection_and_drift_information():
    kp = KeyframePolicy(CommonConfig())
    info = Information(np.eye(6) * 1e4, False, 1.0, np.zeros(6))
    cloud = np.random.default_rng(0).uniform(-5, 5, (2000, 3))
    first = kp.decide(pose(), True, info, np.eye(6), cloud, {})
    assert first.is_keyframe and 0 < len(first.cloud) <= 2000 and first.cloud.dtype == np.float32
    near = kp.decide(pose(0.5), True, info, np.eye(6), cloud, {})
    assert not near.is_keyframe and len(near.cloud) == 0
    assert not kp.decide(pose(2.0), False, None, None, cloud, {}).is_keyframe  # on prediction
    far = kp.decide(pose(2.0), True, info, np.eye(6), cloud, {})
    assert far.is_keyframe and np.allclose(far.relative, pose(2.0)) and kp.n_keyframes == 2
    # drift ~ distance: 2 m -> sigma_t^2 = 1e-4 + (0.01 * 2)^2
    assert 1.0 / far.info[3, 3] == pytest.approx(1e-4 + 0.02**2)


def test_legacy_extras_keeps_the_flat_keys():
    d = OdometryDiagnostics(n_points=10, n_after_crop=9, rejected=True, lost="why")
    d.registration = RegistrationDiagnostics(4, 0.01, True, 90, 0.9)
    d.counts = {"n_edges": 3}
    d.timings_ms = {"total_ms": 1.0}
    ex = legacy_extras(d, ground_plane=np.array([0, 0, 1, 1.7]))
    assert ex["rejected"] == 1 and type(ex["rejected"]) is int and ex["lost"] == "why"
    assert ex["tracking_lost"] == 0 and ex["degenerate"] is False and ex["n_edges"] == 3
    assert ex["iterations"] == 4 and ex["inliers"] == 90 and ex["ground_plane"][3] == 1.7
    assert ex["total_ms"] == 1.0 and "skipped" not in ex and "ambiguity_ms" not in ex
    # the numbers of the flat view are the typed diagnostics' own (what a run averages)
    assert {k: v for k, v in ex.items() if k != "ground_plane"} == d.flat()
    d.ambiguity, d.ambiguity_axis = 0.5, (1.0, 0.0)
    ex = legacy_extras(d, None, np.eye(6), ambiguity_ms=2.5)
    assert d.ambiguity_ms == 2.5 == ex["ambiguity_ms"] and ex["_info_before_ambiguity"][0, 0] == 1


def test_a_start_hypothesis_replaces_the_prediction_only_when_it_explains_more():
    from slam.odometry.estimate import Estimate
    from slam.odometry.search import start_beats

    c = CommonConfig()
    base = Estimate(pose(0.015), result=result(inliers=537))
    same = Estimate(pose(0.014), result=result(inliers=539))  # the same minimum again
    assert not start_beats(same, base, c)
    elsewhere = Estimate(pose(1.3), result=result(inliers=600))
    assert start_beats(elsewhere, base, c)
    assert not start_beats(Estimate(pose(1.3), result=result(inliers=540)), base, c)
    stuck = Estimate(pose(1.25), result=result(inliers=7032, converged=False))
    assert start_beats(Estimate(pose(1.3), result=result(inliers=6988)), stuck, c)
    assert start_beats(same, None, c)  # the prediction's registration failed
    assert not start_beats(Estimate(pose(1.3), result=result(converged=False)), None, c)


def test_a_start_that_pairs_slightly_fewer_points_much_tighter_explains_more():
    """Measured on the 64-beam street started mid-drive (simulated, frame 60, 7.6 m/s): the
    registration left near rest pairs more points (every point is within the 1 m
    correspondence distance of something) but loosely; the true step pairs 2 % fewer, 17 %
    tighter. A slid alignment along a plain street pairs many fewer points tighter."""
    from slam.odometry.estimate import Estimate
    from slam.odometry.search import explains_better, start_beats

    c = CommonConfig()
    rest = Estimate(pose(0.038), result=result(rmse=0.3008, inliers=6754, source=8000))
    step = Estimate(pose(0.755), result=result(rmse=0.2508, inliers=6601, source=8000))
    assert explains_better(step, rest, c) == pytest.approx(-0.02265 + 0.5 * 0.16622, abs=1e-4)
    assert start_beats(step, rest, c)
    assert not start_beats(rest, step, c)
    slid = Estimate(pose(2.5), result=result(rmse=0.2508, inliers=5700, source=8000))
    assert not start_beats(slid, rest, c)  # 16 % fewer pairs for 17 % tighter
    # frame 130 at 15 m/s: a facade repeating at about the step keeps the rest's alias
    alias = Estimate(pose(-0.355), result=result(rmse=0.327, inliers=6444, source=8000))
    true = Estimate(pose(1.301), result=result(rmse=0.3117, inliers=6501, source=8000))
    assert start_beats(true, alias, c) and not start_beats(alias, true, c)


def test_a_front_end_may_judge_starts_by_its_own_evidence():
    """On an open road the features' ring samples fit the pose at rest as well as the moving
    one; improved_floam then judges a start by its scatter points (``Estimate.evidence``):
    the registration's own numbers would keep the rest, the evidence picks the step."""
    from slam.odometry.estimate import Estimate
    from slam.odometry.search import evidence, most_explained, start_beats

    c = CommonConfig()
    rest = Estimate(pose(0.02), result=result(rmse=0.20, inliers=3000, source=3500))
    step = Estimate(pose(2.10), result=result(rmse=0.21, inliers=2980, source=3500))
    assert not start_beats(step, rest, c)
    rest.evidence, step.evidence = (600, 0.42), (900, 0.30)
    assert evidence(step) == (900, 0.30)
    assert start_beats(step, rest, c) and not start_beats(rest, step, c)
    assert most_explained([(rest, np.eye(4)), (step, np.eye(4))])[0] is step


def test_start_hypotheses_search_forward_and_backward_up_to_the_speed_cap():
    m = MotionModel(CommonConfig(start_max_speed=40.0, start_speed_step=20.0), SweepClock())
    m.T_last = pose(5.0)
    starts = m.start_hypotheses(0.1)
    shifts = np.array([T[:3, 3] - [5.0, 0, 0] for T in starts])
    along_x = sorted(d[0] for d in shifts if d[1] == 0)
    along_y = sorted(d[1] for d in shifts if d[0] == 0)
    assert np.allclose(along_x, [-4.0, -2.0, 0.0, 2.0, 4.0])  # rest, +-20, +-40 m/s over 0.1 s
    assert np.allclose(along_y, along_x)  # a sensor mounted sideways (nuScenes: y forward)
    assert len(starts) == 9 and np.allclose(starts[0], pose(5.0))  # rest first
    # 2 Hz keyframes: neighbouring starts at most start_max_shift (2 m) apart, to 40 m/s
    slow = sorted(T[0, 3] - 5.0 for T in m.start_hypotheses(0.5) if T[1, 3] == 0)
    assert np.allclose(np.diff(slow), 2.0) and np.isclose(max(slow), 20.0)
    assert m.start_hypotheses(None) == []
    assert MotionModel(CommonConfig(start_max_speed=0.0), SweepClock()).start_hypotheses(0.1) == []


def test_gate_believes_a_dropped_sweep_only_when_the_scan_is_explained_as_usual():
    clock = clock_with([0.0, 0.1, 0.2, 0.3])
    gate = TrackingGate(CommonConfig(), clock)
    for i in range(6):
        gate.trust(pose(0.15 * i, yaw_deg=-9.0 * i), 0.1 * i, result(), 30.0, learn=True)
    step = np.linalg.inv(pose(0.6, yaw_deg=-36.0)) @ pose(0.75, yaw_deg=-45.0)
    last = pose(0.75, yaw_deg=-45.0)
    # 0.7 m and 27 deg in what the stamps call one sweep: 270 deg/s, rejected ...
    moved = last @ pose(0.7, yaw_deg=-27.0)
    why = gate.judge(result(), 30.0, moved, last @ step, 0.6)
    assert why is not None and "turn rate" in why
    assert gate.may_have_missed(result(), 30.0)
    # ... but over two sweeps (one dropped) it is the motion extrapolated twice
    assert gate.judge(result(), 30.0, moved, last @ step @ step, 0.6, missed=1) is None
    assert gate.explains_as_usual(result(), 30.0)
    # a registration that fits or covers worse than usual, or is degenerate, is not believed
    assert not gate.explains_as_usual(result(rmse=0.16), 30.0)  # > 3 x the median
    assert not gate.explains_as_usual(result(inliers=1500), 30.0)
    assert not gate.explains_as_usual(result(), 0.03)  # degenerate: sigma > 5 x its floor
    # 3 m is no dropped sweep (nor two) at this speed
    far = last @ pose(3.0, yaw_deg=-27.0)
    for k in (1, 2):
        assert gate.judge(result(), 30.0, far, last @ np.linalg.matrix_power(step, k + 1), 0.6, k)
    # after a believed dropped sweep the velocity is unknown for one frame
    gate.trust(moved, 0.6, result(), 30.0, learn=True, missed=1)
    assert gate.n_chained == 1 and not gate.may_have_missed(result(), 30.0)
    assert gate.judge(result(), 30.0, moved @ pose(0.1), moved @ pose(0.6), 0.7) is None
    gate.trust(moved @ pose(0.1), 0.7, result(), 30.0, learn=True)
    assert gate.judge(result(), 30.0, moved @ pose(0.2), moved @ pose(0.7), 0.8) is not None


def test_a_dropped_sweep_must_be_the_scans_answer_not_its_starts():
    """Along a plain street every start converges near itself: a motion over a dropped
    sweep is believed only where the registration from the prediction agrees with it or
    clearly fits worse (real Hilti jump: all starts within 3 mm; 64-beam street: 0.8-3.2 m
    apart with the prediction's start covering the most of the scan)."""
    gate = TrackingGate(CommonConfig(), clock_with([0.0, 0.1]))
    first = pose(1.50)  # from the constant-velocity prediction
    assert gate.shown_by_scan(result(), pose(1.503), result(), first)  # the starts agree
    # 1.8 m apart, the prediction's start covers as much or more of the scan: its start chose
    assert not gate.shown_by_scan(result(inliers=1780), pose(3.3), result(), first)
    assert not gate.shown_by_scan(result(inliers=1820), pose(3.3), result(), first)
    # ... unless the prediction's start converged to a clearly worse minimum
    assert gate.shown_by_scan(result(inliers=1800), pose(3.3), result(inliers=1650), first)
    # a turn counts like a shift: 5 deg apart is no agreement
    assert not gate.shown_by_scan(result(), pose(1.5, yaw_deg=5.0), result(), first)


def placed(x=0.0, y=0.0, yaw_deg=0.0) -> np.ndarray:
    """The pose at (x, y) turned ``yaw_deg`` about z (translation not coupled to the turn)."""
    T = pose(yaw_deg=yaw_deg)
    T[:2, 3] = x, y
    return T


def test_turn_hypotheses_turn_the_prediction_about_the_sensor_z_axis():
    m = MotionModel(CommonConfig(lost_turn_hypotheses_deg=(15.0, 30.0)), SweepClock())
    T_pred = placed(2.0, 1.0, yaw_deg=10.0)
    starts = m.turn_hypotheses(T_pred)
    assert len(starts) == 5 and starts[0] is T_pred
    yaws = sorted(np.degrees(np.arctan2(T[1, 0], T[0, 0])) for T in starts)
    assert np.allclose(yaws, [-20.0, -5.0, 10.0, 25.0, 40.0])
    assert all(np.allclose(T[:3, 3], [2.0, 1.0, 0.0]) for T in starts)  # turned in place
    off = MotionModel(CommonConfig(lost_turn_hypotheses_deg=()), SweepClock())
    assert len(off.turn_hypotheses(T_pred)) == 1


def test_a_turn_replaces_the_prediction_when_turned_apart_and_explaining_more():
    from slam.odometry.estimate import Estimate
    from slam.odometry.search import _near, start_beats

    c = CommonConfig()
    base = Estimate(placed(0.5, yaw_deg=5.0), result=result(inliers=1000))
    turned = Estimate(placed(0.5, yaw_deg=35.0), result=result(inliers=1200))
    assert not start_beats(turned, base, c)  # only 0 m apart: a speed hypothesis's test
    assert start_beats(turned, base, c, turns=True)
    weaker = Estimate(placed(0.5, yaw_deg=35.0), result=result(inliers=1010))
    assert not start_beats(weaker, base, c, turns=True)  # 1 % more: not enough
    again = Estimate(placed(0.5, yaw_deg=6.0), result=result(inliers=1300))
    assert not start_beats(again, base, c, turns=True)  # 1 deg: the same minimum
    assert _near(again, base, c) and not _near(turned, base, c)


def _snap_search(free_x: bool):
    """A StartSearch whose registration snaps every start to the pose (1, 0, yaw 30 deg),
    except, with ``free_x``, along x, which stays where the start was (a plain corridor)."""
    from slam.odometry.estimate import Estimate
    from slam.odometry.search import StartSearch

    def register(scan, T0, timings, wide):
        x = T0[0, 3] if free_x else 1.0
        return Estimate(placed(x, 0.0, 30.0), result=result(inliers=1500))

    return StartSearch(CommonConfig(), register, lambda: None, lambda state: None)


def test_lost_tracking_trusts_a_pose_only_where_starts_apart_converge_to_it():
    m = MotionModel(CommonConfig(), SweepClock())
    T_pred = placed(0.6, 0.0, 0.0)
    starts, shifts = m.turn_hypotheses(T_pred), m.shift_hypotheses()
    assert len(starts) == 7 and len(shifts) == 4
    est, shown = _snap_search(free_x=False).after_turns(None, starts, shifts, {})
    assert np.allclose(est.pose, placed(1.0, 0.0, 30.0)) and shown
    est, shown = _snap_search(free_x=True).after_turns(None, starts, shifts, {})
    assert not shown  # the starts moved along x stay there: x is the start's, not the scan's
