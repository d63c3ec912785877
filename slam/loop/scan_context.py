"""Scan Context descriptor (Kim & Kim, IROS 2018) with the ring/sector keys of Scan Context++.

The descriptor is a polar grid of ``rings x sectors`` bins around the sensor (rows = rings
by range, columns = sectors by azimuth); each bin holds the maximum point height
``z + lidar_height`` (>= 0; 0 marks an empty bin). A yaw rotation of the sensor is a
circular shift of the columns, which the column-shift distance (SC eq. 5-6) searches.

Yaw convention (tested): for a query scan and a candidate scan of the same place,
:func:`column_shift_distance` returns the shift ``s`` with
``query[:, j] ~ candidate[:, (j + s) % sectors]``; the yaw of ``T_candidate_query``
(the rotation taking query-frame points into the candidate frame) is
``s * 360 / sectors`` degrees (see :func:`shift_to_yaw`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class ScanContextParams:
    """Grid geometry. max_radius in metres (~80 outdoors, ~20-30 indoors); lidar_height in
    metres is added to z so bin values are heights above the ground (clipped at 0)."""

    rings: int = 20
    sectors: int = 60
    max_radius: float = 80.0
    lidar_height: float = 2.0

    def __post_init__(self) -> None:
        if self.rings < 1 or self.sectors < 2:
            raise ValueError(f"need rings >= 1 and sectors >= 2, got {self.rings}, {self.sectors}")
        if not self.max_radius > 0:
            raise ValueError(f"max_radius must be > 0 m, got {self.max_radius}")


def scan_context(points: np.ndarray, params: ScanContextParams = ScanContextParams()) -> np.ndarray:
    """The (rings, sectors) Scan Context of sensor-frame ``points`` (N, 3): max height per bin."""
    pts = np.asarray(points, dtype=np.float64)
    desc = np.zeros(params.rings * params.sectors, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] == 0:
        return desc.reshape(params.rings, params.sectors)
    x, y = pts[:, 0], pts[:, 1]
    r = np.hypot(x, y)
    keep = (r > 0.0) & (r < params.max_radius) & np.isfinite(r) & np.isfinite(pts[:, 2])
    if not keep.any():
        return desc.reshape(params.rings, params.sectors)
    r = r[keep]
    height = np.maximum(pts[keep, 2] + params.lidar_height, 0.0)
    ring = np.minimum((r * (params.rings / params.max_radius)).astype(np.intp), params.rings - 1)
    azimuth = np.mod(np.arctan2(y[keep], x[keep]), TWO_PI)
    sector = np.minimum((azimuth * (params.sectors / TWO_PI)).astype(np.intp), params.sectors - 1)
    np.maximum.at(desc, ring * params.sectors + sector, height)
    return desc.reshape(params.rings, params.sectors)


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Rotation-invariant retrieval key (SC++): mean bin value of each ring, shape (..., rings)."""
    return np.asarray(desc).mean(axis=-1)


def sector_key(desc: np.ndarray) -> np.ndarray:
    """Yaw pre-alignment key (SC++ "aligning key"): mean of each sector column, (..., sectors)."""
    return np.asarray(desc).mean(axis=-2)


def shift_to_yaw(shift: int | np.ndarray, sectors: int) -> np.ndarray | float:
    """Yaw of T_candidate_query in radians, wrapped to (-pi, pi], for a column shift."""
    yaw = np.asarray(shift, dtype=np.float64) * (TWO_PI / sectors)
    wrapped = np.pi - np.mod(np.pi - yaw, TWO_PI)
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def yaw_to_shift(yaw: float, sectors: int) -> int:
    """Nearest column shift (0..sectors-1) for a yaw in radians of T_candidate_query."""
    return int(np.round(yaw * sectors / TWO_PI)) % sectors


def sector_key_shift(query_key: np.ndarray, candidate_keys: np.ndarray) -> np.ndarray:
    """Best shift per candidate by L2 distance of sector keys over all circular shifts.

    query_key (S,), candidate_keys (K, S) -> (K,) shifts with the module's convention.
    """
    cand = np.atleast_2d(np.asarray(candidate_keys, dtype=np.float64))
    s = cand.shape[-1]
    idx = (np.arange(s)[:, None] + np.arange(s)[None, :]) % s  # idx[shift, j] = (j + shift) % S
    diff = cand[:, idx] - np.asarray(query_key, dtype=np.float64)[None, None, :]
    return np.argmin(np.einsum("ksj,ksj->ks", diff, diff), axis=1)


def _unit_columns(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit norm (empty columns stay 0) and the non-empty mask."""
    norms = np.linalg.norm(desc, axis=-2)
    valid = norms > 0.0
    unit = desc / np.where(valid, norms, 1.0)[..., None, :]
    return unit, valid


def column_shift_distance(
    query: np.ndarray, candidates: np.ndarray, shifts: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Scan Context distance (SC eq. 5-6) of ``query`` (R, S) to each of ``candidates`` (K, R, S).

    d = min over column shifts of the mean, over columns non-empty in both, of
    (1 - cosine similarity of the two columns). With unit columns, the summed cosines of
    every shift are one circular cross-correlation along the sectors (summed over rings),
    computed for all shifts at once by FFT; likewise the count of columns non-empty in both.
    ``shifts`` (K, W) restricts the minimum (e.g. to a window around a sector-key
    pre-alignment); None takes all S shifts. Returns (distance (K,) in [0, 2], shift (K,)).
    """
    q = np.asarray(query, dtype=np.float64)
    c = np.asarray(candidates, dtype=np.float64)
    if c.ndim == 2:
        c = c[None]
    k, _, s = c.shape
    qu, qv = _unit_columns(q)
    cu, cv = _unit_columns(c)
    # corr[k, shift] = sum_j q[j] . c_k[(j + shift) % S] = irfft(conj(Q) * C)
    spec = (np.conj(np.fft.rfft(qu, axis=-1))[None] * np.fft.rfft(cu, axis=-1)).sum(axis=1)
    sims = np.fft.irfft(spec, n=s, axis=-1)
    count = np.rint(
        np.fft.irfft(
            np.conj(np.fft.rfft(qv.astype(np.float64)))[None]
            * np.fft.rfft(cv.astype(np.float64), axis=-1),
            n=s,
            axis=-1,
        )
    )
    dist_all = np.where(count > 0, 1.0 - sims / np.maximum(count, 1.0), 1.0)  # (K, S)
    if shifts is None:
        shifts = np.broadcast_to(np.arange(s), (k, s))
    shifts = np.asarray(shifts, dtype=np.intp) % s
    dist = np.take_along_axis(dist_all, shifts, axis=1)
    best = np.argmin(dist, axis=1)
    rows = np.arange(k)
    return dist[rows, best], shifts[rows, best] % s
