"""Where the graph's correction between two keyframes goes (slam/spread.py): rigid with the
keyframe without spreads; where the frames' spreads put it with them."""

from __future__ import annotations

import numpy as np

from slam.registration.se3 import se3_exp
from slam.spread import spread_corrections


def _line(n: int) -> np.ndarray:
    """n odometry poses 1 m apart along x."""
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, 0, 3] = np.arange(n, dtype=float)
    return P


def _setup(spread: np.ndarray):
    """Keyframes at frames 0, 10, 20 of a 21-frame line; the graph moved keyframe 1 by 0.3 m
    in y and keyframe 2 by 0.3 m in y and 2 deg about z."""
    odom = _line(21)
    frame_kf = np.repeat([0, 1, 2], [10, 10, 1])
    kf_frames = {0: 0, 1: 10, 2: 20}
    shift = np.eye(4)
    shift[1, 3] = 0.3
    turn = shift @ se3_exp(np.array([0.0, 0.0, np.radians(2.0), 0.0, 0.0, 0.0]))
    est = {0: odom[0].copy(), 1: shift @ odom[10], 2: turn @ odom[20]}
    return (
        odom,
        frame_kf,
        kf_frames,
        est,
        spread_corrections(odom, frame_kf, kf_frames, est, spread),
    )


def test_without_spreads_every_frame_follows_its_keyframe():
    odom, frame_kf, kf_frames, est, out = _setup(np.full(21, np.nan))
    for i in range(21):
        k = int(frame_kf[i])
        rigid = est[k] @ np.linalg.inv(odom[kf_frames[k]]) @ odom[i]
        assert np.allclose(out[i], rigid, atol=1e-12)


def test_keyframes_keep_their_estimates():
    odom, _, kf_frames, est, out = _setup(np.ones(21))
    for k, i in kf_frames.items():
        assert np.allclose(out[i], est[k], atol=1e-12)


def test_equal_spreads_share_the_change_evenly():
    """Frames 1-9 between keyframe 0 (no correction) and keyframe 1 (0.3 m in y) move
    0.03 m per frame: frame 5 by half."""
    *_, out = _setup(np.ones(21))
    assert np.allclose(out[1:10, 1, 3], 0.03 * np.arange(1, 10), atol=1e-12)
    assert np.allclose(out[:10, 0, 3], np.arange(10.0), atol=1e-12)


def test_the_change_goes_where_the_spread_is():
    """All of the stretch's spread on frame 6 (a poor fit): frames 1-5 keep keyframe 0's
    correction, frames 6-9 take keyframe 1's."""
    spread = np.full(21, 1e-6)
    spread[1:11] = 0.0
    spread[6] = 1.0
    odom, _, _, est, out = _setup(spread)
    assert np.allclose(out[1:6], odom[1:6], atol=1e-12)
    moved = est[1] @ np.linalg.inv(odom[10]) @ odom[6:10]
    assert np.allclose(out[6:10], moved, atol=1e-12)


def test_a_stretch_with_a_missing_spread_stays_rigid():
    spread = np.ones(21)
    spread[15] = np.nan
    odom, _, kf_frames, est, out = _setup(spread)
    rigid = est[1] @ np.linalg.inv(odom[10]) @ odom[11:20]
    assert np.allclose(out[11:20], rigid, atol=1e-12)
    assert not np.allclose(out[1:10], odom[1:10])  # the other stretch is spread


def test_the_run_state_spreads_where_its_front_end_gave_spreads():
    """``RunState.trajectory`` (what trajectory.tum holds): rigid while no frame gave a
    spread (as for the 3D front ends), spread once they all do."""
    from slam.state import RunState

    spread = np.ones(21)
    odom, frame_kf, kf_frames, est, out = _setup(spread)
    st = RunState()
    for i in range(21):
        k = int(frame_kf[i])
        st.stamps.append(0.1 * i)
        st.odom_poses.append(odom[i])
        st.frame_kf.append(k)
        st.T_kf_frame.append(np.linalg.solve(odom[kf_frames[k]], odom[i]))
        st.frame_spread.append(np.nan)
    st.estimates.update(est)
    rigid = st.trajectory()
    assert np.allclose(rigid[5], est[0] @ np.linalg.inv(odom[0]) @ odom[5], atol=1e-12)
    for i in range(21):
        st.frame_spread[i] = 1.0
    assert np.allclose(st.trajectory(), out, atol=1e-12)
    assert abs(st.trajectory()[5, 1, 3] - 0.15) < 1e-12
