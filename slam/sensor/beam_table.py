"""Beam-table inference: the elevation table of a spinning lidar from its first scans (driver
ring field, point layout, column order or elevation histogram; ``slam.sensor``)."""

from __future__ import annotations

import numpy as np

from slam.errors import InputError
from slam.sensor.beam_model import BeamModel
from slam.sensor.layout import (
    MAX_TURN_BEAMS,
    MIN_TURN_BEAMS,
    MIN_TURN_POINTS,
    elevation_deg,
    group_medians,
    layout_rings,
    layout_seam,
)

HIST_BIN_DEG = 0.02  # histogram bin; the finest real spacing is Pandar128's 0.125 deg
HIST_SMOOTH_DEG = 0.04  # Gaussian smoothing of the histogram (sigma)
MIN_BEAM_GAP_DEG = 0.1  # two peaks closer than this are one beam
MIN_PEAK_SHARE = 0.05  # a peak holding < 5 % of the median peak's points is noise


def _histogram_beams(elev: np.ndarray) -> np.ndarray:
    """Ascending beam elevations (deg): peaks of the smoothed elevation histogram."""
    lo, hi = float(elev.min()) - 0.5, float(elev.max()) + 0.5
    edges = np.arange(lo, hi + HIST_BIN_DEG, HIST_BIN_DEG)
    h, _ = np.histogram(elev, bins=edges)
    # here: scipy.signal costs ~1 s of every start, scipy.ndimage 0.09 s, and a driver with
    # a ring field never needs them
    from scipy.ndimage import gaussian_filter1d
    from scipy.signal import find_peaks

    hs = gaussian_filter1d(h.astype(np.float64), HIST_SMOOTH_DEG / HIST_BIN_DEG)

    peaks, props = find_peaks(
        hs, distance=max(int(MIN_BEAM_GAP_DEG / HIST_BIN_DEG), 1), prominence=1e-9
    )
    if peaks.size == 0:
        raise InputError("no beam found in the elevation histogram: is this a spinning lidar?")
    # a beam is a peak standing out of the valleys beside it by a share of a typical beam
    prom = props["prominences"]
    keep = prom >= MIN_PEAK_SHARE * np.median(np.sort(prom)[-min(len(prom), 16) :])
    centres = edges[:-1] + 0.5 * HIST_BIN_DEG
    return centres[peaks[keep]]


def _ranges(scans: list[np.ndarray]) -> np.ndarray:
    """(sum N,) range (m) of every point of every scan."""
    return np.concatenate([np.linalg.norm(s, axis=1) for s in scans])


def _check_scans(scans: list[np.ndarray]) -> list[np.ndarray]:
    """The scans as float64 (N, 3) without non-finite or origin points; InputError if empty."""
    out = []
    for s in scans:
        s = np.asarray(s, dtype=np.float64)
        if s.ndim != 2 or s.shape[1] != 3:
            raise InputError(f"points must be (N, 3) arrays, got shape {s.shape}")
        ok = np.isfinite(s).all(axis=1) & (np.einsum("ij,ij->i", s, s) > 1e-6)
        out.append(s if ok.all() else s[ok])
    if not out or sum(len(s) for s in out) < 10:
        raise InputError("need at least one scan with points to estimate the beam model")
    return out


def beams_from_rings(scans: list[np.ndarray], rings: list[np.ndarray]) -> BeamModel:
    """Beam model of scans that carry a driver ring field: per ring the median elevation.

    Rings are renumbered by elevation only in the model; a ring absent from the data gets
    no entry (``n_beams`` counts the rings seen)."""
    scans = [np.asarray(s, dtype=np.float64).reshape(-1, 3) for s in scans]
    rings = [np.asarray(r, dtype=np.int64).ravel() for r in rings]
    if (
        not scans
        or len(rings) != len(scans)
        or any(len(s) != len(r) for s, r in zip(scans, rings, strict=True))
    ):
        raise InputError("beams_from_rings needs scans and one ring per point of each")
    xyz, ring = np.concatenate(scans), np.concatenate(rings)
    fine = np.isfinite(xyz).all(axis=1) & (ring >= 0)
    if fine.sum() < 10:
        raise InputError("need at least one scan with points to read the beam model")
    xyz, ring = xyz[fine], ring[fine]
    elev = elevation_deg(xyz)
    ids, dense = np.unique(ring, return_inverse=True)
    med = group_medians(elev, dense.ravel(), len(ids))
    max_range = float(np.percentile(np.linalg.norm(xyz, axis=1), 99))
    return BeamModel(np.sort(med), layout=False, max_range=max_range, source="ring field")


