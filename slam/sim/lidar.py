"""A ray-cast spinning 16-beam LiDAR (VLP-16-like) with per-column motion.

Each column (one azimuth, all beams) fires at its own time within the sweep and is cast
from the sensor pose at that time, so motion distorts the scan exactly like a real
spinning LiDAR. Points are returned in the sensor frame *at each point's own time*,
which is what a driver publishes; undoing the distortion needs the per-point ``time``.

Rotation is clockwise seen from above (like Velodyne): the sweep starts pointing
backwards (azimuth +pi) and passes left, front, right. Points are in firing order
(column-major, rings bottom -> top within a column), as the Velodyne driver emits them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slam.errors import InputError
from slam.types import Scan

# Intensity of spurious returns (dust, rain, multipath) is low and random.
_SPURIOUS_INTENSITY_MAX = 12.0


@dataclass
class LidarModel:
    """Sensor intrinsics. Angles in degrees, ranges in metres, rate in Hz.

    range_sigma: std-dev of Gaussian range noise (m). spurious_fraction: probability that
    a return is replaced by a point at a random range along its ray, floating in air.
    """

    beams: int = 16
    fov_deg: tuple[float, float] = (-15.0, 15.0)
    columns: int = 1800
    rate_hz: float = 10.0
    max_range: float = 100.0
    min_range: float = 0.3
    range_sigma: float = 0.01
    spurious_fraction: float = 0.005

    def __post_init__(self) -> None:
        if self.beams < 1 or self.columns < 1:
            raise InputError("LidarModel needs beams >= 1 and columns >= 1")
        if not self.fov_deg[0] < self.fov_deg[1] and self.beams > 1:
            raise InputError(f"LidarModel.fov_deg must be (low, high), got {self.fov_deg}")
        if self.rate_hz <= 0 or self.max_range <= self.min_range or self.min_range < 0:
            raise InputError("LidarModel needs rate_hz > 0 and 0 <= min_range < max_range")
        if not 0.0 <= self.spurious_fraction < 1.0 or self.range_sigma < 0:
            raise InputError("LidarModel needs 0 <= spurious_fraction < 1 and range_sigma >= 0")

    @property
    def period(self) -> float:
        """Sweep duration (s)."""
        return 1.0 / self.rate_hz

    def elevations(self) -> np.ndarray:
        """(beams,) elevation angles (rad), ring 0 at the bottom."""
        return np.deg2rad(np.linspace(self.fov_deg[0], self.fov_deg[1], self.beams))

    def azimuths(self) -> np.ndarray:
        """(columns,) azimuth (rad) of each column in firing order (clockwise from +pi)."""
        return np.pi - 2.0 * np.pi * np.arange(self.columns) / self.columns

    def column_times(self) -> np.ndarray:
        """(columns,) firing time of each column (s from the sweep start), in [0, period)."""
        return np.arange(self.columns) * (self.period / self.columns)

    def directions(self) -> np.ndarray:
        """(columns, beams, 3) unit ray directions in the sensor frame."""
        az = self.azimuths()[:, None]
        el = self.elevations()[None, :]
        ce = np.cos(el)
        return np.stack(
            np.broadcast_arrays(ce * np.cos(az), ce * np.sin(az), np.sin(el)), axis=-1
        ).astype(np.float64)


@dataclass
class RayHits:
    """First hits of a batch of rays: range (m, inf = none), reflectivity (0..1), cos of
    incidence, and a dynamic flag (hit a moving object)."""

    range: np.ndarray
    reflectivity: np.ndarray
    cos_incidence: np.ndarray
    dynamic: np.ndarray


@dataclass
class ScanTruth:
    """What the simulator knows about each point of a scan (same order as the Scan).

    true_range: noise-free range (m) along the ray. spurious: the point is a fake return.
    dynamic: the point lies on a pedestrian. column: firing column of the point.
    T_world_sensor_columns: (columns, 4, 4) sensor pose at each column's time.
    """

    true_range: np.ndarray
    spurious: np.ndarray
    dynamic: np.ndarray
    column: np.ndarray
    T_world_sensor_columns: np.ndarray


def simulate_scan_truth(
    scene,
    pose_at: Callable[[np.ndarray], np.ndarray],
    t0: float,
    model: LidarModel | None = None,
    rng: np.random.Generator | None = None,
    *,
    time_offset: float = 0.0,
) -> tuple[Scan, ScanTruth]:
    """Ray-cast one sweep starting at ``t0`` (s) and return it with per-point ground truth.

    scene: has ``cast(origins (M,3), dirs (M,3), times (M,)) -> RayHits`` in world frame.
    pose_at(times (M,)) -> (M,4,4) T_world_sensor. Scene objects that move (pedestrians)
    are evaluated at ``times - time_offset`` (scene time), poses at ``times``.
    """
    model = model or LidarModel()
    rng = rng if rng is not None else np.random.default_rng(0)
    col_t = model.column_times()
    T = np.asarray(pose_at(t0 + col_t), dtype=np.float64).reshape(model.columns, 4, 4)
    dirs_s = model.directions()  # (C, B, 3)
    dirs_w = np.matmul(dirs_s, T[:, :3, :3].transpose(0, 2, 1))
    origins = np.broadcast_to(T[:, None, :3, 3], dirs_w.shape)
    times = np.broadcast_to((t0 + col_t - time_offset)[:, None], dirs_w.shape[:2])
    hits = scene.cast(
        origins.reshape(-1, 3), dirs_w.reshape(-1, 3), times.reshape(-1), group=model.beams
    )

    true_r = hits.range
    valid = np.isfinite(true_r) & (true_r >= model.min_range) & (true_r <= model.max_range)
    idx = np.flatnonzero(valid)  # firing order: column-major, ring bottom -> top
    r_true = true_r[idx]
    n = idx.size
    r = r_true + rng.normal(0.0, model.range_sigma, n) if model.range_sigma > 0 else r_true.copy()
    refl = hits.reflectivity[idx]
    cosi = np.abs(hits.cos_incidence[idx])
    # Intensity 0..255 like a Velodyne: reflectivity x incidence with mild range falloff.
    intensity = 255.0 * refl * (0.35 + 0.65 * cosi) / (1.0 + (r_true / 60.0) ** 2)
    intensity = np.clip(intensity + rng.normal(0.0, 1.5, n), 0.0, 255.0)

    # Spurious returns: a random point along the ray, >= 1 m in front of the true surface.
    # Drawn among returns far enough away so that the overall rate matches the model.
    lo = max(model.min_range, 0.5)
    eligible = r_true > lo + 1.5
    p = model.spurious_fraction * n / max(int(eligible.sum()), 1)
    spurious = eligible & (rng.random(n) < p)
    k = int(spurious.sum())
    if k:
        r[spurious] = lo + rng.random(k) * (r_true[spurious] - 1.0 - lo)
        intensity[spurious] = rng.random(k) * _SPURIOUS_INTENSITY_MAX
    r = np.clip(r, model.min_range, model.max_range)

    xyz = dirs_s.reshape(-1, 3)[idx] * r[:, None]
    column = (idx // model.beams).astype(np.int32)
    scan = Scan(
        stamp=float(t0),
        xyz=xyz,
        intensity=intensity.astype(np.float32),
        ring=(idx % model.beams).astype(np.int16),
        time=col_t[column].astype(np.float64),
    )
    truth = ScanTruth(
        true_range=r_true,
        spurious=spurious,
        dynamic=hits.dynamic[idx] & ~spurious,
        column=column,
        T_world_sensor_columns=T,
    )
    return scan, truth


def simulate_scan(
    scene,
    pose_at: Callable[[np.ndarray], np.ndarray],
    t0: float,
    model: LidarModel | None = None,
    rng: np.random.Generator | None = None,
    *,
    time_offset: float = 0.0,
) -> Scan:
    """Ray-cast one sweep starting at ``t0`` (s): Scan(stamp=t0, xyz in the sensor frame at
    each point's own time, intensity 0..255, ring 0..beams-1 bottom->top, time s from t0)."""
    return simulate_scan_truth(scene, pose_at, t0, model, rng, time_offset=time_offset)[0]
