"""Motion compensation of a sweep under a constant-velocity (constant twist) model."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError, InputError
from slam.registration.gicp import skew


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian V(phi) for (M, 3) rotation vectors (the 'V' of the SE(3) exp)."""
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    K = skew(phi)
    return np.eye(3) + a * K + b * (K @ K)


def se3_log(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Twist (rho, phi) of a 4x4 pose: T = exp([rho, phi]); phi a rotation vector (rad)."""
    phi = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    rho = np.linalg.solve(_left_jacobian(phi[None])[0], T[:3, 3])
    return rho, phi


def interpolate_pose(T_start_end: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (M, 3, 3) and translations (M, 3) of exp(s * log T) for fractions s (M,)."""
    rho, phi = se3_log(np.asarray(T_start_end, dtype=np.float64))
    sphi = s[:, None] * phi[None, :]
    R = Rotation.from_rotvec(sphi).as_matrix()
    t = np.einsum("mij,mj->mi", _left_jacobian(sphi), s[:, None] * rho[None, :])
    return R, t


@njit(cache=True, nogil=True)
def _deskew_kernel(xyz, time, period, theta, u, rho, u_rho, uu_rho):
    """The closed form of ``deskew`` (backend "numpy") point by point in one pass; cos and sin
    once per run of equal stamps (e.g. a firing column)."""
    n = len(time)
    out = np.empty((n, 3))
    s_last = np.nan
    c = sn = a = b = 0.0
    for i in range(n):
        si = time[i] / period
        if si != s_last:
            s_last = si
            x = si * theta
            c, sn = math.cos(x), math.sin(x)
            if abs(x) < 1e-4:  # series: (1 - cos x)/x and (x - sin x)/x lose precision
                a = x / 2.0 - x**3 / 24.0
                b = x**2 / 6.0 - x**4 / 120.0
            else:
                a = (1.0 - c) / x
                b = (x - sn) / x
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        along = (px * u[0] + py * u[1] + pz * u[2]) * (1.0 - c)
        sa, sb = si * a, si * b
        out[i, 0] = (
            px * c
            + (u[1] * pz - u[2] * py) * sn
            + along * u[0]
            + (si * rho[0] + sa * u_rho[0] + sb * uu_rho[0])
        )
        out[i, 1] = (
            py * c
            + (u[2] * px - u[0] * pz) * sn
            + along * u[1]
            + (si * rho[1] + sa * u_rho[1] + sb * uu_rho[1])
        )
        out[i, 2] = (
            pz * c
            + (u[0] * py - u[1] * px) * sn
            + along * u[2]
            + (si * rho[2] + sa * u_rho[2] + sb * uu_rho[2])
        )
    return out


def time_from_firing_order(
    xyz: np.ndarray, sweep_period: float, *, max_backward_share: float = 0.01
) -> np.ndarray | None:
    """(N,) per-point time (s from the sweep start, in [0, sweep_period]) of a spinning-LiDAR
    sweep stored in firing order, column after column (what Velodyne drivers publish), for a
    driver that gives no time field; None when the storage order is not one turn.

    Along the storage order the azimuth of such a cloud turns once, in one direction, in
    small steps: t = (azimuth unwrapped along the order, from the first point) / 2 pi *
    sweep_period, clipped to one sweep. A cloud stored beam by beam (several turns: the
    pipeline reads its times from the layout, ``slam.sensor``), sorted, voxelised or merged
    (steps back and forth) gives None. ``max_backward_share``: the share of steps allowed to
    go back by more than 5 deg (a column straddling the seam, sensors firing their lasers
    at staggered azimuths). Points without an azimuth (at the origin, not finite) take the
    time of the valid points around them.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    if not sweep_period > 0:
        raise InputError(f"sweep_period must be > 0 s, got {sweep_period}")
    valid = np.flatnonzero(np.einsum("ij,ij->i", xyz[:, :2], xyz[:, :2]) > 1e-6)
    if len(valid) < 100:
        return None
    az = np.arctan2(xyz[valid, 1], xyz[valid, 0])
    step = (np.diff(az) + np.pi) % (2.0 * np.pi) - np.pi  # wrapped to [-pi, pi)
    total = float(step.sum())
    # one turn, give or take a few columns (an FOV-limited driver may cut the sweep)
    if not 0.5 * 2.0 * np.pi <= abs(total) <= 1.1 * 2.0 * np.pi:
        return None
    advance = np.sign(total) * step
    if np.mean(advance < -np.radians(5.0)) > max_backward_share:
        return None
    u = np.concatenate([[0.0], np.cumsum(advance)])
    t = np.clip(u, 0.0, 2.0 * np.pi) / (2.0 * np.pi) * sweep_period
    if len(valid) == len(xyz):
        return t
    return np.interp(np.arange(len(xyz)), valid, t)


def deskew(
    xyz: np.ndarray,
    time: np.ndarray | None,
    T_start_end: np.ndarray,
    sweep_period: float,
    *,
    backend: str = "numba",
) -> np.ndarray:
    """Move every point into the sensor frame at the sweep start (constant-velocity model).

    time: (N,) seconds from sweep start, or None (then xyz is returned unchanged).
    T_start_end: 4x4 pose of the sensor at sweep end in the start frame (e.g. the last
    frame-to-frame motion). sweep_period: seconds (0.1 at 10 Hz). A point stamped t is mapped
    by T(s) = exp(s * log T_start_end), s = t / sweep_period (SE(3) geodesic, i.e. constant
    twist over the sweep), p_start = R(s) p + t(s).
    backend: "numba" (default, one compiled pass) or "numpy" (the vectorised reference);
    they agree to ~1e-12 m.
    """
    if backend not in ("numba", "numpy"):
        raise ConfigError(f"deskew: backend must be 'numba' or 'numpy', got {backend!r}")
    if time is None:
        return xyz
    xyz = np.asarray(xyz, dtype=np.float64)
    time = np.asarray(time, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or time.shape != (len(xyz),):
        raise InputError(f"deskew needs xyz (N, 3) and time (N,), got {xyz.shape}, {time.shape}")
    T = np.asarray(T_start_end, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"T_start_end must be 4x4, got {T.shape}")
    if not sweep_period > 0:
        raise InputError(f"sweep_period must be > 0 s, got {sweep_period}")
    if len(xyz) == 0:
        return xyz.copy()
    rho, phi = se3_log(T)
    theta = float(np.linalg.norm(phi))
    if theta < 1e-12:  # pure translation
        return xyz + (time / sweep_period)[:, None] * rho
    # closed form of exp(s * log T) along the fixed axis u: Rodrigues for R(s) p and
    # t(s) = s (rho + (1 - cos x)/x u x rho + (x - sin x)/x u x (u x rho)), x = s * theta;
    # only scalars per point, no per-point matrices
    u = phi / theta
    u_rho = np.cross(u, rho)
    uu_rho = np.cross(u, u_rho)
    if backend == "numba":
        xyz, time = np.ascontiguousarray(xyz), np.ascontiguousarray(time)
        return _deskew_kernel(xyz, time, float(sweep_period), theta, u, rho, u_rho, uu_rho)
    return _deskew_numpy(xyz, time / sweep_period, theta, u, rho, u_rho, uu_rho)


def _deskew_numpy(
    xyz: np.ndarray,
    s: np.ndarray,
    theta: float,
    u: np.ndarray,
    rho: np.ndarray,
    u_rho: np.ndarray,
    uu_rho: np.ndarray,
) -> np.ndarray:
    """The vectorised reference of ``_deskew_kernel``: points at sweep fractions ``s``
    moved by exp(s * log T), T a rotation ``theta`` (rad) about the unit axis ``u``."""
    x = s * theta
    c, sn = np.cos(x), np.sin(x)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)
    a = (1.0 - c) / xs
    b = (xs - sn) / xs
    if small.any():  # series: (1 - cos x)/x and (x - sin x)/x lose precision as x -> 0
        xm = x[small]
        a[small] = xm / 2.0 - xm**3 / 24.0
        b[small] = xm**2 / 6.0 - xm**4 / 120.0
    px, py, pz = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    along = (xyz @ u) * (1.0 - c)
    out = np.empty_like(xyz)
    out[:, 0] = px * c + (u[1] * pz - u[2] * py) * sn + along * u[0]
    out[:, 1] = py * c + (u[2] * px - u[0] * pz) * sn + along * u[1]
    out[:, 2] = pz * c + (u[0] * py - u[1] * px) * sn + along * u[2]
    out += np.outer(s, rho) + np.outer(s * a, u_rho) + np.outer(s * b, uu_rho)
    return out
