"""A ray-cast spinning multi-beam LiDAR (VLP-16-like by default) with per-column motion.

The beam elevations are uniform over ``fov_deg`` or an explicit per-beam table
(``elevations_deg``, e.g. the two non-uniform blocks of an HDL-64E); the named sensor
models (VLP-16, HDL-32E, HDL-64E, OS1-128) live in :mod:`slam.sim.sensors`.

Each column (one azimuth, all beams) fires at its own time within the sweep and is cast
from the sensor pose at that time, so motion distorts the scan exactly like a real
spinning LiDAR. Points are returned in the sensor frame *at each point's own time*,
which is what a driver publishes; undoing the distortion needs the per-point ``time``.

Rotation is clockwise seen from above (like Velodyne): the sweep starts pointing
backwards (azimuth +pi) and passes left, front, right. Points are in firing order
(column-major, rings bottom -> top within a column), as the Velodyne driver emits them.

Optional error sources (all off by default, see :meth:`LidarModel.realistic`): per-beam
calibration errors (the ray really travels along a slightly different direction than the
driver assumes, and its range has a per-beam offset), range noise growing with range, and
mixed pixels (a return at a depth edge lands between foreground and background).
Porous vegetation is a property of the scene (see :class:`slam.sim.scene.Scene`).
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

    Realism options (all 0 = off by default):

    range_sigma_per_m: range noise grows with range, sigma = range_sigma + this * r.
    calib_elevation_deg, calib_azimuth_deg, calib_range_m: std-dev of per-beam calibration
    errors, drawn once per sensor from ``calibration_seed`` (see :meth:`calibration`). The
    ray travels along the true (perturbed) direction; the driver publishes the point along
    the nominal direction at the measured range plus the beam's range offset.
    mixed_pixel_prob: probability that a return at a depth discontinuity between
    neighbouring columns of the same beam (range gap in [mixed_pixel_min_gap,
    mixed_pixel_max_gap] m) is a mixed pixel: the beam footprint (divergence ~3 mrad)
    straddles the edge and the echoes of foreground and background merge into one at a
    random range in between (a "veil" point floating in air behind the edge). Larger gaps
    give two separable echoes (the strongest wins), smaller ones are the same surface.

    elevations_deg: explicit per-beam elevation table (deg, ascending: ring 0 at the
    bottom, ``beams`` entries) for sensors with non-uniform beam spacing; None = uniform
    over ``fov_deg``.
    """

    beams: int = 16
    fov_deg: tuple[float, float] = (-15.0, 15.0)
    columns: int = 1800
    rate_hz: float = 10.0
    max_range: float = 100.0
    min_range: float = 0.3
    range_sigma: float = 0.01
    spurious_fraction: float = 0.005
    range_sigma_per_m: float = 0.0
    calib_elevation_deg: float = 0.0
    calib_azimuth_deg: float = 0.0
    calib_range_m: float = 0.0
    calibration_seed: int = 0
    mixed_pixel_prob: float = 0.0
    mixed_pixel_min_gap: float = 0.3
    mixed_pixel_max_gap: float = 5.0
    elevations_deg: tuple[float, ...] | None = None

    @classmethod
    def realistic(cls, calibration_seed: int = 0, **overrides) -> LidarModel:
        """A VLP-16 with the error sources of a real, factory-calibrated unit.

        Values (plausible, not a particular unit):
        - range accuracy: the VLP-16 datasheet states +-3 cm typical; here 1.2 cm + 0.2 mm/m
          (1-sigma 1.4 cm at 10 m, 2.2 cm at 50 m).
        - per-beam calibration: the driver's per-laser angles and range offsets are off by
          ~0.1-0.2 deg and a few cm on uncalibrated units (the order of magnitude that
          Velodyne intrinsic-calibration studies report, e.g. Glennie & Lichti 2010 for
          the HDL-64E S2, Glennie et al. 2016 for the VLP-16): here 0.1 deg elevation,
          0.1 deg azimuth, 2 cm range (1-sigma per beam).
        - mixed pixels: beam divergence ~3 mrad is about one column step (0.2 deg = 3.5
          mrad) at 10 Hz, so edge footprints often straddle; 30 % of edge returns mix when
          the surfaces are 0.3-5 m apart along the ray.
        - spurious returns (dust, multipath) 0.5 % as in the default model.
        """
        values = dict(
            range_sigma=0.012,
            range_sigma_per_m=0.0002,
            spurious_fraction=0.005,
            calib_elevation_deg=0.1,
            calib_azimuth_deg=0.1,
            calib_range_m=0.02,
            calibration_seed=calibration_seed,
            mixed_pixel_prob=0.3,
            mixed_pixel_min_gap=0.3,
            mixed_pixel_max_gap=5.0,
        )
        values.update(overrides)
        return cls(**values)

    def __post_init__(self) -> None:
        if self.beams < 1 or self.columns < 1:
            raise InputError("LidarModel needs beams >= 1 and columns >= 1")
        if not self.fov_deg[0] < self.fov_deg[1] and self.beams > 1:
            raise InputError(f"LidarModel.fov_deg must be (low, high), got {self.fov_deg}")
        if self.rate_hz <= 0 or self.max_range <= self.min_range or self.min_range < 0:
            raise InputError("LidarModel needs rate_hz > 0 and 0 <= min_range < max_range")
        if not 0.0 <= self.spurious_fraction < 1.0 or self.range_sigma < 0:
            raise InputError("LidarModel needs 0 <= spurious_fraction < 1 and range_sigma >= 0")
        if min(self.range_sigma_per_m, self.calib_elevation_deg, self.calib_azimuth_deg) < 0:
            raise InputError("LidarModel noise and calibration std-devs must be >= 0")
        if self.calib_range_m < 0:
            raise InputError("LidarModel.calib_range_m must be >= 0")
        if not 0.0 <= self.mixed_pixel_prob <= 1.0:
            raise InputError("LidarModel needs 0 <= mixed_pixel_prob <= 1")
        if not 0.0 <= self.mixed_pixel_min_gap < self.mixed_pixel_max_gap:
            raise InputError("LidarModel needs 0 <= mixed_pixel_min_gap < mixed_pixel_max_gap")
        if self.elevations_deg is not None:
            el = np.asarray(self.elevations_deg, dtype=float)
            if el.shape != (self.beams,) or np.any(np.diff(el) <= 0):
                raise InputError(
                    f"LidarModel.elevations_deg needs {self.beams} ascending angles (deg), "
                    f"got {len(el)}"
                )

    @property
    def has_calibration_error(self) -> bool:
        """False when the nominal rays and ranges are exact (no calibration error)."""
        return bool(self.calib_elevation_deg or self.calib_azimuth_deg or self.calib_range_m)

    def calibration(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-beam calibration errors: elevation (rad), azimuth (rad) and range (m)
        offsets, each (beams,), drawn from ``calibration_seed`` (fixed for a sensor)."""
        rng = np.random.default_rng([self.calibration_seed, 1601])
        z = rng.standard_normal((3, self.beams))
        return (
            np.deg2rad(self.calib_elevation_deg) * z[0],
            np.deg2rad(self.calib_azimuth_deg) * z[1],
            self.calib_range_m * z[2],
        )

    def true_directions(self) -> np.ndarray:
        """(columns, beams, 3) unit directions the rays really travel (sensor frame): the
        nominal ones perturbed by the per-beam elevation and azimuth errors."""
        if self.calib_elevation_deg == 0 and self.calib_azimuth_deg == 0:
            return self.directions()
        d_el, d_az, _ = self.calibration()
        return _unit_dirs(self.azimuths()[:, None] + d_az[None, :], self.elevations() + d_el)

    @property
    def period(self) -> float:
        """Sweep duration (s)."""
        return 1.0 / self.rate_hz

    def elevations(self) -> np.ndarray:
        """(beams,) elevation angles (rad), ring 0 at the bottom."""
        if self.elevations_deg is not None:
            return np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))
        return np.deg2rad(np.linspace(self.fov_deg[0], self.fov_deg[1], self.beams))

    def azimuths(self) -> np.ndarray:
        """(columns,) azimuth (rad) of each column in firing order (clockwise from +pi)."""
        return np.pi - 2.0 * np.pi * np.arange(self.columns) / self.columns

    def column_times(self) -> np.ndarray:
        """(columns,) firing time of each column (s from the sweep start), in [0, period)."""
        return np.arange(self.columns) * (self.period / self.columns)

    def directions(self) -> np.ndarray:
        """(columns, beams, 3) unit ray directions in the sensor frame."""
        return _unit_dirs(self.azimuths()[:, None], self.elevations())


def _unit_dirs(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """(C, B, 3) unit vectors from azimuths (C, 1) or (C, B) and elevations (B,) (rad)."""
    el = el[None, :]
    ce = np.cos(el)
    return np.stack(
        np.broadcast_arrays(ce * np.cos(az), ce * np.sin(az), np.sin(el)), axis=-1
    ).astype(np.float64)


@dataclass
class RayHits:
    """First hits of a batch of rays: range (m, inf = none), reflectivity (0..1), cos of
    incidence, a dynamic flag (hit a moving object) and a porous flag (a return from
    inside porous vegetation; None = no porous geometry)."""

    range: np.ndarray
    reflectivity: np.ndarray
    cos_incidence: np.ndarray
    dynamic: np.ndarray
    porous: np.ndarray | None = None


@dataclass
class ScanTruth:
    """What the simulator knows about each point of a scan (same order as the Scan).

    true_range: noise-free range (m) along the ray (to the first surface, or to the return
    inside porous vegetation). spurious: the point is a fake return. dynamic: the point
    lies on a pedestrian. column: firing column of the point.
    T_world_sensor_columns: (columns, 4, 4) sensor pose at each column's time.
    mixed: the point is a mixed pixel (between foreground and background at an edge).
    porous: the return comes from inside porous vegetation.
    ray_dir: (N, 3) direction the ray really travelled (sensor frame; differs from the
    published direction with calibration errors): the true hit is ray_dir * true_range.
    """

    true_range: np.ndarray
    spurious: np.ndarray
    dynamic: np.ndarray
    column: np.ndarray
    T_world_sensor_columns: np.ndarray
    mixed: np.ndarray | None = None
    porous: np.ndarray | None = None
    ray_dir: np.ndarray | None = None


def _cast_sweep(
    scene,
    T: np.ndarray,
    times: np.ndarray,
    ray_s: np.ndarray,
    beams: int,
    rng: np.random.Generator,
) -> RayHits:
    """First hits of every ray of a sweep: ray directions ray_s (C, B, 3, sensor frame) from
    each column's pose T (C, 4, 4), the scene evaluated at times (C,) (s, scene time)."""
    dirs_w = np.matmul(ray_s, T[:, :3, :3].transpose(0, 2, 1))
    origins = np.broadcast_to(T[:, None, :3, 3], dirs_w.shape)
    times = np.broadcast_to(times[:, None], dirs_w.shape[:2])
    cast_kw = {"rng": rng} if getattr(scene, "porous_vertices", None) is not None else {}
    return scene.cast(
        origins.reshape(-1, 3),
        dirs_w.reshape(-1, 3),
        times.reshape(-1),
        group=beams,
        **cast_kw,
    )


def _noisy_ranges(r_mix: np.ndarray, model: LidarModel, rng: np.random.Generator) -> np.ndarray:
    """(n,) measured ranges (m): r_mix plus Gaussian noise of sigma range_sigma (+
    range_sigma_per_m x range when that grows with range)."""
    n = len(r_mix)
    if model.range_sigma_per_m > 0:
        sigma = model.range_sigma + model.range_sigma_per_m * r_mix
        return r_mix + rng.standard_normal(n) * sigma
    if model.range_sigma > 0:
        return r_mix + rng.normal(0.0, model.range_sigma, n)
    return r_mix.copy()


def _intensities(
    hits: RayHits,
    idx: np.ndarray,
    r_true: np.ndarray,
    mixed: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n,) intensity 0..255 like a Velodyne: reflectivity x incidence with mild range (m)
    falloff and noise; halved for mixed pixels (the pulse energy is split)."""
    n = idx.size
    refl = hits.reflectivity[idx]
    cosi = np.abs(hits.cos_incidence[idx])
    intensity = 255.0 * refl * (0.35 + 0.65 * cosi) / (1.0 + (r_true / 60.0) ** 2)
    intensity = np.clip(intensity + rng.normal(0.0, 1.5, n), 0.0, 255.0)
    if mixed.any():
        intensity[mixed] *= 0.5  # the pulse energy is split between two surfaces
    return intensity


def _spurious_returns(
    r: np.ndarray,
    intensity: np.ndarray,
    r_true: np.ndarray,
    model: LidarModel,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n,) flags of spurious returns, whose range (m) and intensity are overwritten in place:
    a random point along the ray, >= 1 m in front of the true surface, drawn among returns
    far enough away so that the overall rate matches spurious_fraction."""
    n = len(r)
    lo = max(model.min_range, 0.5)
    eligible = r_true > lo + 1.5
    p = model.spurious_fraction * n / max(int(eligible.sum()), 1)
    spurious = eligible & (rng.random(n) < p)
    k = int(spurious.sum())
    if k:
        r[spurious] = lo + rng.random(k) * (r_true[spurious] - 1.0 - lo)
        intensity[spurious] = rng.random(k) * _SPURIOUS_INTENSITY_MAX
    return spurious


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
    dirs_s = model.directions()  # (C, B, 3) nominal: what the driver publishes along
    ray_s = model.true_directions() if model.has_calibration_error else dirs_s
    hits = _cast_sweep(scene, T, t0 + col_t - time_offset, ray_s, model.beams, rng)
    true_r = hits.range
    valid = np.isfinite(true_r) & (true_r >= model.min_range) & (true_r <= model.max_range)
    idx = np.flatnonzero(valid)  # firing order: column-major, ring bottom -> top
    r_true = true_r[idx]
    n = idx.size
    mixed = np.zeros(n, dtype=bool)
    r_mix = r_true
    if model.mixed_pixel_prob > 0:
        mixed, r_mix = _mixed_pixels(true_r, valid, hits.porous, idx, model, rng)
    r = _noisy_ranges(r_mix, model, rng)
    intensity = _intensities(hits, idx, r_true, mixed, rng)
    spurious = _spurious_returns(r, intensity, r_true, model, rng)
    ring = idx % model.beams
    if model.calib_range_m > 0:
        r = r + model.calibration()[2][ring]  # the beam's range offset
    r = np.clip(r, model.min_range, model.max_range)
    xyz = dirs_s.reshape(-1, 3)[idx] * r[:, None]
    column = (idx // model.beams).astype(np.int32)
    porous = hits.porous[idx] if hits.porous is not None else np.zeros(n, dtype=bool)
    scan = Scan(
        stamp=float(t0),
        xyz=xyz,
        intensity=intensity.astype(np.float32),
        ring=ring.astype(np.int16),
        time=col_t[column].astype(np.float64),
    )
    truth = ScanTruth(
        true_range=r_true,
        spurious=spurious,
        dynamic=hits.dynamic[idx] & ~spurious,
        column=column,
        T_world_sensor_columns=T,
        mixed=mixed & ~spurious,
        porous=porous & ~spurious,
        ray_dir=ray_s.reshape(-1, 3)[idx],
    )
    return scan, truth


def _mixed_pixels(
    true_r: np.ndarray,
    valid: np.ndarray,
    porous: np.ndarray | None,
    idx: np.ndarray,
    model: LidarModel,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Mixed pixels at depth edges: (n,) flags and ranges of the valid returns ``idx``.

    A return is at an edge when the return of the same beam in a neighbouring column (the
    previous or next azimuth step) differs by a gap in [min_gap, max_gap]; with
    probability ``mixed_pixel_prob`` its range becomes a uniform mix between its own and
    that neighbour's (the larger gap if both neighbours qualify). Pairs of two foliage
    returns (``porous`` (M,)) do not count: those are scattered in depth already."""
    C, B = model.columns, model.beams
    grid = np.where(valid, true_r, np.nan).reshape(C, B)
    leafy = np.zeros((C, B), dtype=bool) if porous is None else porous.reshape(C, B)
    best = np.zeros((C, B))  # signed gap to the chosen neighbour (0 = none)
    for shift in (1, -1):
        nb = np.full((C, B), np.nan)
        nb_leafy = np.zeros((C, B), dtype=bool)
        if shift == 1:
            nb[1:], nb_leafy[1:] = grid[:-1], leafy[:-1]
        else:
            nb[:-1], nb_leafy[:-1] = grid[1:], leafy[1:]
        gap = nb - grid
        with np.errstate(invalid="ignore"):
            ok = (np.abs(gap) >= model.mixed_pixel_min_gap) & (
                np.abs(gap) <= model.mixed_pixel_max_gap
            )
            better = ok & ~(leafy & nb_leafy) & (np.abs(gap) > np.abs(best))
        best = np.where(better, gap, best)
    gap = best.reshape(-1)[idx]
    edge = np.flatnonzero(gap != 0)
    mixed = np.zeros(idx.size, dtype=bool)
    r = true_r[idx].copy()
    if edge.size:
        sel = edge[rng.random(edge.size) < model.mixed_pixel_prob]
        mixed[sel] = True
        r[sel] += rng.uniform(0.05, 0.95, sel.size) * gap[sel]
    return mixed, r


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
