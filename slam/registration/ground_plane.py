"""The ground as a plane in GICP: ground returns constrain height, roll and pitch only.

A spinning LiDAR samples flat ground on rings centred under the sensor, a pattern that moves
with the sensor. Eq. (1) on those samples (one ring, or two rings metres apart) gives
covariances thin across the ring, so GICP pairs a scan's rings with the map's rings and is
pulled towards zero motion: on a road with few other features (a motorway, a wide avenue)
and a young map this pull wins (simulated motorway at 9 m/s: 0.2-0.3 m per frame found for
0.9 m). Flat ground tells nothing along itself, so its points keep their spread along the
plane's normal and get ``in_plane_sigma`` along it (docs/paper000.md, "The ground's rings").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError


@dataclass
class GroundPlaneConfig:
    """enabled: ground features act as planes. The ground: the lowest z band (``bin`` m) around
    the sensor (``min_range``..``max_range`` m horizontally) holding at least ``min_share`` of
    those points, refined by two least-squares fits to the points within ``band`` m of it;
    kept when its normal is within ``max_tilt_deg`` of the sensor's z axis. in_plane_sigma
    (m): the ground points' standard deviation along the plane. min_beams: sensors of fewer
    beams keep eq. (1) on the ground (the 1238 m 16-beam urban drive, two seeds, APE 0.76 ->
    0.91 m and 0.94 -> 1.06 m with the plane; docs/paper000.md)."""

    enabled: bool = True
    min_beams: int = 32
    min_range: float = 2.0
    max_range: float = 30.0
    bin: float = 0.2
    min_share: float = 0.1
    band: float = 0.1
    max_tilt_deg: float = 15.0
    in_plane_sigma: float = 3.0

    def __post_init__(self) -> None:
        if not 0 <= self.min_range < self.max_range:
            raise ConfigError("ground: need 0 <= min_range < max_range (m)")
        if self.bin <= 0 or self.band <= 0 or self.in_plane_sigma <= 0:
            raise ConfigError("ground: bin, band and in_plane_sigma must be > 0 m")
        if self.min_beams < 0:
            raise ConfigError(f"ground: min_beams must be >= 0, got {self.min_beams}")
        if not 0 < self.min_share <= 1 or not 0 < self.max_tilt_deg <= 90:
            raise ConfigError("ground: min_share in (0, 1], max_tilt_deg in (0, 90]")


@dataclass
class FixedNormals:
    """Plane points whose normal is known: ``rows`` (N,) bool of a point set, ``normal`` (3,)
    unit vector in the sensor frame (the scan's fitted ground: the map neighbours of a ground
    point lie on one or two rings, whose fitted plane may stand across them and hold the scan
    at the map's rings; docs/paper000.md and docs/paper001.md, "The ground's rings")."""

    rows: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        self.rows = np.asarray(self.rows, dtype=bool)
        self.normal = np.asarray(self.normal, dtype=np.float64)

    def applied(self, n: np.ndarray, ok: np.ndarray, R: np.ndarray) -> np.ndarray:
        """The fitted normals ``n`` (M, 3, map frame) of the rows ``ok`` (N,) bool, with the
        known normal (rotated into the map by R) on the fixed rows among them."""
        g = self.rows[ok]
        if not g.any():
            return n
        n = n.copy()
        n[g] = R @ self.normal
        return n


def fit_ground(xyz: np.ndarray, cfg: GroundPlaneConfig) -> tuple[np.ndarray, float] | None:
    """The ground plane (unit normal n with n_z > 0, d; n.p + d = 0 on it, sensor frame, m)
    of a scan ``xyz`` (N, 3), or None when no low band holds ``min_share`` of the points
    around the sensor or the fit tilts more than ``max_tilt_deg``."""
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    near = xyz[(r >= cfg.min_range) & (r <= cfg.max_range)]
    if len(near) < 50:
        return None
    z = near[:, 2]
    lo = float(z.min())
    counts = np.bincount(((z - lo) / cfg.bin).astype(np.int64))
    full = np.flatnonzero(counts >= cfg.min_share * len(near))
    if not len(full):
        return None
    z0 = lo + (full[0] + 0.5) * cfg.bin
    n, d = np.array([0.0, 0.0, 1.0]), -z0
    for width in (max(cfg.bin, 2 * cfg.band), cfg.band):
        on = near[np.abs(near @ n + d) < width]
        if len(on) < 30:
            return None
        A = np.column_stack([on[:, 0], on[:, 1], np.ones(len(on))])
        (a, b, c), *_ = np.linalg.lstsq(A, on[:, 2], rcond=None)
        norm = float(np.sqrt(a * a + b * b + 1.0))
        n, d = np.array([-a, -b, 1.0]) / norm, -c / norm
    if np.degrees(np.arccos(min(n[2], 1.0))) > cfg.max_tilt_deg:
        return None
    return n, float(d)


def enough_beams(rings: np.ndarray | None, cfg: GroundPlaneConfig) -> bool:
    """Whether a scan of these rings ((N,) beam indices) comes from a sensor of ``min_beams``
    or more."""
    return rings is not None and len(rings) > 0 and int(rings.max()) + 1 >= cfg.min_beams


def scan_ground(
    xyz: np.ndarray, rings: np.ndarray | None, cfg: GroundPlaneConfig
) -> tuple[np.ndarray, float] | None:
    """``fit_ground`` of a scan whose sensor has ``min_beams`` or more (rings (N,) beam
    indices), when ``enabled``; else None."""
    if not cfg.enabled or not enough_beams(rings, cfg):
        return None
    return fit_ground(xyz, cfg)


def on_ground(points: np.ndarray, plane: tuple[np.ndarray, float], band: float) -> np.ndarray:
    """(N,) which ``points`` (N, 3, the plane's frame) lie within ``band`` m of ``plane``."""
    n, d = plane
    return np.abs(points @ n + d) < band


def flatten_ground(
    points: np.ndarray, covs: np.ndarray, plane: tuple[np.ndarray, float], cfg: GroundPlaneConfig
) -> np.ndarray:
    """(N,) which ``points`` lie within ``band`` m of ``plane``; their ``covs`` (N, 3, 3, m^2)
    become n n^T (n^T Sigma n) + in_plane_sigma^2 (I - n n^T) in place: the measured spread
    along the normal, none of the rings' pattern along the plane."""
    n = plane[0]
    on = on_ground(points, plane, cfg.band)
    if on.any():
        nn = np.outer(n, n)
        along = np.einsum("i,nij,j->n", n, covs[on], n)
        covs[on] = along[:, None, None] * nn + cfg.in_plane_sigma**2 * (np.eye(3) - nn)
    return on
