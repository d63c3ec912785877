"""Numba kernels of the range-image k-NN (slam.preprocess.range_image): the ring/azimuth sort
and the certified window search. Equal to the KD-tree k-NN; tested in tests/test_range_image.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

BLOCK = 512  # points per parallel work item (one top-k buffer each)
RING_BLOCK = 8  # consecutive points of a ring summarised by their range interval
H_MARGIN = 1e-12  # haversine slack: float error of the angle bounds (~1e-6 m at 100 m range)


@njit(cache=True)
def sort_rings(rank: np.ndarray, az: np.ndarray, n_rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Order of the points by (ring rank, azimuth) and the ring offsets into it (n_rings + 1).

    A counting sort by ring, then each ring by azimuth; rings that arrive in (reversed)
    azimuth order, as most drivers store them, cost one pass instead of a sort."""
    n = len(rank)
    start = np.zeros(n_rings + 1, dtype=np.int64)
    for i in range(n):
        start[rank[i] + 1] += 1
    for j in range(n_rings):
        start[j + 1] += start[j]
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[rank[i]]] = i
        fill[rank[i]] += 1
    for j in range(n_rings):
        a, b = start[j], start[j + 1]
        if b - a < 2:
            continue
        seg = order[a:b]
        asc = 0
        desc = 0
        for t in range(b - a - 1):
            d = az[seg[t + 1]] - az[seg[t]]
            if d > 0:
                asc += 1
            elif d < 0:
                desc += 1
        if desc == 0:
            continue
        if asc == 0:
            order[a:b] = seg[::-1].copy()
            continue
        order[a:b] = seg[np.argsort(az[seg], kind="mergesort")]
    return order, start


@njit(cache=True, inline="always")
def _bound2(h: float, r2: float) -> float:
    """Squared lower bound of the distance from p (|p|^2 = r2) to any point on a ray at
    angle theta from p's ray, given h <= hav(theta): |p| sin(theta), |p| beyond 90 deg."""
    h -= H_MARGIN
    if h <= 0.0:
        return 0.0
    if h >= 0.5:
        return r2
    return 4.0 * h * (1.0 - h) * r2


@njit(cache=True, inline="always")
def _insert(bd: np.ndarray, bi: np.ndarray, nfound: int, d2: float, q: int) -> int:
    """Insert (d2, q) into the ascending top-k buffers holding nfound entries (the caller
    checked nfound < k or d2 < bd[k-1]); returns the new count."""
    k = len(bd)
    t = nfound if nfound < k else k - 1
    while t > 0 and bd[t - 1] > d2:
        bd[t] = bd[t - 1]
        bi[t] = bi[t - 1]
        t -= 1
    bd[t] = d2
    bi[t] = q
    return nfound + 1 if nfound < k else k


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


