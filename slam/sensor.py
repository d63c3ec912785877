"""Beam model of a spinning lidar, estimated from its data when the driver gives no ring field.

The elevation table (one angle per beam) is read once from the first scans and then assigns
every point of every later scan to a beam (``BeamModel.ring_of``). Two cues, in this order:

1. Point layout (beam by beam). Clouds converted from KITTI .bin files and organised clouds (Ouster,
   ``ring``-less Velodyne exports) store the points beam by beam: along the stored order the
   azimuth unwraps to about one turn per beam. Then the beams are the turns of the unwrapped
   azimuth, exact even where two beams' elevations overlap (HDL-64's upper block is 1/3 deg
   apart while each beam's origin sits a few cm off the sensor origin, so elevations seen from
   the origin smear by ~0.3 deg at 10 m).
2. Column order. Clouds stored column by column with every beam in every column (nuScenes
   HDL-32E: 32 points per firing, missing returns included) hold beam b at position
   i % B of every column: the ring of a point is that of its position, exact even where
   near returns smear a beam's elevation by a degree (the car's own body, nuScenes).
3. Elevation histogram. Otherwise (firing-order clouds without missing returns, shuffled
   clouds) the beams are the peaks of the histogram of elevation angles, and a point
   belongs to the nearest beam.

Ring 0 is the lowest beam (Velodyne's ``ring`` convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from slam.errors import InputError

HIST_BIN_DEG = 0.02  # histogram bin; the finest real spacing is Pandar128's 0.125 deg
HIST_SMOOTH_DEG = 0.04  # Gaussian smoothing of the histogram (sigma)
MIN_BEAM_GAP_DEG = 0.1  # two peaks closer than this are one beam
MIN_PEAK_SHARE = 0.05  # a peak holding < 5 % of the median peak's points is noise
MIN_TURN_BEAMS, MAX_TURN_BEAMS = 4, 256  # layout cue: accepted number of azimuth turns
MIN_TURN_POINTS = 100  # a beam of a layout scan has at least this many points
MAX_BACK_STEP_DEG = 5.0  # layout: a larger backward azimuth step is a forward gap...
# ...unless a near point explains it: motion compensation (KITTI odometry) and the lasers'
# offsets from the origin move a point at range r by up to this much (m), i.e. its azimuth
# by atan(shift / r): 6-11 deg back steps at 1.3-1.9 m on KITTI odometry at 10 m/s
NEAR_SHIFT_M = 1.0
LAYOUT_SEAM_DEG = 3.0  # beams of a layout scan start their turn within this azimuth
# motion compensation stretches a sweep beyond one turn (near points at car speed): the
# first / last beam then spills past the seam, a fragment of < this share of a beam's
# points lying within SEAM_SPILL_DEG of the seam
SEAM_SPILL_SHARE, SEAM_SPILL_DEG = 0.25, 90.0


def elevation_deg(xyz: np.ndarray) -> np.ndarray:
    """(N,) elevation (deg) of each point seen from the sensor origin."""
    return np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))


def _group_medians(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """(n,) median of values per group id 0..n-1 (upper median; NaN for an empty group)."""
    span = float(np.ptp(values)) + 1.0 if len(values) else 1.0
    order = np.argsort(group * span + (values - (values.min() if len(values) else 0.0)))
    counts = np.bincount(group, minlength=n)
    start = np.r_[0, np.cumsum(counts)[:-1]]
    med = np.full(n, np.nan)
    has = counts > 0
    med[has] = values[order][start[has] + counts[has] // 2]
    return med


def _forward_azimuth(xyz: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """(u, sign, az0): the azimuth (rad) advanced along the stored order from the first point,
    the rotation's sign and the first point's azimuth; None for clouds whose azimuth steps
    back often (firing order: every column) or that are too small for a layout.
    The readable numpy reference of ``_forward_kernel`` (tests/test_sensor.py)."""
    if len(xyz) < MIN_TURN_BEAMS * MIN_TURN_POINTS:
        return None
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    step = (np.diff(az) + np.pi) % (2 * np.pi) - np.pi  # in [-pi, pi)
    sign = 1.0 if np.median(step) >= 0 else -1.0  # direction of rotation along the order
    step *= sign
    if np.mean(step < -1e-3) > 0.05:
        return None
    # within a beam's turn the azimuth only advances: a large backward step is a forward gap
    # (no returns over > 180 deg, e.g. sky), not a step back, unless a near point explains it
    rho = np.hypot(xyz[:, 0], xyz[:, 1])
    near = np.minimum(rho[:-1], rho[1:])
    allowed = np.maximum(np.radians(MAX_BACK_STEP_DEG), np.arctan2(NEAR_SHIFT_M, near))
    step = np.where(step < -allowed, step + 2 * np.pi, step)
    u = np.r_[0.0, np.cumsum(step)]
    n_est = int(u[-1] // (2 * np.pi)) + 1
    if not MIN_TURN_BEAMS <= n_est <= MAX_TURN_BEAMS + 1:
        return None
    return u, sign, float(az[0])


def _forward_from_azimuth(az: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(u, sign) of ``_forward_azimuth`` from the azimuths (rad) and horizontal ranges (m)
    already computed, through the compiled ``_forward_kernel``; None where the reference
    returns None."""
    if len(az) < MIN_TURN_BEAMS * MIN_TURN_POINTS:
        return None
    u, sign, ok = _forward_kernel(az, rho, np.radians(MAX_BACK_STEP_DEG), NEAR_SHIFT_M)
    if not ok or not np.isfinite(u[-1]):  # a non-finite point has no azimuth
        return None
    n_est = int(u[-1] // (2 * np.pi)) + 1
    if not MIN_TURN_BEAMS <= n_est <= MAX_TURN_BEAMS + 1:
        return None
    return u, sign


def _turn_spread(u: np.ndarray, elev: np.ndarray, phase: float) -> float:
    """Mean |elevation - its turn's median| (deg) when the turns begin at ``phase`` (rad)."""
    turn = np.floor((u - phase) / (2 * np.pi)).astype(np.int64)
    turn -= turn.min()
    med = _group_medians(elev, turn, int(turn.max()) + 1)
    return float(np.mean(np.abs(elev - med[turn])))


def _merge_spills(
    turn: np.ndarray,
    n_turns: int,
    phase: np.ndarray | None,
    u: np.ndarray | None = None,
    shift: float = 0.0,
    counts: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """(turn, n_turns) with a first / last turn that is only the spill of its neighbour
    beam past the seam merged into it: fewer than SEAM_SPILL_SHARE of the median turn's
    points, all within SEAM_SPILL_DEG after (last turn) / before (first turn) the seam (or
    LAYOUT_SEAM_DEG on its other side, where the beams begin staggered).
    phase: (N,) azimuth (rad) advanced from the seam, or computed from u - shift."""
    if n_turns < MIN_TURN_BEAMS + 1:
        return turn, n_turns
    if counts is None:
        counts = np.bincount(turn, minlength=n_turns)
    small = SEAM_SPILL_SHARE * np.median(counts)
    spill, window = np.radians(SEAM_SPILL_DEG), np.radians(LAYOUT_SEAM_DEG)
    two_pi = 2 * np.pi

    def phases(m: np.ndarray) -> np.ndarray:
        return phase[m] if phase is not None else (u[m] - shift) % two_pi

    if counts[-1] < small:
        last = turn == n_turns - 1
        p = phases(last)
        if np.all((p < spill) | (p > two_pi - window)):
            turn = np.where(last, n_turns - 2, turn)
            n_turns -= 1
    if counts[0] < small:
        first = turn == 0
        p = phases(first)
        if np.all((p > two_pi - spill) | (p < window)):
            turn = np.where(first, 0, turn - 1)
            n_turns -= 1
    return turn, n_turns


def layout_seam(xyz: np.ndarray) -> float | None:
    """Azimuth (rad, atan2 frame) where the beams of a beam-by-beam cloud begin their turn,
    or None when the cloud is not stored beam by beam.

    Candidates: the first point's azimuth, the circular median of the azimuths after the
    largest elevation jumps along the order (a top beam may begin after a stretch of sky)
    and every 15 deg; the one whose turns are the tightest elevation bands wins.
    """
    fa = _forward_azimuth(xyz)
    if fa is None:
        return None
    u, sign, az0 = fa
    elev = elevation_deg(xyz)
    n_est = int(u[-1] // (2 * np.pi)) + 1
    top = np.argpartition(-np.abs(np.diff(elev)), n_est - 2)[: n_est - 1] + 1
    ph = u[top] % (2 * np.pi)
    mean = np.arctan2(np.sin(ph).mean(), np.cos(ph).mean())
    jump_phase = (mean + np.median((ph - mean + np.pi) % (2 * np.pi) - np.pi)) % (2 * np.pi)
    cands = np.r_[0.0, jump_phase, np.radians(np.arange(15.0, 360.0, 15.0))]
    sub = slice(None, None, 4)
    spread = [_turn_spread(u[sub], elev[sub], c) for c in cands]
    return float(az0 + sign * cands[int(np.argmin(spread))])


def layout_rings_reference(xyz: np.ndarray, seam: float | None = None) -> np.ndarray | None:
    """The readable numpy reference of ``layout_rings`` (same result; tests/test_sensor.py).

    (N,) ring of each point from the stored order when the cloud is stored beam by beam,
    else None. Ring 0 = lowest beam. seam: azimuth (rad) where the turns begin
    (``layout_seam``; searched when None).

    Beam by beam: along the order the azimuth advances by a whole number of turns (one per
    beam), mostly monotone, and the turns' median elevations are monotone. Points within
    LAYOUT_SEAM_DEG of the seam (beams begin their turn a little staggered) join the
    adjacent turn whose median elevation is nearer.
    """
    fa = _forward_azimuth(xyz)
    if fa is None:
        return None
    u, sign, az0 = fa
    if seam is None:
        seam = layout_seam(xyz)
        if seam is None:
            return None
    u = u - (sign * (seam - az0)) % (2 * np.pi)
    elev = elevation_deg(xyz)
    turn = np.floor(u / (2 * np.pi)).astype(np.int64)
    turn -= turn.min()
    n_turns = int(turn.max()) + 1
    if not MIN_TURN_BEAMS <= n_turns <= MAX_TURN_BEAMS + 1:
        return None
    phase = u - 2 * np.pi * np.floor(u / (2 * np.pi))
    window = np.radians(LAYOUT_SEAM_DEG)
    lo, hi = phase < window, phase > 2 * np.pi - window
    clear = ~(lo | hi)
    med = _group_medians(elev[clear], turn[clear], n_turns)
    for near, other in ((lo, turn - 1), (hi, turn + 1)):
        i = np.flatnonzero(near & (other >= 0) & (other < n_turns))
        d_own = np.abs(elev[i] - med[turn[i]])
        d_other = np.abs(elev[i] - med[other[i]])
        move = (d_other < d_own) | (np.isnan(d_own) & ~np.isnan(d_other))
        turn[i[move]] = other[i[move]]
    ids, turn = np.unique(turn, return_inverse=True)
    turn, n_turns = _merge_spills(turn, len(ids), phase)
    counts = np.bincount(turn, minlength=n_turns)
    if not MIN_TURN_BEAMS <= n_turns <= MAX_TURN_BEAMS or np.median(counts) < MIN_TURN_POINTS:
        return None
    d = np.diff(_group_medians(elev, turn, n_turns))
    if not (np.all(d <= 0.05) or np.all(d >= -0.05)):
        return None
    ring = turn if d.sum() >= 0 else n_turns - 1 - turn
    return ring.astype(np.int16)


def layout_rings(xyz: np.ndarray, seam: float | None = None) -> np.ndarray | None:
    """(N,) ring of each point from the stored order when the cloud is stored beam by beam,
    else None. Ring 0 = lowest beam. seam: azimuth (rad) where the turns begin
    (``layout_seam``; searched when None). Compiled; equal to ``layout_rings_reference``.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if seam is None:
        seam = layout_seam(xyz)
        if seam is None:
            return None
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    fa = _forward_from_azimuth(az, np.hypot(xyz[:, 0], xyz[:, 1]))
    return _layout_rings_polar(az, elevation_deg(xyz), seam, fa)


def _layout_rings_polar(
    az: np.ndarray, elev: np.ndarray, seam: float, fa: tuple[np.ndarray, float] | None
) -> np.ndarray | None:
    """``layout_rings`` from the azimuths (rad) and elevations (deg) of the points and their
    ``_forward_from_azimuth`` (None: not a layout)."""
    if fa is None:
        return None
    u, sign = fa
    shift = (sign * (seam - float(az[0]))) % (2 * np.pi)
    turn, n_first, n_turns, counts, med = _layout_kernel(
        u, elev, shift, np.radians(LAYOUT_SEAM_DEG), MIN_TURN_BEAMS, MAX_TURN_BEAMS + 1
    )
    if not MIN_TURN_BEAMS <= n_first <= MAX_TURN_BEAMS + 1:
        return None
    merged, n_merged = _merge_spills(turn, n_turns, None, u, shift, counts)
    if n_merged != n_turns:
        turn, n_turns = merged, n_merged
        counts = np.bincount(turn, minlength=n_turns)
        med = _group_medians_kernel(elev, turn, np.ones(len(turn), np.bool_), n_turns)
    if not MIN_TURN_BEAMS <= n_turns <= MAX_TURN_BEAMS or np.median(counts) < MIN_TURN_POINTS:
        return None
    d = np.diff(med)
    if not (np.all(d <= 0.05) or np.all(d >= -0.05)):
        return None
    ring = turn if d.sum() >= 0 else n_turns - 1 - turn
    return ring.astype(np.int16)


def _histogram_beams(elev: np.ndarray) -> np.ndarray:
    """Ascending beam elevations (deg): peaks of the smoothed elevation histogram."""
    lo, hi = float(elev.min()) - 0.5, float(elev.max()) + 0.5
    edges = np.arange(lo, hi + HIST_BIN_DEG, HIST_BIN_DEG)
    h, _ = np.histogram(elev, bins=edges)
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


@dataclass(frozen=True)
class BeamModel:
    """Beam elevation table of a spinning lidar and what depends on it.

    elevations_deg: (B,) ascending beam elevations (deg) seen from the sensor origin, ring r
    = elevations_deg[r]. layout: True when the clouds are stored beam by beam (``ring_of``
    then reads the rings from the point order); seam_rad: the azimuth (rad) where their
    turns begin. max_range: 99th percentile of the ranges (m)
    of the scans it was estimated from (e.g. Scan Context's radius). source: "ring field",
    "point layout", "column order" or "elevation histogram". column_rings: for clouds stored
    column by column with B points per column, the ring of position i % B (None otherwise).
    """

    elevations_deg: np.ndarray
    layout: bool = False
    seam_rad: float | None = None
    max_range: float = 0.0
    source: str = "elevation histogram"
    column_rings: np.ndarray | None = None  # column order: (B,) ring of each position

    @property
    def n_beams(self) -> int:
        return int(len(self.elevations_deg))

    @property
    def fov_deg(self) -> tuple[float, float]:
        """(lowest, highest) beam elevation (deg)."""
        return float(self.elevations_deg[0]), float(self.elevations_deg[-1])

    @property
    def vertical_resolution_deg(self) -> float:
        """Median angle (deg) between adjacent beams (0 for a single beam)."""
        if self.n_beams < 2:
            return 0.0
        return float(np.median(np.diff(self.elevations_deg)))

    def ring_of(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) int16 beam index of each point (0 = lowest). Stored beam by beam with this
        model's beam count: the order's azimuth turns; otherwise the nearest beam elevation.
        Points without an azimuth (at the origin, range <= 1 mm, or not finite: drivers
        write (0, 0, 0) for a missing return) do not count for the layout; they get the
        nearest beam elevation."""
        return self.fill(xyz, 0.0, time=False)[0]

    def time_of(self, xyz: np.ndarray, period_s: float) -> np.ndarray | None:
        """(N,) per-point time (s from the sweep start, in [0, period_s)) of a beam-by-beam
        cloud without a time field, or None when the cloud carries no usable order.

        Assumes each beam's points are stored in firing order and its sweep begins at the
        seam (true for organised Ouster clouds and the simulator's KITTI-style HDL-64E):
        t = (azimuth advanced from the seam) / (2 pi) * period_s.
        """
        return self.fill(xyz, period_s, ring=False)[1]

    def fill(
        self, xyz: np.ndarray, period_s: float, *, ring: bool = True, time: bool = True
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(ring, time): ``ring_of(xyz)`` and ``time_of(xyz, period_s)`` in one pass, the
        azimuth, elevation and stored-order test computed once (what a driver without ring
        and time fields costs per scan). ring / time False: that one is not computed (None).
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
        want_time = time and self.layout and self.seam_rad is not None and period_s > 0
        if not (ring or want_time):
            return None, None
        elev = elevation_deg(xyz) if ring else None
        ring_out = time_out = None
        if self.layout and len(xyz):
            az = np.arctan2(xyz[:, 1], xyz[:, 0])
            valid = np.einsum("ij,ij->i", xyz, xyz) > 1e-6  # False for NaN too
            every = bool(valid.all())
            az_v = az if every else az[valid]
            rho = np.hypot(xyz[:, 0], xyz[:, 1])
            fa = _forward_from_azimuth(az_v, rho if every else rho[valid])
            if ring and fa is not None:
                elev_v = elev if every else elev[valid]
                seam = self.seam_rad
                if seam is None:
                    seam = layout_seam(xyz if every else xyz[valid])
                r = None if seam is None else _layout_rings_polar(az_v, elev_v, seam, fa)
                if r is not None and int(r.max()) + 1 == self.n_beams:
                    if every:
                        ring_out = r
                    else:
                        ring_out = self._nearest_beam(elev)
                        ring_out[valid] = r
            if want_time and fa is not None:
                phase = (fa[1] * (az - self.seam_rad)) % (2 * np.pi)
                time_out = phase / (2 * np.pi) * period_s
        if ring and ring_out is None and self.column_rings is not None:
            b = len(self.column_rings)
            if len(xyz) % b == 0:
                ring_out = np.tile(self.column_rings, len(xyz) // b)
        if ring and ring_out is None:
            ring_out = self._nearest_beam(elev)
        return ring_out, time_out

    def _nearest_beam(self, elev: np.ndarray) -> np.ndarray:
        """(N,) int16 ring of the nearest beam elevation to each elevation (deg)."""
        mid = 0.5 * (self.elevations_deg[1:] + self.elevations_deg[:-1])
        return np.searchsorted(mid, elev).astype(np.int16)

    def describe(self) -> str:
        """One line for the log, e.g. 'inferred 64 beams, +2.8..-23.6 deg, ...'."""
        lo, hi = self.fov_deg
        verb = "read" if self.source == "ring field" else "inferred"
        return (
            f"{verb} {self.n_beams} beams, {hi:+.1f}..{lo:+.1f} deg "
            f"(median spacing {self.vertical_resolution_deg:.2f} deg, from the {self.source}), "
            f"99 % of returns within {self.max_range:.0f} m"
        )


def _ranges(scans: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([np.linalg.norm(s, axis=1) for s in scans])


def _check_scans(scans: list[np.ndarray]) -> list[np.ndarray]:
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
    med = _group_medians(elev, dense.ravel(), len(ids))
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
        med = _group_medians(elev[ok], pos[ok], b)
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
            med = _group_medians(elev, ring, n)
            return BeamModel(np.sort(med), True, seam, max_range=max_range, source="point layout")
    raw = [np.asarray(s, dtype=np.float64) for s in given]
    cols = column_rings(raw) if all(np.isfinite(s).all() for s in raw) else None
    if cols is not None:
        elev = np.concatenate([elevation_deg(s) for s in raw])
        pos = np.concatenate([cols[np.arange(len(s)) % len(cols)] for s in raw]).astype(np.int64)
        ok = np.concatenate([np.einsum("ij,ij->i", s, s) > 1e-6 for s in raw])
        med = _group_medians(elev[ok], pos[ok], len(cols))
        return BeamModel(med, max_range=max_range, source="column order", column_rings=cols)
    elev = np.concatenate([elevation_deg(s) for s in scans])
    return BeamModel(_histogram_beams(elev), layout=False, max_range=max_range)


# ---------------------------------------------------------------- compiled kernels
# Each equals the numpy code it replaces (``_forward_azimuth``, ``layout_rings_reference``,
# ``_group_medians``): same float operations in the same order, tested in tests/test_sensor.py.


@njit(cache=True)
def _forward_kernel(
    az: np.ndarray, rho: np.ndarray, max_back: float, near_shift: float
) -> tuple[np.ndarray, float, bool]:
    """(u, sign, ok) of ``_forward_azimuth`` from the (N >= 2,) azimuths (rad) and
    horizontal ranges (m); ok False where the reference gives None for back steps (more
    than 5 % step back > 1e-3 rad)."""
    n = az.size
    m = n - 1
    two_pi = 2.0 * np.pi
    step = np.empty(m)
    n_neg = 0
    big_neg = -np.inf  # the largest negative step
    small_pos = np.inf  # the smallest non-negative step
    for i in range(m):
        s = (az[i + 1] - az[i] + np.pi) % two_pi - np.pi
        step[i] = s
        if s < 0.0:
            n_neg += 1
            big_neg = max(big_neg, s)
        else:
            small_pos = min(small_pos, s)
    # the sign of np.median(step) from the count of negative steps (the two middle values
    # of an even count are the largest negative and the smallest non-negative step)
    h = m // 2
    if m % 2 == 1:
        forward = n_neg <= h
    elif n_neg != h:
        forward = n_neg < h
    else:
        forward = (big_neg + small_pos) / 2.0 >= 0.0
    sign = 1.0 if forward else -1.0
    u = np.empty(n)
    u[0] = 0.0
    n_back = 0
    acc = 0.0
    for i in range(m):
        s = step[i] * sign
        if s < -1e-3:
            n_back += 1
        if s < -max_back and s < -np.arctan2(near_shift, min(rho[i], rho[i + 1])):
            s += two_pi
        acc += s
        u[i + 1] = acc
    return u, sign, n_back / m <= 0.05


@njit(cache=True)
def _group_medians_kernel(
    values: np.ndarray, group: np.ndarray, mask: np.ndarray, n: int
) -> np.ndarray:
    """(n,) upper median of values[mask] per group id 0..n-1 (NaN for an empty group):
    ``_group_medians`` by a counting sort into groups, then one selection per group."""
    counts = np.zeros(n, np.int64)
    for i in range(values.size):
        if mask[i]:
            counts[group[i]] += 1
    start = np.zeros(n + 1, np.int64)
    for g in range(n):
        start[g + 1] = start[g] + counts[g]
    buf = np.empty(start[n])
    fill = start[:n].copy()
    for i in range(values.size):
        if mask[i]:
            g = group[i]
            buf[fill[g]] = values[i]
            fill[g] += 1
    med = np.full(n, np.nan)
    for g in range(n):
        if counts[g] > 0:
            seg = np.partition(buf[start[g] : start[g + 1]], counts[g] // 2)
            med[g] = seg[counts[g] // 2]
    return med


@njit(cache=True)
def _layout_kernel(
    u: np.ndarray, elev: np.ndarray, shift: float, window: float, lo_turns: int, hi_turns: int
) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
    """The per-point work of ``layout_rings_reference``: (turn, n_first, n_turns, counts,
    med). turn: (N,) compacted turn id 0..n_turns-1 of each point after the seam-window
    reassignment; n_first: the turn count before it (outside [lo_turns, hi_turns] the rest
    is not computed); counts, med: points and median elevation (deg) per turn."""
    n = u.size
    two_pi = 2.0 * np.pi
    turn = np.empty(n, np.int64)
    phase = np.empty(n)
    t_min = np.iinfo(np.int64).max
    t_max = np.iinfo(np.int64).min
    for i in range(n):
        v = u[i] - shift
        f = np.floor(v / two_pi)
        t = np.int64(f)
        turn[i] = t
        phase[i] = v - two_pi * f
        t_min = min(t_min, t)
        t_max = max(t_max, t)
    n_first = t_max - t_min + 1
    empty = np.empty(0, np.int64)
    if n_first < lo_turns or n_first > hi_turns:
        return turn, n_first, 0, empty, np.empty(0)
    clear = np.empty(n, np.bool_)
    top = two_pi - window
    for i in range(n):
        turn[i] -= t_min
        clear[i] = not (phase[i] < window or phase[i] > top)
    med = _group_medians_kernel(elev, turn, clear, n_first)
    # points near the seam join the adjacent turn whose median elevation is nearer
    out = turn.copy()
    for i in range(n):
        if clear[i]:
            continue
        other = turn[i] - 1 if phase[i] < window else turn[i] + 1
        if other < 0 or other >= n_first:
            continue
        d_own = abs(elev[i] - med[turn[i]])
        d_other = abs(elev[i] - med[other])
        if d_other < d_own or (np.isnan(d_own) and not np.isnan(d_other)):
            out[i] = other
    # compact the turn ids (np.unique's inverse)
    present = np.zeros(n_first, np.int64)
    for i in range(n):
        present[out[i]] = 1
    new_id = np.empty(n_first, np.int64)
    k = 0
    for g in range(n_first):
        new_id[g] = k
        k += present[g]
    counts = np.zeros(k, np.int64)
    for i in range(n):
        out[i] = new_id[out[i]]
        counts[out[i]] += 1
    med_all = _group_medians_kernel(elev, out, np.ones(n, np.bool_), k)
    return out, n_first, k, counts, med_all
