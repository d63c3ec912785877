"""Wide-basin 2D registration: a correlative search of a target cloud against a reference
cloud over a window of rotations and translations (Olson's correlative scan matching,
"Real-time correlative scan matching", ICRA 2009, brute force at one resolution), for
revisits whose drift is beyond the basin of PLICP (DPCR-SLAM region edges, paper 003
section 3.5, on real logs 15 deg / 3 m off).

The reference becomes a likelihood field on a coarse grid (exp(-d^2 / 2 sigma^2) of the
distance d to the nearest reference cell); for every rotation of the window the target's
occupied cells are correlated with the field by FFT, which scores every translation of
the window at once. The result is the best pose, its score (the mean likelihood of the
target cells, 1 = every cell on a reference cell) and the best score of any pose at
least ``separation`` away from it: a corridor scores the same along its length, and a
second peak close to the first says the match is not unique. Refine the pose with PLICP.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from slam.errors import ConfigError, InputError
from slam.mapping.grid2d import transform2d


@dataclass
class CorrelativeConfig:
    """resolution (m): cells of the search (translation step); max_shift (m) and
    max_angle_deg: half-widths of the window around the guess; angle_step_deg: rotation
    step (1 deg moves a point 6 m away by 10 cm, one cell; PLICP refines); sigma (m): width of
    the likelihood field; separation_m / separation_deg: a pose this far from the best
    (either) counts as another peak for the uniqueness ratio; coarse: the whole window is
    first searched with cells and rotation steps ``coarse`` times larger (same sigma; its
    uniqueness is the result's), then +-``coarse`` steps around its best at full resolution (1: one
    level; 2 costs about a fifth of it)."""

    resolution: float = 0.1
    max_shift: float = 3.0
    max_angle_deg: float = 25.0
    angle_step_deg: float = 1.0
    sigma: float = 0.1
    separation_m: float = 0.6
    separation_deg: float = 6.0
    coarse: int = 2

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and self.max_shift >= 0 and self.sigma > 0):
            raise ConfigError("correlative: resolution, sigma > 0 and max_shift >= 0 required")
        if self.coarse < 1:
            raise ConfigError(f"correlative: coarse must be >= 1, got {self.coarse}")
        if not (self.angle_step_deg > 0 and self.max_angle_deg >= 0):
            raise ConfigError("correlative: angle_step_deg > 0 and max_angle_deg >= 0 required")


@dataclass
class CorrelativeResult:
    """pose (x, y, theta) mapping target points into the reference frame; score: mean
    likelihood of the target cells at the pose (0..1); second: best score of a pose at
    least the separation away; uniqueness = second / score (1 = ambiguous, a corridor)."""

    pose: np.ndarray
    score: float
    second: float

    @property
    def uniqueness(self) -> float:
        return self.second / self.score if self.score > 0 else 1.0


def _cells(xy: np.ndarray, res: float) -> np.ndarray:
    """Unique integer cells (K, 2) (ix, iy) of points (N, 2)."""
    return np.unique(np.floor(xy / res).astype(np.int64), axis=0)


def _likelihood_field(
    reference: np.ndarray, res: float, k: int, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """(field, lo): exp(-d^2 / 2 sigma^2) of the distance d (m) to the nearest reference cell
    on a grid of ``res`` (m) cells (rows = y, cols = x) padded for shifts of +-k cells, and
    the (x, y) cell of its corner."""
    ref_cells = _cells(reference, res)
    pad = k + int(np.ceil(3 * sigma / res)) + 2
    lo = ref_cells.min(axis=0) - pad
    hi = ref_cells.max(axis=0) + pad
    occ = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), dtype=bool)  # (rows=y, cols=x)
    occ[ref_cells[:, 1] - lo[1], ref_cells[:, 0] - lo[0]] = True
    dist = ndimage.distance_transform_edt(~occ) * res
    return np.exp(-0.5 * (dist / sigma) ** 2), lo


def _shift_scores(
    field: np.ndarray,
    lo: np.ndarray,
    target: np.ndarray,
    theta: float,
    centre: np.ndarray,
    k: int,
    res: float,
) -> np.ndarray:
    """(2k+1, 2k+1) (dy, dx) mean field value of the target's cells rotated by theta (rad),
    for every shift of -k..k cells around the ``centre`` cell, by one FFT correlation."""
    cells = _cells(transform2d(np.array([0.0, 0.0, theta]), target), res)
    c_lo = cells.min(axis=0)
    c_hi = cells.max(axis=0)
    img = np.zeros((c_hi[1] - c_lo[1] + 1, c_hi[0] - c_lo[0] + 1))
    img[cells[:, 1] - c_lo[1], cells[:, 0] - c_lo[0]] = 1.0
    # score(s) = sum_h img[h] field[h + c_lo + centre + s - lo], s in [-k, k]^2
    start = c_lo + centre - k - lo  # (x, y) offset into the field of shift -k
    rows = slice(start[1], start[1] + 2 * k + img.shape[0])
    cols = slice(start[0], start[0] + 2 * k + img.shape[1])
    window = np.zeros((2 * k + img.shape[0], 2 * k + img.shape[1]))
    r0, c0 = max(rows.start, 0), max(cols.start, 0)
    r1, c1 = min(rows.stop, field.shape[0]), min(cols.stop, field.shape[1])
    if r1 > r0 and c1 > c0:
        window[r0 - rows.start : r1 - rows.start, c0 - cols.start : c1 - cols.start] = field[
            r0:r1, c0:c1
        ]
    from scipy.signal import fftconvolve  # here: scipy.signal costs ~1 s of every start

    corr = fftconvolve(window, img[::-1, ::-1], mode="valid")  # (2k+1, 2k+1)
    return corr / len(cells)


def _second_peak(
    scores: np.ndarray, best: tuple[int, int, int], k: int, cfg: CorrelativeConfig
) -> float:
    """Best score of the (angle, dy, dx) volume outside the separation neighbourhood of the
    peak ``best`` (separation_deg in rotation, separation_m in translation)."""
    a, dy, dx = best
    ia = np.abs(np.arange(len(scores)) - a) * cfg.angle_step_deg < cfg.separation_deg
    yy, xx = np.mgrid[-k : k + 1, -k : k + 1]
    near = np.hypot(yy - (dy - k), xx - (dx - k)) * cfg.resolution < cfg.separation_m
    masked = scores.copy()
    masked[ia] *= ~near[None]
    return float(masked.max())


def correlative_search(
    reference: np.ndarray,
    target: np.ndarray,
    guess: np.ndarray,
    cfg: CorrelativeConfig | None = None,
) -> CorrelativeResult:
    """Best pose of ``target`` (N, 2) on ``reference`` (M, 2) within the window around
    ``guess`` (x, y, theta; target frame -> reference frame): rotations guess_theta +-
    max_angle_deg, translations guess_xy +- max_shift."""
    cfg = cfg or CorrelativeConfig()
    if cfg.coarse > 1:
        f = cfg.coarse
        wide = replace(cfg, resolution=f * cfg.resolution, angle_step_deg=f * cfg.angle_step_deg,
                       coarse=1)  # fmt: skip
        first = correlative_search(reference, target, guess, wide)
        if first.score <= 0.0:  # nothing of the target near the reference in the window
            return first
        fine = replace(cfg, max_shift=f * cfg.resolution, max_angle_deg=f * cfg.angle_step_deg,
                       coarse=1)  # fmt: skip
        best = correlative_search(reference, target, first.pose, fine)
        return CorrelativeResult(best.pose, best.score, first.second * best.score / first.score)
    reference = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    if len(reference) < 3 or len(target) < 3:
        raise InputError(
            f"correlative_search: {len(reference)} reference / {len(target)} target points, "
            "need >= 3 each"
        )
    res = cfg.resolution
    k = int(np.ceil(cfg.max_shift / res))  # shifts -k..k cells per axis
    field, lo = _likelihood_field(reference, res, k, cfg.sigma)
    n_ang = int(np.floor(cfg.max_angle_deg / cfg.angle_step_deg))
    angles = guess[2] + np.radians(cfg.angle_step_deg) * np.arange(-n_ang, n_ang + 1)
    centre = np.floor(guess[:2] / res).astype(np.int64)  # cell of the guess translation
    scores = np.zeros((len(angles), 2 * k + 1, 2 * k + 1))  # (angle, dy, dx)
    for a, theta in enumerate(angles):
        scores[a] = _shift_scores(field, lo, target, theta, centre, k, res)
    best = np.unravel_index(int(np.argmax(scores)), scores.shape)
    a, dy, dx = best
    # the rotation about the target origin, then the shift (whole cells)
    shift = (centre + np.array([dx - k, dy - k])) * res
    pose = np.array([shift[0], shift[1], float(angles[a])])
    return CorrelativeResult(pose, float(scores[best]), _second_peak(scores, best, k, cfg))
