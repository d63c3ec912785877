"""Compiled kernels of the layout cue (``slam.sensor.layout``).

Each equals the numpy code it replaces (``forward_azimuth``, ``layout_rings_reference``,
``group_medians``): same float operations in the same order, tested in tests/test_sensor.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def forward_kernel(
    az: np.ndarray, rho: np.ndarray, max_back: float, near_shift: float, max_share: float
) -> tuple[np.ndarray, float, bool]:
    """(u, sign, ok) of ``forward_azimuth`` from the (N >= 2,) azimuths (rad) and
    horizontal ranges (m); ok False where the reference gives None for back steps (more
    than ``max_share`` step back > 1e-3 rad)."""
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
        near = min(rho[i], rho[i + 1])
        if s < -max_back and near >= near_shift and s < -np.arctan2(near_shift, near):
            s += two_pi
        acc += s
        u[i + 1] = acc
    return u, sign, n_back / m <= max_share


@njit(cache=True)
def group_medians_kernel(
    values: np.ndarray, group: np.ndarray, mask: np.ndarray, n: int
) -> np.ndarray:
    """(n,) upper median of values[mask] per group id 0..n-1 (NaN for an empty group):
    ``group_medians`` by a counting sort into groups, then one selection per group."""
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
def layout_kernel(
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
    med = group_medians_kernel(elev, turn, clear, n_first)
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
    med_all = group_medians_kernel(elev, out, np.ones(n, np.bool_), k)
    return out, n_first, k, counts, med_all
