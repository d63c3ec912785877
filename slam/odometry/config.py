"""Settings every scan-to-map front end has (the one source of their defaults)."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam.frontend import KeyframeConfig
from slam.registration.ambiguity import OdometryAmbiguityConfig
from slam.registration.information import InformationConfig
from slam.registration.plausibility import PlausibilityConfig


@dataclass
class CommonConfig:
    """Settings every scan-to-map front end has.

    min_range / max_range: crop (m). min_points: fewer valid points -> the frame is skipped
    (the prediction is returned). deskew: motion-compensate with the filtered frame-to-frame
    twist when the scan has per-point time (else the time from the firing order).
    constant_velocity: initial guess = last pose x last motion (else the last pose).
    deskew_smoothing in [0, 1): weight of the past in the exponential filter of the twist
    used for deskewing; it breaks the feedback loop registration error -> wrong velocity ->
    distorted next scan on weakly constrained axes.
    cloud_voxel (m): ``Odometry.cloud`` on keyframes is the filtered, deskewed scan (sensor
    frame) thinned to one real point per voxel, float32 and C-contiguous; (0, 3) elsewhere.
    drift_translation / drift_rotation_deg_per_m: odometry drift per metre travelled added
    to the covariance of the keyframe-to-keyframe motion.
    plausibility: the gate of each registration (``slam.registration.plausibility``).
    recovery_correspondence_factor: while tracking is lost, a coarse registration with this
    many times the correspondence distance runs from the prediction before the normal one.
    max_lost_seconds: every this many seconds of lost tracking the gate's relative
    tolerances double, so that a scene that changed for good is accepted again while a
    blinded sensor stays rejected for longer; an acceptance with relaxed tolerances starts
    a new running normal. 0 = never relax. fitness_relax_seconds: the fitness ratios double
    every this many seconds instead (0 = with the others): a residual that rose with the
    scene is believed again within a few frames.
    max_extrapolation_seconds: the prediction spans a gap between scans up to this long.
    gap_hypotheses_after: after a gap of this many frame durations the registration starts
    from several points along the extrapolated motion, one every gap_hypothesis_step metres
    within what gap_acceleration (m/s^2) changes over the gap, and keeps the one that
    explains the most of the scan (0 = off).
    start_max_speed (m/s) / start_speed_step (m/s): while no velocity has been measured
    (the first registration of a run, until one is trusted), the registration starts from
    the last pose moved by every speed step up to +-start_max_speed along the sensor's x
    and y axes over the time since it, and keeps the one that explains the most of the
    scan: a recording that starts mid-drive is not assumed at rest (0 = off). The
    registration from the prediction stands unless it failed or did not converge, or a
    hypothesis converged more than start_min_shift (m) away from it with more than
    start_min_gain (fraction) more correspondences.
    map_min_translation / map_min_rotation_deg: a trusted scan enters the map (and the
    gate's running normal) only once the sensor moved this far (m) or turned this much (deg)
    since the last one that did: a standing sensor's scans resample the same rays and would
    pull departing scans back to rest. 0 = every trusted scan.
    odometry_ambiguity: degeneracy-aware keyframe information (off by default;
    ``slam.registration.ambiguity``); the poses are not affected.
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
    start_max_speed: float = 40.0
    start_speed_step: float = 20.0
    start_min_shift: float = 0.1
    start_min_gain: float = 0.02
    map_min_translation: float = 0.01
    map_min_rotation_deg: float = 0.2
    odometry_ambiguity: OdometryAmbiguityConfig = field(default_factory=OdometryAmbiguityConfig)
