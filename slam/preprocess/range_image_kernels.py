"""Numba kernels of the range-image k-NN (slam.preprocess.range_image): the ring/azimuth sort
and the certified window search. Equal to the KD-tree k-NN; tested in tests/test_range_image.py.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

# the parallel window search's threading layer: OpenMP or numba's own workqueue before TBB
# (the TBB of the wheels we depend on is older than numba accepts and it warns on first use)
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

RING_BLOCK = 16  # ring points summarised by their range interval (8, 32: within 3 %); 2^n
H_MARGIN = 1e-12  # haversine slack: float error of the angle bounds (~1e-6 m at 100 m range)
# Rings whose elevations span more than WIDE_RING (rad) get elevation bounds per azimuth
# sector (SECTORS over the full turn) and per block: a real sensor's beams sit off the
# origin, so a ring's elevation seen from the origin moves with range (KITTI-raw HDL-64E:
# 1.9 deg per ring, every ring overlapping its neighbours), and the ring-wide interval
# then prunes no ring; a simulated ring spans ~1e-8 rad.
WIDE_RING = 1e-4
SECTORS = 256


@njit(cache=True, nogil=True)
def sort_rings(rank: np.ndarray, az: np.ndarray, n_rings: int, order: np.ndarray) -> np.ndarray:
    """Writes order (N,), the points by (ring rank, azimuth); returns the ring offsets into it
    (n_rings + 1).

    A counting sort by ring, then each ring by azimuth; rings that arrive in (reversed,
    rotated) azimuth order, as most drivers store them, cost one pass instead of a sort."""
    n = len(rank)
    start = np.zeros(n_rings + 1, dtype=np.int64)
    for i in range(n):
        start[rank[i] + 1] += 1
    for j in range(n_rings):
        start[j + 1] += start[j]
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[rank[i]]] = i
        fill[rank[i]] += 1
    for j in range(n_rings):
        a, b = start[j], start[j + 1]
        if b - a < 2:
            continue
        seg = order[a:b].copy()
        asc = 0
        desc = 0
        for t in range(b - a - 1):
            d = az[seg[t + 1]] - az[seg[t]]
            if d > 0:
                asc += 1
            elif d < 0:
                desc += 1
        if asc < desc:  # clockwise drivers
            seg = seg[::-1].copy()
            asc, desc = desc, asc
        if desc == 0:
            order[a:b] = seg
        elif desc == 1 and az[seg[-1]] <= az[seg[0]]:  # sorted from another start: rotate
            t = 0
            while az[seg[t + 1]] >= az[seg[t]]:
                t += 1
            order[a : b - t - 1] = seg[t + 1 :]
            order[b - t - 1 : b] = seg[: t + 1]
        else:
            order[a:b] = seg[np.argsort(az[seg], kind="mergesort")]
    return start


@njit(cache=True, inline="always")
def _pseudo_azimuth(x: float, y: float) -> float:
    """A monotone stand-in for atan2(y, x), in [-2, 2] (the "diamond angle", wrapping where
    atan2 does): sorting and searching by azimuth need its order only; the bounds use the
    unit direction (cx, cy)."""
    if x == 0.0 and y == 0.0:
        return 0.0
    if y >= 0.0:
        return y / (x + y) if x >= 0.0 else 1.0 - x / (y - x)
    return y / (x + y) - 2.0 if x < 0.0 else x / (x - y) - 1.0


@njit(cache=True, nogil=True)
def ring_ranks(ring: np.ndarray, el: np.ndarray) -> tuple[np.ndarray, int]:
    """(N,) rank of each point's ring among the rings present, ordered by their mean
    elevation el (rad), and the number of rings present. Any integer ring labels."""
    rank = np.empty(len(ring), dtype=np.int64)
    return rank, ring_ranks_into(ring, el, rank)


@njit(cache=True, nogil=True)
def ring_ranks_into(ring: np.ndarray, el: np.ndarray, rank: np.ndarray) -> int:
    """``ring_ranks`` writing the ranks into rank (N,); returns the number of rings."""
    n = len(ring)
    r0 = ring.min()
    size = ring.max() - r0 + 1
    counts = np.zeros(size, dtype=np.int64)
    sums = np.zeros(size)
    for i in range(n):
        counts[ring[i] - r0] += 1
        sums[ring[i] - r0] += el[i]
    present = np.flatnonzero(counts)
    means = sums[present] / counts[present]
    lut = np.zeros(size, dtype=np.int64)
    lut[present[np.argsort(means, kind="mergesort")]] = np.arange(len(present))
    for i in range(n):
        rank[i] = lut[ring[i] - r0]
    return len(present)


def range_image(xyz: np.ndarray, ring: np.ndarray):
    """The scan sorted into its range image: (order, start, xyz_s, rng_s, el_s, az_s, cx_s,
    cy_s, lo, hi, spread): sorted index -> input index, ring offsets, sorted points (m),
    range (m), elevation (rad), pseudo-azimuth (``_pseudo_azimuth``), unit azimuth
    direction, per-ring elevation range (rad), mean absolute deviation of the elevations
    from their ring's mean (rad). Rings ordered by mean elevation (``ring_ranks``). Plain
    Python around ``range_image_into`` (xyz (N, 3) float64, ring (N,) int64)."""
    n = len(xyz)
    order = np.empty(n, dtype=np.int64)
    xyz_s = np.empty((n, 3))
    rng = np.empty(n)
    el_s = np.empty(n)
    az_s = np.empty(n)
    cx = np.empty(n)
    cy = np.empty(n)
    start, lo, hi, spread = range_image_into(
        xyz, ring, np.empty(n), np.empty(n), np.empty(n, dtype=np.int64), order, xyz_s, rng,
        el_s, az_s, cx, cy,
    )  # fmt: skip
    return order, start, xyz_s, rng, el_s, az_s, cx, cy, lo, hi, spread


@njit(cache=True, nogil=True)
def range_image_into(xyz, ring, az, el, rank, order, xyz_s, rng, el_s, az_s, cx, cy):
    """``range_image`` into caller-owned (N,) / (N, 3) buffers (reused from scan to scan:
    fresh arrays cost page faults, a third of the time of a 16-beam scan's SOR); az, el and
    rank are scratch. Returns (start, lo, hi, spread). Serial: as a parallel kernel (the
    atan2 per point in prange) it added a parallel region per scan, and with 2 threads on
    a loaded machine each region's barrier cost more than it saved."""
    n = len(xyz)
    for i in range(n):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        az[i] = _pseudo_azimuth(x, y)
        el[i] = np.arctan2(z, np.sqrt(x * x + y * y))
    n_rings = ring_ranks_into(ring, el, rank)
    start = sort_rings(rank, az, n_rings, order)
    lo = np.full(n_rings, np.inf)
    hi = np.full(n_rings, -np.inf)
    dev = 0.0  # sum |elevation - its ring's mean elevation|
    for j in range(n_rings):
        mean = 0.0
        for s in range(start[j], start[j + 1]):
            i = order[s]
            x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            xyz_s[s, 0], xyz_s[s, 1], xyz_s[s, 2] = x, y, z
            rho = np.sqrt(x * x + y * y)
            rng[s] = np.sqrt(x * x + y * y + z * z)
            e = el[i]
            el_s[s] = e
            mean += e
            az_s[s] = az[i]
            if rho > 0.0:
                cx[s], cy[s] = x / rho, y / rho
            else:
                cx[s], cy[s] = 1.0, 0.0
            lo[j] = min(lo[j], e)
            hi[j] = max(hi[j], e)
        if start[j + 1] > start[j]:
            mean /= start[j + 1] - start[j]
            for s in range(start[j], start[j + 1]):
                dev += abs(el_s[s] - mean)
    return start, lo, hi, dev / max(n, 1)


@njit(cache=True, inline="always")
def _hav_lower(x: float) -> float:
    """A lower bound of hav(x) = sin^2(x / 2) for 0 <= x <= pi (sin y >= y - y^3 / 6)."""
    y = 0.5 * x
    s = y - y * y * y / 6.0
    return s * s


@njit(cache=True, inline="always")
def _ray_bound2(h: float, r2: float) -> float:
    """Squared lower bound (m^2) of |p - q| over the points q on rays at hav(angle) >= h
    from p's ray, |p|^2 = r2 m^2: |p| sin(theta) (sin^2 = 4 hav (1 - hav)), |p| from 90 deg
    on. Compared with the k-th squared distance directly: no square root or division when
    the k-th distance changes (the earlier form inverted it to a haversine per insert)."""
    h -= H_MARGIN
    if h <= 0.0:
        return 0.0
    if h >= 0.5:
        return r2
    return 4.0 * h * (1.0 - h) * r2


@njit(cache=True, inline="always")
def _insert(bd: np.ndarray, bi: np.ndarray, d2: float, q: int) -> None:
    """Insert (d2, q) into the ascending, inf-padded top-k buffers (the caller checked
    d2 < bd[k-1]) after the entries equal to d2, dropping the last. Branch-free (min/max
    and integer selects over all k slots: the shifting loop's exit was mispredicted once
    per insert)."""
    for t in range(len(bd) - 1, 0, -1):
        a = bd[t - 1]
        b = bd[t]
        shift = np.int64(a > d2)  # slot t takes slot t-1
        put = np.int64(a <= d2) * np.int64(b > d2)  # slot t takes the new entry
        bd[t] = max(min(b, d2), a)
        bi[t] += shift * (bi[t - 1] - bi[t]) + put * (q - bi[t])
    put = np.int64(bd[0] > d2)
    bi[0] += put * (q - bi[0])
    bd[0] = min(bd[0], d2)


@njit(cache=True, inline="always")
def _ce(a: float, b: float, ia: int, ib: int) -> tuple[float, float, int, int]:
    """Compare-exchange of a sorting network, branch-free (minsd/maxsd and an integer
    select: the conditional-expression form compiled to branches, mispredicted on half of
    the comparators; ties keep their order, as before)."""
    dd = (ib - ia) * np.int64(b < a)
    return min(a, b), max(a, b), ia + dd, ib - dd


@njit(cache=True, nogil=True)
def _sort10(bd: np.ndarray, bi: np.ndarray) -> None:
    """Sort 10 (distance, index) pairs ascending: Waksman's 29-comparator network on
    registers; the window's first k = 10 candidates arrive in no predictable order, and
    the mispredicted branches of insertion sort were the main cost."""
    d0, d1, d2, d3, d4, d5, d6, d7, d8, d9 = (
        bd[0],
        bd[1],
        bd[2],
        bd[3],
        bd[4],
        bd[5],
        bd[6],
        bd[7],
        bd[8],
        bd[9],
    )
    q0, q1, q2, q3, q4, q5, q6, q7, q8, q9 = (
        bi[0],
        bi[1],
        bi[2],
        bi[3],
        bi[4],
        bi[5],
        bi[6],
        bi[7],
        bi[8],
        bi[9],
    )
    d4, d9, q4, q9 = _ce(d4, d9, q4, q9)
    d3, d8, q3, q8 = _ce(d3, d8, q3, q8)
    d2, d7, q2, q7 = _ce(d2, d7, q2, q7)
    d1, d6, q1, q6 = _ce(d1, d6, q1, q6)
    d0, d5, q0, q5 = _ce(d0, d5, q0, q5)
    d1, d4, q1, q4 = _ce(d1, d4, q1, q4)
    d6, d9, q6, q9 = _ce(d6, d9, q6, q9)
    d0, d3, q0, q3 = _ce(d0, d3, q0, q3)
    d5, d8, q5, q8 = _ce(d5, d8, q5, q8)
    d0, d2, q0, q2 = _ce(d0, d2, q0, q2)
    d3, d6, q3, q6 = _ce(d3, d6, q3, q6)
    d7, d9, q7, q9 = _ce(d7, d9, q7, q9)
    d0, d1, q0, q1 = _ce(d0, d1, q0, q1)
    d2, d4, q2, q4 = _ce(d2, d4, q2, q4)
    d5, d7, q5, q7 = _ce(d5, d7, q5, q7)
    d8, d9, q8, q9 = _ce(d8, d9, q8, q9)
    d1, d2, q1, q2 = _ce(d1, d2, q1, q2)
    d4, d6, q4, q6 = _ce(d4, d6, q4, q6)
    d7, d8, q7, q8 = _ce(d7, d8, q7, q8)
    d3, d5, q3, q5 = _ce(d3, d5, q3, q5)
    d2, d5, q2, q5 = _ce(d2, d5, q2, q5)
    d6, d8, q6, q8 = _ce(d6, d8, q6, q8)
    d1, d3, q1, q3 = _ce(d1, d3, q1, q3)
    d4, d7, q4, q7 = _ce(d4, d7, q4, q7)
    d2, d3, q2, q3 = _ce(d2, d3, q2, q3)
    d6, d7, q6, q7 = _ce(d6, d7, q6, q7)
    d3, d4, q3, q4 = _ce(d3, d4, q3, q4)
    d5, d6, q5, q6 = _ce(d5, d6, q5, q6)
    d4, d5, q4, q5 = _ce(d4, d5, q4, q5)
    bd[0], bd[1], bd[2], bd[3], bd[4], bd[5], bd[6], bd[7], bd[8], bd[9] = (
        d0,
        d1,
        d2,
        d3,
        d4,
        d5,
        d6,
        d7,
        d8,
        d9,
    )
    bi[0], bi[1], bi[2], bi[3], bi[4], bi[5], bi[6], bi[7], bi[8], bi[9] = (
        q0,
        q1,
        q2,
        q3,
        q4,
        q5,
        q6,
        q7,
        q8,
        q9,
    )


@njit(cache=True, inline="always")
def _stop_dot(kth2: float, r2: float, he: float, coef: float) -> float:
    """The 1 - dot(azimuth of p, of q) beyond which ``_ray_bound2(he + coef (1 - dot), r2)``
    exceeds kth2 (inf: nowhere): he + coef (1 - dot) > h + H_MARGIN with 4 h (1 - h) r2 =
    kth2, h < 1/2 (in the form without cancellation, widened by 1e-12 relative). One
    comparison per point walked instead of the bound; recomputed when kth2 shrinks."""
    if not kth2 < r2 or coef <= 0.0:
        return np.inf
    x = kth2 / r2
    h = 0.5 * x / (1.0 + np.sqrt(1.0 - x))
    return max(h * (1.0 + 1e-12) + H_MARGIN - he, 0.0) / coef


@njit(cache=True, inline="always")
def _sector(az: float) -> int:
    """Azimuth sector (0 .. SECTORS - 1) of a pseudo-azimuth in [-2, 2]."""
    return min(max(int((az + 2.0) * (SECTORS / 4.0)), 0), SECTORS - 1)


@njit(cache=True, inline="always")
def _sector_span(kth2: float, r2: float, cep: float, clo_min: float, cxp: float, cyp: float):
    """(first sector, number of sectors) holding every azimuth whose ray bound alone (at
    the lowest cos(elevation) of the scan, clo_min) is <= kth2 m^2, for p with unit azimuth
    (cxp, cyp), cos(elevation) cep and squared range r2; (0, SECTORS) for the whole turn
    (half-width 90 deg or more). Points outside the span are farther than sqrt(kth2), so
    elevation bounds taken over the span alone hold for all points."""
    if not kth2 < r2 or cep * clo_min <= 0.0:
        return 0, SECTORS
    h = 0.5 * (1.0 - np.sqrt(1.0 - kth2 / r2))  # 4 h (1 - h) r2 = kth2, h < 1/2
    c1 = 2.0 * (h + 2.0 * H_MARGIN) * (1.0 + 1e-9) / (cep * clo_min)  # 1 - cos(half-width)
    if c1 >= 1.0:
        return 0, SECTORS
    c = 1.0 - c1
    sn = np.sqrt(c1 * (2.0 - c1))
    a_lo = _pseudo_azimuth(cxp * c + cyp * sn, cyp * c - cxp * sn)  # clockwise edge
    a_hi = _pseudo_azimuth(cxp * c - cyp * sn, cyp * c + cxp * sn)
    s0 = _sector(a_lo)
    s1 = _sector(a_hi)
    return s0, (s1 - s0) % SECTORS + 1


@njit(cache=True, inline="always")
def _block_bound2(h: float, r2: float, rp: float, rmin: float, rmax: float) -> float:
    """Squared lower bound of |p - q| over the points q of a block: rays at hav(angle) >= h
    from p's ray and ranges in [rmin, rmax] m (law of cosines, minimised over the range)."""
    h -= H_MARGIN
    if h <= 0.0:
        return 0.0
    c = 1.0 - 2.0 * h  # cos of the smallest angle
    r = min(max(rp * c, rmin), rmax)
    return max(r2 + r * r - 2.0 * rp * r * c, 0.0)


@njit(cache=True, nogil=True, parallel=True)
def window_knn(
    xyz: np.ndarray,
    rng: np.ndarray,
    el: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    az: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    k: int,
    max_visits: int,
    out_idx: np.ndarray,
    out_dist: np.ndarray,
    certified: np.ndarray,
    n_visits: np.ndarray,
    in_input_order: bool,
    job: np.ndarray,
    exit2: float,
    exited: np.ndarray,
) -> None:
    """k nearest other points of every point, searched ring by ring outward from its own
    ring and, in each ring, outward in azimuth from its own azimuth, until a bound proves
    that no unvisited point can be nearer than the k-th found (then certified[i] = True).

    job: empty (every point searched in full) or (N,) int8 per sorted position: 0 = skip
    (its row is not written), 1 = search in full, 2 = stop as soon as the k-th distance
    found is <= sqrt(exit2) m (exited[row] = True, certified False: the row holds k real
    points, each distance an upper bound of the true one at its rank; the weighted SOR
    needs no more to keep such a point, ``slam.preprocess.sor``). exited: (N,) bool, written
    where job is given.

    Inputs sorted by ``range_image``. The bounds: the spherical law of haversines,
    hav(theta) = hav(de) + cos(e_p) cos(e_q) hav(phi) >= hav(de_min) + cos(e_p)
    min cos(e_ring) hav(phi_min), gives the smallest angle theta from p's ray to the
    unvisited rays (elevation gap de to the rings not searched, azimuth gap phi to the
    columns not searched); all unvisited points are >= |p| sin(theta) away, and the points
    of a block of RING_BLOCK consecutive points >= the law-of-cosines distance at that angle
    over the block's range interval, so such a block is skipped unread.
    Writes out_idx (N, k+1) input indices, the point itself first, and out_dist (N, k)
    distances (m) to the k others, ascending, certified (N,) and n_visits (N,)
    the distance evaluations, in the input order if in_input_order else in sorted order
    (row s is the input point order[s]). A point that needs
    more than max_visits distance evaluations stops uncertified (its row is then not valid).
    """
    n_rings = len(start) - 1
    use_job = len(job) > 0
    B = RING_BLOCK
    half = (k + 1) // 2  # own-ring positions each side read before any bound is tried
    # per-ring bounds: min cos of the elevation range, suffix min / prefix max elevations
    clo = np.empty(n_rings)
    sufmin = np.empty(n_rings + 1)
    prefmax = np.empty(n_rings + 1)
    sufmin[n_rings] = np.inf
    prefmax[0] = -np.inf
    # no np.full / np.zeros at this level: each would be a parallel region of its own
    bstart = np.empty(n_rings + 1, dtype=np.int64)
    bstart[0] = 0
    for j in range(n_rings):
        clo[j] = min(np.cos(lo[j]), np.cos(hi[j]))
        prefmax[j + 1] = max(prefmax[j], hi[j])
        bstart[j + 1] = bstart[j] + (start[j + 1] - start[j] + B - 1) // B
    for j in range(n_rings - 1, -1, -1):
        sufmin[j] = min(sufmin[j + 1], lo[j])
    rmin = np.empty(bstart[n_rings])
    rmax = np.empty(bstart[n_rings])
    for j in range(n_rings):  # serial: a second parallel region costs more than it saves
        a = start[j]
        for ib in range(bstart[j], bstart[j + 1]):
            rmin[ib] = np.inf
            rmax[ib] = 0.0
        for u in range(start[j + 1] - a):
            ib = bstart[j] + u // B
            rmin[ib] = min(rmin[ib], rng[a + u])
            rmax[ib] = max(rmax[ib], rng[a + u])
    # wide rings (WIDE_RING): elevation interval per ring and azimuth sector, its suffix
    # min / prefix max over the rings, and per block
    S = SECTORS
    wide = False
    clo_min = 1.0
    for j in range(n_rings):
        wide = wide or hi[j] - lo[j] > WIDE_RING
        clo_min = min(clo_min, clo[j])
    n_sec = n_rings * S if wide else 1
    n_blk = bstart[n_rings] if wide else 1
    selo = np.empty(n_sec)
    sehi = np.empty(n_sec)
    ssuf = np.empty(n_sec + S)
    spre = np.empty(n_sec + S)
    belo = np.empty(n_blk)
    behi = np.empty(n_blk)
    if wide:
        for t in range(n_rings * S):
            selo[t] = np.inf
            sehi[t] = -np.inf
        for j in range(n_rings):
            a = start[j]
            for ib in range(bstart[j], bstart[j + 1]):
                belo[ib] = np.inf
                behi[ib] = -np.inf
            for u in range(start[j + 1] - a):
                e = el[a + u]
                t = j * S + _sector(az[a + u])
                selo[t] = min(selo[t], e)
                sehi[t] = max(sehi[t], e)
                ib = bstart[j] + u // B
                belo[ib] = min(belo[ib], e)
                behi[ib] = max(behi[ib], e)
        for t in range(S):
            ssuf[n_rings * S + t] = np.inf
            spre[t] = -np.inf
        for j in range(n_rings - 1, -1, -1):
            for t in range(S):
                ssuf[j * S + t] = min(ssuf[(j + 1) * S + t], selo[j * S + t])
        for j in range(n_rings):
            for t in range(S):
                spre[(j + 1) * S + t] = max(spre[j * S + t], sehi[j * S + t])
    for g in prange(n_rings):  # rings are independent: one thread per ring at a time
        bd = np.empty(k)
        bi = np.empty(k, dtype=np.int64)
        cursor = np.full(n_rings, -1, dtype=np.int64)  # per ring: first point at azimuth >= current
        g_a = start[g]
        g_cnt = start[g + 1] - g_a
        for s in range(g_a, g_a + g_cnt):
            ex2 = -1.0  # exit below this squared k-th distance (-1: never)
            if use_job:
                if job[s] == 0:
                    continue
                if job[s] == 2:
                    ex2 = exit2
            px, py, pz = xyz[s, 0], xyz[s, 1], xyz[s, 2]
            cxp, cyp = cx[s], cy[s]
            rp = rng[s]
            r2 = rp * rp
            ep = el[s]
            # cos(elevation) = |(x, y)| / |p|: a root and a division instead of libm's cos
            cep = np.sqrt(px * px + py * py) / rp if rp > 0.0 else 1.0
            azp = az[s]
            for t in range(k):
                bd[t] = np.inf
                bi[t] = -1
            visits = 0
            kth2 = np.inf
            up_open = True
            down_open = True
            m = 0
            span_kth2 = -1.0  # the kth2 the sector span was computed for (-1: none yet)
            s0 = 0
            ns = S
            stop_now = False  # exited (then budget 0 and both sides closed: the loops end)
            while (up_open or down_open) and visits <= max_visits:
                for side in range(2):
                    if side == 0:
                        if not up_open:
                            continue
                        j = g + m
                        if j >= n_rings:
                            up_open = False
                            continue
                        de = sufmin[j] - ep
                    else:
                        if m == 0 or not down_open:
                            continue
                        j = g - m
                        if j < 0:
                            down_open = False
                            continue
                        de = ep - prefmax[j + 1]
                    beyond = m > 0 and de > 0.0 and _ray_bound2(_hav_lower(de), r2) > kth2
                    if m > 0 and wide and not beyond:
                        if span_kth2 != kth2:
                            s0, ns = _sector_span(kth2, r2, cep, clo_min, cx[s], cy[s])
                            span_kth2 = kth2
                        if ns < S:  # the same over the azimuth sectors in reach
                            de = np.inf
                            for t in range(s0, s0 + ns):
                                tt = t - S if t >= S else t
                                if side == 0:
                                    de = min(de, ssuf[j * S + tt] - ep)
                                else:
                                    de = min(de, ep - spre[(j + 1) * S + tt])
                            de = min(de, np.pi)
                            beyond = de > 0.0 and _ray_bound2(_hav_lower(de), r2) > kth2
                    if beyond:
                        # every ring beyond is at least this elevation gap away
                        if side == 0:
                            up_open = False
                        else:
                            down_open = False
                        continue
                    a = start[j]
                    cnt = start[j + 1] - a
                    if cnt == 0:
                        continue
                    if m == 0:
                        # own ring: pos+1, pos-1, pos+2, ... read before any bound is tried
                        # (ascending distances: cheap inserts)
                        pos = s - a
                        w = min(cnt, 2 * half + 1)
                        network = k == 10 and w == 11
                        for t in range(1, w):
                            u = pos + (t + 1) // 2 if t % 2 == 1 else pos - t // 2
                            if u < 0:
                                u += cnt
                            elif u >= cnt:
                                u -= cnt
                            q = a + u
                            dx = xyz[q, 0] - px
                            dy = xyz[q, 1] - py
                            dz = xyz[q, 2] - pz
                            d2 = dx * dx + dy * dy + dz * dz
                            if network:
                                bd[t - 1] = d2
                                bi[t - 1] = q
                            elif d2 < bd[k - 1]:
                                _insert(bd, bi, d2, q)
                        if network:
                            _sort10(bd, bi)
                        visits += w - 1
                        kth2 = bd[k - 1]
                        budget = cnt - w
                        if kth2 <= ex2:
                            stop_now = True
                            budget = 0
                            up_open = down_open = False
                        u_right = pos + half + 1
                        u_left = pos - half - 1
                        he = 0.0
                    else:
                        he = _hav_lower(max(lo[j] - ep, ep - hi[j], 0.0))
                        if _ray_bound2(he, r2) > kth2:
                            continue  # the whole ring is too far in elevation
                        if wide and hi[j] - lo[j] > WIDE_RING:
                            if span_kth2 != kth2:
                                s0, ns = _sector_span(kth2, r2, cep, clo_min, cx[s], cy[s])
                                span_kth2 = kth2
                            if ns < S:  # its elevations over the sectors in reach
                                elo = np.inf
                                ehi = -np.inf
                                for t in range(s0, s0 + ns):
                                    tt = j * S + (t - S if t >= S else t)
                                    elo = min(elo, selo[tt])
                                    ehi = max(ehi, sehi[tt])
                                he = _hav_lower(min(max(elo - ep, ep - ehi, 0.0), np.pi))
                                if _ray_bound2(he, r2) > kth2:
                                    continue
                        c = cursor[j]
                        if c < 0:  # first point of ring j at azimuth >= azp
                            lo_i, hi_i = a, a + cnt
                            while lo_i < hi_i:
                                mid = (lo_i + hi_i) // 2
                                if az[mid] < azp:
                                    lo_i = mid + 1
                                else:
                                    hi_i = mid
                            c = lo_i
                        else:  # azimuth grows along the own ring: walk the cursor on
                            while c < a + cnt and az[c] < azp:
                                c += 1
                        cursor[j] = c
                        budget = cnt
                        u_right = c - a
                        u_left = u_right - 1
                    # hav(angle to q) >= he + coef (1 - dot(azimuth of p, of q))
                    coef = 0.5 * cep * clo[j]
                    stop = _stop_dot(kth2, r2, he, coef)
                    ib0 = bstart[j]
                    for direction in range(2):
                        step = 1 if direction == 0 else -1
                        u = u_right if direction == 0 else u_left
                        while budget > 0 and visits <= max_visits:
                            if u >= cnt:
                                u -= cnt
                            elif u < 0:
                                u += cnt
                            q = a + u
                            if kth2 < np.inf:
                                one_m_dot = 1.0 - (cx[q] * cxp + cy[q] * cyp)
                                if one_m_dot > stop:
                                    break  # the frontier bounds everything beyond it
                                # entering a block at its edge: skip it whole when its range
                                # interval and angle keep it beyond the k-th distance
                                um = u & (B - 1)  # u % B (0 <= u < cnt, B a power of 2)
                                if um == 0 if step > 0 else (um == B - 1 or u == cnt - 1):
                                    b0 = u - um
                                    b1 = min(cnt, b0 + B) - 1
                                    qf = a + (b1 if step > 0 else b0)
                                    far = 1.0 - (cx[qf] * cxp + cy[qf] * cyp)
                                    ib = ib0 + b0 // B
                                    if wide:
                                        de_b = max(belo[ib] - ep, ep - behi[ib], 0.0)
                                        hb = max(he, _hav_lower(de_b))
                                    else:
                                        hb = he
                                    hb += coef * min(one_m_dot, far)
                                    if _block_bound2(hb, r2, rp, rmin[ib], rmax[ib]) > kth2:
                                        n_b = min(b1 - b0 + 1, budget)
                                        budget -= n_b
                                        u += step * n_b
                                        continue
                            budget -= 1
                            u += step
                            if q == s:
                                continue
                            visits += 1
                            dx = xyz[q, 0] - px
                            dy = xyz[q, 1] - py
                            dz = xyz[q, 2] - pz
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 < kth2:
                                _insert(bd, bi, d2, q)
                                kth2 = bd[k - 1]
                                if kth2 <= ex2:
                                    stop_now = True
                                    budget = 0
                                    up_open = down_open = False
                                stop = _stop_dot(kth2, r2, he, coef)
                m += 1
            # rows in input order when the input is stored ring by ring (near-sequential
            # writes), else in sorted order (scattered writes cost a third of the kernel on
            # column-major scans; the caller gathers them back)
            o = order[s] if in_input_order else s
            certified[o] = visits <= max_visits and bd[k - 1] < np.inf and not stop_now
            if use_job:
                exited[o] = stop_now
            n_visits[o] = visits
            out_idx[o, 0] = order[s]
            row = out_dist[o]
            for t in range(k):  # over 0-based 1-D arrays: vsqrtpd
                row[t] = np.sqrt(bd[t])
            for t in range(k):
                out_idx[o, t + 1] = order[bi[t]] if bi[t] >= 0 else -1


BOX = 16  # sorted points per bounding box of the exact search for uncertified points
SUPER = 16  # boxes per super box


@njit(cache=True, nogil=True)
def chunk_boxes(xyz: np.ndarray, size: int) -> np.ndarray:
    """(ceil(N / size), 6) axis-aligned bounds (min xyz, max xyz; m) of consecutive chunks of
    ``size`` points. Chunks of the range-image order are short arcs of one ring: tight boxes."""
    n = len(xyz)
    nb = (n + size - 1) // size
    box = np.empty((nb, 6))
    for b in range(nb):
        for c in range(3):
            box[b, c] = np.inf
            box[b, c + 3] = -np.inf
        for s in range(b * size, min(n, (b + 1) * size)):
            for c in range(3):
                box[b, c] = min(box[b, c], xyz[s, c])
                box[b, c + 3] = max(box[b, c + 3], xyz[s, c])
    return box


@njit(cache=True, nogil=True)
def merge_boxes(box: np.ndarray, size: int) -> np.ndarray:
    """Bounds of consecutive groups of ``size`` boxes (the next level of ``chunk_boxes``)."""
    nb = len(box)
    ns = (nb + size - 1) // size
    out = np.empty((ns, 6))
    for g in range(ns):
        for c in range(3):
            out[g, c] = np.inf
            out[g, c + 3] = -np.inf
        for b in range(g * size, min(nb, (g + 1) * size)):
            for c in range(3):
                out[g, c] = min(out[g, c], box[b, c])
                out[g, c + 3] = max(out[g, c + 3], box[b, c + 3])
    return out


@njit(cache=True, inline="always")
def _box_dist2(box: np.ndarray, b: int, px: float, py: float, pz: float) -> float:
    """Squared distance (m^2) from (px, py, pz) to box b (0 inside)."""
    dx = max(box[b, 0] - px, 0.0, px - box[b, 3])
    dy = max(box[b, 1] - py, 0.0, py - box[b, 4])
    dz = max(box[b, 2] - pz, 0.0, pz - box[b, 5])
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True, parallel=True)
def box_knn(
    xyz: np.ndarray,
    order: np.ndarray,
    queries: np.ndarray,
    k: int,
    out_idx: np.ndarray,
    out_dist: np.ndarray,
    in_input_order: bool,
) -> None:
    """Exact k-NN of the sorted points ``queries`` (positions into the range-image order)
    by a two-level box hierarchy over that order (``chunk_boxes``, BOX points per box, SUPER
    boxes per super box): every box nearer than the current k-th distance is read, so the
    answer is exact whatever the window search left. The rows' window answers (k real
    points, an upper bound of the k-th distance when finite) seed the pruning radius.
    Rows, as ``window_knn`` writes them, are overwritten with the exact answer."""
    box = chunk_boxes(xyz, BOX)
    sup = merge_boxes(box, SUPER)
    n = len(xyz)
    for r in prange(len(queries)):
        s = queries[r]
        o = order[s] if in_input_order else s
        px, py, pz = xyz[s, 0], xyz[s, 1], xyz[s, 2]
        seed = out_dist[o, k - 1]
        # the seed distance was rounded through sqrt: widen it by far more than an ulp
        cut = (seed * (1.0 + 1e-9)) ** 2 + 1e-300 if seed < np.inf else np.inf
        bd = np.full(k, np.inf)
        bi = np.full(k, -1, dtype=np.int64)
        dsup = np.empty(len(sup))
        for g in range(len(sup)):
            dsup[g] = _box_dist2(sup, g, px, py, pz)
        g0 = np.argmin(dsup)
        for h in range(len(sup) + 1):  # the nearest super box first: a small radius early
            g = g0 if h == 0 else h - 1
            if dsup[g] > cut or (h > 0 and g == g0):
                continue
            for b in range(g * SUPER, min(len(box), (g + 1) * SUPER)):
                if _box_dist2(box, b, px, py, pz) > cut:
                    continue
                for q in range(b * BOX, min(n, (b + 1) * BOX)):
                    if q == s:
                        continue
                    dx = xyz[q, 0] - px
                    dy = xyz[q, 1] - py
                    dz = xyz[q, 2] - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < bd[k - 1]:
                        _insert(bd, bi, d2, q)
                        cut = min(cut, bd[k - 1])
        out_idx[o, 0] = order[s]
        for t in range(k):
            out_dist[o, t] = np.sqrt(bd[t])
            out_idx[o, t + 1] = order[bi[t]] if bi[t] >= 0 else -1


@njit(cache=True, nogil=True)
def gather_rows(order, idx_s, dist_s, cert_s, visits_s, idx, dist, cert, visits) -> None:
    """Rows in range-image order (row s is input point order[s]) to the input order: a
    gather (sequential writes); the same CPU time as the scatter it replaces (strided reads
    of 168-byte rows: a page per row on column-major scans). Serial: in parallel chunks it
    was slower with 2 threads on a loaded machine (one more barrier per scan)."""
    n, k = dist.shape
    inv = np.empty(n, dtype=np.int64)
    for s in range(n):
        inv[order[s]] = s
    for o in range(n):
        s = inv[o]
        src = dist_s[s]
        dst = dist[o]
        for t in range(k):
            dst[t] = src[t]
        for t in range(k + 1):
            idx[o, t] = idx_s[s, t]
        cert[o] = cert_s[s]
        visits[o] = visits_s[s]
