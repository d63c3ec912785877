"""Layout detection: is a cloud stored beam by beam, where do its turns begin, and which ring
is each point from the stored order (cue 1 of ``slam.sensor``)."""

from __future__ import annotations

import numpy as np

from slam.sensor.layout_kernels import forward_kernel, group_medians_kernel, layout_kernel

MIN_TURN_BEAMS, MAX_TURN_BEAMS = 4, 256  # layout cue: accepted number of azimuth turns
MIN_TURN_POINTS = 100  # a beam of a layout scan has at least this many points
# a cloud whose azimuth steps back (> 1e-3 rad) on more than this share of its points is not
# stored beam by beam: nuScenes' column order 32 %; KITTI odometry at 10 m/s 0.5 %, a
# simulated motion-compensated HDL-64E at 25 m/s 5.8 % (near and spurious returns)
MAX_BACK_SHARE = 0.1
MAX_BACK_STEP_DEG = 5.0  # layout: a larger backward azimuth step is a forward gap...
# ...unless a near point explains it: motion compensation (KITTI odometry) and the lasers'
# offsets from the origin move a point at range r by up to this much (m), i.e. its azimuth
# by atan(shift / r), any amount within it: a car at 25 m/s moves 2.5 m over a 10 Hz sweep
# (6-11 deg back steps at 1.3-1.9 m on KITTI odometry at 10 m/s; a simulated compensated
# HDL-64E at 18 m/s steps back 100-150 deg at spurious returns within 1.3 m)
NEAR_SHIFT_M = 2.5
LAYOUT_SEAM_DEG = 3.0  # beams of a layout scan start their turn within this azimuth
# motion compensation stretches a sweep beyond one turn (near points at car speed): the
# first / last beam then spills past the seam, a fragment of < this share of a beam's
# points lying within SEAM_SPILL_DEG of the seam (a simulated compensated HDL-64E's bottom
# beam spills 90 deg at 18 m/s, 107 deg at 25 m/s)
SEAM_SPILL_SHARE, SEAM_SPILL_DEG = 0.25, 150.0


def elevation_deg(xyz: np.ndarray) -> np.ndarray:
    """(N,) elevation (deg) of each point seen from the sensor origin."""
    return np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))


def group_medians(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """(n,) median of values per group id 0..n-1 (upper median; NaN for an empty group)."""
    span = float(np.ptp(values)) + 1.0 if len(values) else 1.0
    order = np.argsort(group * span + (values - (values.min() if len(values) else 0.0)))
    counts = np.bincount(group, minlength=n)
    start = np.r_[0, np.cumsum(counts)[:-1]]
    med = np.full(n, np.nan)
    has = counts > 0
    med[has] = values[order][start[has] + counts[has] // 2]
    return med


def forward_azimuth(xyz: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """(u, sign, az0): the azimuth (rad) advanced along the stored order from the first point,
    the rotation's sign and the first point's azimuth; None for clouds whose azimuth steps
    back often (firing order: every column) or that are too small for a layout.
    The readable numpy reference of ``forward_kernel`` (tests/test_sensor.py)."""
    if len(xyz) < MIN_TURN_BEAMS * MIN_TURN_POINTS:
        return None
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    step = (np.diff(az) + np.pi) % (2 * np.pi) - np.pi  # in [-pi, pi)
    sign = 1.0 if np.median(step) >= 0 else -1.0  # direction of rotation along the order
    step *= sign
    if np.mean(step < -1e-3) > MAX_BACK_SHARE:
        return None
    # within a beam's turn the azimuth only advances: a large backward step is a forward gap
    # (no returns over > 180 deg, e.g. sky), not a step back, unless a near point explains it
    rho = np.hypot(xyz[:, 0], xyz[:, 1])
    near = np.minimum(rho[:-1], rho[1:])
    allowed = np.maximum(np.radians(MAX_BACK_STEP_DEG), np.arctan2(NEAR_SHIFT_M, near))
    allowed[near < NEAR_SHIFT_M] = np.pi
    step = np.where(step < -allowed, step + 2 * np.pi, step)
    u = np.r_[0.0, np.cumsum(step)]
    n_est = int(u[-1] // (2 * np.pi)) + 1
    if not MIN_TURN_BEAMS <= n_est <= MAX_TURN_BEAMS + 1:
        return None
    return u, sign, float(az[0])


def forward_from_azimuth(az: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(u, sign) of ``forward_azimuth`` from the azimuths (rad) and horizontal ranges (m)
    already computed, through the compiled ``forward_kernel``; None where the reference
    returns None."""
    if len(az) < MIN_TURN_BEAMS * MIN_TURN_POINTS:
        return None
    u, sign, ok = forward_kernel(
        az, rho, np.radians(MAX_BACK_STEP_DEG), NEAR_SHIFT_M, MAX_BACK_SHARE
    )
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
    med = group_medians(elev, turn, int(turn.max()) + 1)
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
    fa = forward_azimuth(xyz)
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
    fa = forward_azimuth(xyz)
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
    med = group_medians(elev[clear], turn[clear], n_turns)
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
    d = np.diff(group_medians(elev, turn, n_turns))
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
    fa = forward_from_azimuth(az, np.hypot(xyz[:, 0], xyz[:, 1]))
    return layout_rings_polar(az, elevation_deg(xyz), seam, fa)


def layout_rings_polar(
    az: np.ndarray, elev: np.ndarray, seam: float, fa: tuple[np.ndarray, float] | None
) -> np.ndarray | None:
    """``layout_rings`` from the azimuths (rad) and elevations (deg) of the points and their
    ``forward_from_azimuth`` (None: not a layout)."""
    if fa is None:
        return None
    u, sign = fa
    shift = (sign * (seam - float(az[0]))) % (2 * np.pi)
    turn, n_first, n_turns, counts, med = layout_kernel(
        u, elev, shift, np.radians(LAYOUT_SEAM_DEG), MIN_TURN_BEAMS, MAX_TURN_BEAMS + 1
    )
    if not MIN_TURN_BEAMS <= n_first <= MAX_TURN_BEAMS + 1:
        return None
    merged, n_merged = _merge_spills(turn, n_turns, None, u, shift, counts)
    if n_merged != n_turns:
        turn, n_turns = merged, n_merged
        counts = np.bincount(turn, minlength=n_turns)
        med = group_medians_kernel(elev, turn, np.ones(len(turn), np.bool_), n_turns)
    if not MIN_TURN_BEAMS <= n_turns <= MAX_TURN_BEAMS or np.median(counts) < MIN_TURN_POINTS:
        return None
    d = np.diff(med)
    if not (np.all(d <= 0.05) or np.all(d >= -0.05)):
        return None
    ring = turn if d.sum() >= 0 else n_turns - 1 - turn
    return ring.astype(np.int16)
