"""Per-beam elevation, azimuth and range offsets of a spinning lidar, learned online from
the registration residuals.

A laser whose elevation is off by delta from the driver's table draws the ground as a cone:
a return at horizontal range rho lies rho * delta too high or low. Factory calibrations leave
~0.1 deg and a few cm per beam (Glennie & Lichti 2010; KITTI's HDL-64E scans are known to
need a common 0.22 deg), and a scan-to-map odometry turns such cones into a pitch and roll
bias that grows with the distance driven: the map ahead holds returns of other beams at
other ranges than the scan that registers on it. Azimuth and range errors shift a beam's
returns along grazing facades, which misleads the travel along a street. Each accepted
registration measures, per beam, the offsets that would best bring its points onto the map
(weighted least squares in GICP's metric); the offsets are the information-weighted running
mean of those measurements and correct the next scans' points about the sensor's origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError
from slam.sensor.beam_calibration_kernels import apply_offsets, normal_equations_kernel

MIN_RHO = 0.5  # m: points this near the sensor's axis carry no elevation information
P = 3  # offsets per beam: elevation (rad), azimuth (rad), range (m)


@dataclass
class BeamCalibrationConfig:
    """enabled: learn and apply per-beam elevation offsets (rings needed: given or inferred).
    memory: frames over which measurements are averaged (forgetting factor 1 - 1/memory).
    max_gain: the largest share of one frame's measurement applied at once (damps the
    feedback through the map the corrected points build). prior_angle_deg / prior_range:
    the 1-sigma spread of a unit's calibration errors (deg, m), a prior that keeps what the
    scans cannot tell apart (an elevation from a range offset on ground-only beams) at zero.
    max_offset_deg / max_range_offset: offsets are clamped to these (deg, m). min_pairs: a
    beam needs this many registered pairs in a frame for that frame to measure it."""

    enabled: bool = False
    memory: float = 50.0
    max_gain: float = 0.2
    prior_angle_deg: float = 0.1
    prior_range: float = 0.02
    max_offset_deg: float = 0.5
    max_range_offset: float = 0.1
    min_pairs: int = 20

    def __post_init__(self) -> None:
        if self.memory < 1 or not 0 < self.max_gain <= 1:
            raise ConfigError("beam_calibration: memory >= 1 frame and 0 < max_gain <= 1")
        if min(self.max_offset_deg, self.max_range_offset) <= 0 or self.min_pairs < 1:
            raise ConfigError(
                "beam_calibration: max_offset_deg, max_range_offset > 0 and min_pairs >= 1"
            )
        if min(self.prior_angle_deg, self.prior_range) <= 0:
            raise ConfigError("beam_calibration: prior_angle_deg and prior_range must be > 0")

    def prior_information(self) -> np.ndarray:
        """(P, P) information of the prior on one beam's (elevation, azimuth, range)."""
        a = np.radians(self.prior_angle_deg)
        return np.diag([1.0 / a**2, 1.0 / a**2, 1.0 / self.prior_range**2])


