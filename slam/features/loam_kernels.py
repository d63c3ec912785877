"""Compiled kernels of the LOAM feature selection (``slam.features.loam``).

The numpy reference ``loam._extract_features_numpy`` is the readable version; these kernels
do the same arithmetic in the same order (curvature and every decision bit-identical, tested
in tests/test_features_fast.py) in a few sequential passes:

- ``ring_order``: used points sorted by (ring, key, index): a counting sort by ring, then per
  ring a shortcut for the layouts of spinning lidars (sorted, reversed, or two runs of
  azimuth merged once) or a natural merge sort (``stable_argsort``), linear on real scans
  and O(n log n) on any input.
- ``loam_scores``: curvature (A-LOAM, prefix sums), LOAM's occlusion and parallel-beam
  rejections, suppression runs, edge and plane candidates.
- ``greedy_nms``: A-LOAM's sequential greedy non-maximum suppression, cluster by cluster.
- ``sector_top``: the max_less_sharp sharpest picks per ring sector."""

from __future__ import annotations

import numpy as np
from numba import njit

SMALL = 32  # clusters of at most this many NMS candidates are sorted by insertion


@njit(cache=True, nogil=True)
def _merge_runs(idx, key, bounds, n_runs, buf_i, buf_k):
    """Stable bottom-up merge of the sorted runs [bounds[r], bounds[r+1]) of key (and idx
    alongside); ties keep the left run first. Result in idx/key."""
    src_i, src_k, dst_i, dst_k = idx, key, buf_i, buf_k
    in_src = True
    while n_runs > 1:
        r = 0
        m = 0
        while r < n_runs:
            a = bounds[r]
            if r + 1 < n_runs:
                b, e = bounds[r + 1], bounds[r + 2]
                i, j, o = a, b, a
                while i < b and j < e:
                    if src_k[j] < src_k[i]:
                        dst_i[o] = src_i[j]
                        dst_k[o] = src_k[j]
                        j += 1
                    else:
                        dst_i[o] = src_i[i]
                        dst_k[o] = src_k[i]
                        i += 1
                    o += 1
                while i < b:
                    dst_i[o] = src_i[i]
                    dst_k[o] = src_k[i]
                    i += 1
                    o += 1
                while j < e:
                    dst_i[o] = src_i[j]
                    dst_k[o] = src_k[j]
                    j += 1
                    o += 1
            else:
                e = bounds[r + 1]
                dst_i[a:e] = src_i[a:e]
                dst_k[a:e] = src_k[a:e]
            bounds[m] = a
            m += 1
            r += 2
        bounds[m] = bounds[n_runs]
        n_runs = m
        src_i, dst_i = dst_i, src_i
        src_k, dst_k = dst_k, src_k
        in_src = not in_src
    if not in_src:
        idx[:] = src_i
        key[:] = src_k


@njit(cache=True, nogil=True)
def stable_argsort(key):
    """np.argsort(key, kind="stable") for a key without NaN: natural merge sort (runs that
    are non-decreasing, or strictly decreasing and then reversed, merged pairwise)."""
    n = len(key)
    idx = np.arange(n)
    k = key.copy()
    if n < 2:
        return idx
    bounds = np.empty(n + 1, dtype=np.int64)
    n_runs = 0
    i = 0
    while i < n:
        bounds[n_runs] = i
        n_runs += 1
        j = i + 1
        if j < n and k[j] < k[i]:
            while j < n and k[j] < k[j - 1]:
                j += 1
            lo, hi = i, j - 1
            while lo < hi:  # strictly decreasing: reversing keeps ties (there are none) stable
                k[lo], k[hi] = k[hi], k[lo]
                idx[lo], idx[hi] = idx[hi], idx[lo]
                lo += 1
                hi -= 1
        else:
            while j < n and k[j] >= k[j - 1]:
                j += 1
        i = j
    bounds[n_runs] = n
    if n_runs > 1:
        _merge_runs(idx, k, bounds, n_runs, np.empty(n, dtype=np.int64), np.empty(n))
    return idx


@njit(cache=True, nogil=True)
def _sort_ring(seg, key):
    """Sort the indices seg (ascending) in place by key[seg], ties by position (stable).
    Spinning-lidar rings take a shortcut: one non-decreasing run (nothing to do), one
    strictly decreasing run (reversed) or two non-decreasing runs (a turn that starts
    mid-ring, possibly overlapping itself: one merge); anything else is merge-sorted."""
    n = len(seg)
    if n < 2:
        return
    n_drop = 0
    cut = 0
    for j in range(1, n):
        if key[seg[j]] < key[seg[j - 1]]:
            n_drop += 1
            cut = j
    if n_drop == 0:
        return
    if n_drop == n - 1:  # strictly decreasing: no ties, reversing is stable
        seg[:] = seg[::-1].copy()
        return
    if n_drop > 1:
        seg[:] = seg[stable_argsort(key[seg])]
        return
    left = seg[:cut].copy()  # merge seg[:cut] and seg[cut:] (ties: left first)
    i, j, o = 0, cut, 0
    while i < cut and j < n:
        if key[seg[j]] < key[left[i]]:
            seg[o] = seg[j]
            j += 1
        else:
            seg[o] = left[i]
            i += 1
        o += 1
    while i < cut:
        seg[o] = left[i]
        i += 1
        o += 1


