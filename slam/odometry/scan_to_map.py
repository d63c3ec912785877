"""The frame loop of a scan-to-map odometry (``process(scan) -> Odometry``).

Per scan: predict with the constant-velocity motion model, crop and deskew, register
against the map (from several starts after a long gap or while no velocity is known;
wider while tracking is lost), judge
the registration with the tracking gate, insert a trusted scan into the map once the
sensor moved, choose keyframes and their information, and update the motion model. An
implausible or failed registration is replaced by the prediction, is not inserted, and
does not teach the motion model or the gate.

A front end subclasses ``ScanToMapFrontend`` and implements ``_estimate`` (register the
scan against the map without changing it) and ``_insert`` (add a trusted scan to the map).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from slam.odometry.clock import SweepClock
from slam.odometry.config import CommonConfig
from slam.odometry.estimate import Estimate
from slam.odometry.extras import legacy_extras
from slam.odometry.gate import TrackingGate
from slam.odometry.keyframes import KeyframeDecision, KeyframePolicy
from slam.odometry.layout_time import LayoutTimeTrial
from slam.odometry.map_policy import MapInsertPolicy
from slam.odometry.motion import MotionModel
from slam.odometry.search import StartSearch
from slam.registration.gicp import RegistrationError
from slam.registration.information import information_from_hessian
from slam.registration.plausibility import near_prediction
from slam.rigid import kept_rigid
from slam.types import Odometry, OdometryDiagnostics, Scan, TrackingStatus

log = logging.getLogger(__name__)


def crop(scan: Scan, min_range: float, max_range: float) -> Scan:
    """The finite points between ``min_range`` and ``max_range`` (m), xyz float64."""
    xyz = np.asarray(scan.xyz, dtype=np.float64).reshape(-1, 3)
    r2 = np.einsum("ij,ij->i", xyz, xyz)
    ok = np.isfinite(r2) & (r2 >= min_range**2) & (r2 <= max_range**2)
    out = scan.select(ok) if not ok.all() else scan
    out.xyz = np.asarray(out.xyz, dtype=np.float64)
    return out


@dataclass
class _Frame:
    """One scan on its way through the loop."""

    index: int
    stamp: float
    diag: OdometryDiagnostics
    est: Estimate | None = None
    filtered: np.ndarray | None = None
    ground_plane: np.ndarray | None = None
    work: Scan | None = None  # the cropped, deskewed scan that was registered
    missed: int = 0  # sweeps believed dropped before it (unseen by the stamps)
    shown: bool = False  # lost: starts turned and moved apart converged to its pose
    # the previous step was judged wrong by this registration: the motion model restarts
    # from the mean over the two frames (previous_step_check)
    rewound: tuple[np.ndarray, float] | None = None
    scan_state: object = None  # the front end's per-scan state before registering it

    @property
    def timings(self) -> dict[str, float]:
        """Stage name -> wall ms (the diagnostics' own dict)."""
        return self.diag.timings_ms


class ScanToMapFrontend:
    """Scan-to-map odometry composed of a sweep clock, a motion model, a tracking gate, a
    map-insert policy and a keyframe policy."""

    def __init__(self, common: CommonConfig):
        self._c = common
        self.clock = SweepClock()
        self.motion = MotionModel(common, self.clock)
        self.gate = TrackingGate(common, self.clock)
        self.map_policy = MapInsertPolicy(common)
        self.keyframes = KeyframePolicy(common)
        self.search = StartSearch(
            common, self._estimate, self._scan_state, self._restore_scan_state
        )
        # seconds the prediction spans while ``_estimate`` registers from the constant-
        # velocity prediction of a tracked motion (a front end may take it as a prior);
        # None during searches, hypotheses and lost tracking
        self.tracked_horizon: float | None = None
        # beam-by-beam clouds without a time field: compensated or not (``layout_time``)
        self.layout_time = LayoutTimeTrial(common.layout_time)

    # ------------------------------------------------------------------ to implement
    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        """Register ``scan`` against the map from ``T_pred`` without changing the map; ``wide``:
        tracking is lost, search wider (coarse-to-fine from the prediction)."""
        raise NotImplementedError

    def _insert(self, est: Estimate, timings: dict) -> None:
        """Add the trusted scan (``est.pending``) to the map at ``est.pose``."""
        raise NotImplementedError

    def _map_size(self) -> int:
        """Points in the local map(s), for diagnostics."""
        return 0

    # ------------------------------------------------------------------ state by name
    @property
    def T_last(self) -> np.ndarray:
        """T_odom_sensor of the previous frame."""
        return self.motion.T_last

    @T_last.setter
    def T_last(self, T: np.ndarray) -> None:
        self.motion.T_last = T

    @property
    def T_motion(self) -> np.ndarray:
        """T_prev_current of the last tracked frame pair (the constant-velocity motion)."""
        return self.motion.T_motion

    @property
    def n_frames(self) -> int:
        """Frames processed so far."""
        return self.motion.n_frames

    @property
    def n_keyframes(self) -> int:
        """Keyframes chosen so far."""
        return self.keyframes.n_keyframes

    @n_keyframes.setter
    def n_keyframes(self, n: int) -> None:
        self.keyframes.n_keyframes = n

    # ------------------------------------------------------------------ the frame loop
    def process(self, scan: Scan) -> Odometry:
        """Estimate T_odom_sensor at ``scan.stamp`` (sweep start) and decide on a keyframe."""
        t0 = time.perf_counter()
        f = _Frame(scan.index, float(scan.stamp), OdometryDiagnostics(n_points=int(len(scan))))
        T_pred = self.motion.predict(scan.stamp)
        work = crop(scan, self._c.min_range, self._c.max_range)
        f.diag.n_after_crop = int(len(work))
        T_pred = self._register(scan, work, T_pred, f)
        if f.est is not None and f.diag.skipped is None:
            self._judge(f, T_pred)
        self._close_tracking(f)
        # chained poses drift off SO(3) by rounding, and the motion model feeds it back
        pose = kept_rigid(f.est.pose if f.est is not None else T_pred)
        initialising = self.keyframes.n_keyframes == 0 and f.est is None
        if initialising:  # nothing usable yet: stay at the origin, no keyframe
            pose = np.eye(4)
        kf = self._keyframe(pose, f)
        # after dropped sweeps the velocity over them is unknown: the last one stands
        if f.rewound is not None:
            T_before, span = f.rewound
            self.motion.restart(np.linalg.inv(T_before) @ pose, span, 2)
        elif f.est is not None and not f.diag.recovered and not f.missed:
            self.motion.learn(pose, scan.stamp)
        self.clock.observe(scan.stamp)
        self.motion.advance(pose, scan.stamp)
        f.timings["total_ms"] = (time.perf_counter() - t0) * 1e3
        return self._odometry(f, pose, kf, self._status(f, initialising))

    def _register(self, scan: Scan, work: Scan, T_pred: np.ndarray, f: _Frame) -> np.ndarray:
        """Deskew and register the cropped scan ``work`` of ``scan`` (``f.est``,
        ``f.filtered``); returns the prediction it started from (the best gap hypothesis
        after a long gap)."""
        if len(work) < self._c.min_points:
            f.diag.skipped = f"too few points ({len(work)} < {self._c.min_points} after range crop)"
            return T_pred
        self._before_deskew(scan, work, f.timings)
        t = time.perf_counter()
        raw = work
        work = self.motion.deskew(self.layout_time.reading(work))
        f.timings["deskew_ms"] = (time.perf_counter() - t) * 1e3
        f.work = work
        f.scan_state = self._scan_state()
        try:
            starts = self.motion.gap_hypotheses(work.stamp)
            f.diag.gap_hypotheses = len(starts)
            if starts:
                f.est, T_pred = self.search.best_after_gap(work, starts, f.timings)
            elif self.gate.n_trusted == 1:  # a map, but no velocity yet: search the motion
                since = self.clock.duration(self.gate.trusted_stamp, f.stamp)
                f.est, T_pred, n = self.search.first_motion(
                    work, T_pred, self.motion.start_hypotheses(since), f.timings, self.gate.lost
                )
                f.diag.start_hypotheses = n
            elif self.gate.lost and self._c.lost_turn_hypotheses_deg:
                # lost: the prediction may be off by a turn outside the registration's basin
                starts = self.motion.turn_hypotheses(T_pred)
                shifts = self.motion.shift_hypotheses()
                f.est, f.shown = self.search.after_turns(work, starts, shifts, f.timings)
                f.diag.turn_hypotheses = len(starts)
            else:
                self.tracked_horizon = self._tracked_horizon(f.stamp)
                step = None
                if self.tracked_horizon is not None:
                    step = float(np.linalg.norm(self.motion.T_motion[:3, 3]))
                try:
                    if self.layout_time.due(raw, step):
                        f.est, f.work = self._layout_trial(raw, work, T_pred, f)
                    else:
                        f.est = self._estimate(work, T_pred, f.timings, wide=self.gate.lost)
                finally:
                    self.tracked_horizon = None
            f.diag.skipped = f.est.skipped
            f.diag.counts = f.est.counts
            if raw.layout_time is not None:  # made-up times: whether this frame used them
                f.diag.counts["layout_time_deskewed"] = int(f.work.time is not None)
            f.diag.registration = f.est.registration
            f.ground_plane = f.est.ground_plane
        except RegistrationError as exc:
            log.warning("frame %d: registration failed (%s); using prediction", f.index, exc)
            f.diag.lost = f"registration failed: {exc}"
            f.diag.rejected = True
        has_own = f.est is not None and f.est.filtered is not None
        f.filtered = f.est.filtered if has_own else work.xyz
        return T_pred

    def _layout_trial(
        self, raw: Scan, plain: Scan, T_pred: np.ndarray, f: _Frame
    ) -> tuple[Estimate, Scan]:
        """Register ``plain`` (as read) and ``raw`` deskewed with its made-up layout times;
        the one that fits the map better is this frame's, and a vote on whether the
        clouds are motion-compensated (``LayoutTimeTrial``)."""
        plain_est = self._estimate(plain, T_pred, f.timings, wide=False)
        plain_state = self._scan_state()
        self._restore_scan_state(f.scan_state)
        timed = self.motion.deskew(self.layout_time.timed(raw))
        try:
            timed_est = self._estimate(timed, T_pred, f.timings, wide=False)
        except RegistrationError:
            timed_est = None

        def rmse(est: Estimate | None) -> float:
            ok = est is not None and est.result is not None and est.skipped is None
            return float(est.result.rmse) if ok else np.inf

        if self.layout_time.vote(rmse(plain_est), rmse(timed_est), f.index):
            return timed_est, timed
        self._restore_scan_state(plain_state)
        return plain_est, plain

    def _tracked_horizon(self, stamp: float) -> float | None:
        """Seconds from the last frame to ``stamp`` when the prediction comes from a tracked
        velocity (two chained trusted poses, tracking not lost), else None."""
        if self.gate.lost or not self.gate.velocity_known:
            return None
        gap = self.clock.since_last(stamp)
        return gap if gap is not None and gap > 0 else self.clock.period()

    def _before_deskew(self, scan: Scan, work: Scan, timings: dict) -> None:
        """Work on the cropped scan that needs no motion estimate (e.g. outlier removal),
        done before deskew so that it can run ahead of time (``look_ahead``)."""

    def look_ahead(self, scan: Scan) -> None:
        """``scan`` will be processed after the scan in hand: a front end may start its
        ``_before_deskew`` work on another thread meanwhile (same results)."""

    def _scan_state(self) -> object:
        """What ``_estimate`` changes in the front end per scan (e.g. a dynamics tracker),
        restored before each further start so that every start sees the same scan."""
        return None

    def _restore_scan_state(self, state: object) -> None:
        """Undo ``_estimate``'s per-scan changes back to ``state``."""

    def _judge(self, f: _Frame, T_pred: np.ndarray) -> None:
        """The gate's verdict on ``f.est``; a trusted scan enters the map once the sensor
        moved, and teaches the gate's normal only then."""
        est = f.est
        if est.result is not None:
            est.information = information_from_hessian(
                est.H, est.residual_variance, self._c.information
            )
            # a pose the scan showed from starts apart is not judged by the lost prediction
            f.diag.lost = self.gate.judge(
                est.result, est.information.min_eigenvalue, est.pose, T_pred, f.stamp,
                predicted=not f.shown,
            )  # fmt: skip
            if f.diag.lost is not None and self.gate.may_have_missed(
                est.result, est.information.min_eigenvalue
            ):
                self._missed_sweeps(f)
            if f.diag.lost is not None and not f.missed:
                self._previous_step(f)
            est = f.est
        if f.diag.lost is not None:
            f.diag.rejected = True
            log.info("frame %d: registration rejected (%s); using prediction", f.index, f.diag.lost)
            return
        moved = self.map_policy.wants(est.pose)
        if moved:
            t = time.perf_counter()
            self._insert(est, f.timings)
            f.timings["map_ms"] = (time.perf_counter() - t) * 1e3
            self.map_policy.inserted(est.pose)
        f.diag.map_skipped = not moved
        min_eig = est.information.min_eigenvalue if est.information is not None else np.nan
        # the normal learns only from registrations the gate could test against a prediction
        tested = self.gate.n_trusted >= 2
        # only a recovering pose needs it (``recovered_velocity_frames``)
        since = self.clock.duration(self.gate.trusted_stamp, f.stamp) if self.gate.lost else None
        steady = since is not None and near_prediction(
            self._c.plausibility, np.linalg.inv(T_pred) @ est.pose, since
        )
        trusted = self.gate.trust(
            est.pose, f.stamp, est.result, min_eig, learn=moved and tested, missed=f.missed,
            steady=steady,
        )  # fmt: skip
        f.diag.reinitialised = trusted.reinitialised
        if trusted.recovered:  # the motion model restarts from the mean over the stretch
            self.motion.restart(trusted.T_rel, trusted.lost_for, trusted.n)
            f.diag.recovered = True

    def _previous_step(self, f: _Frame) -> None:
        """The registration was rejected: was the previous step the wrong one? Believed
        when it lies within the gate's bound of the prediction from the frame before the
        last (``previous_step_check``: a step accepted 0.36 m short within the floor, and
        the next registration, right, rejected against the short velocity), within one
        frame's bound."""
        before = self.motion.before_last(f.stamp)
        if before is None:
            return
        (T_alt, span), est = before, f.est
        why = self.gate.judge_after_previous(
            est.result, est.information.min_eigenvalue, est.pose, T_alt, f.stamp
        )
        if why is not None:
            return
        log.info(
            "frame %d: the previous step was off (%s from its prediction); the registration"
            " agrees with the motion before it", f.index, f.diag.lost,
        )  # fmt: skip
        f.rewound = (self.motion.T_before, span)
        f.diag.lost = None
        f.diag.counts["previous_step_off"] = 1

    def _missed_sweeps(self, f: _Frame) -> None:
        """The registration was rejected for its motion alone: the driver may have dropped
        sweeps without a gap in the stamps. For 1..``missed_frames`` dropped sweeps, register
        also from the motion repeated over them, and judge every registration with that
        time and prediction; of those the gate believes and that explain the scan as well
        as usual, the one with the most correspondences replaces ``f.est``, when the scan
        shows it (``TrackingGate.shown_by_scan``: not where every start converges near
        itself, as along a plain street)."""
        cfg = self._c.plausibility
        preds = {k: self.motion.after_missed(f.stamp, k) for k in range(1, cfg.missed_frames + 1)}
        tried = [(f.est, self._scan_state())]
        for T_k in preds.values():
            self._restore_scan_state(f.scan_state)
            try:
                est = self._estimate(f.work, T_k, f.timings, False)
            except RegistrationError:
                continue
            if est.result is not None and est.H is not None:
                est.information = information_from_hessian(
                    est.H, est.residual_variance, self._c.information
                )
                tried.append((est, self._scan_state()))
        self._restore_scan_state(tried[0][1])
        believed = []
        for est, state in tried:
            info = est.information.min_eigenvalue
            if not self.gate.explains_as_usual(est.result, info):
                continue
            for k, T_k in preds.items():
                if self.gate.judge(est.result, info, est.pose, T_k, f.stamp, missed=k) is None:
                    believed.append((est, k, state))
                    break
        if not believed:
            return
        best, k, state = max(believed, key=lambda b: (b[0].result.num_inliers, -b[0].result.rmse))
        first = tried[0][0]
        if not self.gate.shown_by_scan(best.result, best.pose, first.result, first.pose):
            log.info(
                "frame %d: registrations from the prediction and over %d dropped sweep(s) end"
                " %.2f m apart and fit alike: a degenerate direction, no sweep assumed dropped",
                f.index, k, float(np.linalg.norm((np.linalg.inv(first.pose) @ best.pose)[:3, 3])),
            )  # fmt: skip
            return
        self._restore_scan_state(state)
        moved = float(np.linalg.norm((np.linalg.inv(self.motion.T_last) @ best.pose)[:3, 3]))
        log.info(
            "frame %d: %d sweep(s) dropped before it, moved %.2f m (%s)",
            f.index, k, moved, f.diag.lost,
        )  # fmt: skip
        f.est, f.missed, f.diag.lost = best, k, None
        f.diag.skipped, f.diag.counts = best.skipped, best.counts
        f.diag.registration, f.ground_plane = best.registration, best.ground_plane
        if best.filtered is not None:
            f.filtered = best.filtered

    def _close_tracking(self, f: _Frame) -> None:
        """A frame without a trusted pose falls back to the prediction (tracking is lost
        once it was established)."""
        d = f.diag
        if d.skipped is not None or d.lost is not None:
            f.est = None
            if self.gate.miss():
                d.lost = d.lost or d.skipped
        d.tracking_lost = d.lost is not None
        d.map_points = self._map_size()

    def _keyframe(self, pose: np.ndarray, f: _Frame) -> KeyframeDecision:
        """The keyframe decision and its diagnostics."""
        est, d = f.est, f.diag
        information = None
        if est is not None and est.H is not None:
            information = est.information or information_from_hessian(
                est.H, est.residual_variance, self._c.information
            )
            d.min_info_eigenvalue = information.min_eigenvalue
        H = None if est is None else est.H
        kf = self.keyframes.decide(pose, est is not None, information, H, f.filtered, f.timings)
        d.degenerate = kf.degenerate
        if kf.ambiguity is not None:
            d.ambiguous = bool(kf.ambiguity.ambiguous)
            d.ambiguity = kf.ambiguity.ratio
            d.ambiguity_axis = (float(kf.ambiguity.axis[0]), float(kf.ambiguity.axis[1]))
        return kf

    def _status(self, f: _Frame, initialising: bool) -> TrackingStatus:
        if initialising:
            return TrackingStatus.INITIALISING
        if f.est is not None:
            return TrackingStatus.RECOVERED if f.diag.recovered else TrackingStatus.TRACKED
        return TrackingStatus.LOST if f.diag.rejected else TrackingStatus.PREDICTED

    def _odometry(
        self, f: _Frame, pose: np.ndarray, kf: KeyframeDecision, status: TrackingStatus
    ) -> Odometry:
        ground = f.ground_plane
        extras = legacy_extras(f.diag, ground, kf.info_before_ambiguity, kf.ambiguity_ms)
        return Odometry(
            stamp=f.stamp,
            pose=pose,
            is_keyframe=kf.is_keyframe,
            relative=kf.relative,
            info=kf.info,
            cloud=kf.cloud,
            extras=extras,
            status=status,
            diagnostics=f.diag,
            ground_plane=ground,
        )
