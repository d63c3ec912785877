"""RANSAC ground plane with a least-squares refit (LeGO-LOAM-LPB, paper 001, 3.1.2).

Plane n.x + d = 0 with a unit normal pointing up (towards the sensor) and d > 0: d is the
sensor's height above the ground (eqs. (3)-(4): "d is the distance from the LiDAR to the
plane, always > 0"). Steps as in the paper: (1) three random points give a plane (eq. 5),
(2) points within ``inlier_band`` of it are its inliers and their count its score (eq. 6),
(3) the best of ``iterations`` samples wins, (4) a least-squares plane through its
inliers refines it (eq. 7; total least squares: the normal is the smallest principal axis).

Ground of a sensor that drives on it: the candidates are the points at least
``min_depth`` below the sensor (along ``up``) and within ``max_range``, and a sample whose
normal is more than ``max_tilt_deg`` from ``up`` is discarded, so that the lower half of a
wall (often as large as the visible floor in a corridor) can never win.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slam.errors import ConfigError, InputError


@dataclass
class RansacGroundConfig:
    """iterations: three-point samples. inlier_band (m): half-thickness of the plane for
    the score (eq. 6). max_tilt_deg: largest angle between a candidate normal and ``up``.
    min_depth (m): candidates lie at least this far below the sensor; max_range (m): and
    within this horizontal distance. max_candidates: candidates subsampled for the score
    (the refit uses all). min_inliers: fewer -> no ground (InputError). refits:
    re-selections of the inliers with the refined plane, the band shrinking to three robust
    sigmas of the ground's residuals but not below min_band (m). max_descents: how many
    times the plane may be replaced by a level plane fitted to the candidates more than
    ``inlier_band`` below it, when at least min_below_fraction x its inliers (and
    min_inliers) lie there and support it as well (the ground is the lowest supported
    level surface; 0 = the paper's plain RANSAC)."""

    iterations: int = 100
    inlier_band: float = 0.08
    max_tilt_deg: float = 15.0
    min_depth: float = 0.3
    max_range: float = 30.0
    max_candidates: int = 3000
    min_inliers: int = 50
    refits: int = 3
    min_band: float = 0.02
    max_descents: int = 2
    min_below_fraction: float = 0.2
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ConfigError(f"ground iterations must be >= 1, got {self.iterations}")
        if self.inlier_band <= 0 or self.max_range <= 0:
            raise ConfigError("ground inlier_band and max_range must be > 0")
        if not 0 < self.max_tilt_deg < 90:
            raise ConfigError(f"max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")
        if self.min_inliers < 3 or self.max_candidates < 3:
            raise ConfigError("ground min_inliers and max_candidates must be >= 3")
        if np.linalg.norm(self.up) == 0:
            raise ConfigError("ground up axis must be a non-zero vector")


@dataclass
class GroundPlane:
    """n.x + d = 0 in the sensor frame: normal (3,) unit, on the side of ``up``; d (m) > 0
    is the sensor's height. inliers: (N,) bool over the points given to fit_ground (within
    the band of the refined plane, among the candidates). rmse (m) of the inliers' distances.
    """

    normal: np.ndarray
    d: float
    inliers: np.ndarray
    rmse: float
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def height(self) -> float:
        """Sensor height above the plane (m)."""
        return float(self.d)

    @property
    def tilt_deg(self) -> float:
        """Angle between the plane normal and the sensor's up axis (deg)."""
        return float(np.degrees(np.arccos(np.clip(self.normal @ self.up, -1.0, 1.0))))

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """Signed distance (m) of points (N, 3) above the plane."""
        return np.asarray(xyz, dtype=np.float64) @ self.normal + self.d


def plane_from_points(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes through point triples p (M, 3, 3): unit normals (M, 3) and d (M,) (eq. 5);
    degenerate (collinear) triples get a zero normal."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n[ok] /= norm[ok, None]
    n[~ok] = 0.0
    return n, -np.einsum("ij,ij->i", n, p[:, 0])


def refit_plane(xyz: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (eq. 7) through points (N, 3): minimises the sum of squared
    perpendicular distances; normal oriented towards ``up``."""
    c = xyz.mean(axis=0)
    q = xyz - c
    _, vecs = np.linalg.eigh(q.T @ q)
    n = vecs[:, 0]
    if n @ up < 0:
        n = -n
    return n, float(-n @ c)


def _best_sample(
    pts: np.ndarray, up: np.ndarray, cfg: RansacGroundConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float] | None:
    """RANSAC steps (1)-(3): the level three-point plane (normal towards ``up``) with the
    most points of ``pts`` within ``inlier_band`` (scored on at most ``max_candidates``
    of them); None when no sample is level."""
    score_pts = pts
    if len(pts) > cfg.max_candidates:
        score_pts = pts[rng.choice(len(pts), cfg.max_candidates, replace=False)]
    triples = pts[rng.integers(0, len(pts), size=(cfg.iterations, 3))]
    normals, ds = plane_from_points(triples)
    flip = normals @ up < 0
    normals[flip] *= -1.0
    ds[flip] *= -1.0
    level = normals @ up >= np.cos(np.radians(cfg.max_tilt_deg))
    if not level.any():
        return None
    normals, ds = normals[level], ds[level]
    dist = np.abs(score_pts @ normals.T + ds)  # (candidates, samples)
    score = (dist <= cfg.inlier_band).sum(axis=0)  # eq. (6)
    best = int(np.argmax(score))
    return normals[best], float(ds[best])


def _refine(
    cand: np.ndarray, n: np.ndarray, d: float, up: np.ndarray, cfg: RansacGroundConfig
) -> tuple[np.ndarray, float, np.ndarray]:
    """Step (4): least-squares refits of the plane (n, d) through its inliers among
    ``cand``; returns the plane and its inlier mask over ``cand``."""
    band = cfg.inlier_band
    inl = np.abs(cand @ n + d) <= band
    for _ in range(max(cfg.refits, 1)):
        if inl.sum() < cfg.min_inliers:
            break
        n, d = refit_plane(cand[inl], up)  # eq. (7)
        res = np.abs(cand @ n + d)
        # the band shrinks to the noise of the ground (3 robust sigmas), so that the feet
        # of walls and kerbs within the coarse band stop tilting the refit
        sigma = 1.4826 * float(np.median(res[res <= band]))
        band = float(np.clip(3.0 * sigma, cfg.min_band, band))
        inl = res <= band
    return n, d, inl


def fit_ground(
    xyz: np.ndarray, cfg: RansacGroundConfig | None = None, seed: int = 0
) -> GroundPlane:
    """The ground plane of one scan (sensor frame, m) by RANSAC + least squares (3.1.2).

    Raises InputError when fewer than ``cfg.min_inliers`` points support a near-level
    plane below the sensor (no ground in view, or the sensor's ``up`` is wrong)."""
    cfg = cfg or RansacGroundConfig()
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    up = np.asarray(cfg.up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    height = xyz @ up
    horizontal = np.linalg.norm(xyz - np.outer(height, up), axis=1)
    cand_idx = np.flatnonzero(
        (height <= -cfg.min_depth) & (horizontal <= cfg.max_range) & np.all(np.isfinite(xyz), 1)
    )
    if len(cand_idx) < cfg.min_inliers:
        raise InputError(
            f"no ground: {len(cand_idx)} points lie {cfg.min_depth} m below the sensor within "
            f"{cfg.max_range} m (need {cfg.min_inliers}); check ground.up / min_depth"
        )
    rng = np.random.default_rng(seed)
    cand = xyz[cand_idx]
    best = _best_sample(cand, up, cfg, rng)
    if best is None:
        raise InputError(
            f"no ground: none of {cfg.iterations} RANSAC samples is within "
            f"{cfg.max_tilt_deg} deg of level; check ground.up"
        )
    n, d, inl = _refine(cand, *best, up, cfg)
    # the ground has nothing under it: a level plane with a supported level plane below it
    # is a ledge (in a corridor the rings of the low beams trace level lines at one height
    # along both walls, often more points than the floor between them): descend to it
    for _ in range(cfg.max_descents):
        below = cand @ n + d < -cfg.inlier_band
        need = max(cfg.min_inliers, cfg.min_below_fraction * int(inl.sum()))
        if below.sum() < need:
            break
        lower = _best_sample(cand[below], up, cfg, rng)
        if lower is None:
            break
        n2, d2, inl2 = _refine(cand, *lower, up, cfg)
        if inl2.sum() < need or n2 @ up < np.cos(np.radians(cfg.max_tilt_deg)):
            break
        n, d, inl = n2, d2, inl2
    if inl.sum() < cfg.min_inliers or n @ up < np.cos(np.radians(cfg.max_tilt_deg)) or d <= 0:
        raise InputError(
            f"no ground: the best plane has {int(inl.sum())} inliers (need {cfg.min_inliers}) "
            f"or is not level below the sensor"
        )
    inliers = np.zeros(len(xyz), dtype=bool)
    inliers[cand_idx[inl]] = True
    rmse = float(np.sqrt(np.mean((cand[inl] @ n + d) ** 2)))
    return GroundPlane(normal=n, d=d, inliers=inliers, rmse=rmse, up=up)


def split_ground(
    xyz: np.ndarray, plane: GroundPlane, band: float = 0.15
) -> tuple[np.ndarray, np.ndarray]:
    """Ground and non-ground masks (N,) bool: ground within ``band`` m of the plane (either
    side); everything else, including points below it (pits, reflections), is non-ground."""
    dist = plane.distance(xyz)
    ground = np.abs(dist) <= band
    return ground, ~ground