@njit(cache=True, nogil=True)
def ring_order(xyz, ring, key, min_range, max_range, ring_max):
    """The points to use (ring >= 0, range in [min_range, max_range] m) sorted by
    (ring, key, index): their indices and the start of each non-empty ring (R + 1,) in that
    order. ring_max >= every ring id. Empty order when a used point has a NaN key (the
    caller falls back to the reference)."""
    n_all = len(ring)
    use = np.zeros(n_all, dtype=np.bool_)
    counts = np.zeros(ring_max + 2, dtype=np.int64)
    r_max = -1
    nan_key = False
    for i in range(n_all):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        d = np.sqrt((x * x + y * y) + z * z)  # = np.linalg.norm(xyz, axis=1)
        r = ring[i]
        if r >= 0 and d >= min_range and d <= max_range:
            use[i] = True
            counts[r + 1] += 1
            r_max = max(r_max, r)
            nan_key |= np.isnan(key[i])
    if nan_key or r_max < 0:
        return np.empty(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    n_dense = 0
    for r in range(r_max + 1):
        if counts[r + 1] > 0:
            n_dense += 1
        counts[r + 1] += counts[r]
    order = np.empty(counts[r_max + 1], dtype=np.int64)
    fill = counts[:-1].copy()
    for i in range(n_all):
        if use[i]:
            order[fill[ring[i]]] = i
            fill[ring[i]] += 1
    start = np.empty(n_dense + 1, dtype=np.int64)
    d = 0
    for r in range(r_max + 1):
        a, b = counts[r], counts[r + 1]
        if b > a:
            start[d] = a
            _sort_ring(order[a:b], key)
            d += 1
    start[n_dense] = len(order)
    return order, start


@njit(cache=True, nogil=True, error_model="numpy")
def loam_scores(
    xyz,
    order,
    start,
    w,
    edge_threshold,
    plane_threshold,
    neighbor_gap,
    reject_occluded,
    reject_parallel,
    occlusion_gap,
    occlusion_ratio,
    parallel_ratio,
    curvature_out,
):
    """Per sorted point (order: input indices, start: rings as from ``ring_order``): curvature
    c (m^2, NaN at ring ends; also written to curvature_out at the input index), suppression
    run, edge candidate and plane candidate flags; the steps of
    ``loam._extract_features_numpy`` in one pass, with the same arithmetic."""
    n = len(order)
    c = np.empty(n)
    run = np.empty(n, dtype=np.int32)
    rejected = np.zeros(n, dtype=np.bool_)
    # prefix sums csum[j] = p_0 + ... + p_{j-1} over the concatenated rings (the sums of
    # np.cumsum), kept for the last 2w + 2 indices only: cb[j % L] = csum[j]
    L = 2 * w + 2
    cb = np.zeros((L, 3))
    j_done = 0
    cur = 0  # = j_done % L (no integer modulo in the loop)
    m = float(2 * w + 1)
    gap_prev = np.inf  # squared gap (m^2) from the previous point of the ring
    run_id = 0
    r = 0
    for k in range(n):
        i = order[k]
        while k >= start[r + 1]:
            r += 1
        r0, r1 = start[r], start[r + 1]
        pos = k - r0
        nr = r1 - r0
        hi = min(k + w + 1, n)
        while j_done < hi:
            nxt = cur + 1 if cur + 1 < L else 0
            q = order[j_done]
            cb[nxt, 0] = cb[cur, 0] + xyz[q, 0]
            cb[nxt, 1] = cb[cur, 1] + xyz[q, 1]
            cb[nxt, 2] = cb[cur, 2] + xyz[q, 2]
            cur = nxt
            j_done += 1
        x0, x1, x2 = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if pos >= w and pos < nr - w:
            # hi = k + w + 1 here: csum[hi] is the newest slot, csum[k - w] the one after it
            up = cur
            lo = cur + 1 if cur + 1 < L else 0
            d0 = cb[up, 0] - cb[lo, 0] - m * x0
            d1 = cb[up, 1] - cb[lo, 1] - m * x1
            d2 = cb[up, 2] - cb[lo, 2] - m * x2
            c[k] = (d0 * d0 + d1 * d1) + d2 * d2
        else:
            c[k] = np.nan
            rejected[k] = True  # not valid: never an edge nor a plane
        curvature_out[i] = c[k]
        run[k] = run_id
        gap = np.inf
        if k + 1 < r1:
            i1 = order[k + 1]
            y0, y1, y2 = xyz[i1, 0], xyz[i1, 1], xyz[i1, 2]
            e0, e1, e2 = y0 - x0, y1 - x1, y2 - x2
            gap = (e0 * e0 + e1 * e1) + e2 * e2
            dk = np.sqrt((x0 * x0 + x1 * x1) + x2 * x2)  # range (m), as np.linalg.norm
            if reject_parallel and gap_prev < np.inf:
                lim = parallel_ratio * (dk * dk)
                if gap > lim and gap_prev > lim:
                    rejected[k] = True
            if reject_occluded and gap > occlusion_gap:
                dn = np.sqrt((y0 * y0 + y1 * y1) + y2 * y2)
                if dk > dn:  # the far point k and w before it are behind the near silhouette
                    f = dn / dk
                    a0, a1, a2 = y0 - x0 * f, y1 - x1 * f, y2 - x2 * f
                    if np.sqrt((a0 * a0 + a1 * a1) + a2 * a2) / dn < occlusion_ratio:
                        rejected[max(k - w, r0) : k + 1] = True
                else:
                    f = dk / dn
                    a0, a1, a2 = y0 * f - x0, y1 * f - x1, y2 * f - x2
                    if np.sqrt((a0 * a0 + a1 * a1) + a2 * a2) / dk < occlusion_ratio:
                        rejected[k + 1 : min(k + w + 2, r1)] = True
        if gap > neighbor_gap:  # a run ends at a large gap or a ring end
            run_id += 1
        gap_prev = gap
    cand = np.empty(n, dtype=np.bool_)
    plane_cand = np.empty(n, dtype=np.bool_)
    for k in range(n):
        ck = c[k]
        cand[k] = not rejected[k] and ck > edge_threshold
        plane_cand[k] = ck < plane_threshold  # False for NaN (ring ends)
    return c, run, cand, plane_cand


@njit(cache=True, nogil=True)
def greedy_nms(key, cand, run, w):
    """A-LOAM's greedy selection with no count limit, picks (positions, ascending): candidates
    visited by decreasing key (ties by position), each picked unless a picked one lies within
    +-w in the same run. Candidates more than w apart (or in other runs) never interact, so
    the greedy order is needed only within each cluster of close candidates."""
    ci = np.flatnonzero(cand)
    n = len(key)
    picked = np.zeros(n, dtype=np.bool_)
    blocked = np.zeros(n, dtype=np.bool_)
    visit = np.empty(SMALL, dtype=np.int64)
    a = 0
    while a < len(ci):
        b = a + 1
        while b < len(ci) and ci[b] - ci[b - 1] <= w and run[ci[b]] == run[ci[a]]:
            b += 1
        m = b - a
        if m == 1:
            picked[ci[a]] = True
            a = b
            continue
        seg = ci[a:b]
        if m <= SMALL:  # insertion sort by decreasing key, ties by position (stable)
            for j in range(m):
                v = seg[j]
                t = j
                while t > 0 and key[visit[t - 1]] < key[v]:
                    visit[t] = visit[t - 1]
                    t -= 1
                visit[t] = v
            order = visit[:m]
        else:
            neg = np.empty(m)
            for j in range(m):
                neg[j] = -key[seg[j]]
            order = seg[stable_argsort(neg)]
        for i in order:
            if blocked[i]:
                continue
            picked[i] = True
            for j in range(max(i - w, seg[0]), min(i + w, seg[-1]) + 1):
                if run[j] == run[i]:
                    blocked[j] = True
        a = b
    return np.flatnonzero(picked)


@njit(cache=True, nogil=True)
def sector_top(sel, start, key, w, n_sectors, n_max):
    """The picks sel (sorted positions, ascending) that rank < n_max by decreasing key (ties
    by position) in their sector: each ring's valid span [w, len - w) cut into n_sectors
    equal parts (the reference's sector numbering; a sector is a range of positions)."""
    keep = np.zeros(len(sel), dtype=np.bool_)
    sector = np.empty(len(sel), dtype=np.int64)
    r = 0
    for j in range(len(sel)):
        k = sel[j]
        while k >= start[r + 1]:
            r += 1
        nr = start[r + 1] - start[r]
        span = max(nr - 2 * w, 1)
        s = (k - start[r] - w) * n_sectors // span
        sector[j] = r * n_sectors + min(max(s, 0), n_sectors - 1)
    a = 0
    while a < len(sel):
        b = a + 1
        while b < len(sel) and sector[b] == sector[a]:
            b += 1
        if b - a <= n_max:
            keep[a:b] = True
        else:
            neg = np.empty(b - a)
            for j in range(b - a):
                neg[j] = -key[sel[a + j]]
            keep[a + stable_argsort(neg)[:n_max]] = True
        a = b
    return sel[keep]