def rotate_beams(xyz: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """(N, 3) points with their elevation and azimuth about the origin changed by
    ``delta[:, :2]`` rad and their range by ``delta[:, 2]`` m."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rho = np.hypot(x, y)
    c, s = np.cos(delta[:, 0]), np.sin(delta[:, 0])
    rho_new = rho * c - z * s
    scale = np.divide(rho_new, rho, out=np.ones_like(rho), where=rho > 0)
    ca, sa = np.cos(delta[:, 1]), np.sin(delta[:, 1])
    xs, ys = x * scale, y * scale
    out = np.stack([xs * ca - ys * sa, xs * sa + ys * ca, z * c + rho * s], axis=1)
    r = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    grow = np.divide(r + delta[:, 2], r, out=np.ones_like(r), where=r > 0)
    return out * grow[:, None]


def beam_jacobian(xyz: np.ndarray) -> np.ndarray:
    """(N, 3, 3) derivative of each point by its elevation and azimuth (m/rad) and range
    (m/m), at zero."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rho = np.maximum(np.hypot(x, y), 1e-9)
    el = np.stack([-z * x / rho, -z * y / rho, rho], axis=1)
    az = np.stack([-y, x, np.zeros_like(x)], axis=1)
    rng = xyz / np.maximum(np.sqrt(np.einsum("ij,ij->i", xyz, xyz)), 1e-9)[:, None]
    return np.stack([el, az, rng], axis=2)


def normal_equations(
    p: np.ndarray,
    rings: np.ndarray,
    T: np.ndarray,
    q: np.ndarray,
    W: np.ndarray,
    weight: np.ndarray,
    n_beams: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per beam sum J^T W J (n_beams, P, P), sum J^T W e (n_beams, P) and the pair counts of
    the pairs (p_i, q_i) at pose T, e = R p + t - q, J the map-frame derivative of p by its
    beam's offsets (numpy reference of ``normal_equations_kernel``)."""
    R, t = T[:3, :3], T[:3, 3]
    e = p @ R.T + t - q
    J = np.einsum("ij,njk->nik", R, beam_jacobian(p))
    WJ = np.einsum("nij,njk->nik", W, J)
    A = np.zeros((n_beams, P, P))
    B = np.zeros((n_beams, P))
    np.add.at(A, rings, np.einsum("nji,njk->nik", J, WJ) * weight[:, None, None])
    np.add.at(B, rings, np.einsum("nji,nj->ni", WJ, e) * weight[:, None])
    return A, B, np.bincount(rings, minlength=n_beams)


class BeamCalibration:
    """Per-beam (elevation rad, azimuth rad, range m) offsets and the information behind
    them."""

    def __init__(self, cfg: BeamCalibrationConfig | None = None):
        self.cfg = cfg or BeamCalibrationConfig()
        self.offsets = np.zeros((0, P))
        self.info = np.zeros((0, P, P))
        self.updates = 0

    def _grow(self, n: int) -> None:
        if n > len(self.offsets):
            m = n - len(self.offsets)
            self.offsets = np.concatenate([self.offsets, np.zeros((m, P))])
            self.info = np.concatenate([self.info, np.zeros((m, P, P))])

    def correct(self, xyz: np.ndarray, rings: np.ndarray | None) -> np.ndarray:
        """``xyz`` (sensor frame) with each beam's offsets applied; unchanged without rings
        or before any offset is known."""
        if rings is None or not self.cfg.enabled or not np.any(self.offsets):
            return xyz
        return apply_offsets(
            np.ascontiguousarray(xyz, dtype=np.float64),
            np.asarray(rings, dtype=np.int64),
            self.offsets,
        )

    def update(
        self,
        p: np.ndarray,
        rings: np.ndarray,
        T: np.ndarray,
        q: np.ndarray,
        W: np.ndarray,
        w: np.ndarray | None = None,
    ) -> None:
        """One accepted registration: sensor-frame points ``p`` (already corrected) of beams
        ``rings``, paired with map points ``q`` under information ``W`` (N, 3, 3) at pose
        ``T``, optional robust weights ``w``. Moves each measured beam's offsets towards the
        change that minimises sum e^T W e over its pairs."""
        if not self.cfg.enabled or len(p) == 0:
            return
        rings = np.asarray(rings, dtype=np.int64)
        rho = np.hypot(p[:, 0], p[:, 1])
        ok = (rings >= 0) & (rho > MIN_RHO)
        if w is not None:
            ok &= w > 0
        weight = np.ones(int(ok.sum())) if w is None else w[ok]
        p, rings, q, W = p[ok], rings[ok], q[ok], W[ok]
        if not len(p):
            return
        n = int(rings.max()) + 1
        self._grow(n)
        A, B, count = normal_equations_kernel(
            np.ascontiguousarray(p, dtype=np.float64),
            rings,
            np.ascontiguousarray(T[:3, :3]),
            np.ascontiguousarray(T[:3, 3]),
            np.ascontiguousarray(q, dtype=np.float64),
            np.ascontiguousarray(W, dtype=np.float64),
            np.ascontiguousarray(weight, dtype=np.float64),
            n,
        )
        seen = np.flatnonzero(count >= self.cfg.min_pairs)
        lam = 1.0 - 1.0 / self.cfg.memory
        self.info[:n] *= lam
        self.info[seen] += A[seen]
        # the step: -(I + c A + L)^-1 (B + L x): at most max_gain of this frame's own
        # solution, the prior L pulling what the data leave open towards zero
        c = 1.0 / self.cfg.max_gain - 1.0
        L = self.cfg.prior_information()
        M = self.info[seen] + c * A[seen] + L
        g = B[seen] + self.offsets[seen] @ L
        step = -np.linalg.solve(M, g[:, :, None])[:, :, 0]
        limit = np.array([np.radians(self.cfg.max_offset_deg)] * 2 + [self.cfg.max_range_offset])
        self.offsets[seen] = np.clip(self.offsets[seen] + step, -limit, limit)
        self.updates += 1
