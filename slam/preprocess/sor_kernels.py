"""Numba kernel of the weighted SOR statistics (paper 000, eqs. (4)-(9)): one fused pass
instead of numpy's temporaries; equal to ``slam.preprocess.sor.weighted_sor_terms`` (the
readable reference), tested in tests/test_sor.py."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def weighted_sor_kernel(
    dist: np.ndarray, alpha: float, delta: float, max_density_ratio: float
) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
    """(d, mu, sigma, rho, theta) of eqs. (4)-(9) from the (N, k) ascending neighbour
    distances (m), N >= 2; see ``weighted_sor_terms``."""
    n, k = dist.shape
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
        d[i] = swd / sw  # eq. (6)
        sum_d += d[i]
        r = max(dist[i, k - 1], 1e-9)
        rho[i] = k / (vol * (r * r * r))
        sum_rho += rho[i]
    mu = sum_d / n  # eq. (8)
    var = 0.0
    for i in range(n):
        var += (d[i] - mu) ** 2
    sigma = np.sqrt(var / (n - 1)) + delta  # eq. (9)
    rho_avg = sum_rho / n
    theta = np.empty(n)
    for i in range(n):
        theta[i] = mu + alpha * sigma * (1.0 + min(rho_avg / rho[i], max_density_ratio))  # (7)
    return d, mu, sigma, rho, theta