def column_rings(scans: list[np.ndarray]) -> np.ndarray | None:
    """(B,) int16 ring of each position within a column when every scan is stored column by
    column with B points per column (B in MIN_TURN_BEAMS..MAX_TURN_BEAMS), else None.

    B fits when the elevations at each position i % B of every scan are one tight band (median
    deviation from the position's median < 1/4 of the median gap between adjacent bands)
    and no two positions share a band (every gap > MIN_BEAM_GAP_DEG: twice the true B
    would repeat each band). Points without a return (at the origin) count for nothing.
    """
    sizes = {len(s) for s in scans}
    if not scans or min(sizes) < MIN_TURN_BEAMS * MIN_TURN_POINTS:
        return None
    best = None
    for b in range(MIN_TURN_BEAMS, MAX_TURN_BEAMS + 1):
        if any(n % b for n in sizes):
            continue
        elev = np.concatenate([elevation_deg(s) for s in scans])
        pos = np.concatenate([np.arange(len(s)) % b for s in scans])
        ok = np.concatenate([np.einsum("ij,ij->i", s, s) > 1e-6 for s in scans])
        med = group_medians(elev[ok], pos[ok], b)
        if np.isnan(med).any():
            continue
        gaps = np.diff(np.sort(med))
        spread = float(np.median(np.abs(elev[ok] - med[pos[ok]])))
        if gaps.min() > MIN_BEAM_GAP_DEG and spread < 0.25 * np.median(gaps):
            if best is None or spread < best[0]:
                best = (spread, med)
    if best is None:
        return None
    return np.argsort(np.argsort(best[1], kind="stable")).astype(np.int16)


def estimate_beams(scans: list[np.ndarray]) -> BeamModel:
    """Beam model from the (N, 3) xyz of the first few scans (3-5 are plenty).

    When most scans (more than half) are stored beam by beam with the same beam count, the
    table is the median elevation per azimuth turn of those; otherwise the peaks of the
    elevation histogram of all points. One odd scan (a glitch the layout test does not
    explain) thus no longer sends a whole run to the histogram.
    """
    given, scans = scans, _check_scans(scans)
    max_range = float(np.percentile(_ranges(scans), 99))
    seams = [layout_seam(s) for s in scans]
    found = [x for x in seams if x is not None]
    if 2 * len(found) > len(scans):
        # one seam for the sensor: the circular median of the scans'
        ref = float(found[0])
        seam = ref + float(np.median([(x - ref + np.pi) % (2 * np.pi) - np.pi for x in found]))
        per_scan = [layout_rings(s, seam) for s in scans]
        counts = [0 if r is None else int(r.max()) + 1 for r in per_scan]
        n = max(set(counts), key=counts.count)
        use = [i for i, c in enumerate(counts) if c == n]
        if n and 2 * len(use) > len(scans):
            elev = np.concatenate([elevation_deg(scans[i]) for i in use])
            ring = np.concatenate([per_scan[i] for i in use]).astype(np.int64)
            med = group_medians(elev, ring, n)
            return BeamModel(np.sort(med), True, seam, max_range=max_range, source="point layout")
    raw = [np.asarray(s, dtype=np.float64) for s in given]
    cols = column_rings(raw) if all(np.isfinite(s).all() for s in raw) else None
    if cols is not None:
        elev = np.concatenate([elevation_deg(s) for s in raw])
        pos = np.concatenate([cols[np.arange(len(s)) % len(cols)] for s in raw]).astype(np.int64)
        ok = np.concatenate([np.einsum("ij,ij->i", s, s) > 1e-6 for s in raw])
        med = group_medians(elev[ok], pos[ok], len(cols))
        return BeamModel(med, max_range=max_range, source="column order", column_rings=cols)
    elev = np.concatenate([elevation_deg(s) for s in scans])
    return BeamModel(_histogram_beams(elev), layout=False, max_range=max_range)
