"""Numba kernel of the weighted SOR statistics (paper 000, eqs. (4)-(9)): one fused pass
instead of numpy's temporaries; equal to ``slam.preprocess.sor.weighted_sor_terms`` (the
readable reference), tested in tests/test_sor.py.

Degenerate input never divides by zero: no rows or no neighbours (every point kept), one
row (sigma = delta), a row whose weights all underflow (``shifted_row_mean``) and a
neighbourhood too wide for its volume to be finite (density 0: the clamped ratio).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def shifted_row_mean(dist: np.ndarray, i: int, d_avg: float) -> float:
    """Eq. (6) for row i with every weight scaled by exp(dist[i, 0] / d_avg): the same value,
    but the nearest neighbour's weight is 1, so it holds when all of exp(-dist / d_avg)
    underflow to 0 (a point tens of metres from its neighbours in a band of centimetre
    spacing): the weighted mean then tends to the nearest distance."""
    sw = 0.0
    swd = 0.0
    for t in range(dist.shape[1]):
        w = np.exp(-(dist[i, t] - dist[i, 0]) / d_avg)
        sw += w
        swd += w * dist[i, t]
    return swd / sw if sw > 0.0 else dist[i, 0]


@njit(cache=True, nogil=True)
def no_neighbours(
    n: int, alpha: float, delta: float, max_density_ratio: float
) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
    """The terms when there is nothing to judge (no rows or k = 0): d 0, every point kept."""
    return (
        np.zeros(n),
        0.0,
        delta,
        np.zeros(n),
        np.full(n, alpha * delta * (1.0 + max_density_ratio)),
    )


@njit(cache=True, nogil=True)
def density_ratio(rho_avg: float, rho: float, max_density_ratio: float) -> float:
    """min(rho_avg / rho, max_density_ratio) of eq. (7); the clamp when rho is 0 (a
    neighbourhood radius whose cube overflows) or not a number."""
    if rho > 0.0:
        return min(rho_avg / rho, max_density_ratio)
    return max_density_ratio


@njit(cache=True, nogil=True)
def weighted_sor_kernel(
    dist: np.ndarray, alpha: float, delta: float, max_density_ratio: float
) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
    """(d, mu, sigma, rho, theta) of eqs. (4)-(9) from the (N, k) ascending neighbour
    distances (m); see ``weighted_sor_terms``."""
    n, k = dist.shape
    if n == 0 or k == 0:
        return no_neighbours(n, alpha, delta, max_density_ratio)
    total = 0.0
    for i in range(n):
        for t in range(k):
            total += dist[i, t]
    d_avg = max(total / (n * k), 1e-12)  # eq. (5)
    d = np.empty(n)
    rho = np.empty(n)
    sum_d = 0.0
    sum_rho = 0.0
    vol = 4.0 / 3.0 * np.pi
    for i in range(n):
        sw = 0.0
        swd = 0.0
        for t in range(k):
            w = np.exp(-dist[i, t] / d_avg)  # eq. (4)
            sw += w
            swd += w * dist[i, t]
        d[i] = swd / sw if sw > 0.0 else shifted_row_mean(dist, i, d_avg)  # eq. (6)
        sum_d += d[i]
        r = max(dist[i, k - 1], 1e-9)
        rho[i] = k / (vol * (r * r * r))
        sum_rho += rho[i]
    mu = sum_d / n  # eq. (8)
    var = 0.0
    for i in range(n):
        var += (d[i] - mu) ** 2
    sigma = np.sqrt(var / max(n - 1, 1)) + delta  # eq. (9); 0 + delta for one row
    rho_avg = sum_rho / n
    theta = np.empty(n)
    for i in range(n):
        theta[i] = mu + alpha * sigma * (
            1.0 + density_ratio(rho_avg, rho[i], max_density_ratio)
        )  # (7)
    return d, mu, sigma, rho, theta


LN2_HI = 6.93147180369123816490e-01  # ln 2 split for exact range reduction (fdlibm)
LN2_LO = 1.90821492927058770002e-10
LOG2E = 1.44269504088896338700e00
# 1/j! for the Taylor series of exp on |r| <= ln(2)/2 (degree 13: truncation < 5e-18)
EXP_TAYLOR = np.array([1.0 / float(np.prod(np.arange(1, j + 1))) for j in range(14)])
EXP_CHUNK = 256  # rows per pass of the vectorised exp (scratch stays in L1/L2)


@njit(cache=True, nogil=True)
def exp_neg(x: np.ndarray, scale: float, w: np.ndarray, bits: np.ndarray) -> None:
    """w[j] = exp(-x[j] * scale) for x >= 0 (1-D), in loops without calls so that they
    compile to SIMD (libm's exp goes one value at a time): Cody-Waite reduction
    -x scale = n ln2 + r, the Taylor series of exp(r) (EXP_TAYLOR), 2^n from its exponent
    bits (int64 scratch ``bits``, len(x)); within 1 ulp of np.exp (tests/test_sor.py), 0
    below 2^-1022 (np.exp: subnormals)."""
    c = EXP_TAYLOR
    for j in range(len(x)):
        y = -x[j] * scale
        n = np.floor(y * LOG2E + 0.5)
        r = (y - n * LN2_HI) - n * LN2_LO
        p = c[13]
        for t in range(12, -1, -1):
            p = p * r + c[t]
        ok = n >= -1022.0
        w[j] = p if ok else 0.0
        bits[j] = (np.int64(n) + 1023 if ok else 1023) << 52
    two_n = bits.view(np.float64)
    for j in range(len(x)):
        w[j] *= two_n[j]


@njit(cache=True, nogil=True)
def weighted_sor_kernel_simd(
    dist: np.ndarray, alpha: float, delta: float, max_density_ratio: float
) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
    """``weighted_sor_kernel`` with the exp of eq. (4) vectorised (``exp_neg``) in chunks of
    EXP_CHUNK rows; dist C-contiguous. Sums go row by row (the earlier single running sum
    over all N k distances was one add chain), d in per-chunk partial sums added in chunk
    order; values within 1e-13 of ``weighted_sor_kernel`` (tests/test_sor.py). Serial: as a
    parallel kernel it was slower with 2 threads on a loaded machine (one more barrier per
    scan than it saved)."""
    n, k = dist.shape
    if n == 0 or k == 0:
        return no_neighbours(n, alpha, delta, max_density_ratio)
    n_chunks = (n + EXP_CHUNK - 1) // EXP_CHUNK
    d = np.empty(n)
    rho = np.empty(n)
    theta = np.empty(n)
    vol = 4.0 / 3.0 * np.pi
    total = 0.0
    sum_rho = 0.0
    for i in range(n):
        row = 0.0
        for t in range(k):
            row += dist[i, t]
        total += row
        r = max(dist[i, k - 1], 1e-9)
        rho[i] = k / (vol * (r * r * r))
        sum_rho += rho[i]
    d_avg = max(total / (n * k), 1e-12)  # eq. (5)
    flat = dist.reshape(n * k)
    part = np.empty(n_chunks)  # per chunk: sum of d
    w = np.empty(EXP_CHUNK * k)
    bits = np.empty(EXP_CHUNK * k, dtype=np.int64)
    for c in range(n_chunks):
        a = c * EXP_CHUNK
        b = min(n, a + EXP_CHUNK)
        m = (b - a) * k
        exp_neg(flat[a * k : b * k], 1.0 / d_avg, w[:m], bits[:m])  # eq. (4)
        sum_d = 0.0
        for i in range(a, b):
            sw = 0.0
            swd = 0.0
            for t in range(k):
                wt = w[(i - a) * k + t]
                sw += wt
                swd += wt * dist[i, t]
            d[i] = swd / sw if sw > 0.0 else shifted_row_mean(dist, i, d_avg)  # eq. (6)
            sum_d += d[i]
        part[c] = sum_d
    sum_d = 0.0
    for c in range(n_chunks):
        sum_d += part[c]
    mu = sum_d / n  # eq. (8)
    var = 0.0
    for i in range(n):
        var += (d[i] - mu) ** 2
    sigma = np.sqrt(var / max(n - 1, 1)) + delta  # eq. (9); 0 + delta for one row
    rho_avg = sum_rho / n
    for i in range(n):
        theta[i] = mu + alpha * sigma * (
            1.0 + density_ratio(rho_avg, rho[i], max_density_ratio)
        )  # (7)
    return d, mu, sigma, rho, theta
