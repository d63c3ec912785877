"""The constant-velocity motion model of a scan-to-map odometry: prediction, its scaling
over gaps between scans, the hypotheses after a long gap, and the deskew twist."""

from __future__ import annotations

import numpy as np

from slam.deskew import deskew, se3_log, time_from_firing_order
from slam.odometry.clock import SweepClock, off_duration
from slam.odometry.config import CommonConfig
from slam.registration.gicp import se3_exp
from slam.types import Scan


def _twist(T: np.ndarray) -> np.ndarray:
    """(omega, v) of a 4x4 pose: the order the motion model and deskew keep."""
    rho, phi = se3_log(T)
    return np.concatenate([phi, rho])


class MotionModel:
    """Last pose, last frame-to-frame motion and its duration, and the smoothed twist.

    T_last: T_odom_sensor of the previous frame. T_motion: T_prev_current of the last frame
    pair that was tracked, over ``motion_dt`` seconds. twist: exponentially filtered
    (omega, v) per ``motion_dt``, for deskewing.
    """

    def __init__(self, cfg: CommonConfig, clock: SweepClock):
        self._c = cfg
        self._clock = clock
        self.T_last = np.eye(4)
        self.T_motion = np.eye(4)
        self.motion_dt: float | None = None
        self.twist = np.zeros(6)
        self.n_frames = 0
        # the frame before the last: its pose, its stamp, the motion that led to it (and its
        # duration), and how many frames in a row taught the model (previous_step_check)
        self.T_before: np.ndarray | None = None
        self.stamp_before: float | None = None
        self.motion_before: np.ndarray | None = None
        self.dt_before: float | None = None
        self.learned_run = 0
        self._learned = False
        self._stamp_last: float | None = None

    def predict(self, stamp: float) -> np.ndarray:
        """The initial guess of T_odom_sensor at ``stamp``."""
        if not self._c.constant_velocity:
            return self.T_last.copy()
        return self.T_last @ self.motion_to(stamp)

    def motion_to(self, stamp: float) -> np.ndarray:
        """The motion from the last frame to ``stamp``: ``T_motion`` while the gap is within
        [2/3, 3/2] of its duration, else scaled along its twist to the gap (a dropped
        message, a stalled driver), up to ``max_extrapolation_seconds``: at 12 m/s one
        missing scan otherwise puts the prediction 1.2 m short."""
        gap = self._clock.since_last(stamp)
        if self.motion_dt is None or gap is None or self.motion_dt <= 0:
            return self.T_motion
        ratio = gap / self.motion_dt
        if not off_duration(ratio):
            return self.T_motion
        limit = max(self._c.max_extrapolation_seconds / self.motion_dt, 1.0)
        return se3_exp(_twist(self.T_motion) * min(ratio, limit))

    def after_missed(self, stamp: float, missed: int) -> np.ndarray:
        """The prediction at ``stamp`` had the driver dropped ``missed`` sweeps before it
        unseen by the stamps: the motion to ``stamp`` repeated ``missed`` + 1 times along its
        twist."""
        step = self.motion_to(stamp)
        if not missed:
            return self.T_last @ step
        return self.T_last @ se3_exp(_twist(step) * (missed + 1))

    def gap_hypotheses(self, stamp: float) -> list[np.ndarray]:
        """Initial guesses after a long gap (``gap_hypotheses_after`` frames or more), else
        []: the constant-velocity motion every ``gap_hypothesis_step`` metres within
        +-0.5 ``gap_acceleration`` T^2 of its extrapolation (braking or speeding up)."""
        c = self._c
        gap = self._clock.since_last(stamp)
        if (
            not c.constant_velocity
            or c.gap_hypotheses_after <= 0
            or self.motion_dt is None
            or self.motion_dt <= 0
            or gap is None
            or gap / self.motion_dt < c.gap_hypotheses_after
        ):
            return []
        span = min(gap, c.max_extrapolation_seconds)
        twist = _twist(self.T_motion) * span / self.motion_dt
        reach = float(np.linalg.norm(twist[3:]))
        if reach < 1e-3:  # standing: no direction to search along
            return [self.T_last @ se3_exp(twist)]
        spread = 0.5 * c.gap_acceleration * span**2
        lo, hi = max(reach - spread, 0.0) / reach, (reach + spread) / reach
        n = int(min(np.ceil((hi - lo) * reach / max(c.gap_hypothesis_step, 1e-3)), 24)) + 1
        return [self.T_last @ se3_exp(twist * f) for f in np.linspace(lo, hi, n)]

    def start_hypotheses(self, span: float | None) -> list[np.ndarray]:
        """Initial guesses while no velocity is known: the last pose moved along the
        sensor's x and y axes by every ``start_speed_step`` up to +-``start_max_speed``
        (m/s) over ``span`` seconds, at rest first ([] when off or without a span). The step
        shrinks so that neighbouring guesses are at most ``start_max_shift`` m apart (a slow
        frame rate: 2 Hz keyframes move 1-5 m per scan)."""
        c = self._c
        if c.start_max_speed <= 0 or c.start_speed_step <= 0 or span is None or span <= 0:
            return []
        step = c.start_speed_step
        if c.start_max_shift > 0 and step * span > 1.05 * c.start_max_shift:
            step = c.start_max_shift / span
        n = int(np.floor(c.start_max_speed / step + 1e-9))
        speeds = step * np.arange(1, n + 1)
        steps = [np.zeros(3)]
        for axis in (0, 1):
            for v in np.concatenate([speeds, -speeds]):
                d = np.zeros(3)
                d[axis] = v * span
                steps.append(d)
        starts = []
        for d in steps:
            T = np.eye(4)
            T[:3, 3] = d
            starts.append(self.T_last @ T)
        return starts

    def turn_hypotheses(self, T_pred: np.ndarray) -> list[np.ndarray]:
        """``T_pred`` first, then turned by +-each ``lost_turn_hypotheses_deg`` about the
        sensor's z axis (a hand-held or skidding sensor's unpredicted turn)."""
        turns = [sign * np.radians(d) for d in self._c.lost_turn_hypotheses_deg for sign in (1, -1)]
        return [T_pred, *(T_pred @ se3_exp(np.array([0, 0, a, 0, 0, 0])) for a in turns)]

    def shift_hypotheses(self) -> list[np.ndarray]:
        """Sensor-frame offsets (4x4) by +-each ``lost_shift_hypotheses_m`` along x and y."""
        out = []
        for d in self._c.lost_shift_hypotheses_m:
            for axis in (0, 1):
                for sign in (1.0, -1.0):
                    D = np.eye(4)
                    D[axis, 3] = sign * d
                    out.append(D)
        return out

    def deskew(self, scan: Scan) -> Scan:
        """The scan motion-compensated with the smoothed twist over ``motion_dt`` (as it is
        before any motion is known, without per-point time or ``deskew`` off)."""
        if not self._c.deskew or self.motion_dt is None or len(scan) == 0:
            return scan
        time = scan.time
        if time is None:
            # no time field: the time from the azimuth along the firing order
            period = self._clock.period()
            time = time_from_firing_order(scan.xyz, self.motion_dt if period is None else period)
            if time is None:
                return scan
        if not np.any(time > 0):
            return scan
        xyz = deskew(scan.xyz, time, se3_exp(self.twist), float(self.motion_dt))
        return Scan(scan.stamp, xyz, scan.intensity, scan.ring, time, scan.index)

    def restart(self, T_rel: np.ndarray, lost_for: float | None, n: int) -> None:
        """After ``n`` frames of lost tracking: the mean motion over the stretch ``T_rel``
        (last trusted pose -> now) of ``lost_for`` seconds."""
        if lost_for is not None:
            self.motion_dt = lost_for / n
        self.twist = _twist(T_rel) / n
        self.T_motion = se3_exp(self.twist)

    def learn(self, pose: np.ndarray, stamp: float) -> None:
        """A tracked frame at ``pose``: its motion from the last frame and its duration; the
        smoothed twist is rescaled to a new duration before the new motion is mixed in."""
        dt_before = self.motion_dt
        self.motion_before, self.dt_before = self.T_motion, dt_before
        self._learned = True
        gap = self._clock.since_last(stamp)
        if gap is not None:
            self.motion_dt = gap
        self.T_motion = np.linalg.inv(self.T_last) @ pose
        a = self._c.deskew_smoothing if self.n_frames > 1 else 0.0
        ratio = 1.0 if dt_before is None else self.motion_dt / dt_before
        old = self.twist * ratio if off_duration(ratio) else self.twist
        self.twist = a * old + (1.0 - a) * _twist(self.T_motion)

    def advance(self, pose: np.ndarray, stamp: float | None = None) -> None:
        """The frame (at ``stamp``) is done: ``pose`` is the last pose."""
        self.T_before, self.stamp_before = self.T_last, self._stamp_last
        self.T_last = pose.copy()
        self._stamp_last = None if stamp is None else float(stamp)
        self.learned_run = self.learned_run + 1 if self._learned else 0
        self._learned = False
        self.n_frames += 1

    def before_last(self, stamp: float) -> tuple[np.ndarray, float] | None:
        """The prediction at ``stamp`` from the frame before the last, moved on by the
        motion that led to it, and the span (s) it covers (None unless the last two frames
        taught the model with motions of known duration): what the last step should have
        been if it was wrong."""
        if (
            self.learned_run < 2
            or self.T_before is None
            or self.stamp_before is None
            or self.motion_before is None
            or not self.dt_before
        ):
            return None
        span = float(stamp) - self.stamp_before
        if not span > 0:
            return None
        return self.T_before @ se3_exp(_twist(self.motion_before) * span / self.dt_before), span
