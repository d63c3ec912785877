"""Settings every scan-to-map front end has (the one source of their defaults)."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam.errors import ConfigError
from slam.frontend import KeyframeConfig
from slam.odometry.layout_time import LayoutTimeConfig
from slam.registration.ambiguity import OdometryAmbiguityConfig
from slam.registration.information import InformationConfig
from slam.registration.plausibility import PlausibilityConfig

# CommonConfig fields that are counts, distances (m), angles (deg), durations (s), speeds or
# rates: a negative value has no meaning (0 switches several of them off)
NON_NEGATIVE = (
    "min_points",
    "drift_translation",
    "drift_rotation_deg_per_m",
    "max_lost_seconds",
    "fitness_relax_seconds",
    "max_extrapolation_seconds",
    "gap_hypotheses_after",
    "gap_hypothesis_step",
    "gap_acceleration",
    "start_max_speed",
    "start_speed_step",
    "start_max_shift",
    "start_min_shift",
    "start_min_turn_deg",
    "map_min_translation",
    "map_min_rotation_deg",
)


def check_positive(cfg: object, section: str, names: tuple[str, ...]) -> None:
    """ConfigError naming ``section.name``, its value and the rule when one is not > 0."""
    for name in names:
        value = getattr(cfg, name)
        if not value > 0:
            raise ConfigError(f"{section}.{name} must be > 0, got {value}")


def check_non_negative(cfg: object, section: str, names: tuple[str, ...]) -> None:
    """ConfigError naming ``section.name``, its value and the rule when one is negative."""
    for name in names:
        value = getattr(cfg, name)
        if not value >= 0:
            raise ConfigError(f"{section}.{name} must be >= 0, got {value}")


@dataclass
class CommonConfig:
    """Settings every scan-to-map front end has; distances in m, times in s. What each
    tracking safeguard does on real and simulated data: docs/robustness.md."""

    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    information: InformationConfig = field(default_factory=InformationConfig)
    # motion-compensate with the filtered frame-to-frame twist (per-point time from the scan,
    # else from the firing order)
    deskew: bool = True
    constant_velocity: bool = True  # initial guess = last pose x last motion (else last pose)
    min_range: float = 0.5  # crop
    max_range: float = 100.0  # crop
    min_points: int = 100  # fewer valid points: the frame is skipped (the prediction returned)
    # keyframes' ``Odometry.cloud``: the filtered, deskewed scan thinned to one point per voxel
    cloud_voxel: float = 0.15
    # weight in [0, 1) of the past in the filter of the deskew twist: breaks the feedback
    # registration error -> wrong velocity -> distorted next scan on weak axes
    deskew_smoothing: float = 0.7
    drift_translation: float = 0.01  # odometry drift per metre, added to keyframe covariances
    drift_rotation_deg_per_m: float = 0.1  # likewise, deg per metre
    plausibility: PlausibilityConfig = field(default_factory=PlausibilityConfig)  # the gate
    # while tracking is lost, a coarse registration with this many times the correspondence
    # distance runs from the prediction first
    recovery_correspondence_factor: float = 3.0
    # while tracking is lost the gate's support and information tolerances double every this
    # long (a changed scene is accepted again, a blinded sensor later); 0 = never
    max_lost_seconds: float = 5.0
    fitness_relax_seconds: float = 0.5  # likewise for its fitness ratios (0 = with the others)
    max_extrapolation_seconds: float = 3.0  # longest gap between scans the prediction spans
    # after a gap of this many frame durations the registration starts from several points
    # along the extrapolated motion and keeps the one that explains most of the scan (0 = off)
    gap_hypotheses_after: float = 3.0
    gap_hypothesis_step: float = 2.0  # m between those starts
    gap_acceleration: float = 3.0  # m/s^2: how far the motion may have changed over the gap
    # until a velocity is trusted, the first registrations also start from the last pose
    # moved at every speed step up to +-start_max_speed (m/s) along x and y (0 = off) ...
    start_max_speed: float = 40.0
    start_speed_step: float = 20.0  # m/s
    start_max_shift: float = 2.0  # m: at most this far apart (slow frame rates: finer steps)
    # ... and such a start replaces the prediction's result only when it converged this far
    # (m) from it and explains the scan better by this share (``slam.odometry.search``:
    # the share more correspondences plus start_rmse_weight x the share lower RMSE), or the
    # prediction's did not converge
    start_min_shift: float = 0.1
    start_min_gain: float = 0.02
    start_rmse_weight: float = 0.5
    # while tracking is lost, the registration also starts from the prediction turned by
    # +-each of these angles (deg) about the sensor's z axis, and one replaces the
    # prediction's as a speed hypothesis does (converged start_min_turn_deg away or
    # start_min_shift m, explains better): a hand-held sensor that turned 30 deg over a
    # dropped sweep lies outside GICP's basin from the prediction (() = off) ...
    lost_turn_hypotheses_deg: tuple[float, ...] = (15.0, 30.0, 45.0)
    start_min_turn_deg: float = 2.0
    # ... and where another of those starts, and along each of x and y a start moved by
    # +-this much (m) from the kept pose, converged to it, the scan shows it: it is not
    # judged against the lost prediction (its quality and rates still are; () = always)
    lost_shift_hypotheses_m: tuple[float, ...] = (0.5,)
    # a trusted scan enters the map and the gate's normal only after this much motion since
    # the last one that did: a standing sensor's scans would pull departing ones back to rest
    map_min_translation: float = 0.01
    map_min_rotation_deg: float = 0.2
    # degeneracy-aware keyframe information (``slam.registration.ambiguity``); poses unchanged
    odometry_ambiguity: OdometryAmbiguityConfig = field(default_factory=OdometryAmbiguityConfig)
    # beam-by-beam clouds without a time field: deskew with times from the azimuth only
    # once registrations at speed show they are not motion-compensated
    layout_time: LayoutTimeConfig = field(default_factory=LayoutTimeConfig)

    def __post_init__(self) -> None:
        if not (self.min_range >= 0 and self.max_range > 0 and self.min_range < self.max_range):
            raise ConfigError(
                f"frontend.min_range ({self.min_range} m) must be >= 0 and below "
                f"frontend.max_range ({self.max_range} m): the crop keeps the points between"
            )
        check_positive(self, "frontend", ("cloud_voxel", "recovery_correspondence_factor"))
        check_non_negative(self, "frontend", NON_NEGATIVE)
        if not 0 <= self.deskew_smoothing < 1:
            raise ConfigError(
                f"frontend.deskew_smoothing must be in [0, 1) (the weight of the past in the "
                f"filtered deskew twist), got {self.deskew_smoothing}"
            )
