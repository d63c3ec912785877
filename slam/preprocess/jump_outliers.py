"""Range and intensity jump outliers along each ring (LeGO-LOAM-LPB, paper 001, 3.1.1).

The paper removes a point i whose range r_i or intensity I_i jumps against its ring
neighbours j in i-5..i+5 (eqs. (1), (2); the thresholds were lost in the text we have).
Read literally ("differs from a neighbour"), every depth edge and every material boundary
would go, and with them the LOAM edge features. We keep the physics of a spike instead: a
real surface is sampled by several consecutive returns of a ring, a spike by one. A point is
an outlier when fewer than ``min_agree`` of its window neighbours agree with it:

    |r_i - r_j| <= max(range_jump_abs, range_jump_rel * r_i)          (range, eq. 1)
    |I_i - I_j| <= intensity_jump * s  for a range-agreeing j          (intensity, eq. 2)

where s is the scan's robust intensity scale (its ``intensity_quantile`` quantile), so that
the same default serves 0..1 (KITTI), 0..255 (Velodyne) and 16-bit (Ouster) drivers.
Intensity is compared on the same surface only (neighbours that agree in range), as the
paper describes: the intensity jumps although the distance stays nearly identical.
The edge of a wall or of a painted strip has half a window of agreeing neighbours on its
own side and is kept. Neighbours more than ``max_gap_deg`` away in azimuth (a missing
return between them) are not compared; a point with fewer than ``min_neighbours``
comparable neighbours is kept (nothing to judge it against).

The numpy statement (``reference=True``: ``2 * window`` shifted copies of the ring-sorted
arrays) is the tested reference of a numba kernel that walks each point's window once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from slam.errors import ConfigError, InputError


@dataclass
class JumpOutlierConfig:
    """window: neighbours each side along the ring (paper: 5). range_jump_abs (m) and
    range_jump_rel (fraction of the range): a neighbour agrees in range within
    max(abs, rel * r). intensity_jump: agreement in intensity within this fraction of the
    scan's ``intensity_quantile`` intensity. min_agree: agreeing neighbours needed to stay
    (1: a surface seen by two consecutive returns survives). max_gap_deg: neighbours farther
    in azimuth are not compared. min_neighbours: fewer comparable neighbours -> kept."""

    enabled: bool = True
    window: int = 5
    range_jump_abs: float = 0.3
    range_jump_rel: float = 0.05
    intensity_jump: float = 0.35
    intensity_quantile: float = 0.95
    min_agree: int = 1
    max_gap_deg: float = 3.0
    min_neighbours: int = 2
    use_intensity: bool = True

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ConfigError(f"jump outlier window must be >= 1, got {self.window}")
        if not 1 <= self.min_agree <= 2 * self.window:
            raise ConfigError(
                f"min_agree must be in 1..{2 * self.window} (2 * window), got {self.min_agree}"
            )
        if self.range_jump_abs < 0 or self.range_jump_rel < 0 or self.intensity_jump < 0:
            raise ConfigError("range_jump_abs, range_jump_rel and intensity_jump must be >= 0")
        if not 0 < self.intensity_quantile <= 1:
            raise ConfigError(
                f"intensity_quantile must be in (0, 1], got {self.intensity_quantile}"
            )
        if self.max_gap_deg <= 0:
            raise ConfigError(f"max_gap_deg must be > 0, got {self.max_gap_deg}")


def _ring_order(ring: np.ndarray, azimuth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Order sorting points by (ring, azimuth), and each sorted point's ring start/size."""
    order = np.lexsort((azimuth, ring))
    r = ring[order]
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
    sizes = np.diff(np.r_[starts, len(r)])
    group = np.repeat(np.arange(len(starts)), sizes)
    return order, np.column_stack([starts[group], sizes[group]])


@njit(cache=True)
def _bad_kernel(
    r, az, inten, start, size, window, max_gap, tol_abs, tol_rel, int_tol, use_int,
    min_agree, min_neighbours,
):  # fmt: skip
    """Outlier flags of the ring-sorted points (see ``jump_outlier_mask``): each point's
    window of +-``window`` ring neighbours (circular), compared once."""
    n = len(r)
    bad = np.zeros(n, dtype=np.bool_)
    two_pi = 2.0 * np.pi
    for i in range(n):
        s0, m = start[i], size[i]
        pos = i - s0
        tol = max(tol_abs, tol_rel * r[i])
        comparable = 0
        agree_r = 0
        agree_i = 0
        for s in range(-window, window + 1):
            if s == 0 or abs(s) >= m:
                continue
            j = s0 + (pos + s) % m
            gap = abs((az[j] - az[i] + np.pi) % two_pi - np.pi)
            if gap > max_gap:
                continue
            comparable += 1
            if abs(r[j] - r[i]) <= tol:
                agree_r += 1
                if use_int and abs(inten[j] - inten[i]) <= int_tol:
                    agree_i += 1
        if comparable >= min_neighbours:
            if agree_r < min_agree or (use_int and agree_i < min_agree):
                bad[i] = True
    return bad


