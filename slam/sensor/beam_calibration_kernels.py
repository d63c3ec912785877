"""Compiled kernels of ``slam.sensor.beam_calibration``: the same numbers as its numpy
references (``rotate_beams`` with per-beam offsets, ``normal_equations``) in one pass over
the points (tests/test_beam_calibration.py)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def apply_offsets(xyz, rings, table):
    """(N, 3) points with the offsets ``table`` (B, 3: elevation rad, azimuth rad, range m)
    of their beam applied about the origin; rings outside the table are copied."""
    n_b = table.shape[0]
    ce, se = np.cos(table[:, 0]), np.sin(table[:, 0])
    ca, sa = np.cos(table[:, 1]), np.sin(table[:, 1])
    out = np.empty_like(xyz)
    for i in range(xyz.shape[0]):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        b = rings[i]
        if b < 0 or b >= n_b:
            out[i, 0], out[i, 1], out[i, 2] = x, y, z
            continue
        rho = math.sqrt(x * x + y * y)
        rho_new = rho * ce[b] - z * se[b]
        s = rho_new / rho if rho > 0 else 1.0
        xs, ys = x * s, y * s
        nx, ny, nz = xs * ca[b] - ys * sa[b], xs * sa[b] + ys * ca[b], z * ce[b] + rho * se[b]
        r = math.sqrt(x * x + y * y + z * z)
        g = (r + table[b, 2]) / r if r > 0 else 1.0
        out[i, 0], out[i, 1], out[i, 2] = nx * g, ny * g, nz * g
    return out


@njit(cache=True, nogil=True)
def normal_equations_kernel(p, rings, R, t, q, W, weight, n_beams):
    """Per beam sum_i J_i^T W_i J_i (n_beams, 3, 3), sum_i J_i^T W_i e_i (n_beams, 3) and the
    pair counts, J_i the map-frame derivative of point i by its beam's (elevation, azimuth,
    range), e_i = R p_i + t - q_i."""
    A = np.zeros((n_beams, 3, 3))
    B = np.zeros((n_beams, 3))
    count = np.zeros(n_beams, dtype=np.int64)
    J = np.empty((3, 3))
    Js = np.empty((3, 3))
    WJ = np.empty((3, 3))
    e = np.empty(3)
    for i in range(p.shape[0]):
        b = rings[i]
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        rho = max(math.sqrt(x * x + y * y), 1e-9)
        r = max(math.sqrt(x * x + y * y + z * z), 1e-9)
        # sensor-frame derivatives: columns elevation, azimuth, range
        Js[0, 0], Js[1, 0], Js[2, 0] = -z * x / rho, -z * y / rho, rho
        Js[0, 1], Js[1, 1], Js[2, 1] = -y, x, 0.0
        Js[0, 2], Js[1, 2], Js[2, 2] = x / r, y / r, z / r
        for a in range(3):
            e[a] = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z + t[a] - q[i, a]
            for c in range(3):
                J[a, c] = R[a, 0] * Js[0, c] + R[a, 1] * Js[1, c] + R[a, 2] * Js[2, c]
        for a in range(3):
            for c in range(3):
                WJ[a, c] = W[i, a, 0] * J[0, c] + W[i, a, 1] * J[1, c] + W[i, a, 2] * J[2, c]
        w = weight[i]
        for c in range(3):
            B[b, c] += w * (WJ[0, c] * e[0] + WJ[1, c] * e[1] + WJ[2, c] * e[2])
            for d in range(3):
                A[b, c, d] += w * (J[0, c] * WJ[0, d] + J[1, c] * WJ[1, d] + J[2, c] * WJ[2, d])
        count[b] += 1
    return A, B, count
