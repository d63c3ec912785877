"""Is a scan-to-map registration believable? Tests relative to the run's own normal.

A registration that ends on its iteration cap, or whose fitness (RMSE of inlier
distances) is many times the recent median, or which found a correspondence for far fewer
source points than usual, or which moves the sensor faster than a vehicle can or far from
the constant-velocity prediction, is not a measurement of the motion: the sensor is blinded
(a bush, a truck beside it), the view changed or the solver slid into a wrong minimum.
Such a result must feed neither the map nor the motion model.

Fitness and inlier share depend on the scene (sensor noise, foliage, map density), so they
are judged against running medians of the accepted registrations, never against absolute
numbers tuned to one scene. Motion is judged against physics: speed and turn rate bounds
(m/s, deg/s) and how far a bounded acceleration can take the sensor from the
constant-velocity prediction over the time since the last trusted registration.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from slam.errors import ConfigError
from slam.registration.gicp import RegistrationResult


@dataclass
class PlausibilityConfig:
    """Gate of a registration: relative tests against running medians of trusted frames, and
    physical bounds. Why the values: docs/robustness.md (What the front end does with bad
    motion)."""

    enabled: bool = True
    window: int = 50  # trusted frames in the running medians
    warmup: int = 5  # trusted frames before the relative tests apply
    max_fitness_ratio: float = 3.0  # RMSE above this x the median RMSE: implausible
    min_inlier_ratio: float = 0.5  # inlier share below this x the median share: implausible
    # likewise for the number of correspondences (a blinded sensor registers a hundred close
    # points where the scene gave thousands)
    min_support_ratio: float = 0.2
    # likewise for the smallest eigenvalue of the normalised information
    # (``information.information_from_hessian``)
    min_information_ratio: float = 1e-3
    max_speed: float = 40.0  # m/s
    max_turn_rate_deg: float = 180.0  # deg/s
    # how far the pose may leave the constant-velocity prediction: 0.5 a T^2 over the time T
    # since the last trusted pose (m/s^2, deg/s^2) plus the floors (m, deg: estimate noise)
    max_acceleration: float = 20.0
    max_angular_acceleration_deg: float = 720.0
    prediction_floor: float = 0.3  # improved_floam: 0.1
    prediction_floor_deg: float = 3.0
    # a registration flagged not converged (iteration cap, stalled) is believed only when
    # its RMSE is within this factor of the median (never before there is a median)
    unconverged_fitness_ratio: float = 1.5
    # a registration rejected only for its motion may follow frames the driver dropped with
    # stamps that do not show it: up to this many missed frames are hypothesised (0 = off),
    # each with its time and motion, and believed only when the registration also passes
    # the quality tests, covers the scan as usual (inlier share at least
    # ``missed_inlier_ratio`` x the median) and is not degenerate (a slide along a corridor is)
    missed_frames: int = 2
    missed_inlier_ratio: float = 0.9
    # ... and the scan itself must show it: the registration from the constant-velocity
    # prediction ends within the prediction floor of it, or covers a share of the scan this
    # much smaller (inlier share, absolute). Along a plain street every start converges near
    # itself, so there the start, not the scan, would choose the motion.
    missed_min_gain: float = 0.05
    # a registration rejected only for its motion may show that the previous step was the
    # wrong one (accepted within the floor, 0.3 m short at 25 m/s): when it lies within the
    # bound of the prediction from the motion before that step (two frames on), it is
    # believed and the velocity restarts from the two frames' mean
    previous_step_check: bool = True
    # a lost stretch of at most this many frames (the lost ones and the one that recovers)
    # whose recovering pose lies within the bound of the prediction gives the next frame a
    # velocity to be judged by, the mean over the stretch: a registration that then slides
    # 0.5 m back along a motorway is rejected (0: never). A recovering pose off the
    # prediction (a true jump over a dropped sweep) leaves the velocity unknown.
    recovered_velocity_frames: int = 2

    def __post_init__(self) -> None:
        if self.window < 1 or self.warmup < 0:
            raise ConfigError("plausibility window must be >= 1 and warmup >= 0")
        ratios = (self.min_inlier_ratio, self.min_support_ratio, self.min_information_ratio)
        if self.max_fitness_ratio <= 1.0 or not all(0.0 <= r < 1.0 for r in ratios):
            raise ConfigError(
                "plausibility needs max_fitness_ratio > 1 and min_inlier_ratio,"
                " min_support_ratio, min_information_ratio in [0, 1)"
            )
        if self.missed_frames < 0 or not 0 <= self.missed_inlier_ratio <= 1:
            raise ConfigError(
                "plausibility missed_frames must be >= 0 and missed_inlier_ratio in [0, 1]"
            )
        if not 0 <= self.missed_min_gain <= 1:
            raise ConfigError("plausibility missed_min_gain must be in [0, 1] (inlier share)")
        if min(self.max_speed, self.max_turn_rate_deg) <= 0:
            raise ConfigError("plausibility max_speed and max_turn_rate_deg must be > 0")


def relaxed(
    cfg: PlausibilityConfig, factor: float, fitness_factor: float | None = None
) -> PlausibilityConfig:
    """``cfg`` with its relative tolerances widened ``factor`` times (1 = unchanged), the
    fitness ratios ``fitness_factor`` times (default ``factor``); the physical motion
    bounds stay."""
    fitness_factor = factor if fitness_factor is None else fitness_factor
    if factor == 1.0 and fitness_factor == 1.0:
        return cfg
    return replace(
        cfg,
        max_fitness_ratio=cfg.max_fitness_ratio * fitness_factor,
        unconverged_fitness_ratio=cfg.unconverged_fitness_ratio * fitness_factor,
        min_inlier_ratio=cfg.min_inlier_ratio / factor,
        min_support_ratio=cfg.min_support_ratio / factor,
        min_information_ratio=cfg.min_information_ratio / factor,
    )


def motion_magnitude(T: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (deg) of a 4x4 relative pose."""
    cos = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