def _intensity_tolerance(
    intensity: np.ndarray | None, order: np.ndarray, n: int, cfg: JumpOutlierConfig
) -> tuple[np.ndarray | None, float]:
    """(inten, tol): the intensities in ring order and the largest jump (intensity units) to a
    neighbour that still agrees, intensity_jump x the scan's intensity_quantile; inten None
    when the intensity test is off, absent, all zero or not finite."""
    if not (cfg.use_intensity and intensity is not None):
        return None, 0.0
    inten = np.asarray(intensity, dtype=np.float64).reshape(-1)
    if len(inten) != n:
        raise InputError(f"intensity has {len(inten)} entries for {n} points")
    inten = inten[order]
    scale = float(np.quantile(inten, cfg.intensity_quantile))
    if not (scale > 0 and np.all(np.isfinite(inten))):
        return None, 0.0
    return inten, cfg.intensity_jump * scale


def _bad_reference(
    r: np.ndarray,
    az: np.ndarray,
    inten: np.ndarray | None,
    start: np.ndarray,
    size: np.ndarray,
    int_tol: float,
    cfg: JumpOutlierConfig,
) -> np.ndarray:
    """(N,) spikes in ring order, the numpy statement of ``_bad_kernel``: a point with at
    least min_neighbours comparable ring neighbours (within max_gap_deg of azimuth) of which
    fewer than min_agree agree in range (m) (and in intensity when given)."""
    n = len(r)
    pos = np.arange(n) - start
    max_gap = np.radians(cfg.max_gap_deg)
    range_tol = np.maximum(cfg.range_jump_abs, cfg.range_jump_rel * r)
    comparable = np.zeros(n, dtype=np.int32)
    agree_r = np.zeros(n, dtype=np.int32)
    agree_i = np.zeros(n, dtype=np.int32)
    for s in range(-cfg.window, cfg.window + 1):
        if s == 0:
            continue
        j = start + np.mod(pos + s, size)  # circular along the ring (the seam wraps)
        gap = np.abs(np.angle(np.exp(1j * (az[j] - az))))
        valid = (gap <= max_gap) & (np.abs(s) < size)
        comparable += valid
        same = valid & (np.abs(r[j] - r) <= range_tol)
        agree_r += same
        if inten is not None:
            agree_i += same & (np.abs(inten[j] - inten) <= int_tol)
    judged = comparable >= cfg.min_neighbours
    bad = judged & (agree_r < cfg.min_agree)
    if inten is not None:
        bad |= judged & (agree_i < cfg.min_agree)
    return bad


def jump_outlier_mask(
    xyz: np.ndarray,
    intensity: np.ndarray | None,
    ring: np.ndarray | None,
    cfg: JumpOutlierConfig | None = None,
    *,
    reference: bool = False,
) -> np.ndarray:
    """Keep-mask (N,) bool: False for range or intensity spikes along the rings (3.1.1).

    xyz: (N, 3) m, sensor frame. intensity: (N,) any unit, or None (range test only).
    ring: (N,) beam index, or None: then the test is skipped (all kept), since neighbours
    along a beam are unknown (the pipeline fills rings from its beam model).
    reference: the numpy statement instead of the numba kernel (the same mask).
    """
    cfg = cfg or JumpOutlierConfig()
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    keep = np.ones(n, dtype=bool)
    if not cfg.enabled or ring is None or n == 0:
        return keep
    ring = np.asarray(ring).reshape(-1)
    if len(ring) != n:
        raise InputError(f"ring has {len(ring)} entries for {n} points")
    rng = np.linalg.norm(xyz, axis=1)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    order, start_size = _ring_order(ring, azimuth)
    r = rng[order]
    az = azimuth[order]
    start, size = start_size[:, 0], start_size[:, 1]
    inten, int_tol = _intensity_tolerance(intensity, order, n, cfg)
    if reference:
        bad = _bad_reference(r, az, inten, start, size, int_tol, cfg)
    else:
        bad = _bad_kernel(
            r,
            az,
            inten if inten is not None else np.zeros(1),
            start.astype(np.int64),
            size.astype(np.int64),
            int(cfg.window),
            float(np.radians(cfg.max_gap_deg)),
            float(cfg.range_jump_abs),
            float(cfg.range_jump_rel),
            float(int_tol),
            inten is not None,
            int(cfg.min_agree),
            int(cfg.min_neighbours),
        )
    keep[order[bad]] = False
    return keep