@njit(cache=True, parallel=True)
def window_knn(
    xyz: np.ndarray,
    el: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    az_sorted: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    k: int,
    max_visits: int,
    out_idx: np.ndarray,
    out_d2: np.ndarray,
    certified: np.ndarray,
    n_visits: np.ndarray,
) -> None:
    """k nearest other points of every point, searched ring by ring outward from its own
    ring and, in each ring, outward in azimuth from its own azimuth, until a bound proves
    that no unvisited point can be nearer than the k-th found (then certified[i] = True).

    Inputs in sorted order (``sort_rings``): xyz (N, 3) m, el elevation (rad), (cx, cy) unit
    azimuth direction, az_sorted azimuth (rad), lo/hi per-ring elevation range (rad). The
    bounds: the spherical law of haversines, hav(theta) = hav(de) + cos(e_p) cos(e_q)
    hav(phi) >= hav(de_min) + cos(e_p) min cos(e_ring) hav(phi_min), gives the smallest
    angle theta to the unvisited rays; all unvisited points are >= |p| sin(theta) away, and
    the points of a block of RING_BLOCK consecutive points >= the law-of-cosines distance at
    that angle over the block's range interval, so such a block is skipped unread.
    Writes out_idx (N, k) original indices and out_d2 (N, k) squared distances (m^2),
    ascending, and n_visits (N,) the distance evaluations, at each point's original index.
    A point that needs more than max_visits distance evaluations stops uncertified (its row
    is then not valid)."""
    n = len(order)
    n_rings = len(start) - 1
    B = RING_BLOCK
    half = (k + 1) // 2  # own-ring positions each side read before any bound is tried
    # per-ring bounds: min cos of the elevation range, suffix min / prefix max elevations
    clo = np.empty(n_rings)
    sufmin = np.empty(n_rings + 1)
    prefmax = np.empty(n_rings + 1)
    sufmin[n_rings] = np.inf
    prefmax[0] = -np.inf
    bstart = np.zeros(n_rings + 1, dtype=np.int64)
    for j in range(n_rings):
        clo[j] = min(np.cos(lo[j]), np.cos(hi[j]))
        prefmax[j + 1] = max(prefmax[j], hi[j])
        bstart[j + 1] = bstart[j] + (start[j + 1] - start[j] + B - 1) // B
    for j in range(n_rings - 1, -1, -1):
        sufmin[j] = min(sufmin[j + 1], lo[j])
    # range of every point, range interval of every block
    rng = np.empty(n)
    for s in range(n):
        rng[s] = np.sqrt(xyz[s, 0] * xyz[s, 0] + xyz[s, 1] * xyz[s, 1] + xyz[s, 2] * xyz[s, 2])
    rmin = np.full(bstart[n_rings], np.inf)
    rmax = np.zeros(bstart[n_rings])
    for j in range(n_rings):
        a = start[j]
        for u in range(start[j + 1] - a):
            ib = bstart[j] + u // B
            rmin[ib] = min(rmin[ib], rng[a + u])
            rmax[ib] = max(rmax[ib], rng[a + u])
    n_chunks = (n + BLOCK - 1) // BLOCK
    for chunk in prange(n_chunks):
        bd = np.empty(k)
        bi = np.empty(k, dtype=np.int64)
        g = 0
        while start[g + 1] <= chunk * BLOCK:
            g += 1
        for s in range(chunk * BLOCK, min(n, (chunk + 1) * BLOCK)):
            while start[g + 1] <= s:
                g += 1
            px, py, pz = xyz[s, 0], xyz[s, 1], xyz[s, 2]
            cxp, cyp = cx[s], cy[s]
            rp = rng[s]
            r2 = rp * rp
            ep = el[s]
            cep = np.cos(ep)
            azp = az_sorted[s]
            nfound = 0
            visits = 0
            up_open = True
            down_open = True
            m = 0
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
                    if m > 0 and nfound == k and de > 0.0:
                        # every ring beyond: at least this elevation gap away
                        sh = np.sin(0.5 * de)
                        if _bound2(sh * sh, r2) > bd[k - 1]:
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
                            if nfound < k or d2 < bd[k - 1]:
                                nfound = _insert(bd, bi, nfound, d2, q)
                        visits += w - 1
                        budget = cnt - w
                        u_right = pos + half + 1
                        u_left = pos - half - 1
                        he = 0.0
                    else:
                        lo_i, hi_i = a, a + cnt  # first point of ring j at azimuth >= azp
                        while lo_i < hi_i:
                            mid = (lo_i + hi_i) // 2
                            if az_sorted[mid] < azp:
                                lo_i = mid + 1
                            else:
                                hi_i = mid
                        budget = cnt
                        u_right = lo_i - a
                        u_left = u_right - 1
                        dej = max(lo[j] - ep, ep - hi[j], 0.0)
                        she = np.sin(0.5 * dej)
                        he = she * she
                    coef = 0.5 * cep * clo[j]
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
                            if nfound == k:
                                h = he + coef * (1.0 - (cx[q] * cxp + cy[q] * cyp))
                                if _bound2(h, r2) > bd[k - 1]:
                                    break  # the frontier bounds everything beyond it
                                # entering a block at its edge: skip it whole when its range
                                # interval and angle keep it beyond the k-th distance
                                b0 = u - u % B
                                b1 = min(cnt, b0 + B) - 1
                                if u == (b0 if step > 0 else b1):
                                    qf = a + (b1 if step > 0 else b0)
                                    hf = he + coef * (1.0 - (cx[qf] * cxp + cy[qf] * cyp))
                                    bb = _block_bound2(
                                        min(h, hf), r2, rp, rmin[ib0 + b0 // B], rmax[ib0 + b0 // B]
                                    )
                                    if bb > bd[k - 1]:
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
                            if nfound < k or d2 < bd[k - 1]:
                                nfound = _insert(bd, bi, nfound, d2, q)
                m += 1
            o = order[s]
            certified[o] = visits <= max_visits and nfound == k
            n_visits[o] = visits
            for t in range(k):
                if t < nfound:
                    out_d2[o, t] = bd[t]
                    out_idx[o, t] = order[bi[t]]
                else:
                    out_d2[o, t] = np.inf
                    out_idx[o, t] = -1