class RunningNormal:
    """Running medians over the last trusted registrations: RMSE (m), inlier share, number of
    correspondences and the smallest eigenvalue of the normalised information."""

    _FIELDS = ("rmse", "inlier_ratio", "num_inliers", "information")

    def __init__(self, window: int):
        self._values = {k: deque(maxlen=window) for k in self._FIELDS}

    def __len__(self) -> int:
        return len(self._values["rmse"])

    def add(self, res: RegistrationResult, information: float) -> None:
        """Record a trusted registration and its information's smallest eigenvalue."""
        if np.isfinite(res.rmse) and np.isfinite(information):
            values = (res.rmse, res.inlier_ratio, res.num_inliers, information)
            for k, v in zip(self._FIELDS, values, strict=True):
                self._values[k].append(float(v))

    def clear(self) -> None:
        for v in self._values.values():
            v.clear()

    def median(self, name: str) -> float:
        """Running median of one of ``rmse``, ``inlier_ratio``, ``num_inliers``,
        ``information`` (nan while empty)."""
        v = self._values[name]
        return float(np.median(v)) if v else float("nan")


def explains_as_usual(
    res: RegistrationResult,
    information: float,
    min_information: float,
    normal: RunningNormal,
    cfg: PlausibilityConfig,
) -> bool:
    """Whether ``res`` converged, passes the quality tests, covers the scan about as well
    as the running normal (``missed_inlier_ratio``) and is not degenerate (``information``,
    the smallest eigenvalue of the normalised information, >= ``min_information``): the bar
    for believing a motion the stamps do not explain. False without a normal."""
    if len(normal) < max(cfg.warmup, 1) or not res.converged:
        return False
    return bool(
        quality_problem(res, information, normal, cfg) is None
        and res.inlier_ratio >= cfg.missed_inlier_ratio * normal.median("inlier_ratio")
        and information >= min_information
    )


def shown_by_scan(
    res: RegistrationResult,
    pose: np.ndarray,
    first: RegistrationResult,
    first_pose: np.ndarray,
    cfg: PlausibilityConfig,
) -> bool:
    """Whether the scan itself shows a motion over dropped sweeps (``res`` at ``pose``),
    not only the start it was registered from: the registration from the constant-velocity
    prediction (``first`` at ``first_pose``) ends within the prediction floor of it, or
    covers at least ``missed_min_gain`` less of the scan (it converged to a worse minimum)."""
    t, r = motion_magnitude(np.linalg.inv(first_pose) @ pose)
    if t <= cfg.prediction_floor and r <= cfg.prediction_floor_deg:
        return True
    return bool(res.inlier_ratio >= first.inlier_ratio + cfg.missed_min_gain)


