"""What the scan-to-map front ends share: cropping, constant-velocity prediction, deskew,
keyframe selection, information of the keyframe-to-keyframe motion, never crashing on a
bad scan, and not believing a registration that is implausible (lost tracking).

A front end subclasses ``ScanToMapFrontend`` and implements ``_estimate`` (register the
scan against the map, without changing the map) and ``_insert`` (add a trusted scan to
the map). Between the two the frame loop judges the registration
(``slam.registration.plausibility``): an implausible one is replaced by the
constant-velocity prediction, is not inserted into the map, does not update the motion
model or the deskew twist, and the frame is flagged (``extras["lost"]`` = the reason,
``extras["rejected"]`` = 1; ``extras["tracking_lost"]`` = 1 also for frames skipped while
tracking, e.g. too few points; the counters are 0/1 on every frame, as is
``extras["recovered"]``). While tracking is lost the next scans are registered with a wider
search (coarse pass with ``recovery_correspondence_factor`` times the correspondence
distance from the prediction, then the normal pass), and the first plausible result
re-acquires the map (``extras["recovered"]`` = 1).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slam.deskew import deskew, se3_log, time_from_firing_order
from slam.features.thinning import voxel_thin
from slam.frontend import KeyframeConfig, is_new_keyframe
from slam.registration.ambiguity import (
    OdometryAmbiguityConfig,
    loosened_information,
    odometry_ambiguity,
)
from slam.registration.gicp import RegistrationError, RegistrationResult, se3_exp
from slam.registration.information import (
    Information,
    InformationConfig,
    default_information,
    information_from_hessian,
)
from slam.registration.plausibility import (
    PlausibilityConfig,
    RunningNormal,
    implausibility,
    motion_magnitude,
    relaxed,
)
from slam.rigid import kept_rigid
from slam.types import Odometry, Scan

log = logging.getLogger(__name__)


def _off_duration(ratio: float) -> bool:
    """Whether a frame gap ``ratio`` times the motion model's duration is a different
    duration (a dropped message, a burst) rather than stamp jitter: outside [2/3, 3/2]."""
    return not 2.0 / 3.0 <= ratio <= 1.5


@dataclass
class CommonConfig:
    """Settings every scan-to-map front end has.

    min_range/max_range: crop (m). min_points: fewer valid points -> the frame is skipped
    (constant-velocity prediction returned). deskew: motion-compensate with the previous
    frame's motion when the scan has per-point time. constant_velocity: initial guess =
    last pose x last motion (else the last pose). deskew_smoothing in [0, 1): weight of the
    past in an exponential filter of the frame-to-frame twist used for deskewing; it breaks
    the feedback loop (a registration error -> a wrong velocity -> a distorted next scan ->
    a new error) that a raw last-motion deskew closes on weakly constrained axes.
    cloud_voxel: voxel (m) of ``Odometry.cloud``: on keyframes the filtered, deskewed scan
    (sensor frame) voxel-downsampled to this size (one real point per voxel), float32 and
    C-contiguous, so the pipeline stores it as given (the one copy the loop verification
    reads); empty (0, 3) on other frames.
    drift_translation / drift_rotation_deg_per_m: odometry drift per metre travelled added to
    the covariance of the keyframe-to-keyframe motion.
    plausibility: the gate of each registration (see ``slam.registration.plausibility``).
    recovery_correspondence_factor: while tracking is lost, a coarse registration with this
    many times the correspondence distance runs from the prediction before the normal one.
    max_lost_seconds: every this many seconds of lost tracking the relative tolerances of
    the gate are doubled (fitness and unconverged ratios x2, inlier/support/information
    ratios /2), so that a scene that changed for good (an open field after a built-up
    street) is accepted again after a while, while a sensor blinded by something moving
    with it (correspondences ~0.08 x normal) stays rejected for longer; a registration
    accepted with relaxed tolerances starts a new running normal
    (``extras["reinitialised"]`` = 1). 0 = never relax.
    max_extrapolation_seconds: the constant-velocity prediction spans a gap between scans
    (dropped messages, a stalled driver) up to this long; beyond it the motion stops there.
    gap_hypotheses_after: after a gap of this many frame durations (two scans missing or
    more) the registration starts from several points along the extrapolated motion, one
    every gap_hypothesis_step metres within what gap_acceleration (m/s^2, a car's firm
    braking or acceleration) changes over the gap, and keeps the one that explains the
    most of the scan (0 = off).
    fitness_relax_seconds: the fitness ratios (plain and unconverged) double every this many
    seconds of lost tracking instead (0 = with the others): a residual that rose with the
    scene (a normal set while the car stood, a street opening up) is believed again within
    a few frames instead of seconds of dead reckoning. With 5 s an urban HDL-64E run whose
    normal came from its slow start lost 75 of 100 frames and ended 30 m off, every
    rejected registration right (APE 1.9 cm with the gate's fitness test off); with 0.5 s
    it lost 4 (4.8 cm).
    map_min_translation / map_min_rotation_deg: a trusted scan enters the map (and the
    gate's running normal) only once the sensor has moved this far (m) or turned this much
    (deg) since the last scan that did: a standing sensor's scans do not. They sample the
    same spots on the same rays, so in the map the k neighbours of a point became repeated
    samples of one ray (a covariance along the ray instead of the surface), GICP snapped
    the departing scans back onto them (toward zero motion), and the gate's normal learned
    a fitness (2-5 mm) no moving scan has and rejected the departure. Street scene,
    HDL-64E, 200 frames from a 1 s standstill: improved_floam 98 frames rejected, 41 m APE
    -> 2.8 m (5 cm / 0.5 deg gave 0.81 m there but mapped a 0.2 m/s start every third
    frame, and the slow corridor starts lost frames). 1 cm: every frame of a sensor moving
    0.1 m/s or more at 10 Hz. 0 = every trusted scan (the old behaviour).
    odometry_ambiguity: degeneracy-aware keyframe odometry information (off by default;
    ``slam.registration.ambiguity.OdometryAmbiguityConfig``): a keyframe whose alignment
    is not unique along the registration's weakest horizontal direction (the slide test
    against the previous keyframes' clouds) gets a loose sigma along it, so that a graph
    with loops puts a corridor slip where it happened. The poses are not affected.
    """

    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    information: InformationConfig = field(default_factory=InformationConfig)
    deskew: bool = True
    constant_velocity: bool = True
    min_range: float = 0.5
    max_range: float = 100.0
    min_points: int = 100
    cloud_voxel: float = 0.15
    deskew_smoothing: float = 0.7
    drift_translation: float = 0.01
    drift_rotation_deg_per_m: float = 0.1
    plausibility: PlausibilityConfig = field(default_factory=PlausibilityConfig)
    recovery_correspondence_factor: float = 3.0
    max_lost_seconds: float = 5.0
    fitness_relax_seconds: float = 0.5
    max_extrapolation_seconds: float = 3.0
    gap_hypotheses_after: float = 3.0
    gap_hypothesis_step: float = 2.0
    gap_acceleration: float = 3.0
    map_min_translation: float = 0.01
    map_min_rotation_deg: float = 0.2
    odometry_ambiguity: OdometryAmbiguityConfig = field(default_factory=OdometryAmbiguityConfig)


@dataclass
class Estimate:
    """What ``_estimate`` returns: the pose T_odom_sensor, registration Hessian/variance (or
    None when there was nothing to register against), diagnostics, the registration result
    (None without one), ``pending``: what ``_insert`` adds to the map if it is trusted, and
    the registration's information once computed."""

    pose: np.ndarray
    H: np.ndarray | None = None
    residual_variance: float = 1.0
    extras: dict = field(default_factory=dict)
    result: RegistrationResult | None = None
    pending: object = None
    information: Information | None = None

    @classmethod
    def from_registration(cls, res: RegistrationResult, extras: dict) -> Estimate:
        """From a RegistrationResult; its diagnostics are recorded in ``extras``."""
        extras.update(
            iterations=res.iterations,
            fitness=res.fitness,
            converged=res.converged,
            inliers=res.num_inliers,
            inlier_ratio=res.inlier_ratio,
        )
        return cls(
            res.T_target_source,
            H=res.H,
            residual_variance=res.cost / max(res.dof, 1),
            extras=extras,
            result=res,
        )


class ScanToMapFrontend:
    """Frame loop of a scan-to-map odometry; ``process(scan) -> Odometry``."""

    def __init__(self, common: CommonConfig):
        self._c = common
        self.T_last = np.eye(4)  # T_odom_sensor of the previous processed frame
        self.T_motion = np.eye(4)  # T_prev_current of the last frame pair
        self.T_kf = np.eye(4)
        self.last_stamp: float | None = None
        self.motion_dt: float | None = None
        self.twist = np.zeros(6)  # filtered (omega, v) per frame, for deskew
        self.n_frames = 0
        self.n_keyframes = 0
        # tracking: running normal of trusted registrations, the last trusted pose
        self.normal = RunningNormal(common.plausibility.window)
        self.n_trusted = 0  # trusted poses so far (the first frame included)
        self.lost_frames = 0  # consecutive frames without a trusted registration
        self.T_trusted = np.eye(4)
        self.T_inserted: np.ndarray | None = None  # pose of the last scan put in the map
        self.trusted_stamp: float | None = None
        self.trusted_frames_ago = 0
        self._gaps: deque[float] = deque(maxlen=100)  # recent stamp gaps (s)
        # (T_odom_sensor, cloud in the sensor frame) of the last keyframes: the slide test's
        # target (odometry_ambiguity)
        self._kf_clouds: deque[tuple[np.ndarray, np.ndarray]] = deque(
            maxlen=common.odometry_ambiguity.window
        )

    # ------------------------------------------------------------------ to implement
    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        """Register ``scan`` against the map from ``T_pred`` without changing the map; ``wide``:
        tracking is lost, search wider (coarse-to-fine from the prediction)."""
        raise NotImplementedError

    def _insert(self, est: Estimate, timings: dict) -> None:
        """Add the trusted scan (``est.pending``) to the map at ``est.pose``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ helpers
    def _crop(self, scan: Scan) -> Scan:
        xyz = np.asarray(scan.xyz, dtype=np.float64).reshape(-1, 3)
        r2 = np.einsum("ij,ij->i", xyz, xyz)
        ok = np.isfinite(r2) & (r2 >= self._c.min_range**2) & (r2 <= self._c.max_range**2)
        out = scan.select(ok) if not ok.all() else scan
        out.xyz = np.asarray(out.xyz, dtype=np.float64)
        return out

    def _deskew(self, scan: Scan) -> Scan:
        if not self._c.deskew or self.motion_dt is None or len(scan) == 0:
            return scan
        period = float(self.motion_dt)
        time = scan.time
        if time is None:
            # a driver without a time field (and a cloud the pipeline could not read one
            # from: column by column, as Velodyne drivers store it): the time from the
            # azimuth along the firing order. Without it a VLP-16 bag without ring/time at
            # 12-15 m/s went undeskewed (urban, 400 frames: APE 0.072 -> 0.396 m)
            time = time_from_firing_order(scan.xyz, self._sweep_period())
            if time is None:
                return scan
        if not np.any(time > 0):
            return scan
        xyz = deskew(scan.xyz, time, se3_exp(self.twist), period)
        return Scan(scan.stamp, xyz, scan.intensity, scan.ring, time, scan.index)

    def _sweep_period(self) -> float:
        """The sensor's sweep period (s) from the recent stamp gaps: their span over the
        sweeps they hold (each gap rounded to whole multiples of their median), so that
        neither dropped messages nor stamp jitter change it (+-20 ms jitter: the median of
        the gaps alone is ~3 % off, a 4.5 cm deskew error at the end of a 15 m/s sweep;
        over the last 100 gaps ~0.3 %). ``motion_dt`` before any gap."""
        if not self._gaps:
            return float(self.motion_dt)
        gaps = np.asarray(self._gaps)
        sweeps = np.maximum(1.0, np.round(gaps / np.median(gaps)))
        return float(gaps.sum() / sweeps.sum())

    def _duration(self, t0: float | None, t1: float) -> float | None:
        """Time (s) the sensor moved between the scans stamped ``t0`` and ``t1`` (None when
        ``t1`` is not after ``t0``): a whole number of sweep periods, the stamp gap rounded
        to it (at least one). A spinning LiDAR's scans are whole turns, so a gap of 1.4
        periods is one period and late stamps, not 1.4 periods of motion: header stamps
        taken when the driver got the data jitter by tens of ms, and with the raw gaps
        (+-20 ms on the urban drive at 12-15 m/s) the prediction was scaled to 0.6-1.4
        periods, 85 of 400 registrations were rejected and the written poses jumped by up
        to 1.8 m. Until a few gaps give the period, and for a gap within 1e-4 periods of a
        whole number of them (exact stamps), the gap is taken as it is."""
        if t0 is None or not t1 > t0:
            return None
        gap = float(t1) - float(t0)
        if len(self._gaps) < 3:
            return gap
        period = self._sweep_period()
        whole = max(1.0, float(np.round(gap / period))) * period
        return gap if abs(gap - whole) <= 1e-4 * period else whole

    def _keyframe_information(self, info_reg: np.ndarray, relative: np.ndarray) -> np.ndarray:
        """Information of T_prevkf_current: the registration's covariance plus drift ~ distance."""
        dist = float(np.linalg.norm(relative[:3, 3]))
        cov = np.linalg.inv(info_reg)
        s_t = self._c.drift_translation * dist
        s_r = np.radians(self._c.drift_rotation_deg_per_m) * dist
        cov = cov + np.diag([s_r**2] * 3 + [s_t**2] * 3)
        info = np.linalg.inv(cov)
        return 0.5 * (info + info.T)

    def _ambiguity_information(
        self, info: np.ndarray, H: np.ndarray, pose: np.ndarray, cloud: np.ndarray, extras: dict
    ) -> np.ndarray:
        """A keyframe's odometry information after the slide test (``odometry_ambiguity``)
        of its cloud against the previous keyframes' (moved into its frame by the odometry);
        records ``ambiguity`` (ratio), ``ambiguous`` (0/1) and the tested axis
        (``ambiguity_axis_x/y``, sensor frame) in ``extras``."""
        c = self._c.odometry_ambiguity
        t = time.perf_counter()
        inv = np.linalg.inv(pose)
        parts = []
        for T_kf, pts in self._kf_clouds:
            T = inv @ T_kf
            parts.append(pts @ T[:3, :3].T + T[:3, 3])
        target = np.concatenate(parts) if parts else np.zeros((0, 3))
        amb = odometry_ambiguity(cloud, target, H, c)
        extras.update(
            ambiguity=amb.ratio,
            ambiguous=int(amb.ambiguous),
            ambiguity_axis_x=float(amb.axis[0]),
            ambiguity_axis_y=float(amb.axis[1]),
        )
        if amb.ambiguous:
            extras["_info_before_ambiguity"] = info
            info = loosened_information(info, amb.axis, c.sigma)
        extras["ambiguity_ms"] = (time.perf_counter() - t) * 1e3
        return info

    # ------------------------------------------------------------------ tracking
    def _judge(self, est: Estimate, stamp: float, T_pred: np.ndarray) -> str | None:
        """Why the registration in ``est`` is not believable (None: trust it)."""
        res = est.result
        if res is None:  # nothing to register against yet: the map is being started
            return None
        est.information = information_from_hessian(
            est.H, est.residual_variance, self._c.information
        )
        since = self._duration(self.trusted_stamp, stamp)
        # the constant-velocity prediction is a measurement only once two trusted poses gave
        # it a velocity: a drive that starts at car speed has none on its first registration
        off_prediction = np.linalg.inv(T_pred) @ est.pose if self.n_trusted >= 2 else np.eye(4)
        return implausibility(
            res,
            est.information.min_eigenvalue,
            self.normal,
            np.linalg.inv(self.T_trusted) @ est.pose,
            off_prediction,
            since,
            relaxed(
                self._c.plausibility,
                self._relaxation(since),
                self._relaxation(since, self._c.fitness_relax_seconds or None),
            ),
        )

    def _relaxation(self, since: float | None, every: float | None = None) -> float:
        """Factor (1, 2, 4, ...) by which the gate's relative tolerances are widened: doubled
        every ``every`` seconds of lost tracking (default ``max_lost_seconds``)."""
        every = self._c.max_lost_seconds if every is None else every
        if not self.lost_frames or since is None or every <= 0:
            return 1.0
        return float(2.0 ** np.floor(since / every))

    def _moved_since_insert(self, pose: np.ndarray) -> bool:
        """Whether ``pose`` is far enough from the last scan put in the map to add a new one
        (``map_min_translation`` / ``map_min_rotation_deg``)."""
        if self.T_inserted is None:
            return True
        t, r = motion_magnitude(np.linalg.inv(self.T_inserted) @ pose)
        return t >= self._c.map_min_translation or r >= self._c.map_min_rotation_deg

    def _trust(self, est: Estimate, stamp: float, extras: dict, learn: bool = True) -> None:
        """Book-keeping of a trusted registration: running normal (only when ``learn``: the
        scan entered the map), re-acquired motion."""
        if est.result is not None and learn:
            since = self._duration(self.trusted_stamp, stamp)
            fit_every = self._c.fitness_relax_seconds or None
            if max(self._relaxation(since), self._relaxation(since, fit_every)) > 1.0:
                # lost long enough to accept a changed scene: a new normal starts
                self.normal.clear()
                extras["reinitialised"] = 1
            self.normal.add(est.result, est.information.min_eigenvalue)
        if self.lost_frames > 0 and self.trusted_stamp is not None:
            # the motion model restarts from the mean motion over the lost stretch
            n = self.lost_frames + 1
            lost_for = self._duration(self.trusted_stamp, stamp)
            if lost_for is not None:
                self.motion_dt = lost_for / n
            rho, phi = se3_log(np.linalg.inv(self.T_trusted) @ est.pose)
            self.T_motion = se3_exp(np.concatenate([phi, rho]) / n)
            self.twist = np.concatenate([phi, rho]) / n
            extras["recovered"] = 1
        self.lost_frames = 0
        self.T_trusted = est.pose.copy()
        self.trusted_stamp = float(stamp)
        self.n_trusted += 1

    def _motion_to(self, stamp: float) -> np.ndarray:
        """The constant-velocity motion from the last frame to ``stamp``: ``T_motion`` as it
        is while the gap is within a third of its own duration (``motion_dt``), else scaled
        along its twist to the gap (a dropped message or a stalled driver, up to
        ``max_extrapolation_seconds``): at 12 m/s one missing scan otherwise puts the
        prediction 1.2 m short, every registration from it is rejected as implausible and
        tracking is lost for a while (urban drive with every 7th scan dropped: 29 of 89
        frames lost, APE 5 -> 64 cm). A braking car leaves the extrapolation 0.5 a T^2
        behind (4 m after 2 s at 2 m/s^2); stopping it at 1 s put it 12 m short after a
        2 s stall at 12 m/s instead, and the registration ended 2.8 m off."""
        gap = self._duration(self.last_stamp, stamp)
        if self.motion_dt is None or gap is None or self.motion_dt <= 0:
            return self.T_motion
        ratio = gap / self.motion_dt
        if not _off_duration(ratio):
            return self.T_motion
        rho, phi = se3_log(self.T_motion)
        limit = max(self._c.max_extrapolation_seconds / self.motion_dt, 1.0)
        return se3_exp(np.concatenate([phi, rho]) * min(ratio, limit))

    def _gap_hypotheses(self, stamp: float) -> list[np.ndarray]:
        """Initial guesses after a long gap (``gap_hypotheses_after`` frames or more without a
        scan: a stalled driver, a recorder pause), else []: over a gap T the car may have
        braked or sped up, so the constant-velocity motion is tried every
        ``gap_hypothesis_step`` metres within +-0.5 ``gap_acceleration`` T^2 of its
        extrapolation (urban-gap20: the car 19.4 m on after 2.1 s, the extrapolation 26 m,
        the old 1 s one 12 m)."""
        c = self._c
        gap = self._duration(self.last_stamp, stamp)
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
        rho, phi = se3_log(self.T_motion)
        twist = np.concatenate([phi, rho]) * span / self.motion_dt
        reach = float(np.linalg.norm(twist[3:]))
        if reach < 1e-3:  # standing: no direction to search along
            return [self.T_last @ se3_exp(twist)]
        spread = 0.5 * c.gap_acceleration * span**2  # braking or speeding up over the gap
        lo, hi = max(reach - spread, 0.0) / reach, (reach + spread) / reach
        n = int(min(np.ceil((hi - lo) * reach / max(c.gap_hypothesis_step, 1e-3)), 24)) + 1
        return [self.T_last @ se3_exp(twist * f) for f in np.linspace(lo, hi, n)]

    def _best_of(
        self, work: Scan, starts: list[np.ndarray], timings: dict
    ) -> tuple[Estimate, np.ndarray]:
        """The registration (wide search) from each start that explains the most of the scan
        (most correspondences, the consensus; fitness breaks ties), and its start. Along a
        street the wrong alignments fit tighter (RMSE 0.28 vs 0.36 m after urban-gap20's
        stall) but on fewer points (2216-3131 vs 3415)."""
        tried = []
        for T0 in starts:
            try:
                tried.append((self._estimate(work, T0, timings, wide=True), T0))
            except RegistrationError:
                continue
        if not tried:
            raise RegistrationError("no registration converged from any gap hypothesis")
        scored = [(e, T0) for e, T0 in tried if e.result is not None]
        if not scored:
            return tried[0]
        return max(scored, key=lambda et: (et[0].result.num_inliers, -et[0].result.rmse))

    # ------------------------------------------------------------------ main loop
    def process(self, scan: Scan) -> Odometry:
        """Estimate T_odom_sensor at ``scan.stamp`` (sweep start) and decide on a keyframe."""
        t0 = time.perf_counter()
        timings: dict[str, float] = {}
        T_pred = (
            self.T_last @ self._motion_to(scan.stamp)
            if self._c.constant_velocity
            else self.T_last.copy()
        )
        # 0/1 counters on every frame: summed (or averaged) over a run by the pipeline
        extras: dict = {"n_points": int(len(scan)), "rejected": 0, "recovered": 0}
        extras["map_skipped"] = 0
        extras["reinitialised"] = 0
        skipped = None
        lost = None
        est = None
        filtered = None
        work = self._crop(scan)
        extras["n_after_crop"] = int(len(work))
        if len(work) < self._c.min_points:
            skipped = f"too few points ({len(work)} < {self._c.min_points} after range crop)"
        else:
            t = time.perf_counter()
            work = self._deskew(work)
            timings["deskew_ms"] = (time.perf_counter() - t) * 1e3
            try:
                starts = self._gap_hypotheses(scan.stamp)
                if starts:
                    est, T_pred = self._best_of(work, starts, timings)
                    extras["gap_hypotheses"] = len(starts)
                else:
                    est = self._estimate(work, T_pred, timings, wide=self.lost_frames > 0)
                extras.update(est.extras)
                skipped = est.extras.get("skipped")
            except RegistrationError as exc:
                log.warning("frame %d: registration failed (%s); using prediction", scan.index, exc)
                lost = f"registration failed: {exc}"
                extras["rejected"] = 1
            filtered = extras.pop("_filtered_xyz", work.xyz)
        if est is not None and skipped is None:
            lost = self._judge(est, float(scan.stamp), T_pred)
            if lost is not None:
                extras["rejected"] = 1
                log.info("frame %d: registration rejected (%s); using prediction", scan.index, lost)
            else:
                moved = self._moved_since_insert(est.pose)
                if moved:
                    t = time.perf_counter()
                    self._insert(est, timings)
                    timings["map_ms"] = (time.perf_counter() - t) * 1e3
                    self.T_inserted = est.pose.copy()
                extras["map_skipped"] = int(not moved)
                self._trust(est, float(scan.stamp), extras, learn=moved)
        if skipped is not None or lost is not None:
            est = None
            if self.trusted_stamp is not None:  # tracking was established: now it is lost
                self.lost_frames += 1
                lost = lost or skipped
        if lost is not None:
            extras["lost"] = lost
        extras["tracking_lost"] = int(lost is not None)
        extras["map_points"] = self._map_size()

        # chained poses drift off SO(3) by rounding, and the motion model feeds it back
        pose = kept_rigid(est.pose if est is not None else T_pred)
        first = self.n_keyframes == 0
        if first and est is None:
            # nothing usable yet: stay at the origin, no keyframe
            pose = np.eye(4)
        relative = np.linalg.inv(self.T_kf) @ pose if not first else np.eye(4)
        if est is not None and est.H is not None:
            inf = est.information or information_from_hessian(
                est.H, est.residual_variance, self._c.information
            )
            info_reg, degenerate = inf.info, inf.degenerate
            extras["min_info_eigenvalue"] = inf.min_eigenvalue
        else:
            info_reg, degenerate = default_information(self._c.information), est is None
        is_kf = est is not None and (first or is_new_keyframe(relative, self._c.keyframe))
        info = self._keyframe_information(info_reg, relative)
        cloud = np.zeros((0, 3), dtype=np.float32)
        if filtered is not None and is_kf:
            # only keyframes keep a cloud (the pipeline stores it; the first frame always
            # becomes one): no voxel pass over the scans in between
            t = time.perf_counter()
            kept = voxel_thin(filtered, self._c.cloud_voxel)
            cloud = np.ascontiguousarray(filtered[kept], dtype=np.float32)
            timings["cloud_ms"] = (time.perf_counter() - t) * 1e3
        extras["ambiguous"] = 0
        if is_kf and self._c.odometry_ambiguity.enabled:
            if not first and est.H is not None and len(self._kf_clouds):
                info = self._ambiguity_information(info, est.H, pose, cloud, extras)
            if len(cloud):
                self._kf_clouds.append((pose.copy(), np.asarray(cloud, dtype=np.float64)))
        if is_kf:
            self.T_kf = pose.copy()
            self.n_keyframes += 1
        # motion model: frame-to-frame motion and its duration; a frame on the prediction
        # (lost) keeps the motion model and the deskew twist as they were
        if est is not None and extras["recovered"] == 0:
            dt_before = self.motion_dt
            gap = self._duration(self.last_stamp, scan.stamp)
            if gap is not None:
                self.motion_dt = gap  # T_motion's duration
            self.T_motion = np.linalg.inv(self.T_last) @ pose
            rho, phi = se3_log(self.T_motion)
            a = self._c.deskew_smoothing if self.n_frames > 1 else 0.0
            # the smoothed twist spans motion_dt (the deskew period): after a gap it is
            # rescaled to the new duration before the new motion is mixed in
            ratio = 1.0 if dt_before is None else self.motion_dt / dt_before
            old = self.twist * ratio if _off_duration(ratio) else self.twist
            self.twist = a * old + (1.0 - a) * np.concatenate([phi, rho])
        if self.last_stamp is not None and scan.stamp > self.last_stamp:
            self._gaps.append(float(scan.stamp) - self.last_stamp)
        self.T_last = pose.copy()
        self.last_stamp = float(scan.stamp)
        self.n_frames += 1
        extras["degenerate"] = bool(degenerate)
        if skipped is not None:
            extras["skipped"] = skipped
        timings["total_ms"] = (time.perf_counter() - t0) * 1e3
        extras.update(timings)
        return Odometry(
            stamp=float(scan.stamp),
            pose=pose,
            is_keyframe=is_kf,
            relative=relative,
            info=info,
            cloud=cloud,
            extras=extras,
        )

    def _map_size(self) -> int:
        """Points in the local map(s), for diagnostics."""
        return 0
