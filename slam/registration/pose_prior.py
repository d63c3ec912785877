"""A Gaussian prior on the pose a registration solves for: the constant-velocity prediction
with the spread a vehicle's acceleration allows over one frame.

Along a direction the scan observes well the registration's own information is thousands
of times larger and the prior changes nothing; along one it barely observes (a plain street,
a corridor) it keeps the solution from wandering over a flat, rugged cost. Same tangent as
the solver (``slam.registration.solver``): rotation first, ``T = T_prior exp(delta)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError


@dataclass
class MotionPriorConfig:
    """The prediction as a prior of the registration once the velocity is tracked
    (docs/robustness.md, "A plain street"). Its spread over a frame of dt seconds is
    acceleration * dt^2 (m) and angular_acceleration_deg * dt^2 (deg): 2 cm and 0.2 deg at
    10 Hz, what a car's braking, accelerating and steering change of the constant-velocity
    motion within one frame."""

    enabled: bool = False
    acceleration: float = 2.0  # m/s^2
    angular_acceleration_deg: float = 20.0  # deg/s^2

    def __post_init__(self) -> None:
        if self.acceleration <= 0 or self.angular_acceleration_deg <= 0:
            raise ConfigError("motion_prior acceleration and angular_acceleration_deg must be > 0")

    def prior(self, T_pred: np.ndarray, dt: float) -> PosePrior:
        """The prior around ``T_pred`` for a prediction over ``dt`` seconds."""
        dt = max(float(dt), 1e-3)
        sigma_t = self.acceleration * dt**2
        sigma_r = np.radians(self.angular_acceleration_deg) * dt**2
        return PosePrior.isotropic(T_pred, sigma_t, sigma_r)


@dataclass(frozen=True)
class PosePrior:
    """``T = T exp(delta)``, delta ~ N(0, information^-1) (6 x 6, rotation first)."""

    T: np.ndarray
    information: np.ndarray

    @classmethod
    def isotropic(cls, T: np.ndarray, sigma_translation: float, sigma_rotation: float) -> PosePrior:
        """Sigmas in m and rad, the same along every axis."""
        w = [sigma_rotation**-2] * 3 + [sigma_translation**-2] * 3
        return cls(np.asarray(T, dtype=np.float64), np.diag(w))

    def residual(self, T: np.ndarray) -> np.ndarray:
        """delta of ``T`` (rotation vector rad, translation m)."""
        D = np.linalg.solve(self.T, T)
        return np.concatenate([Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]])

    def cost(self, T: np.ndarray) -> float:
        """delta^T information delta (the solver's cost units)."""
        d = self.residual(T)
        return float(d @ self.information @ d)

    def linearised(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(H, b, cost) of the prior at ``T`` in the solver's form (d delta / d xi ~ I)."""
        d = self.residual(T)
        Ld = self.information @ d
        return self.information, Ld, float(d @ Ld)
