"""What every registration returns or raises: the result, its stop reasons, the typed error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import SlamError

STOP_REASONS = ("step", "fitness", "cycle", "least_cost", "stalled", "max_iterations")
CONVERGED_REASONS = ("step", "fitness", "cycle", "least_cost")


class RegistrationError(SlamError):
    """Registration could not run (too few points or correspondences)."""


@dataclass
class RegistrationResult:
    """Outcome of a registration.

    T_target_source: 4x4. H: 6x6 Gauss-Newton Hessian of the cost at the solution (rotation
    first, source-frame tangent), b: gradient. cost: final weighted cost (sum of squared
    Mahalanobis / point-to-feature distances); fitness: mean squared Euclidean distance of
    inlier correspondences (m^2, PCL's fitness score); rmse = sqrt(fitness). dof: number of
    scalar residuals minus 6 (for the residual variance cost / dof).

    stop_reason: why the solver stopped, one of ``STOP_REASONS``: "step" (update below
    transformation_epsilon), "fitness" (relative cost change below fitness_epsilon),
    "cycle" (the pose came back to one of a few iterations before: the association cycles
    around the minimum; only where the matcher asks for it), "least_cost" (at the
    iteration cap, the pose of least re-associated cost, which the later steps left; only
    where asked), "stalled" (no damped step lowered the cost although the Gauss-Newton step
    was not yet small: a saddle, a bad association or numerical trouble) or
    "max_iterations". converged is True only for "step", "fitness", "cycle" and
    "least_cost".
    """

    T_target_source: np.ndarray
    H: np.ndarray
    b: np.ndarray
    cost: float
    fitness: float
    rmse: float
    num_inliers: int
    num_source: int
    iterations: int
    converged: bool
    dof: int = 0
    stop_reason: str = "step"

    @property
    def inlier_ratio(self) -> float:
        """Share of source points that found a correspondence (0-1)."""
        return self.num_inliers / max(self.num_source, 1)


def _check_points(xyz: np.ndarray, name: str) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise RegistrationError(f"{name} must be an (N, 3) array, got shape {xyz.shape}")
    return xyz
