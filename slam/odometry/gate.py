"""The tracking gate: whether a registration is believable, how long tracking has been
lost, and when its tolerances relax (``slam.registration.plausibility`` does the tests)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.odometry.clock import SweepClock
from slam.odometry.config import CommonConfig
from slam.registration.gicp import RegistrationResult
from slam.registration.plausibility import (
    RunningNormal,
    explains_as_usual,
    implausibility,
    quality_problem,
    relaxed,
    shown_by_scan,
)


@dataclass
class Trusted:
    """What trusting a registration changed. reinitialised: the running normal restarted
    (accepted with relaxed tolerances). recovered: tracking had been lost; then
    ``T_rel`` (last trusted pose -> this one), over ``lost_for`` seconds and ``n`` frames."""

    reinitialised: bool = False
    recovered: bool = False
    T_rel: np.ndarray | None = None
    lost_for: float | None = None
    n: int = 0


class TrackingGate:
    """The running normal of trusted registrations, the last trusted pose and stamp, and
    the count of consecutive frames without a trusted registration."""

    def __init__(self, cfg: CommonConfig, clock: SweepClock):
        self._c = cfg
        self._clock = clock
        self.normal = RunningNormal(cfg.plausibility.window)
        self.n_trusted = 0  # trusted poses so far (the first frame included)
        # trusted poses since the velocity was last unknown (a hypothesised dropped frame)
        self.n_chained = 0
        self.lost_frames = 0
        self.T_trusted = np.eye(4)
        self.trusted_stamp: float | None = None

    @property
    def velocity_known(self) -> bool:
        """Two chained trusted poses give the constant-velocity prediction (none since a
        hypothesised dropped sweep)."""
        return self.n_trusted >= 2 and self.n_chained >= 2

    @property
    def lost(self) -> bool:
        """Whether the last frame had no trusted registration (search wider)."""
        return self.lost_frames > 0

    def judge(
        self,
        res: RegistrationResult,
        min_eigenvalue: float,
        pose: np.ndarray,
        T_pred: np.ndarray,
        stamp: float,
        missed: int = 0,
        predicted: bool = True,
    ) -> str | None:
        """Why the registration ``res`` ending at ``pose`` is not believable (None: trust
        it). The prediction is a measurement only once two trusted poses gave it a velocity
        (and ``predicted``). ``missed``: sweeps hypothesised dropped before this scan (its
        time is that much longer; ``T_pred`` the prediction over it)."""
        since = self._clock.duration(self.trusted_stamp, stamp)
        if missed and since is not None:
            since += missed * (self._clock.period() or since)
        known = self.velocity_known and predicted
        off_prediction = np.linalg.inv(T_pred) @ pose if known else np.eye(4)
        return implausibility(
            res,
            min_eigenvalue,
            self.normal,
            np.linalg.inv(self.T_trusted) @ pose,
            off_prediction,
            since,
            relaxed(
                self._c.plausibility,
                self.relaxation(since),
                self.relaxation(since, self._c.fitness_relax_seconds or None),
            ),
        )

    def judge_after_previous(
        self,
        res: RegistrationResult,
        min_eigenvalue: float,
        pose: np.ndarray,
        T_before_pred: np.ndarray,
        stamp: float,
    ) -> str | None:
        """Why ``res`` ending at ``pose`` is not believable as the motion from the frame
        before the last (``T_before_pred``: its prediction at ``stamp``), had the last step
        been wrong; None: believe it (``previous_step_check``). The bound is one frame's,
        as strict as the usual test. Only while tracking holds with a known velocity."""
        if not (self._c.plausibility.previous_step_check and self.velocity_known) or self.lost:
            return "no previous-step check"
        return implausibility(
            res,
            min_eigenvalue,
            self.normal,
            np.linalg.inv(self.T_trusted) @ pose,
            np.linalg.inv(T_before_pred) @ pose,
            self._clock.duration(self.trusted_stamp, stamp),
            self._c.plausibility,
        )  # fmt: skip

    def may_have_missed(self, res: RegistrationResult, min_eigenvalue: float) -> bool:
        """Whether a registration rejected for its motion may be a true motion over sweeps
        the driver dropped: tracking holds with a known velocity, hypotheses are on and the
        registration's own quality passes the gate, or it did not converge (a start a
        dropped sweep's motion away from the truth)."""
        cfg = self._c.plausibility
        return bool(
            cfg.enabled
            and cfg.missed_frames > 0
            and not self.lost
            and self.velocity_known
            and (
                not res.converged or quality_problem(res, min_eigenvalue, self.normal, cfg) is None
            )
        )

    def explains_as_usual(self, res: RegistrationResult, min_eigenvalue: float) -> bool:
        """Whether ``res`` is as good as the running normal and not degenerate (the bar for
        a motion over dropped sweeps)."""
        floor = 1.0 / self._c.information.degenerate_factor**2
        return explains_as_usual(res, min_eigenvalue, floor, self.normal, self._c.plausibility)

    def shown_by_scan(
        self,
        res: RegistrationResult,
        pose: np.ndarray,
        first: RegistrationResult,
        first_pose: np.ndarray,
    ) -> bool:
        """Whether a motion over dropped sweeps (``res`` at ``pose``) is the scan's own
        answer rather than its start's: the registration from the constant-velocity
        prediction (``first``) agrees, or fits clearly worse (``shown_by_scan``)."""
        return shown_by_scan(res, pose, first, first_pose, self._c.plausibility)

    def relaxation(self, since: float | None, every: float | None = None) -> float:
        """Factor (1, 2, 4, ...) by which the relative tolerances are widened: doubled every
        ``every`` seconds of lost tracking (default ``max_lost_seconds``)."""
        every = self._c.max_lost_seconds if every is None else every
        if not self.lost_frames or since is None or every <= 0:
            return 1.0
        return float(2.0 ** np.floor(since / every))

    def trust(
        self,
        pose: np.ndarray,
        stamp: float,
        res: RegistrationResult | None,
        min_eigenvalue: float,
        learn: bool,
        missed: int = 0,
        steady: bool = False,
    ) -> Trusted:
        """Book-keeping of a trusted pose: the running normal learns ``res`` when ``learn``
        (the scan entered the map), a lost stretch ends. ``missed`` > 0: sweeps were dropped
        before it, the velocity is unknown until the next trusted pose. ``steady``: the pose
        lies within the gate's bound of the prediction (a short lost stretch then gives a
        velocity, ``recovered_velocity_frames``)."""
        out = Trusted()
        if res is not None and learn:
            since = self._clock.duration(self.trusted_stamp, stamp)
            fit_every = self._c.fitness_relax_seconds or None
            if max(self.relaxation(since), self.relaxation(since, fit_every)) > 1.0:
                self.normal.clear()  # lost long enough to accept a changed scene
                out.reinitialised = True
            self.normal.add(res, min_eigenvalue)
        if self.lost_frames > 0 and self.trusted_stamp is not None:
            out.recovered = True
            out.n = self.lost_frames + 1
            out.lost_for = self._clock.duration(self.trusted_stamp, stamp)
            out.T_rel = np.linalg.inv(self.T_trusted) @ pose
        self.lost_frames = 0
        self.T_trusted = pose.copy()
        self.trusted_stamp = float(stamp)
        self.n_trusted += 1
        # the velocity over dropped sweeps or a long lost stretch is a guess, not a
        # measurement; over a short one it is the mean of two trusted poses
        frames = self._c.plausibility.recovered_velocity_frames
        short = out.recovered and steady and out.n <= frames
        if missed or (out.recovered and not short):
            self.n_chained = 1
        else:
            self.n_chained = 2 if short else self.n_chained + 1
        return out

    def miss(self) -> bool:
        """A frame without a trusted pose; True when tracking was established (it is lost
        now), False while the map has not started."""
        if self.trusted_stamp is None:
            return False
        self.lost_frames += 1
        return True