def quality_problem(
    res: RegistrationResult, information: float, normal: RunningNormal, cfg: PlausibilityConfig
) -> str | None:
    """Why the registration's own quality (convergence, fitness m, inlier share, support,
    information) falls short of the running normal, or None."""
    have_normal = len(normal) >= max(cfg.warmup, 1)
    rmse = normal.median("rmse")
    if not res.converged and (not have_normal or res.rmse > cfg.unconverged_fitness_ratio * rmse):
        return (
            f"registration {res.stop_reason} after {res.iterations} iterations,"
            f" fitness {res.rmse:.3f} m"
        )
    if not have_normal:
        return None
    if res.rmse > cfg.max_fitness_ratio * rmse:
        return f"fitness {res.rmse:.3f} m > {cfg.max_fitness_ratio:g} x median {rmse:.3f} m"
    share = normal.median("inlier_ratio")
    if res.inlier_ratio < cfg.min_inlier_ratio * share:
        return (
            f"inlier share {res.inlier_ratio:.2f} < {cfg.min_inlier_ratio:g} x median {share:.2f}"
        )
    count = normal.median("num_inliers")
    if res.num_inliers < cfg.min_support_ratio * count:
        return f"{res.num_inliers} correspondences < {cfg.min_support_ratio:g} x median {count:.0f}"
    info = normal.median("information")
    if information < cfg.min_information_ratio * info:
        return f"information {information:.2g} < {cfg.min_information_ratio:g} x median {info:.2g}"
    return None


def prediction_bound(cfg: PlausibilityConfig, elapsed: float) -> float:
    """How far (m) a pose may leave the constant-velocity prediction over ``elapsed`` s:
    the floor plus what the bounded acceleration allows, a T^2 / 2."""
    return cfg.prediction_floor + 0.5 * cfg.max_acceleration * elapsed**2


def turn_bound(cfg: PlausibilityConfig, elapsed: float) -> float:
    """How far (deg) a pose may turn off the constant-velocity prediction over ``elapsed`` s:
    the floor plus what the bounded angular acceleration allows."""
    return cfg.prediction_floor_deg + 0.5 * cfg.max_angular_acceleration_deg * elapsed**2


def near_prediction(cfg: PlausibilityConfig, T_pred_current: np.ndarray, elapsed: float) -> bool:
    """Whether a pose ``T_pred_current`` off the constant-velocity prediction over
    ``elapsed`` s is within the gate's bound of it (translation and rotation)."""
    t, r = motion_magnitude(T_pred_current)
    return t <= prediction_bound(cfg, elapsed) and r <= turn_bound(cfg, elapsed)


def _motion_problem(
    T_trusted_current: np.ndarray,
    T_pred_current: np.ndarray,
    elapsed: float,
    cfg: PlausibilityConfig,
) -> str | None:
    """Why the motion over ``elapsed`` (s) is not physical: speed (m/s), turn rate (deg/s), or
    a departure from the constant-velocity prediction beyond what the bounded (angular)
    acceleration allows; None when it is."""
    t, r = motion_magnitude(T_trusted_current)
    if t > cfg.max_speed * elapsed:
        return f"speed {t / elapsed:.1f} m/s > {cfg.max_speed:g} m/s"
    if r > cfg.max_turn_rate_deg * elapsed:
        return f"turn rate {r / elapsed:.0f} deg/s > {cfg.max_turn_rate_deg:g} deg/s"
    t, r = motion_magnitude(T_pred_current)
    lim_t = prediction_bound(cfg, elapsed)
    lim_r = turn_bound(cfg, elapsed)
    if t > lim_t:
        return f"{t:.2f} m from the constant-velocity prediction (> {lim_t:.2f} m)"
    if r > lim_r:
        return f"{r:.1f} deg from the constant-velocity prediction (> {lim_r:.1f} deg)"
    return None


def implausibility(
    res: RegistrationResult,
    information: float,
    normal: RunningNormal,
    T_trusted_current: np.ndarray,
    T_pred_current: np.ndarray,
    elapsed: float | None,
    cfg: PlausibilityConfig,
) -> str | None:
    """Why ``res`` is not believable, or None when it is.

    information: smallest eigenvalue of the result's normalised information.
    T_trusted_current: the registered pose relative to the last trusted pose (the previous
    frame while tracking); T_pred_current: relative to the constant-velocity prediction;
    elapsed (s): time since the last trusted pose (the prediction drifts with it). Without
    a time the motion tests are skipped.
    """
    if not cfg.enabled:
        return None
    problem = quality_problem(res, information, normal, cfg)
    if problem is not None or elapsed is None or not elapsed > 0:
        return problem
    return _motion_problem(T_trusted_current, T_pred_current, elapsed, cfg)
